"""The discover job (``python -m jobs.run +experiment=discover``): the nominal fit (two-stage RGA + polish, or a
polish from the base values), the discovery loop (:func:`toggle_id.discovery.discover`), figures, MLflow (one child
run per refit) and ``discovery.json``."""
from __future__ import annotations

import re
import time
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .. import console, mlflow_run
from .. import params as P
from ..curve import RmseCurve
from ..data import read_csv
from ..discovery import discover
from ..discovery.refit import Refit
from ..discovery.report import summary_text, write_figures
from ..discovery.residual import level_varies, noise_lines
from ..discovery.settings import DiscoverJobSettings, DiscoverSettings
from ..effects import ALL_INDEX, ALL_NAMES
from ..errors import ConfigError, DataError
from ..identify import IdentificationResult, identify
from ..simulate import extend
from .common import (evaluator_factory, fast_settings, flat_config, ga_config, jsonable_config, make_tracker,
                     polish_settings, publish_report, ray_session, solver_tier, validate_config)
from .job_report import stage_child_run
from .records import build_record


def discover_settings(cfg: Mapping) -> DiscoverSettings:
    """Settings from the ``discover`` node of a job config (ConfigError on a bad value)."""
    node = dict(cfg.get("discover") or {})
    nominal = node.get("nominal", DiscoverJobSettings.nominal)
    if nominal not in ("ga", "base"):
        raise ConfigError(f"discover.nominal must be 'ga' (two-stage RGA + polish) or 'base' (polish from the "
                          f"assigned/base values), got {nominal!r}")
    alternatives = node.get("alternatives", DiscoverJobSettings.alternatives)
    if isinstance(alternatives, str) or not all(m in ("one_stage", "two_stage", "fast") for m in alternatives):
        raise ConfigError(f"discover.alternatives must be a list of identification methods (one_stage, two_stage, "
                          f"fast), got {alternatives!r}")
    restarts = node.get("restarts", DiscoverJobSettings.restarts)
    if isinstance(restarts, bool) or not isinstance(restarts, int) or restarts < 0:
        raise ConfigError(f"discover.restarts must be a whole number of further seeds (0 or more), got {restarts!r}")
    if node.get("noise_std") is None:
        noise = (cfg.get("identifiability") or {}).get("noise_std_m")
        if noise is not None:
            node["noise_std"] = float(noise)
    try:
        return DiscoverSettings.from_dict(node)
    except TypeError as err:
        raise ConfigError(f"discover: {err}") from err


def run_discover(cfg: Mapping, run_dir: str | Path, project_root: str | Path = ".") -> Path:
    """The discover job: nominal two-stage fit, the discovery loop, figures, MLflow, ``discovery.json``."""
    validate_config(cfg)
    settings = discover_settings(cfg)
    nominal_mode = (cfg.get("discover") or {}).get("nominal", DiscoverJobSettings.nominal)
    method = cfg.get("method", "two_stage")
    seed = int(cfg.get("seed", 0))
    fixed = dict(cfg.get("fixed") or {})
    for nm in fixed:
        if nm not in ALL_INDEX:
            raise ConfigError(f"fixed: unknown parameter {nm!r}")
    if cfg.get("extra_free"):
        raise ConfigError("extra_free is not used by the discover job: the loop frees effect parameters itself")
    base_start = _base_vector(cfg)
    ga = ga_config(cfg)
    polish_cfg = polish_settings(cfg)
    tier = solver_tier(cfg)
    ev = cfg.get("evaluator") or {}
    make_eval = evaluator_factory(ev)
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    record, truth = build_record(cfg.get("data") or {})
    if record.x_B is None:
        raise DataError(f"record {record.name!r} has no measured x_B")
    validation = None
    vpath = (cfg.get("validation") or {}).get("path")
    if vpath:  # a second record of the same machine: predicted, never fitted
        vp = Path(vpath).expanduser()
        validation = read_csv(vp if vp.is_absolute() else Path(project_root) / vp, x_B0=record.x_B0)
    if settings.noise_std is None and truth is not None:
        noise = float((cfg.get("data") or {}).get("noise_m", 0.0) or 0.0)
        settings.noise_std = noise if noise > 0 else None
    tracker = make_tracker(cfg, project_root)
    show = bool(cfg.get("progress", True))
    t0 = time.perf_counter()
    log_datasets = (cfg.get("tracking") or {}).get("log_datasets", True)
    with ray_session(ev), tracker.run("discover", tags={"job": "discover", "method": method}) as run:
        tracker.log_params(flat_config(cfg))
        datasets = mlflow_run.log_records(tracker, [record], run_dir, enabled=log_datasets)
        if validation is not None:
            datasets += mlflow_run.log_records(tracker, [validation], run_dir, "validation", enabled=log_datasets)
        curve = RmseCurve(record, on_point=mlflow_run.curve_logger(tracker, run.run_id), t0=t0)
        def fit_nominal(fit_method: str, name: str, seed: int = seed, **extra) -> IdentificationResult:
            """One nominal fit as its own MLflow child run (the job's own, or a further route's)."""
            with tracker.run(name, tags={"stage": "nominal", "route": fit_method, "seed": str(seed)}, nested=True):
                res = identify(record, method=fit_method, ga=ga, seed=seed,
                               make_evaluator=make_eval, fixed=fixed, bounds=dict(cfg.get("bounds") or {}),
                               settings=tier, polish=polish_cfg, identifiability=False, fast=fast_settings(cfg),
                               progress=lambda total, desc: console.progress(total, desc, enabled=show), **extra)
                tracker.log_metrics({"fitness": res.fitness, "rmse_m": res.rmse_m, "seconds": res.seconds})
            return res

        nominal_result = fit_nominal(method, "nominal", on_stage=lambda st: stage_child_run(tracker, st, truth),
                                     curve=curve) if nominal_mode == "ga" else None
        nominal = nominal_result if nominal_result is not None else base_start
        starts = [base_start] if nominal_result is not None else []
        label = method if nominal_result is not None else "base"
        # further routes' nominal fits (toggle_id/discovery/routes.py): made only when the loop asks for them
        alt_methods = (cfg.get("discover") or {}).get("alternatives", DiscoverJobSettings.alternatives)
        alternatives = [(m, lambda m=m: fit_nominal(m, f"nominal_{m}")) for m in alt_methods if m != label]
        n_restarts = (cfg.get("discover") or {}).get("restarts", DiscoverJobSettings.restarts)
        restarts = [(f"{label}_seed{s}", lambda s=s: fit_nominal(method, f"nominal_seed{s}", seed=s))
                    for s in range(seed + 1, seed + 1 + n_restarts)] if nominal_result is not None else []

        def on_refit(rf: Refit) -> None:
            with tracker.run(f"refit_{rf.iteration}_{rf.name}", tags={"effect": rf.name,
                                                                       "iteration": str(rf.iteration)}, nested=True):
                tracker.log_params({"effect": rf.name, "iteration": rf.iteration,
                                    **{f"start.{k}": v for k, v in (rf.search.get("best_grid") or {}).items()}})
                tracker.log_metrics({"sse_before_m2": rf.sse0, "sse_after_m2": rf.sse1, "F": rf.F,
                                     "p_value": rf.p_value, "delta_bic": rf.delta_bic, "accepted": float(rf.accepted),
                                     "rmse_after_m": float(np.sqrt(rf.sse1 / record.n)) if np.isfinite(rf.sse1) else
                                     float("nan"), "seconds": rf.seconds,
                                     **{f"param.{k}": v for k, v in rf.params.items()}})

        res = discover(record, nominal=nominal, settings=settings, fixed=fixed, starts=starts, reference=base_start,
                       validation=validation, label=label, alternatives=alternatives, restarts=restarts,
                       on_refit=on_refit, bounds=dict(cfg.get("bounds") or {}),
                       progress=(lambda msg: print(msg, flush=True)) if show else None)
        curve.add("discovery", curve.simulations + res.n_simulations, rmse_m=res.rmse_after_m)
        wall = time.perf_counter() - t0
        report = res.to_dict()
        report.update({"job": "discover", "wall_seconds": wall, "mlflow_run_id": run.run_id,
                       "rmse_um": 1e6 * res.rmse_after_m, "curve": curve.to_list(), "datasets": datasets,
                       "config": jsonable_config(cfg), "nominal_mode": nominal_mode,
                       "settings": asdict(settings)})
        if truth is not None:
            report["truth"] = {nm: float(truth[i]) for i, nm in enumerate(ALL_NAMES)}
        tracker.log_metrics({"rmse_before_m": res.rmse_before_m, "rmse_after_m": res.rmse_after_m,
                             "rmse_m": res.rmse_after_m, "rmse_um": 1e6 * res.rmse_after_m,
                             "rmse_before_um": 1e6 * res.rmse_before_m, "n_simulations": curve.simulations,
                             "fitness_before": report["fitness_before"], "fitness_after": report["fitness_after"],
                             "n_effects_added": len(res.effects_added), "wall_seconds": wall,
                             "n_glitches": sum(g["count"] for g in res.extra.get("glitches") or []),
                             "n_noise_lines": len(noise_lines(res.diagnostics_after)),
                             "noise_level_varies": float(bool(level_varies(res.diagnostics_after))),
                             "ljung_box_p_before": res.diagnostics_before.get("whiteness", {}).get("p_value", np.nan),
                             "ljung_box_p_after": res.diagnostics_after.get("whiteness", {}).get("p_value", np.nan),
                             **{f"score.{c['name']}": c["score"] for c in res.candidates},
                             # where the loop's time went (toggle_id/discovery/timing.py), one metric per phase
                             **{"seconds_loop." + re.sub(r"[^A-Za-z0-9]+", "_", r["phase"]).strip("_"): r["seconds"]
                                for r in res.extra.get("time_by_phase", [])}})
        tracker.set_tags({"effects_added": ",".join(a["name"] for a in res.effects_added) or "none",
                          "route": next((r["label"] for r in res.extra.get("routes", []) if r["chosen"]), label)})
        for path in write_figures(run_dir, record, res, settings):
            tracker.log_artifact(path, "figures")
        report["model_uri"], report["seconds_model_logging"] = mlflow_run.log_identified_model(
            tracker, res.final.theta, [record], run_dir, method=f"discover ({method} nominal)",
            rmse_m=res.rmse_after_m, enabled=(cfg.get("tracking") or {}).get("log_model", True),
            extra={"effects_added": [a["name"] for a in res.effects_added]})
        tracker.set_tags({"mlflow.note.content": mlflow_run.describe_discovery(
            method, record, res.rmse_before_m, res.rmse_after_m, [a["name"] for a in res.effects_added], wall)})
        path = publish_report(tracker, run_dir, summary_text(res), report, "discovery.json", "discovery.txt")
    return path


def _base_vector(cfg: Mapping) -> np.ndarray:
    """Start of the baseline polish when no GA runs: the assigned values with ``discover.base`` overrides."""
    theta = extend(P.ASSIGNED)[0]
    for k, v in ((cfg.get("discover") or {}).get("base") or {}).items():
        if k not in ALL_INDEX:
            raise ConfigError(f"discover.base: unknown parameter {k!r}")
        theta[ALL_INDEX[k]] = float(v)
    return theta
