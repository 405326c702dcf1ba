"""Identifiability of the toggle plant (issue 4): polish to the noise floor, interval coverage, null directions."""
from __future__ import annotations

import numpy as np
import pytest

from toggle_id import params as P
from toggle_id.polish import polish
from toggle_id.problem import FitProblem
from toggle_id.record import Record
from toggle_id.sensitivity import identifiability_report
from toggle_id.simulate import PRECISE, simulate

DURATION = 1.5  # s: free motion, impact and 1.1 s of clamping
FIXED = ("K_i", "J_m")  # exact symmetries of x_B: (K_i, λ_d, K_t) scaling and m_C + J_m·Z²
FREE = tuple(n for n in P.PARAM_NAMES if n not in FIXED)


def _record(noise: float, seed: int, duration: float = DURATION) -> tuple[Record, np.ndarray]:
    rec = Record.from_sweep("simulation", duration=duration)
    clean = simulate(P.ASSIGNED[None], rec, PRECISE).x_B[0]
    rec.x_B = clean + noise * np.random.default_rng(seed).standard_normal(rec.n)
    return rec, clean


def _fit(rec: Record, start_rel: float, seed: int) -> tuple[FitProblem, np.ndarray]:
    prob = FitProblem(rec, FREE, P.ASSIGNED, (0, rec.n), PRECISE)
    x_true = prob.x0()
    x0 = x_true * (1 + start_rel * np.random.default_rng(100 + seed).uniform(-1, 1, x_true.size))
    lo, hi = P.bounds(FREE)
    res = polish(lambda x: prob.residuals(x[None], PRECISE)[0], x0, lo, hi, max_nfev=200)
    return prob, res.x


def test_noise_free_polish_reaches_far_below_a_micrometre():
    """Without noise the polish ends far below a micrometre, and each parameter the report calls identifiable
    at 1 µm of noise lies within a quarter of its 95 % interval's half-width of the truth: what is left of the
    start's error lies along the directions the record does not determine. (Measured: stepping freely, as the
    precise tier does on this continuous sweep, 3.8e-3 µm, λ_d alone identifiable; with stops at the samples,
    ``stops="all"``, 2.5e-5 µm, and B_m, D and K_l identifiable too, together 0.56 % off: 0.07 half-widths.)"""
    rec, _ = _record(0.0, 0)
    prob, x = _fit(rec, 0.02, 0)
    rms = float(np.sqrt(prob.sse(x[None], PRECISE)[0] / rec.n))
    assert rms < 0.05e-6, rms
    rep = identifiability_report(prob, x, noise_var=(1e-6) ** 2)
    ident = [n for n, ok in rep["identifiable"].items() if ok]
    assert ident, "the report calls nothing identifiable"
    truth, fitted = dict(zip(FREE, prob.x0())), dict(zip(FREE, x))
    for n in ident:
        lo, hi = rep["ci95"][n]
        assert abs(fitted[n] - truth[n]) < 0.25 * 0.5 * (hi - lo), (n, fitted[n], truth[n], lo, hi)


@pytest.mark.slow
def test_confidence_intervals_cover_the_truth():
    hits, total = 0, 0
    for seed in range(20):
        rec, _ = _record(1e-6, seed)
        prob, x = _fit(rec, 0.01, seed)
        rep = identifiability_report(prob, x)
        truth = dict(zip(FREE, prob.x0()))
        for n, ci in rep["ci95"].items():
            if ci is not None:
                total += 1
                hits += ci[0] <= truth[n] <= ci[1]
    assert total >= 20
    assert hits / total >= 0.85, (hits, total)


def test_moving_along_a_null_direction_leaves_x_B_unchanged():
    rec, _ = _record(1e-6, 1)
    names = P.PARAM_NAMES
    prob = FitProblem(rec, names, P.ASSIGNED, (0, rec.n), PRECISE)
    rep = identifiability_report(prob, prob.x0(), noise_var=(1e-6) ** 2)
    assert rep["null_directions"], "no null direction found for the 15-parameter problem"
    d = np.array(rep["null_directions"][0])
    x0 = prob.x0()
    moved = x0 * np.exp(0.05 * d)  # 5 % along the direction in log space
    y0 = simulate(x0[None], rec, PRECISE).x_B[0]
    y1 = simulate(moved[None], rec, PRECISE).x_B[0]
    assert np.sqrt(np.mean((y1 - y0) ** 2)) < 1e-6  # below the noise level
    # while a random direction of the same size moves it far more
    r = np.random.default_rng(0).standard_normal(d.size)
    y2 = simulate((x0 * np.exp(0.05 * r / np.linalg.norm(r)))[None], rec, PRECISE).x_B[0]
    assert np.sqrt(np.mean((y2 - y0) ** 2)) > 1e-5


@pytest.mark.slow
def test_intervals_cover_the_truth_when_the_noise_is_loud_at_speed():
    """The paper's 5-s sweep with noise whose σ grows with slider B's speed (0.3 + |ẋ_B|/mean|ẋ_B|, rms 1 µm):
    intervals that take one noise variance (the report's classical covariance, ``cov_log``) miss the truth far more
    often than 5 %; the report's own, each variance no smaller than the HC3 sandwich's, keep their level (measured,
    20 draws: 47 intervals, classical 0.77, robust 0.98)."""
    hits, classical, total = 0, 0, 0
    for seed in range(20):
        rec, clean = _record(0.0, seed, 5.0)
        v = np.abs(np.gradient(clean, rec.t))
        level = 0.3 + v / v.mean()
        rec.x_B = clean + 1e-6 * level / np.sqrt(np.mean(level ** 2)) * np.random.default_rng(seed).standard_normal(
            rec.n)
        prob, x = _fit(rec, 0.01, seed)
        rep = identifiability_report(prob, x)
        assert rep["covariance"].startswith("classical and HC3")
        truth = dict(zip(FREE, prob.x0()))
        for i, (n, ci) in enumerate(rep["ci95"].items()):
            if ci is not None and rep["log_mask"][n]:
                total += 1
                hits += ci[0] <= truth[n] <= ci[1]
                classical += abs(np.log(truth[n] / rep["values"][n])) <= rep["quantile"] * rep["cov_log"][i][i] ** 0.5
    print(f"\n[intervals, noise loud at speed] {total} intervals: classical {classical / total:.2f}, "
          f"robust {hits / total:.2f}")
    assert total >= 20
    assert hits / total >= 0.85, (hits, total)
    assert classical / total <= hits / total - 0.1, (classical, hits, total)
