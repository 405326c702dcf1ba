"""Wall-clock benchmark of the discover job on a 5-s record (the issue's budget: within 5 minutes on 2 cores).

``python -m jobs.bench_discover [--repeat N] [--json PATH] [OVERRIDE ...]`` composes ``+experiment=discover`` with
the Hydra overrides given after the default ones (a simulated 5-s record with motor-side Coulomb friction,
``data.effects.tau_c=5``; an override of the same key wins, e.g. ``data.effects.tau_c=0`` for a record without it),
runs the whole job N times — nominal two-stage RGA + polish, the discovery loop, figures, MLflow logging — in a
temporary directory with its own MLflow store, and prints the wall time of each run, the median, and what the
loop found. The first run includes Ray's start and numba's cache load; every run includes them, as a user's would.
Then where the time went (medians over the runs): the job split into the nominal fit, the loop and the rest
(start-up, figures, MLflow), and the loop into its phases (:mod:`toggle_id.discovery.timing`).
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from jobs._cli import CONF_DIR, guarded

DEFAULT_OVERRIDES = ["data.effects.tau_c=5.0"]


def compose(overrides: list[str], store: Path) -> dict:
    """The discover job's configuration with ``overrides``; tracking into ``store``; no progress bars."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = hydra_compose(config_name="config", overrides=["+experiment=discover", "progress=false",
                                                             f"tracking.uri=sqlite:///{store / 'mlflow.db'}",
                                                             f"run_dir={store}",
                                                             *overrides])
    return OmegaConf.to_container(cfg, resolve=True)


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=1, help="timed runs (median)")
    ap.add_argument("--json", type=str, default=None, help="also write the runs as JSON")
    ap.add_argument("overrides", nargs="*", help=f"Hydra overrides, applied after {' '.join(DEFAULT_OVERRIDES)}")
    args = ap.parse_args(argv)
    from toggle_id.app.discover import run_discover

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_discover_") as tmp:
        tmp = Path(tmp)
        cfg = guarded(lambda: compose([*DEFAULT_OVERRIDES, *args.overrides], tmp))
        for k in range(args.repeat):
            t0 = time.perf_counter()
            path = guarded(lambda k=k: run_discover(cfg, tmp / f"run{k}", tmp))
            wall = time.perf_counter() - t0
            rep = json.loads(Path(path).read_text(encoding="utf-8"))
            rows.append({"run": k, "wall_s": wall, "n_samples": rep.get("n_samples"),
                         "effects_added": [a["name"] for a in rep["effects_added"]],
                         "rmse_before_um": rep["rmse_before_m"] * 1e6, "rmse_after_um": rep["rmse_after_m"] * 1e6,
                         "loop_s": rep.get("seconds"), "n_simulations": rep.get("n_simulations"),
                         "nominal_s": (rep.get("nominal") or {}).get("seconds_total", 0.0),
                         "phases": rep.get("time_by_phase", [])})
            r = rows[-1]
            print(f"run {k}: {wall:7.1f} s wall (loop {r['loop_s'] or float('nan'):.1f} s, "
                  f"{r['n_simulations']} simulations)  "
                  f"effects {r['effects_added'] or 'none'}  rms {r['rmse_before_um']:.3g} -> {r['rmse_after_um']:.3g} um",
                  flush=True)
    med = statistics.median(r["wall_s"] for r in rows)
    print(f"discover job, {len(rows)} run(s): median wall {med:.1f} s ({med / 60:.2f} min; issue 14 asks 60 s)")
    print(where_the_time_went(rows))
    print("wall-clock figures depend on other jobs on the machine")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1), encoding="utf-8")
    return rows


def where_the_time_went(rows: list[dict]) -> str:
    """The job's wall split into the nominal fit, the loop and the rest, and the loop's phases, the most
    expensive first (medians over ``rows``; a phase a run did not enter counts 0 s there)."""
    med = statistics.median  # (rows is never empty: main has timed at least one run)
    loop = med([r["loop_s"] or 0.0 for r in rows])
    nominal = med([r["nominal_s"] for r in rows])
    rest = med([r["wall_s"] - (r["loop_s"] or 0.0) - r["nominal_s"] for r in rows])
    lines = [f"where the time went (medians): nominal fit {nominal:.1f} s, loop {loop:.1f} s, the rest (start-up, "
             f"figures, MLflow) {rest:.1f} s",
             f"  {'loop phase':<42s} {'seconds':>8s} {'share':>6s} {'simulations':>11s}"]
    names = {p["phase"] for r in rows for p in r["phases"]}
    by = {nm: [next((p for p in r["phases"] if p["phase"] == nm), {"seconds": 0.0, "simulations": 0}) for r in rows]
          for nm in names}
    table = sorted(((nm, med([p["seconds"] for p in ps]), med([p["simulations"] for p in ps]))
                    for nm, ps in by.items()), key=lambda x: -x[1])
    for nm, sec, sims in table:
        if sec >= 0.05 or sims:
            lines.append(f"  {nm:<42s} {sec:8.1f} {sec / loop if loop else 0.0:6.1%} {sims:11.0f}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
