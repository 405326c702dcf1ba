"""The tracker's artifact, dataset and model logging (a mixin of :class:`toggle_id.tracking.Tracker`: every call
goes through its guard, so a store that is down never stops a job)."""
from __future__ import annotations

import contextlib
import json
import logging
import os
import warnings
from typing import Any, Iterator

from .tracking_keys import _jsonable


class ArtifactLogging:
    """log_dict, log_text, log_figure, log_input, log_model and log_artifact of :class:`~toggle_id.tracking.Tracker`."""

    def log_dict(self, obj: Any, artifact_file: str) -> None:
        """Save ``obj`` as a JSON (or ``.yaml``/``.yml``) artifact; numpy arrays/scalars are converted."""
        run_id = self._target("log_dict", 1)
        if run_id is not None:
            try:
                data = _jsonable(obj)
                if not artifact_file.endswith((".yaml", ".yml")):
                    json.dumps(data)  # fail here (rejection), not inside MLflow's artifact upload
            except (TypeError, ValueError) as exc:
                self._reject("log_dict", 1, exc)
                return
            self._call("log_dict", 1, self._client.log_dict, run_id, data, artifact_file)

    def log_text(self, text: str, artifact_file: str) -> None:
        """Save ``text`` as an artifact file."""
        run_id = self._target("log_text", 1)
        if run_id is not None:
            self._call("log_text", 1, self._client.log_text, run_id, str(text), artifact_file)

    def log_figure(self, fig: Any, artifact_file: str) -> None:
        """Save a matplotlib figure as an image artifact (format from the extension, e.g. ``.png``).
        The figure is not closed."""
        run_id = self._target("log_figure", 1)
        if run_id is not None:
            self._call("log_figure", 1, self._client.log_figure, run_id, fig, artifact_file)

    def log_input(self, df: Any, *, name: str, source: str | None = None, context: str = "training",
                  targets: str | None = None) -> str | None:
        """Log a pandas DataFrame as a dataset input of the active run (``mlflow.data.from_pandas``: name, digest,
        schema, profile and ``source`` — a file path or URI; ``None``: the code that logged it) with
        ``context`` (``mlflow.data.context``: ``training``, ``validation``, …). Returns the dataset's digest."""
        run_id = self._target("log_input", 1)
        if run_id is None:
            return None

        def log() -> str:
            import mlflow.data
            from mlflow.entities import DatasetInput, InputTag
            from mlflow.utils.mlflow_tags import MLFLOW_DATASET_CONTEXT

            with warnings.catch_warnings():  # a local path "can be interpreted in multiple ways": all the same
                warnings.filterwarnings("ignore", message=r".*dataset source can be interpreted")
                dataset = mlflow.data.from_pandas(df, source=source, name=name, targets=targets)
            tags = [InputTag(MLFLOW_DATASET_CONTEXT, context)] if context else []
            self._client.log_inputs(run_id, datasets=[DatasetInput(dataset._to_mlflow_entity(), tags=tags)])
            return dataset.digest

        return self._call("log_input", 1, log)[1]

    @contextlib.contextmanager
    def _fluent_defaults(self) -> Iterator[None]:
        """Point MLflow's process-wide defaults (tracking URI and experiment, read through the environment) at
        this tracker's store for the duration of a call that reads them, then restore the environment."""
        saved = {k: os.environ.get(k) for k in ("MLFLOW_TRACKING_URI", "MLFLOW_EXPERIMENT_ID", "MLFLOW_EXPERIMENT_NAME",
                                               "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR")}
        os.environ["MLFLOW_TRACKING_URI"] = self.uri
        os.environ["MLFLOW_EXPERIMENT_ID"] = str(self.experiment_id)
        os.environ.pop("MLFLOW_EXPERIMENT_NAME", None)
        os.environ["MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"] = "false"  # no progress bars on the job's stderr
        try:
            yield
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value

    def log_model(self, name: str, flavor: Any = None, **kwargs: Any) -> str | None:
        """Log a model of the active run with MLflow's ``mlflow.models.Model.log`` (what ``mlflow.pyfunc.log_model``
        calls, plus the run to link it to): ``flavor`` is the flavor module (default ``mlflow.pyfunc``),
        ``kwargs`` go to its ``save_model`` (``python_model``, ``artifacts``, ``signature``,
        ``pip_requirements``, …). The model is linked to the run with the run's step-0 metrics and its params.
        Returns its ``model_uri`` (``models:/<model id>``), or ``None`` when not logged. A model that cannot be
        saved (e.g. not picklable) drops this call only."""
        run_id = self._target("log_model", 1)
        if run_id is None:
            return None

        def log() -> str:
            import mlflow.pyfunc
            from mlflow.exceptions import MlflowException
            from mlflow.models import Model

            quiet = logging.getLogger("mlflow.pyfunc")
            level = quiet.level
            quiet.setLevel(max(level, logging.WARNING))  # not "Validating input example against model signature"
            try:
                with self._fluent_defaults():
                    info = Model.log(artifact_path=None, name=name, flavor=flavor or mlflow.pyfunc, run_id=run_id,
                                     **kwargs)
            except (OSError, MlflowException):
                raise
            except Exception as exc:  # the model itself, not the store: refuse this call only
                raise ValueError(f"{type(exc).__name__}: {exc}") from exc
            finally:
                quiet.setLevel(level)
            return info.model_uri

        return self._call("log_model", 1, log)[1]

    def log_artifact(self, path: str | os.PathLike, artifact_path: str | None = None) -> None:
        """Copy a local file (or a directory's contents) into the run's artifacts (under ``artifact_path``)."""
        run_id = self._target("log_artifact", 1)
        if run_id is None:
            return
        path = os.fspath(path)
        if not os.path.exists(path):
            self._reject("log_artifact", 1, FileNotFoundError(f"no such file: {path}"))
            return
        fn = self._client.log_artifacts if os.path.isdir(path) else self._client.log_artifact
        self._call("log_artifact", 1, fn, run_id, path, artifact_path)
