"""The code of the logged pyfunc model (MLflow's "models from code"): MLflow copies this file into every model
it logs and runs it when the model is loaded; it names the model class, which needs this package installed."""
import mlflow.models

from toggle_id.mlflow_model import ToggleModel

mlflow.models.set_model(ToggleModel())
