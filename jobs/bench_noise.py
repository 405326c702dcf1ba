"""Benchmark: how well the noise model's estimators whiten the noises a record may carry.

For each noise (white, AR(1) ρ = 0.5 and 0.9, the adversarial set's resonant AR(2) and its 50-Hz tone, 5001 samples
of 1 µm) and each estimator of :func:`toggle_id.discovery.noise.fit_noise` (Yule–Walker, Burg), over independent
draws: the order BIC chooses, the coefficients' distance to the truth (AR noises), how often a Ljung–Box test
(20 lags) rejects the prewhitened residual at 1 %, and how often the prewhitened F-test of a constant (a sensor
offset) and of a ramp (a drift) fires at 1 % on pure noise — what the loop's score tests and F-tests rest on. A
whitened residual that is still coloured makes every such test over-confident. Prints a table (and ``--json``).

    python -m jobs.bench_noise [--draws 100] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from jobs.adversarial_set import AR2_HZ, AR2_RADIUS, disturbance
from toggle_id.discovery.noise import METHODS, fit_noise, whitened_sse
from toggle_id.discovery.stats import f_test
from toggle_id.record import ar1_noise
from toggle_id.residuals import ljung_box

N, SIGMA, LAGS, ALPHA = 5001, 1e-6, 20, 0.01
T = np.arange(N) * 1e-3
#: AR coefficients of the noises that have them (the truth the estimates are measured against)
TH2 = 2 * np.pi * AR2_HZ / 1000.0
TRUTH = {"AR(1) ρ 0.5": (0.5,), "AR(1) ρ 0.9": (0.9,),
         "resonant AR(2), 20 Hz": (2 * AR2_RADIUS * math.cos(TH2), -AR2_RADIUS ** 2)}


def draw(kind: str, seed: int) -> np.ndarray:
    """One record's noise (m)."""
    rng = np.random.default_rng(seed)
    if kind == "white":
        return SIGMA * rng.standard_normal(N)
    if kind.startswith("AR(1)"):
        return ar1_noise(N, SIGMA, TRUTH[kind][0], rng)
    if kind.startswith("resonant"):
        return disturbance("ar2", T, seed)
    if kind.startswith("50-Hz"):
        return disturbance("tone", T, seed)
    raise ValueError(kind)


KINDS = ("white", "AR(1) ρ 0.5", "AR(1) ρ 0.9", "resonant AR(2), 20 Hz", "50-Hz tone + white")


def f_test_p(nm, r: np.ndarray, x: np.ndarray) -> float:
    """p-value of the prewhitened F-test of the regressor ``x`` on the noise ``r``, as the loop compares nested
    models (:func:`toggle_id.discovery.stats.f_test` on whitened SSEs)."""
    xw, rw = nm.whiten(x), nm.whiten(r)
    beta = float(xw @ rw) / float(xw @ xw)
    sse0, sse1 = whitened_sse(nm, np.vstack([r, r - beta * x]))
    return f_test(float(sse0), float(sse1), 1, N, 1 + nm.order)[1]


def run(draws: int) -> list[dict]:
    rows = []
    ramp = (T - T.mean()) / np.ptp(T)
    for kind in KINDS:
        for method in METHODS:
            orders, errs, lb, off, dr = [], [], [], [], []
            for k in range(draws):
                r = draw(kind, 20_000 + k)
                nm = fit_noise(r, method=method)
                orders.append(nm.order)
                if kind in TRUTH:
                    a = np.zeros(max(nm.order, len(TRUTH[kind])))
                    a[:nm.order] = nm.a
                    t = np.zeros_like(a)
                    t[:len(TRUTH[kind])] = TRUTH[kind]
                    errs.append(float(np.max(np.abs(a - t))))
                lb.append(not ljung_box(nm.whiten(r)[nm.order:], LAGS, ALPHA, nm.order)["white"])
                off.append(f_test_p(nm, r, np.ones(N)) < ALPHA)
                dr.append(f_test_p(nm, r, ramp) < ALPHA)
            rows.append({"noise": kind, "method": method, "draws": draws, "median_order": float(np.median(orders)),
                         "coefficient_error_median": float(np.median(errs)) if errs else None,
                         "ljung_box_rejects": float(np.mean(lb)), "offset_false_alarms": float(np.mean(off)),
                         "drift_false_alarms": float(np.mean(dr))})
    return rows


def table(rows: list[dict]) -> str:
    out = ["| noise | estimator | order (median) | coefficients off by (median, max over lags) | Ljung–Box rejects "
           "the whitened residual at 1 % | offset F-test fires at 1 % | drift F-test fires at 1 % |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        err = "–" if r["coefficient_error_median"] is None else f"{r['coefficient_error_median']:.3g}"
        out.append(f"| {r['noise']} | {r['method']} | {r['median_order']:g} | {err} | {r['ljung_box_rejects']:.1%} | "
                   f"{r['offset_false_alarms']:.1%} | {r['drift_false_alarms']:.1%} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m jobs.bench_noise", description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=100, help="independent draws of each noise (default 100)")
    ap.add_argument("--json", type=Path, help="also write the rows to this file")
    args = ap.parse_args(argv)
    if args.draws < 1:
        print(f"error: --draws must be at least 1, got {args.draws}", file=sys.stderr)
        return 2
    rows = run(args.draws)
    print(f"{args.draws} draws of {N} samples per noise; tests at {ALPHA:.0%}")
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
