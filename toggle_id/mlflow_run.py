"""What a job's MLflow run carries for comparing and reusing results, beside its parameters and metrics.

* the shared curve: ``best_rmse_um`` against cumulative simulations (:mod:`toggle_id.curve`), logged live;
* the record(s) it was fitted on as MLflow datasets (``mlflow.data.from_pandas``: name, source, digest, schema),
  context ``training`` (and ``validation`` for a record it only predicts);
* the identified model as an MLflow pyfunc model (:mod:`toggle_id.mlflow_model`), whose ``model_uri`` goes
  into the job's report;
* a one-line description (``mlflow.note.content``): method, record, result in µm.

Everything here goes through :class:`toggle_id.tracking.Tracker`, so a store that is down never stops the job.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .checkpoint import atomic_write_json
from .curve import CurvePoint
from .record import Record
from .tracking import Tracker

#: The curve's MLflow metric (µm; step = cumulative simulations).
CURVE_METRIC = "best_rmse_um"


def curve_logger(tracker: Tracker, run_id: str | None) -> Callable[[CurvePoint], None]:
    """A curve's ``on_point``: ``best_rmse_um`` at ``step`` = simulations into run ``run_id`` (the job's parent
    run, also while a child run is open)."""
    def log(point: CurvePoint) -> None:
        tracker.log_metrics({CURVE_METRIC: 1e6 * point.best_rmse_m}, step=point.simulations, run_id=run_id)

    return log


def record_frame(record: Record):
    """The record as a DataFrame: ``t`` (s), ``v_in`` (V), ``x_B`` (m) and ``i_q`` (A) where present."""
    import pandas as pd

    cols = {"t": record.t, "v_in": record.v_in}
    for name in ("x_B", "i_q"):
        if getattr(record, name) is not None:
            cols[name] = getattr(record, name)
    return pd.DataFrame(cols)


def log_records(tracker: Tracker, records: Sequence[Record], run_dir: str | Path, context: str = "training",
                enabled: bool = True) -> list[dict]:
    """Log ``records`` as dataset inputs of the active run; return ``[{name, source, digest, context}]``.

    A record read from a file has that file (absolute path) as its source; a simulated one is written to the
    run directory first (``record.csv``, ``record_<k>_<name>.csv`` for further records of a joint fit) — a file
    that ``data=csv data.path=…`` reads back — and has that as its source.
    """
    if not (enabled and tracker.ok):
        return []
    from .data import write_csv

    out = []
    for k, rec in enumerate(records):
        path = rec.meta.get("path")
        if path:
            source = str(Path(path).expanduser().resolve())
        else:
            name = "record.csv" if k == 0 else f"record_{k}_{rec.name}.csv"
            if context != "training":
                name = f"{context}_{name}"
            try:
                source = str(write_csv(rec, Path(run_dir) / name, validate=False).resolve())
            except OSError:
                source = None  # MLflow then names the code that logged it
        digest = tracker.log_input(record_frame(rec), name=rec.name, source=source, context=context,
                                   targets="x_B" if rec.x_B is not None else None)
        if digest is not None:
            out.append({"name": rec.name, "source": source, "digest": digest, "context": context})
    return out


def log_identified_model(tracker: Tracker, theta: np.ndarray, records: Sequence[Record], run_dir: str | Path, *,
                         method: str, rmse_m: float, enabled: bool = True, extra: dict | None = None
                         ) -> tuple[str | None, float]:
    """Log the model of ``theta`` (extended vector) as an MLflow pyfunc model named ``model`` of the active run.

    Its parameters are written to ``<run_dir>/toggle_model.json`` (the model's artifact). Returns the model's
    URI (``models:/<id>``; ``None`` when not logged) and the seconds the logging took.
    """
    if not (enabled and tracker.ok):
        return None, 0.0
    t0 = time.perf_counter()
    from .mlflow_model import SPEC_FILE, SPEC_KEY, model_spec, pip_requirements, signature

    spec = model_spec(theta, x_B0=records[0].x_B0, method=method, records=[r.name for r in records],
                      rmse_m=rmse_m, extra=extra)
    path = atomic_write_json(Path(run_dir) / SPEC_FILE, spec)
    code = Path(__file__).with_name("mlflow_model_code.py")  # MLflow's models from code: no pickle
    uri = tracker.log_model("model", python_model=str(code), artifacts={SPEC_KEY: str(path)},
                            signature=signature(), pip_requirements=pip_requirements(),
                            input_example=record_frame(records[0])[["t", "v_in"]].head(10),
                            metadata={"toggle_id": {"method": method, "records": spec["records"],
                                                    "rmse_um": 1e6 * float(rmse_m)}})
    return uri, time.perf_counter() - t0


def describe_identification(method: str, records: Sequence[Record], rmse_m: float, n_simulations: int,
                            seconds: float, simulated: bool) -> str:
    """One line for the run's description: method, record, result."""
    what = " + ".join(r.name for r in records)
    n = sum(r.n for r in records)
    kind = "simulated" if simulated else "measured"
    return (f"{method.replace('_', '-')} identification of {what} ({kind}, {n} samples): RMS error "
            f"{1e6 * rmse_m:.4g} µm after {n_simulations} simulations, {seconds:.0f} s")


def describe_discovery(method: str, record: Record, rmse_before_m: float, rmse_after_m: float,
                       added: Sequence[str], seconds: float) -> str:
    """One line for a discover run's description: nominal method, record, effects added, result."""
    return (f"discovery on {record.name} ({record.n} samples, nominal fit {method.replace('_', '-')}): effects "
            f"added {', '.join(added) or 'none'}; RMS error {1e6 * rmse_before_m:.4g} → {1e6 * rmse_after_m:.4g} µm, "
            f"{seconds:.0f} s")
