"""`python -m jobs.run +experiment=table1`: the paper's Table 1 — one- and two-stage identification on the
same simulated record with several seeds — as a markdown table and CSV (artifacts and files in the run dir).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Mapping

import numpy as np

from .. import console, figures
from .. import params as P
from ..checkpoint import atomic_write_json, atomic_write_text
from ..curve import RmseCurve
from ..errors import ConfigError
from ..identify import identify
from ..mlflow_run import curve_logger
from ..provenance import code_version
from ..stages import METHODS
from .common import (evaluator_factory, flat_config, identify_kwargs, jsonable_config, make_tracker, ray_session,
                     validate_config)
from .job_report import stage_child_run
from .records import build_record


def run_table1(cfg: Mapping, run_dir: str | Path, project_root: str | Path = ".") -> Path:
    """Identify the simulated record by every method of ``table1.methods`` with every seed of ``table1.seeds`` (one
    MLflow child run each) and write the table of median parameters and % errors; return ``result.json``'s path."""
    validate_config(cfg)
    node = cfg.get("table1") or {}
    methods = list(node.get("methods") or METHODS)
    seeds = [int(s) for s in (node.get("seeds") or [0])]
    bad = [m for m in methods if m not in METHODS]
    if bad or not seeds:
        raise ConfigError(f"table1: unknown method(s) {bad} or no seeds")
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    record, truth = build_record(cfg.get("data") or {})
    if truth is None:
        raise ConfigError("table1 needs a simulated record with known parameters (data=simulated)")
    tracker = make_tracker(cfg, project_root)
    ev = cfg.get("evaluator") or {}
    show = bool(cfg.get("progress", True))
    runs = []
    t0 = time.perf_counter()
    with ray_session(ev), tracker.run("table1", tags={"job": "table1"}):
        tracker.log_params(flat_config(cfg))
        for method in methods:
            for seed in seeds:
                kw = identify_kwargs({**cfg, "seed": seed}, run_dir / f"{method}_seed{seed}", False)
                (run_dir / f"{method}_seed{seed}").mkdir(exist_ok=True)
                with tracker.run(f"{method}_seed{seed}", tags={"method": method, "seed": seed}, nested=True) as child:
                    curve = RmseCurve(record, on_point=curve_logger(tracker, child.run_id))  # comparable curves
                    res = identify(record, method=method, make_evaluator=evaluator_factory(ev),
                                   progress=lambda total, desc, m=method, s=seed: console.progress(
                                       total, f"{m} seed {s} {desc}", enabled=show),
                                   on_stage=lambda st: stage_child_run(tracker, st, truth), curve=curve, **kw)
                    tracker.log_metrics({"fitness": res.fitness, "rmse_m": res.rmse_m, "rmse_um": 1e6 * res.rmse_m,
                                         "n_simulations": res.n_simulations, "seconds": res.seconds})
                runs.append({"method": method, "seed": seed, "result": res})
        header, rows, summary_header, summary = _tables(runs, truth)
        md = ("## Identified parameters (median over seeds; % error = |A − B| / A)\n\n"
              + console.markdown_table(header, rows)
              + "\n\n## Runs\n\n" + console.markdown_table(summary_header, summary) + "\n")
        atomic_write_text(run_dir / "table1.md", md)
        console.write_csv_table(run_dir / "table1.csv", header, rows)
        console.write_csv_table(run_dir / "table1_runs.csv", summary_header, summary)
        pct = {f"{m}": np.array([r[3 + 2 * k] for r in rows], float) for k, m in enumerate(methods)}
        fig = figures.parameter_errors(list(P.PARAM_NAMES), pct, threshold=2.0, logy=True)
        figures.save(fig, run_dir / "table1_errors.png")
        report = {"job": "table1", "methods": methods, "seeds": seeds, "wall_seconds": time.perf_counter() - t0,
                  "runs": [{"method": r["method"], "seed": r["seed"], **r["result"].to_dict()} for r in runs],
                  "truth": {n: float(truth[i]) for i, n in enumerate(P.PARAM_NAMES)}, "config": jsonable_config(cfg),
                  "code": code_version()}
        path = atomic_write_json(run_dir / "result.json", report)
        for f in ("table1.md", "table1.csv", "table1_runs.csv", "table1_errors.png", "result.json"):
            tracker.log_artifact(run_dir / f)
        best = {m: min(1e6 * r["result"].rmse_m for r in runs if r["method"] == m) for m in methods}
        tracker.set_tags({"mlflow.note.content": f"Table 1 on {record.name}: {', '.join(methods)} × seeds "
                          f"{', '.join(map(str, seeds))}; best RMS error " +
                          ", ".join(f"{m} {v:.4g} µm" for m, v in best.items())})
        print(md)
    return Path(path).resolve()


def _tables(runs: list[dict], truth: np.ndarray):
    """(header, rows) of the parameter table (medians over seeds, % errors) and (header, rows) of the runs."""
    methods = list(dict.fromkeys(r["method"] for r in runs))
    header = ["parameter", "unit", "feasible domain", "assigned (A)"]
    for m in methods:
        header += [f"{m} (median)", f"% error {m}"]
    rows = []
    for i, spec in enumerate(P.PARAMS):
        row = [spec.name, spec.unit, f"{spec.lower:g} – {spec.upper:g}", spec.assigned if truth is None else float(truth[i])]
        for m in methods:
            vals = np.array([r["result"].theta[i] for r in runs if r["method"] == m])
            med = float(np.median(vals))
            row += [med, float(np.median([console.pct_error(float(truth[i]), v) for v in vals]))]
        rows.append(row)
    summary_header = ["method", "seed", "fitness", "RMS error (µm)", "converged generation (per stage)",
                      "run time (s)"]
    summary = [[r["method"], r["seed"], r["result"].fitness, r["result"].rmse_m * 1e6,
                "/".join(str(s.converged_generation) for s in r["result"].stages), r["result"].seconds]
               for r in runs]
    return header, rows, summary_header, summary
