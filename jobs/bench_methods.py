"""Benchmark of the identification methods on one record: success rate, simulations and seconds per method.

``python -m jobs.bench_methods [--fast N] [--two-stage N] [--one-stage N] [--floor-um X] [--out FILE.md]
[--mlflow-uri URI] [OVERRIDE ...]`` runs each method's whole job (``python -m jobs.run +experiment=METHOD
seed=S``, as a user would: Ray start-up, numba's cache, figures and MLflow logging included) for seeds 0…N−1, one
job at a time, on the default record (Table 1, the simulation sweep, 5 s, σ = 1 µm) or on the one the Hydra
overrides describe (e.g. ``data.sweep=experiment``). Per method it prints how many seeds reached the noise floor
(whole-record RMS ≤ ``--floor-um``), the median identification time (``seconds_fit``, the job's start-up, reports
and logging excluded; for the GA methods the identification's own time), the median time to the floor (first point
of the ``best_rmse_um`` curve at or below it), the median simulations and the median whole-job wall time. The jobs
log their runs to one MLflow store (``--mlflow-uri``, default a temporary one), and a ``bench_methods`` run there
holds the table.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_one(method: str, seed: int, overrides: list[str], run_dir: Path, env: dict, timeout: float) -> dict:
    """One whole job; its result.json's figures (or the error)."""
    args = [sys.executable, "-m", "jobs.run", f"+experiment={method}", f"seed={seed}", f"hydra.run.dir={run_dir}",
            "progress=false", *overrides]
    t0 = time.perf_counter()
    proc = subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"method": method, "seed": seed, "error": (proc.stderr.strip().splitlines() or ["?"])[-1],
                "wall_s": wall}
    d = json.loads((run_dir / "result.json").read_text(encoding="utf-8"))
    return {"method": method, "seed": seed, "rmse_um": 1e6 * d["rmse_m"], "wall_s": wall,
            "seconds_fit": d.get("seconds_fit", d.get("seconds_total")), "simulations": d.get("n_simulations"),
            "curve": [(p["seconds"], p["simulations"], 1e6 * p["best_rmse_m"]) for p in d.get("curve") or []],
            "params": d.get("params"), "pct_error": d.get("pct_error")}


def _time_to(curve: list, floor_um: float) -> tuple[float | None, int | None]:
    for sec, sims, rms in curve:
        if rms <= floor_um:
            return sec, sims
    return None, None


def _median(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def table(rows: list[dict], floor_um: float) -> list[str]:
    """Markdown table, one line per method."""
    def f(v, fmt):
        return "–" if v is None else format(v, fmt)

    out = [f"| method | reached RMS ≤ {floor_um:g} µm | median RMS (µm) | median seconds_fit | median time to the floor "
           "(s) | median simulations | median whole job (s) |", "|---|---|---|---|---|---|---|"]
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == method]
        ok = [r for r in mine if "error" not in r]
        reached = [r for r in ok if r["rmse_um"] <= floor_um]
        to_floor = [_time_to(r["curve"], floor_um)[0] for r in reached]
        out.append(f"| {method} | {len(reached)} of {len(mine)} | {f(_median([r['rmse_um'] for r in ok]), '.3f')} | "
                   f"{f(_median([r['seconds_fit'] for r in ok]), '.1f')} | {f(_median(to_floor), '.1f')} | "
                   f"{f(_median([r['simulations'] for r in ok]), '.0f')} | {f(_median([r['wall_s'] for r in mine]), '.1f')} |")
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fast", type=int, default=10, help="seeds of the fast method")
    ap.add_argument("--two-stage", type=int, default=3, help="seeds of the paper's two-stage GA")
    ap.add_argument("--one-stage", type=int, default=2, help="seeds of the paper's one-stage GA")
    ap.add_argument("--floor-um", type=float, default=1.05, help="the noise floor to reach (µm)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per job")
    ap.add_argument("--out", type=str, default=None, help="also write the table (Markdown) and the runs (JSON)")
    ap.add_argument("--mlflow-uri", type=str, default=None, help="MLflow store of the jobs and of the summary")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides of every job (the record, e.g. data.sweep=...)")
    args = ap.parse_args(argv)
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench_methods_") as tmp:
        tmp = Path(tmp)
        uri = args.mlflow_uri or f"sqlite:///{tmp / 'mlflow.db'}"
        env = {**os.environ, "MLFLOW_TRACKING_URI": uri, "PYTHONPATH": str(ROOT)}
        plan = [("fast", args.fast), ("two_stage", args.two_stage), ("one_stage", args.one_stage)]
        for method, n in plan:
            for seed in range(n):
                r = run_one(method, seed, args.overrides, tmp / f"{method}_{seed}", env, args.timeout)
                rows.append(r)
                msg = r.get("error") or (f"rms {r['rmse_um']:.4g} µm, seconds_fit {r['seconds_fit']:.1f}, "
                                         f"{r['simulations']} simulations")
                print(f"{method} seed {seed}: {msg} ({r['wall_s']:.1f} s whole job)", flush=True)
        lines = table(rows, args.floor_um)
        print("\n".join(lines))
        if args.out:
            Path(args.out).write_text("\n".join(lines) + "\n", encoding="utf-8")
            Path(args.out).with_suffix(".json").write_text(json.dumps(rows, indent=1), encoding="utf-8")
        try:
            import mlflow

            mlflow.set_tracking_uri(uri)
            mlflow.set_experiment("toggle-id")
            with mlflow.start_run(run_name="bench_methods " + " ".join(args.overrides)):
                mlflow.set_tag("mlflow.note.content", "identification methods compared: " + ", ".join(
                    f"{m} × {n}" for m, n in plan if n))
                mlflow.log_text("\n".join(lines) + "\n", "bench_methods.md")
                mlflow.log_dict(rows, "bench_methods.json")
        except Exception as err:  # noqa: BLE001 — the figures are printed already; a store that is down is no failure
            print(f"MLflow: the summary was not logged ({err})", file=sys.stderr)
    return rows


if __name__ == "__main__":
    main()
