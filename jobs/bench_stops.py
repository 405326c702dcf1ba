"""Benchmark of the precise integrators with and without steps that stop at the samples (``SolverSettings.stops``).

``python -m jobs.bench_stops [--n 16] [--repeat 5] [--duration 5] [--only TEXT] [--json PATH]`` simulates, side
by side in one run, the precise tier (:data:`~toggle_id.simulate.PRECISE`) and the Jacobian tier
(:data:`~toggle_id.simulate.JACOBIAN`), each with ``stops`` = ``none``, ``sampled`` (the tiers' own: on an input
given by its samples) and ``all``, on 5-s records: the two swept sines given in continuous time (a record
simulated in memory), the same sweeps and the open/close cycling command given by their samples (a record read
from a CSV: the input is linear between samples), and a 0.5-mm screw backlash (the two-body kernel) on the
sampled cycling command (``--only``: the records whose name contains TEXT; ``--duration``: their length in s).
For each it prints

- ``ms/sim``: median wall time per simulation of ``n`` near-assigned individuals on one core;
- ``steps``: the mean number of steps;
- ``max err um``: the largest |x_B| error against a DOPRI5 reference at rtol 1e-13 (the assigned values);
- ``fd noise``: how far the forward-difference columns of the 15 parameters (relative step 1e-4) lie from the
  reference's own forward differences, relative to each column's norm — the median and the worst column.
  That is what a finite-difference Jacobian of the loop's fits is made of: step-selection jitter shows here.

Timings on a shared machine are noisy: compare rows of the same run.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from jobs.bench import with_backlash
from toggle_id.params import ASSIGNED, PARAM_NAMES
from toggle_id.record import Record
from toggle_id.simulate import JACOBIAN, PRECISE, STOPS, SolverSettings, simulate

REFERENCE = SolverSettings(rtol=1e-13, atol_q=1e-15, atol_w=1e-12, atol_i=1e-9, hmax=2e-4, max_steps=5_000_000,
                           method="dopri5", stops="all")
FD_STEP = 1e-4


def records(duration: float = 5.0) -> dict[str, tuple[Record, float]]:
    """The benchmark's records by name, each with its backlash (0: the rigid kernel)."""
    sweep = {name: Record.from_sweep(name, duration) for name in ("simulation", "experiment")}
    return {
        "simulation sweep, continuous": (sweep["simulation"], 0.0),
        "experiment sweep, continuous": (sweep["experiment"], 0.0),
        "simulation sweep, sampled": (Record(t=sweep["simulation"].t, v_in=sweep["simulation"].v_in), 0.0),
        "experiment sweep, sampled": (Record(t=sweep["experiment"].t, v_in=sweep["experiment"].v_in), 0.0),
        "cycling, sampled": (Record.from_cycling(duration=duration), 0.0),
        "cycling, sampled, backlash 0.5 mm": (Record.from_cycling(duration=duration), 5e-4),
    }


def fd_points(theta: np.ndarray) -> np.ndarray:
    """``theta`` (1, p) and, after it, ``theta`` with each of the 15 parameters moved by its forward step."""
    n = len(PARAM_NAMES)
    steps = FD_STEP * np.where(theta[0, :n] != 0.0, np.abs(theta[0, :n]), 1.0)
    T = np.repeat(theta, n + 1, 0)
    T[1 + np.arange(n), np.arange(n)] += steps
    return T


def fd_noise(x: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per parameter: ‖forward difference − the reference's‖ / ‖the reference's‖ (rows as :func:`fd_points`)."""
    cols, ref_cols = x[1:] - x[0], reference[1:] - reference[0]
    return np.linalg.norm(cols - ref_cols, axis=1) / np.linalg.norm(ref_cols, axis=1)


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=16, help="near-assigned individuals timed per case")
    ap.add_argument("--repeat", type=int, default=5, help="timed repeats (median)")
    ap.add_argument("--duration", type=float, default=5.0, help="record length in s")
    ap.add_argument("--only", type=str, default="", help="only the records whose name contains this text")
    ap.add_argument("--json", type=str, default=None, help="also write the table as JSON")
    args = ap.parse_args(argv)
    every = records(args.duration)
    chosen = {k: v for k, v in every.items() if args.only in k}
    if not chosen:
        raise SystemExit(f"bench_stops: no record name contains {args.only!r}; names: {', '.join(every)}")
    rng = np.random.default_rng(1)
    tiers = {"PRECISE": PRECISE, "JACOBIAN": JACOBIAN}
    rows: list[dict] = []
    print(f"{'record':36s} {'tier':9s} {'stops':7s} {'ms/sim':>7s} {'steps':>7s} {'max err um':>10s} "
          f"{'fd noise median':>15s} {'worst':>8s} {'(param)':>9s}")
    for rname, (rec, lash) in chosen.items():
        theta = with_backlash(ASSIGNED[None], lash)
        near = with_backlash(ASSIGNED * (1.0 + 0.1 * rng.uniform(-1.0, 1.0, (args.n, ASSIGNED.size))), lash)
        points = fd_points(theta)
        ref_fd = simulate(points, rec, REFERENCE, parallel=True).x_B
        for tname, base in tiers.items():
            for stops in STOPS:
                s = dataclasses.replace(base, stops=stops,
                                        fallback=dataclasses.replace(base.fallback, stops=stops))
                simulate(near[:2], rec, s)
                times = []
                for _ in range(args.repeat):
                    t0 = time.perf_counter()
                    res = simulate(near, rec, s)
                    times.append((time.perf_counter() - t0) / args.n)
                x = simulate(points, rec, s, parallel=True).x_B
                err = float(np.nanmax(np.abs(x[0] - ref_fd[0])))
                noise = fd_noise(x, ref_fd)
                worst = int(np.argmax(noise))
                r = {"record": rname, "tier": tname, "stops": stops, "ms_per_sim": 1e3 * float(np.median(times)),
                     "times_s": times, "mean_steps": float(np.mean(res.n_steps)), "max_err_um": err * 1e6,
                     "fd_noise_median": float(np.median(noise)), "fd_noise_worst": float(noise[worst]),
                     "fd_noise_worst_param": PARAM_NAMES[worst], "fell_back": int(res.fell_back.sum())}
                rows.append(r)
                print(f"{rname:36s} {tname:9s} {stops:7s} {r['ms_per_sim']:7.2f} {r['mean_steps']:7.0f} "
                      f"{r['max_err_um']:10.2g} {r['fd_noise_median']:15.2g} {r['fd_noise_worst']:8.2g} "
                      f"{r['fd_noise_worst_param']:>9s}", flush=True)
    print("one core per timed simulation; fd noise relative to each column's norm (forward differences, step 1e-4)")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1), encoding="utf-8")
    return rows


if __name__ == "__main__":
    main()
