"""The identify job (``python -m jobs.run``, ``job: identify``): identify the parameters of one record — or of
several jointly (``data=joint``) — by the configured method, then report: ``result.json`` and ``table.txt``, the
figures, the MLflow run (one child run per stage) and the identified model.

The run directory holds the checkpoints of the GA; ``resume=`` (or an interrupted run in the same directory)
continues one that this very job wrote (:mod:`toggle_id.jobdir`).
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Mapping

import numpy as np

from .. import console, jobdir, mlflow_run
from .. import params as P
from ..checkpoint import atomic_write_json
from ..curve import RmseCurve
from ..data import read_csv
from ..errors import ConfigError
from ..identify import identify
from ..simulate import PRECISE, extend, simulate
from ..stages import joint_plan
from .common import (evaluator_factory, flat_config, get, identify_kwargs, jsonable_config, make_tracker,
                     publish_report, ray_session, validate_config)
from .job_report import console_report, model_response, stage_child_run, write_figures
from .records import build_records


def run_identify(cfg: Mapping, run_dir: str | Path, project_root: str | Path = ".") -> Path:
    """The main job: identify the parameters of one record — or of several jointly (data=joint) — one- or
    two-stage, log and report."""
    validate_config(cfg)
    records, truth = build_records(cfg.get("data") or {})
    identity = jobdir.job_identity(cfg, records)  # stored in every checkpoint; a resume must match it
    run_dir, resume = _run_dir(cfg, run_dir, identity)
    record = records[0]
    method = cfg.get("method", "two_stage")
    kw = identify_kwargs(cfg, run_dir, resume)
    kw["checkpoint_meta"] = {jobdir.META_KEY: identity}
    joint_plan(records, method, extend(P.ASSIGNED)[0], fixed=tuple(kw["fixed"]))  # records fit the method?
    tracker = make_tracker(cfg, project_root)
    ev = cfg.get("evaluator") or {}
    show = bool(cfg.get("progress", True))
    t0 = time.perf_counter()
    with ray_session(ev), tracker.run(method, tags={"method": method, "job": "identify"},
                                     run_id=_mlflow_run_id(run_dir) if resume else None) as run:
        _remember_mlflow_run(run_dir, run.run_id)
        tracker.log_params(flat_config(cfg))
        datasets = mlflow_run.log_records(tracker, records, run_dir, enabled=get(cfg, "tracking.log_datasets", True))
        curve = RmseCurve(records, on_point=mlflow_run.curve_logger(tracker, run.run_id))
        result = identify(records if len(records) > 1 else record, method=method, make_evaluator=evaluator_factory(ev),
                          progress=lambda total, desc: console.progress(total, desc, enabled=show),
                          on_stage=lambda st: stage_child_run(tracker, st, truth),
                          on_generation=_fault_injection(cfg), curve=curve, **kw)
        wall = time.perf_counter() - t0
        report = result.to_dict()
        report.update(_truth_report(result.theta, truth))
        responses = [model_response(r, result.theta) for r in records]
        status = [int(resp["status"]) for resp in responses]
        report.update({"job": "identify", "record": "+".join(r.name for r in records), "wall_seconds": wall,
                       "config": jsonable_config(cfg), "mlflow_run_id": run.run_id,
                       "solver_status": max(status, key=abs)})
        for entry, st in zip(report.get("records") or [], status):
            entry["solver_status"] = st
        final = result.stages[-1] if result.stages else None
        if final is not None and final.identifiability:  # the final fit's (the joint polish's, two-stage)
            report["identifiability"] = {"stage": final.name, **final.identifiability}
        validation = get(cfg, "validation.path")
        if validation:
            report["validation"] = validation_report(validation, result.theta)
            datasets += mlflow_run.log_records(tracker, [read_csv(validation)], run_dir, "validation",
                                               enabled=get(cfg, "tracking.log_datasets", True))
        tracker.log_metrics({"fitness": result.fitness, "sse_m2": result.sse, "rmse_m": result.rmse_m,
                             "rmse_um": 1e6 * result.rmse_m, "n_simulations": result.n_simulations,
                             "seconds_total": result.seconds, "wall_seconds": wall,
                             **({"validation.rmse_um": 1e6 * report["validation"]["rmse_m"]} if validation else {}),
                             **{f"rmse_m.{r['name']}": r["rmse_m"] for r in report.get("records") or []},
                             **{f"param.{k}": v for k, v in result.params.items()},
                             **{f"pct_error.{k}": v for k, v in (report.get("pct_error") or {}).items()}})
        write_figures(run_dir, records, result, tracker, method, responses)
        report["datasets"] = datasets
        report["model_uri"], report["seconds_model_logging"] = mlflow_run.log_identified_model(
            tracker, result.theta, records, run_dir, method=method, rmse_m=result.rmse_m,
            enabled=get(cfg, "tracking.log_model", True))
        tracker.set_tags({"mlflow.note.content": mlflow_run.describe_identification(
            method, records, result.rmse_m, result.n_simulations, wall, truth is not None)})
        path = publish_report(tracker, run_dir, console_report(result, truth), report)
    return path


def _fault_injection(cfg: Mapping):
    """``debug.stop_after_generations=N``: interrupt the run after N generations (as a kill would), to test
    checkpoints and ``resume=``; off by default."""
    n = get(cfg, "debug.stop_after_generations")
    if not n:
        return None
    count = {"n": 0}

    def stop(stage: str, ga) -> None:
        count["n"] += 1
        if count["n"] >= int(n):
            raise KeyboardInterrupt(f"debug.stop_after_generations={n} reached in {stage}")

    return stop


def validation_report(path: str, theta: np.ndarray) -> dict:
    """Simulation error of the identified model on a second record."""
    rec = read_csv(path)
    sim = simulate(theta[None, :], rec, PRECISE)
    e = rec.x_B - sim.x_B[0]
    return {"path": str(Path(path).resolve()), "status": int(sim.status[0]), "sse_m2": float(np.sum(e * e)),
            "rmse_m": float(np.sqrt(np.mean(e * e))),
            "rel_error_pct": float(100 * np.linalg.norm(e) / np.linalg.norm(rec.x_B))}


def _truth_report(theta: np.ndarray, truth: np.ndarray | None) -> dict:
    """The truth of a simulated record and the identified parameters' % errors from it ({} without a truth)."""
    if truth is None:
        return {}
    return {"truth": {n: float(truth[i]) for i, n in enumerate(P.PARAM_NAMES)},
            "pct_error": {n: console.pct_error(float(truth[i]), float(theta[i])) for i, n in enumerate(P.PARAM_NAMES)}}


def _run_dir(cfg: Mapping, run_dir: str | Path, identity: Mapping) -> tuple[Path, bool]:
    """The directory the job works in (claimed for this process) and whether it continues a checkpoint there —
    only one that this job (``identity``) wrote (:mod:`toggle_id.jobdir`)."""
    resume = cfg.get("resume")
    if resume:
        path = Path(resume).expanduser().resolve()
        if not (path / "checkpoint.json").exists():
            raise ConfigError(f"resume: no checkpoint in {path}")
        jobdir.claim(path)
        jobdir.check_resume(path, identity)
        return path, True
    path = Path(run_dir).resolve()
    path.mkdir(parents=True, exist_ok=True)
    jobdir.claim(path)
    again = (path / "checkpoint.json").exists() and not (path / "result.json").exists()
    if again:  # an interrupted run in this very directory (an explicit hydra.run.dir): continue it if it is ours
        jobdir.check_resume(path, identity, what=f"run directory {path} holds an unfinished run",
                            fix="give the job another hydra.run.dir")
    return path, again


def _mlflow_run_id(run_dir: Path) -> str | None:
    """The MLflow run a resumed job continues (``mlflow_run.json`` in its run directory), if it has one."""
    try:
        return json.loads((run_dir / "mlflow_run.json").read_text())["run_id"]
    except (OSError, ValueError, KeyError):
        return None


def _remember_mlflow_run(run_dir: Path, run_id: str | None) -> None:
    """Note the job's MLflow run in its run directory, for a later ``resume=``."""
    if run_id:
        atomic_write_json(run_dir / "mlflow_run.json", {"run_id": run_id})
