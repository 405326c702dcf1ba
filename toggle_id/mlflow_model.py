"""The identified model as an MLflow pyfunc model: a voltage command in, the slider position x_B out.

``mlflow.pyfunc.load_model(uri).predict(df)`` takes a DataFrame with columns ``t`` (s, a uniform grid) and
``v_in`` (V) and returns one with ``t``, ``x_B`` (m) and ``i_q`` (A), simulated by :func:`toggle_id.simulate.simulate`
(PRECISE tier, v_in linearly interpolated between samples, as for a measured record) with the identified
parameters and effects, which the model carries as a JSON artifact (:data:`SPEC_FILE`). The initial position
``x_B0`` (m) is the fitted record's unless the call passes ``params={"x_B0": ...}``.

The model's class is pickled by reference: loading it needs this package installed (``pip install -e .`` of
the repository) in the loading environment, as its requirements say.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping

import mlflow.pyfunc
import numpy as np
import pandas as pd

#: The artifact key and file name of the identified model's parameters inside the MLflow model.
SPEC_KEY = "toggle_model"
SPEC_FILE = "toggle_model.json"
SPEC_FORMAT = 1


def model_spec(theta: np.ndarray, *, x_B0: float, method: str, records: list[str], rmse_m: float,
               extra: Mapping[str, Any] | None = None) -> dict:
    """Everything the model needs, as plain JSON: the extended parameter vector by name, x_B0 and provenance."""
    from .effects import ALL_NAMES
    from .params import N_PARAMS, PARAM_NAMES

    theta = np.asarray(theta, float).ravel()
    if theta.size != len(ALL_NAMES):
        raise ValueError(f"theta must have {len(ALL_NAMES)} entries (the extended vector), got {theta.size}")
    values = {n: float(v) for n, v in zip(ALL_NAMES, theta)}
    return {"format": SPEC_FORMAT, "params": {n: values[n] for n in PARAM_NAMES},
            "effect_params": {n: values[n] for n in ALL_NAMES[N_PARAMS:]}, "x_B0": float(x_B0),
            "solver": "precise", "method": method, "records": list(records), "rmse_m": float(rmse_m),
            **dict(extra or {})}


def theta_of(spec: Mapping[str, Any]) -> np.ndarray:
    """The extended parameter vector of a :func:`model_spec` (effects not named stay off)."""
    from . import params as P
    from .effects import ALL_INDEX
    from .simulate import extend

    if spec.get("format") != SPEC_FORMAT:
        raise ValueError(f"unknown toggle-id model format {spec.get('format')!r} (expected {SPEC_FORMAT})")
    theta = extend(P.ASSIGNED)[0]
    for group in ("params", "effect_params"):
        for name, value in (spec.get(group) or {}).items():
            theta[ALL_INDEX[name]] = float(value)
    return theta


def signature() -> Any:
    """Input ``t, v_in``; output ``t, x_B, i_q`` (all doubles); optional parameter ``x_B0`` (m)."""
    from mlflow.models import ModelSignature
    from mlflow.types import ColSpec, ParamSchema, ParamSpec, Schema

    return ModelSignature(inputs=Schema([ColSpec("double", "t"), ColSpec("double", "v_in")]),
                          outputs=Schema([ColSpec("double", "t"), ColSpec("double", "x_B"), ColSpec("double", "i_q")]),
                          params=ParamSchema([ParamSpec("x_B0", "double", None)]))


def pip_requirements() -> list[str]:
    """What the model imports, pinned to the versions it was logged with (no inference, no network)."""
    from importlib.metadata import PackageNotFoundError, version

    out = []
    for dist in ("toggle-id", "mlflow", "numpy", "scipy", "numba", "pandas", "cloudpickle"):
        try:
            out.append(f"{dist}=={version(dist)}")
        except PackageNotFoundError:
            out.append(dist)
    return out


class ToggleModel(mlflow.pyfunc.PythonModel):
    """x_B of the identified motor-toggle model for a voltage command (see the module's docstring)."""

    def load_context(self, context: Any) -> None:
        spec = json.loads(Path(context.artifacts[SPEC_KEY]).read_text(encoding="utf-8"))
        self._spec = spec
        self._theta = theta_of(spec)
        self._x_B0 = float(spec["x_B0"])

    def predict(self, context: Any, model_input: pd.DataFrame, params: dict | None = None) -> pd.DataFrame:
        """``model_input``: a DataFrame (or mapping) with columns ``t`` (s, uniform grid) and ``v_in`` (V).
        Returns a DataFrame with ``t``, ``x_B`` (m) and ``i_q`` (A); NaN where the simulation failed."""
        from .record import Record
        from .simulate import PRECISE, simulate

        df = model_input if isinstance(model_input, pd.DataFrame) else pd.DataFrame(model_input)
        missing = [c for c in ("t", "v_in") if c not in df.columns]
        if missing:
            raise ValueError(f"model input lacks column(s) {', '.join(missing)}; it needs t (s) and v_in (V)")
        t = df["t"].to_numpy(dtype=float)
        v = df["v_in"].to_numpy(dtype=float)
        if t.size < 2 or not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))) or not np.all(np.diff(t) > 0):
            raise ValueError("model input: t must be at least two finite, increasing times and v_in finite")
        x_B0 = (params or {}).get("x_B0")
        x_B0 = self._x_B0 if x_B0 is None or (isinstance(x_B0, float) and math.isnan(x_B0)) else float(x_B0)
        sim = simulate(self._theta[None, :], Record(t=t, v_in=v, x_B0=x_B0, name="input"), PRECISE)
        return pd.DataFrame({"t": t, "x_B": sim.x_B[0], "i_q": sim.i_q[0]}, index=df.index)
