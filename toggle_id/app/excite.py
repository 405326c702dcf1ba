"""The excite job (``python -m jobs.run +experiment=excite``): fit the record, collect the rivals, search the
input that tells them apart (:mod:`toggle_id.excite`), write ``excitation.csv``, ``excite.json``, ``excite.png``
and log to MLflow."""
from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .. import mlflow_run
from .. import params as P
from ..data import write_csv
from ..discovery.stats import vuong_power
from ..effects import ALL_INDEX
from ..errors import ConfigError, DataError
from ..identify import identify
from ..excite.report import summary_text, write_figure
from ..excite.rivals import build_rivals, discovery_base, specs_from_discovery
from ..excite.score import spectrum, sv_at
from ..excite.search import Evaluation, Scorer, resolved_sv, search, verify_best
from ..excite.settings import ExciteSettings
from ..record import Record, time_grid
from .common import (fast_settings, flat_config, jsonable_config, make_tracker, publish_report, solver_tier,
                     validate_config)
from .records import build_record


def excite_settings(cfg: Mapping) -> ExciteSettings:
    """Settings from the ``excite`` node of a job config (ConfigError on a bad value)."""
    try:
        return ExciteSettings.from_dict(cfg.get("excite") or {})
    except TypeError as err:
        raise ConfigError(f"excite: {err}") from err


def noise_sigma(settings: ExciteSettings, cfg: Mapping, truth, rmse_m: float) -> tuple[float, str]:
    """σ of the separations: the setting, else a simulated record's noise, else the nominal fit's RMS error."""
    if settings.noise_std_m is not None:
        return float(settings.noise_std_m), "excite.noise_std_m"
    noise = float((cfg.get("data") or {}).get("noise_m") or 0.0)
    if truth is not None and noise > 0:
        return noise, "data.noise_m"
    if not np.isfinite(rmse_m) or rmse_m <= 0:
        raise DataError("no noise level: set excite.noise_std_m (m)")
    return float(rmse_m), "nominal RMS error"


def run_excite(cfg: Mapping, run_dir: str | Path, project_root: str | Path = ".") -> Path:
    """Fit the record (fast method), build its rivals, search and verify the input that separates them; write
    ``excitation.csv`` (the proposed input), ``excite.png`` and ``excite.json``; return the latter's path."""
    validate_config(cfg)
    settings = excite_settings(cfg)
    fast = fast_settings(cfg)
    tier = solver_tier(cfg)
    fixed = dict(cfg.get("fixed") or {})
    for nm in fixed:
        if nm not in ALL_INDEX:
            raise ConfigError(f"fixed: unknown parameter {nm!r}")
    bounds = dict(cfg.get("bounds") or {})
    specs = [(s, "config") for s in settings.rivals]
    pair_bases = {}
    if settings.discovery:
        dp = Path(settings.discovery).expanduser()
        dp = dp if dp.is_absolute() else Path(project_root) / dp
        specs += [(s, "discovery") for s in specs_from_discovery(dp)]
        base = discovery_base(dp)
        if base is not None:
            pair_bases["discovery"] = base
    if not specs and not settings.parameters:
        raise ConfigError("excite: nothing to tell apart: name excite.rivals, give excite.discovery or set "
                          "excite.parameters=true")
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    record, truth = build_record(cfg.get("data") or {})
    if record.x_B is None:
        raise DataError(f"record {record.name!r} has no measured x_B")
    show = bool(cfg.get("progress", True))
    say = (lambda m: print(m, flush=True)) if show else (lambda m: None)
    tracker = make_tracker(cfg, project_root)
    t0 = time.perf_counter()
    log_datasets = (cfg.get("tracking") or {}).get("log_datasets", True)
    with tracker.run("excite", tags={"job": "excite", "method": "fast"}) as run:
        tracker.log_params(flat_config(cfg))
        datasets = mlflow_run.log_records(tracker, [record], run_dir, enabled=log_datasets)
        say("nominal fit (fast method) ...")
        nominal = identify(record, method="fast", seed=int(cfg.get("seed", 0)), fixed=fixed, bounds=bounds,
                           settings=tier, identifiability=False, fast=fast)
        theta = nominal.theta.copy()
        sigma, sigma_source = noise_sigma(settings, cfg, truth, nominal.rmse_m)
        say(f"nominal fit: RMS {1e6 * nominal.rmse_m:.4g} µm ({nominal.seconds:.1f} s); σ = {1e6 * sigma:.3g} µm "
            f"({sigma_source})")
        rivals = build_rivals(record, theta, specs, max_nfev=settings.rival_nfev, fd_rel_step=settings.fd_rel_step,
                              progress=say, pair_bases=pair_bases)
        warnings = rival_warnings(rivals, sigma, settings.rival_rms_sigma)
        for w in warnings:
            say(f"warning: {w}")
        baseline = spectrum(record, theta, sigma) if settings.parameters else None
        if baseline is not None and "error" in baseline:
            raise DataError(f"the record's sensitivities: {baseline['error']}")
        if baseline is not None:
            say(f"parameters on the record's input: numerical rank {baseline['rank']}, s{settings.sv_index} = "
                f"{sv_at(baseline, settings.sv_index):.3g} m")
        scorer = Scorer(settings, rivals, theta, sigma, record.x_B0, baseline)
        evals = search(scorer, say)
        verified = verify_best(scorer, evals, say)
        best = verified[0] if verified else None
        report = _report(settings, record, rivals, evals, verified, best, baseline, sigma, sigma_source)
        report["warnings"] = warnings
        report.update({"job": "excite", "nominal": {"rmse_um": 1e6 * nominal.rmse_m, "seconds": nominal.seconds,
                                                    "params": {n: float(theta[i]) for i, n in enumerate(P.PARAM_NAMES)}},
                       "datasets": datasets, "mlflow_run_id": run.run_id, "config": jsonable_config(cfg),
                       "settings": _settings_dict(settings)})
        if truth is not None:
            report["truth"] = {n: float(truth[ALL_INDEX[n]]) for n in ALL_INDEX if truth[ALL_INDEX[n]] != 0.0}
        if best is not None:
            proposed = scorer.record_of(best.candidate)
            proposed.name = "excitation"
            report["excitation_csv"] = str(write_csv(Record(t=proposed.t, v_in=proposed.v_in, name="excitation"),
                                                     run_dir / "excitation.csv"))
            tracker.log_artifact(run_dir / "excitation.csv")
            curves = [{"name": r.name, "y_a": best.curves[r.name][0], "y_b": best.curves[r.name][1]}
                      for r in rivals if r.name in best.curves]
            par = report.get("parameters") or {}
            fig = write_figure(run_dir / "excite.png", proposed, curves, sigma,
                               baseline["singular_values"] if baseline else None,
                               (best.spectrum or {}).get("singular_values") if baseline else None,
                               (par.get("rank_before"), par.get("rank_after")) if par else None)
            tracker.log_artifact(fig, "figures")
        report["wall_seconds"] = time.perf_counter() - t0
        metrics = {"wall_seconds": report["wall_seconds"], "n_candidates": report["n_candidates"],
                   "n_rejected": report["n_rejected"], "sigma_um": 1e6 * sigma}
        for r in report.get("rivals", []):
            key = r["key"]
            metrics[f"separation_sigma.{key}"] = r["predicted_separation_sigma"]
            metrics[f"separation_um.{key}"] = r["predicted_separation_um"]
        par = report.get("parameters")
        if par:
            metrics.update({"rank_before": par["rank_before"], "rank_after": par["rank_after"]})
            if par.get("sv_gain") is not None:
                metrics["sv_gain"] = par["sv_gain"]
        tracker.log_metrics({k: v for k, v in metrics.items() if v is not None and np.isfinite(v)})
        tracker.set_tags({"mlflow.note.content": _describe(record, report)})
        path = publish_report(tracker, run_dir, summary_text(report), report, "excite.json", "excite.txt")
    return path


def rival_warnings(rivals, sigma: float, limit: float) -> list[str]:
    """One line per rival that does not explain the record (either side's RMS above ``limit`` σ): its separations
    compare explanations of something else, and a nominal fit stuck above the noise is the usual cause."""
    out = []
    for r in rivals:
        worst = max(r.rms_a_m, r.rms_b_m)
        if not (np.isfinite(worst) and worst <= limit * sigma):
            out.append(f"{r.name}: the rivals do not both explain the record (RMS A {1e6 * r.rms_a_m:.3g} µm, B "
                       f"{1e6 * r.rms_b_m:.3g} µm against σ = {1e6 * sigma:.3g} µm, limit {limit:g} σ), so its "
                       "separations are not evidence; raise excite.rival_nfev, or give the discovery.json of a fit "
                       "that reached the noise")
    return out


def _settings_dict(s: ExciteSettings) -> dict:
    """The settings as JSON values (rivals as plain dicts) for ``excite.json``."""
    d = asdict(s)
    d["rivals"] = [{"effect": r.effect, "params": r.params} | ({"against": {"effect": r.against.effect,
                                                                          "params": r.against.params}}
                                                               if r.against is not None else {})
                   for r in s.rivals]
    d["families"] = list(s.families)
    return d


def _report(s: ExciteSettings, record: Record, rivals, evals: list[Evaluation], verified: list[Evaluation],
            best: Evaluation | None, baseline: dict | None, sigma: float, sigma_source: str) -> dict:
    """The body of ``excite.json``: limits, targets, every candidate, the proposed input, each rival's predicted
    separation and, when the parameters count, the singular values and ranks before and after."""
    out = {"record": record.name, "n_samples": record.n, "sigma_um": 1e6 * sigma, "sigma_source": sigma_source,
           "limits": {"v_max": s.v_max, "duration": s.duration, "rate_hz": s.rate_hz, "x_B_min": s.x_B_min,
                      "min_exits": s.min_exits},
           "targets": {"separation_sigma": s.separation_target, "sv_gain": s.sv_gain_target},
           "families": list(s.families), "n_candidates": len(evals),
           "n_rejected": sum(not e.ok for e in evals), "n_verified": len(verified),
           "candidates": [e.to_dict(sigma) for e in evals],
           "proposed": None if best is None else {**best.to_dict(sigma), "index": best.index}}
    rv_out = []
    for r in rivals:
        d = r.to_dict()
        d["record_separation_um"] = 1e6 * r.record_separation_m
        sep = (best.refit_m or {}).get(r.name, float("nan")) if best is not None else float("nan")
        d["predicted_separation_um"] = 1e6 * sep
        d["predicted_separation_sigma"] = sep / sigma
        d["separated"] = bool(np.isfinite(sep) and sep / sigma >= s.separation_target)
        # what a record under the proposed input would let Vuong's test do (white noise σ, both models exact;
        # NaN where nothing was verified)
        d["expected_vuong_z"] = float(np.sqrt(time_grid(s.duration, s.rate_hz).size) * sep / (2.0 * sigma))
        d["vuong_power"] = vuong_power(d["expected_vuong_z"])
        # the best verified input for this rival alone
        per = max((e for e in verified if e.refit_m), key=lambda e: e.refit_m.get(r.name, -np.inf), default=None)
        if per is not None:
            d["best_input_for_this_rival"] = {"index": per.index, "family": per.candidate.family,
                                             "predicted_separation_um": 1e6 * per.refit_m[r.name],
                                             "predicted_separation_sigma": per.refit_m[r.name] / sigma}
        rv_out.append(d)
    out["rivals"] = rv_out
    out["separates"] = [d["name"] for d in rv_out if d["separated"]]
    if baseline is not None:
        after = (best.spectrum if best is not None else None) or {}
        k = s.sv_index
        before_ident = set(baseline.get("identifiable", []))
        after_ident = set(after.get("identifiable", []))
        gain = best.sv_gain if best is not None else float("nan")
        out["parameters"] = {
            "sv_index": k, "singular_values_before": baseline["singular_values"],
            "singular_values_after": after.get("singular_values"), "rank_before": baseline["rank"],
            "rank_after": after.get("rank"), "sv_before": sv_at(baseline, k), "sv_after": sv_at(after, k),
            "sv_after_resolved": resolved_sv(after, k) or None, "sv_gain": gain if np.isfinite(gain) else None,
            "identifiable_before": sorted(before_ident, key=P.PARAM_NAMES.index),
            "identifiable_after": sorted(after_ident, key=P.PARAM_NAMES.index),
            "become_identifiable": sorted(after_ident - before_ident, key=P.PARAM_NAMES.index),
            "null_combinations_before": baseline.get("null_combinations"),
            "null_combinations_after": after.get("null_combinations"),
            "met": bool((after.get("rank") or 0) > baseline["rank"] or (np.isfinite(gain) and gain >= s.sv_gain_target)),
        }
    return out


def _describe(record: Record, report: Mapping) -> str:
    """One sentence for the MLflow run's note: the proposed input and what it separates."""
    best = report.get("proposed")
    if not best:
        return f"excite on {record.name}: no candidate input passed the checks"
    parts = [f"{r['name']} {r['predicted_separation_sigma']:.3g} σ" for r in report.get("rivals", [])]
    par = report.get("parameters")
    if par:
        parts.append(f"rank {par['rank_before']} → {par['rank_after']}")
    return (f"excite on {record.name}: proposed {best['family']} input; " + "; ".join(parts) +
            f"; {report['n_candidates']} candidates, {report['wall_seconds']:.0f} s")
