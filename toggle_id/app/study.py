"""`python -m jobs.run +experiment=identifiability`: what a record can and cannot determine, scenario by scenario.

At the true parameters of a simulated record (no fit needed), the sensitivity analysis of
:mod:`toggle_id.identifiability` is run for each scenario of the configuration: which parameters are free,
which are fixed at known values, which samples count (the whole record, or stage 1's free motion),
whether the measured current i_q is a second output, and which excitations are recorded (``records:
[simulation, experiment]``: the data's record simulated with each sweep, all fitted jointly — multi-experiment).
The result is a table of numerical/practical ranks, identifiable parameters and null combinations (markdown +
JSON), the measured basis of the project's claims.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Mapping

from .. import params as P
from ..checkpoint import atomic_write_json, atomic_write_text
from ..console import markdown_table
from ..errors import ConfigError
from ..plant import GEOMETRY
from ..problem import FitProblem, joint
from ..provenance import code_version
from ..record import SWEEPS
from ..sensitivity import identifiability_report
from ..simulate import PRECISE
from .common import flat_config, jsonable_config, make_tracker
from .records import build_record


def run_study(cfg: Mapping, run_dir: str | Path, project_root: str | Path = ".") -> Path:
    """Run the identifiability analysis of every scenario of ``study.scenarios`` at the truth; write the table
    (``identifiability.md``) and ``result.json``; return the latter's path."""
    node = cfg.get("study") or {}
    scenarios = node.get("scenarios") or []
    if not scenarios:
        raise ConfigError("study.scenarios is empty")
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    record, truth = build_record(cfg.get("data") or {})
    if truth is None:
        raise ConfigError("the identifiability study needs a simulated record with known parameters")
    noise = float((cfg.get("data") or {}).get("noise_m") or 1e-6)
    k_c = record.clamp_index(GEOMETRY.x_B_L)
    by_sweep = {(cfg.get("data") or {}).get("sweep", "simulation"): record}
    rows, out = [], []
    tracker = make_tracker(cfg, project_root)
    t0 = time.perf_counter()
    with tracker.run("identifiability", tags={"job": "identifiability"}):
        tracker.log_params(flat_config(cfg))
        for sc in scenarios:
            name = sc.get("name") or "scenario"
            fixed = set(sc.get("fixed") or [])
            unknown = fixed - set(P.PARAM_NAMES)
            if unknown:
                raise ConfigError(f"study scenario {name}: unknown fixed parameter(s) {sorted(unknown)}")
            names = P.FREE_NAMES if sc.get("window") == "stage1" else P.PARAM_NAMES
            free = tuple(n for n in names if n not in fixed)
            sweeps = sc.get("records") or []
            sweeps = [sweeps] if isinstance(sweeps, str) else list(sweeps)
            recs = [_sweep_record(cfg, by_sweep, s, name) for s in sweeps] or [record]
            windows = [(0, r.clamp_index(GEOMETRY.x_B_L)) if sc.get("window") == "stage1" else (0, r.n)
                       for r in recs]
            window = windows[0]
            w = float(sc.get("i_q_weight") or 0.0)
            prob = joint([FitProblem(r, free, truth, wd, PRECISE, i_q_weight=w) for r, wd in zip(recs, windows)])
            rep = identifiability_report(prob, prob.x0(), noise_var=noise ** 2, robust=False)
            ident = [n for n, ok in rep["identifiable"].items() if ok]
            n_samples = sum(b - a for a, b in windows)
            output = ("x_B + i_q" if w else "x_B") + (f" ({' + '.join(sweeps)})" if sweeps else "")
            rows.append([name, len(free), n_samples, output, rep["rank"],
                         rep["practical_rank"], ", ".join(ident) or "none",
                         "; ".join(rep["null_combinations"][:3]) + (" …" if len(rep["null_combinations"]) > 3 else "")])
            out.append({"scenario": sc, "free": list(free), "window": list(window),
                        "records": [{"name": r.name, "window": list(wd)} for r, wd in zip(recs, windows)],
                        "report": rep})
            tracker.log_metrics({f"{name}.rank": rep["rank"], f"{name}.practical_rank": rep["practical_rank"]})
        header = ["scenario", "free", "samples", "output", "numerical rank", "practical rank", "identifiable",
                  "null combinations (first 3; log-space directions that leave the output unchanged)"]
        md = markdown_table(header, rows) + "\n"
        print(md)
        atomic_write_text(run_dir / "identifiability.md", md)
        path = atomic_write_json(run_dir / "result.json", {"job": "identifiability", "noise_m": noise,
                                                         "clamp_index": k_c, "scenarios": out,
                                                         "seconds": time.perf_counter() - t0,
                                                         "config": jsonable_config(cfg),
                                                         "code": code_version()})
        tracker.log_artifact(run_dir / "identifiability.md")
        tracker.log_artifact(path)
        tracker.set_tags({"mlflow.note.content": f"identifiability study on {record.name}: " + "; ".join(
            f"{r[0]} rank {r[4]} of {r[1]}" for r in rows)})
    return Path(path).resolve()


def _sweep_record(cfg: Mapping, cache: dict, sweep: str, scenario: str):
    """The study's simulated record with the excitation ``sweep`` (same truth, noise and duration)."""
    if sweep not in SWEEPS:
        raise ConfigError(f"study scenario {scenario}: unknown sweep {sweep!r} in records; known: {', '.join(SWEEPS)}")
    if sweep not in cache:
        cache[sweep] = build_record({**(cfg.get("data") or {}), "sweep": sweep})[0]
    return cache[sweep]
