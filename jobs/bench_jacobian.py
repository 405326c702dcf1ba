"""Benchmark: one Jacobian of x_B by forward differences against forward sensitivities
(:func:`toggle_id.simulate.simulate_sensitivities`), on the PRECISE tier (DOPRI5) and on its stiff fallback (Rodas4),
with each one's error. ``python -m jobs.bench_jacobian [--repeat 5] [--json FILE]``; figures, never timed assertions.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from jobs.bench import _write_json, near_assigned
from toggle_id.kernels import slots as K
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, PRECISE_STIFF, extend, simulate, simulate_sensitivities


def jacobian_rows(repeat: int) -> list[dict]:
    """One Jacobian of x_B on the 5-s record near the assigned values, w.r.t. the 15 parameters and w.r.t. those and
    10 effect parameters (5 of them on), on the PRECISE tier (DOPRI5) and on its stiff fallback (Rodas4): forward
    differences (one batched simulation of p + 1 rows, numba threads) against forward sensitivities
    (:func:`toggle_id.simulate.simulate_sensitivities`, one thread and two), interleaved; medians, and each one's
    worst column error against the nearest of central differences at three steps."""
    rec = Record.from_sweep("simulation")
    theta = extend(near_assigned(1, rel=0.05, seed=9))[0]
    for slot, value in ((K.TAU_C, 0.05), (K.C_B, 20.0), (K.F_LOAD, 3.0), (K.A_COG, 0.02), (K.K3, 1e12)):
        theta[slot] = value
    sets = {"15 parameters": list(range(15)),
            "25 (15 + 10 of effects)": list(range(15)) + [K.TAU_C, K.F_S, K.V_S, K.C_B, K.A_COG, K.N_COG, K.PHI_COG,
                                                          K.F_LOAD, K.K3, K.X_OFF]}
    rows = []
    for tier_name, tier in (("DOPRI5", PRECISE), ("Rodas4", PRECISE_STIFF)):
        for label, slots in sets.items():
            refs = []  # central differences at three steps: too short drowns in the integrator's noise, too long
            for rel in (1e-5, 1e-3, 1e-2):  # in curvature (n_cog's fast phase), and which wins differs by column
                h_ref = np.array([rel * abs(theta[c]) if theta[c] != 0 else 10 * rel for c in slots])
                T = np.repeat(theta[None], 2 * len(slots), axis=0)
                T[0::2, slots] += np.diag(h_ref)
                T[1::2, slots] -= np.diag(h_ref)
                R = simulate(T, rec, tier, parallel=True).x_B
                refs.append((R[0::2] - R[1::2]) / (2 * h_ref[:, None]))
            h = 1e-4 * np.maximum(np.abs(theta[slots]), 1e-3)

            def forward(tier=tier, slots=slots, h=h):
                X = np.repeat(theta[None], len(slots) + 1, axis=0)
                X[1:, slots] += np.diag(h)
                Y = simulate(X, rec, tier, parallel=True).x_B
                return (Y[1:] - Y[0]) / h[:, None]

            ways = {"forward differences, parallel": forward,
                    "sensitivities, 1 thread":
                        lambda tier=tier, slots=slots: simulate_sensitivities(theta, rec, tier, slots, threads=1).dx,
                    "sensitivities, 2 threads":
                        lambda tier=tier, slots=slots: simulate_sensitivities(theta, rec, tier, slots, threads=2).dx}
            times: dict[str, list[float]] = {k: [] for k in ways}
            err: dict[str, float] = {}
            for fn in ways.values():  # warm-up: compilation or cache load
                fn()
            for _ in range(repeat):
                for k, fn in ways.items():
                    t0 = time.perf_counter()
                    D = fn()
                    times[k].append(time.perf_counter() - t0)
                    err[k] = _worst_error(D, refs)
            for k in ways:
                rows.append({"case": f"{tier_name}, {label}: {k}", "n": repeat, "median_s": float(np.median(times[k])),
                             "times_s": times[k], "max_rel_error": err[k]})
    return rows


def _worst_error(D: np.ndarray, refs: list[np.ndarray]) -> float:
    """The worst column's relative distance to the nearest of the reference differences; columns the record does
    not see (v_s with F_s at 0: every reference below 1e-12 of the largest column) are left out."""
    scale = np.max([np.linalg.norm(r, axis=1) for r in refs], axis=0)
    on = scale > 1e-12 * scale.max()
    err = np.min([np.linalg.norm(D - r, axis=1) / np.maximum(np.linalg.norm(r, axis=1), 1e-300) for r in refs],
                 axis=0)
    return float(np.max(err[on]))


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="timed repeats (median)")
    ap.add_argument("--json", type=str, default=None, help="also write the table as JSON")
    args = ap.parse_args(argv)
    rows = jacobian_rows(args.repeat)
    print(f"{'case':66s} {'runs':>4s} {'median s':>9s}  worst column's error vs central differences")
    for r in rows:
        print(f"{r['case']:66s} {r['n']:4d} {r['median_s']:9.4f}  {r['max_rel_error']:.2e}")
    print("5-s record (the simulation sweep), near the assigned values; medians; other jobs on the machine count")
    _write_json(args.json, rows)
    return rows


if __name__ == "__main__":
    main()
