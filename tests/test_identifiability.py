"""Tests of toggle_id.identifiability on toy models with known answers."""
from __future__ import annotations

import json

import numpy as np
import pytest

from toggle_id.errors import ConfigError, DataError
from toggle_id.identifiability import analyze, fd_jacobian, format_table, log_jacobian
from toggle_id.polish import polish

T = np.linspace(0.0, 5.0, 50)


def _same_up_to_sign(u: np.ndarray, v: np.ndarray, atol: float) -> bool:
    return bool(min(np.max(np.abs(u - v)), np.max(np.abs(u + v))) < atol)


# (a) linear in log(theta) with one collinear direction ------------------------------------------------
def _collinear_design(m: int = 80, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((m, 4))
    a[:, 2] = a[:, 0] - a[:, 1]  # A · (1, -1, -1, 0) = 0
    return a


def test_linear_in_log_collinear_direction_found():
    a = _collinear_design()
    theta = np.array([2.0, 0.5, 3.0, 7.0])
    names = ["p0", "p1", "p2", "p3"]
    rng = np.random.default_rng(2)
    y = a @ np.log(theta) + 0.01 * rng.standard_normal(a.shape[0])
    # least-squares fit in log space (minimum norm), residual at the fit
    u_hat = np.linalg.lstsq(a, y, rcond=None)[0]
    theta_hat = np.exp(u_hat)
    residual = a @ u_hat - y
    np.testing.assert_allclose(fd_jacobian(lambda th: a @ np.log(th), theta_hat), a, atol=1e-8)
    rep = analyze(a, residual, names, theta_hat)
    assert rep.rank == 3 and rep.practical_rank == 3
    assert len(rep.null_directions) == 1 and rep.null_kinds == ["numerical"]
    assert _same_up_to_sign(rep.null_directions[0], np.array([1.0, -1.0, -1.0, 0.0]) / np.sqrt(3), 1e-8)
    assert rep.null_combinations == ["p0^1 · p1^-1 · p2^-1"]
    d = rep.to_dict()
    assert d["ci95"]["p0"] is None and d["ci95"]["p1"] is None and d["ci95"]["p2"] is None
    assert d["std_errors"]["p2"] is None
    assert d["identifiable"] == {"p0": False, "p1": False, "p2": False, "p3": True}
    low, high = d["ci95"]["p3"]
    assert low < 7.0 < high and high / low < 1.1
    assert d["noise_std"] == pytest.approx(0.01, rel=0.25)
    assert d["dof"] == a.shape[0] - 3


def test_practically_non_identifiable_direction():
    # two well-determined directions and one that the data barely see
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.standard_normal((60, 3)))
    v, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    s = np.array([10.0, 5.0, 0.02])
    jac = q @ np.diag(s) @ v.T
    residual = 0.1 * rng.standard_normal(60)
    rep = analyze(jac, residual, ["a", "b", "c"], np.ones(3), noise_var=0.01)
    assert rep.rank == 3 and rep.practical_rank == 2
    assert rep.null_kinds == ["practical"]
    assert rep.null_halfwidths[0] == pytest.approx(1.959964 * 0.1 / 0.02, rel=1e-6)
    assert _same_up_to_sign(rep.null_directions[0], v[:, 2], 1e-10)
    # std errors include the weak direction (no exact null direction): the honest, wide uncertainty
    std_u = 0.1 * np.sqrt(((v / s[None, :]) ** 2).sum(axis=1))
    np.testing.assert_allclose(rep.std_u, std_u, rtol=1e-10)
    # a parameter is flagged exactly when its interval is wider than a factor e
    np.testing.assert_array_equal(rep.identifiable, 1.959964 * std_u <= 1.0)
    # a's component along the weak direction is only 0.024: 0.024 · 9.8 < 1, so a stays identifiable
    assert abs(v[0, 2]) < 0.03 and rep.identifiable.tolist() == [True, False, False]
    assert rep.ci95[0] is not None and rep.ci95[1] is None and rep.ci95[2] is None


# (b) coverage of the confidence intervals ------------------------------------------------------------
def _decay(p: np.ndarray) -> np.ndarray:
    a, b, c = p
    return a * np.exp(-b * T) + c


def test_ci_coverage_exponential_decay():
    truth = np.array([2.0, 0.8, 0.5])
    sigma = 0.05
    rng = np.random.default_rng(1234)
    hits = np.zeros(3)
    n_rep = 40
    for _ in range(n_rep):
        y = _decay(truth) + sigma * rng.standard_normal(T.shape)
        res = polish(lambda p: _decay(p) - y, truth * 1.3, [0.0] * 3, [10.0] * 3)
        rep = analyze(res.jac_log(), res.residual, ["a", "b", "c"], res.x, n_params_fitted=3)
        assert rep.identifiable.all()
        for i, ci in enumerate(rep.ci95):
            hits[i] += ci[0] <= truth[i] <= ci[1]
    coverage = hits / n_rep
    assert np.all((coverage >= 0.8) & (coverage <= 1.0)), coverage


# (e) a true scaling symmetry y = (a·b)·f(t) -----------------------------------------------------------
def _sym(p: np.ndarray) -> np.ndarray:
    a, b, k = p
    return a * b * np.exp(-k * T)


def test_scaling_symmetry_null_direction_leaves_output_unchanged():
    x = np.array([3.0, 0.4, 0.7])
    jac = fd_jacobian(_sym, x, rel_step=1e-5)
    residual = 1e-3 * np.random.default_rng(4).standard_normal(T.shape)
    rep = analyze(jac, residual, ["a", "b", "k"], x)
    assert rep.rank == 2
    d = rep.null_directions[0]
    assert _same_up_to_sign(d, np.array([1.0, -1.0, 0.0]) / np.sqrt(2), 1e-6)
    assert rep.null_combinations == ["a^1 · b^-1"]
    assert rep.identifiable.tolist() == [False, False, True]
    for step in (-1.0, 0.3, 2.0):
        moved = x * np.exp(step * d)
        np.testing.assert_allclose(_sym(moved), _sym(x), rtol=1e-6, atol=1e-12)
    # whereas moving along an identifiable direction does change it
    assert np.max(np.abs(_sym(x * np.exp(0.3 * rep.vt[0])) - _sym(x))) > 1e-2


# helpers, coordinates, serialisation, errors ---------------------------------------------------------
def test_log_jacobian_and_fd_agree_with_linear_coordinates_and_vectorized():
    x = np.array([2.0, 0.8, -0.3])  # third parameter is an offset (may be negative)

    def f(p):
        return p[0] * np.exp(-p[1] * T) + p[2]

    jphys = np.column_stack([np.exp(-x[1] * T), -x[0] * T * np.exp(-x[1] * T), np.ones_like(T)])
    mask = [True, True, False]
    expected = log_jacobian(jphys, x, mask)
    np.testing.assert_allclose(expected[:, 2], 0.3 * np.ones_like(T))  # scale = |x|
    jfd = fd_jacobian(f, x, 1e-5, mask)
    np.testing.assert_allclose(jfd, expected, rtol=1e-7, atol=1e-9)
    jvec = fd_jacobian(lambda P: np.stack([f(p) for p in P]), x, 1e-5, mask, vectorized=True)
    np.testing.assert_array_equal(jvec, jfd)
    with pytest.raises(ConfigError, match="theta > 0"):
        fd_jacobian(f, x, 1e-5, True)


def test_offset_parameter_gets_symmetric_interval():
    x = np.array([2.0, 0.8, -0.3])
    jphys = np.column_stack([np.exp(-x[1] * T), -x[0] * T * np.exp(-x[1] * T), np.ones_like(T)])
    mask = [True, True, False]
    residual = 0.01 * np.random.default_rng(7).standard_normal(T.shape)
    rep = analyze(log_jacobian(jphys, x, mask), residual, ["a", "b", "off"], x, log_mask=mask)
    low, high = rep.ci95[2]
    assert high - x[2] == pytest.approx(x[2] - low) and low < x[2] < high
    assert rep.ci95[0][0] > 0.0  # log interval stays positive


def test_to_dict_is_json_and_table_readable():
    x = np.array([3.0, 0.4, 0.7])
    rep = analyze(fd_jacobian(_sym, x), 1e-3 * np.ones_like(T), ["a", "b", "k"], x)
    d = rep.to_dict()
    text = json.dumps(d, allow_nan=False)
    back = json.loads(text)
    for key in ("param_order", "singular_values", "rank", "practical_rank", "null_directions",
                "null_combinations", "std_errors", "ci95", "identifiable", "noise_std"):
        assert key in back
    assert back["null_halfwidths"] == [None]  # numerical null: infinite half-width → null
    table = format_table(rep)
    assert "a^1 · b^-1" in table and "NO" in table and "k " in table
    assert len(table.splitlines()) == 2 + 3 + 1 + 1


def test_too_few_data_points_gives_unknown_noise_not_crash():
    jac = np.array([[1.0, 0.0], [0.0, 2.0]])
    rep = analyze(jac, np.zeros(2), ["a", "b"], [1.0, 1.0])
    assert rep.noise_std is None and rep.ci95 == [None, None] and rep.rank == 2
    assert rep.identifiable.all()  # structurally identifiable; intervals unknown
    json.dumps(rep.to_dict(), allow_nan=False)


def test_bad_input():
    jac = np.ones((5, 2))
    with pytest.raises(DataError, match="b"):
        analyze(np.column_stack([np.ones(5), [1, 2, np.nan, 4, 5]]), np.zeros(5), ["a", "b"], [1.0, 1.0])
    with pytest.raises(ConfigError, match="residual"):
        analyze(jac, np.zeros(4), ["a", "b"], [1.0, 1.0])
    with pytest.raises(ConfigError, match="shape"):
        analyze(jac, np.zeros(5), ["a", "b", "c"], [1.0, 1.0, 1.0])
    with pytest.raises(ConfigError, match="theta > 0"):
        analyze(jac, np.zeros(5), ["a", "b"], [1.0, -1.0])


def _coverage(loud: bool, robust: bool, draws: int = 400, m: int = 1000) -> tuple[float, float]:
    """Fraction of (1 − 0.05) intervals of the slope that hold the truth, and their median width, for a straight
    line fitted by least squares; noise σ ∝ 0.05 + (2|t − ½|)² (loud at the ends, where the slope's sensitivity
    is) or constant, of the same rms."""
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 1.0, m)
    X = np.column_stack([np.ones(m), t])
    sd = 0.05 + (2.0 * np.abs(t - 0.5)) ** 2 if loud else np.ones(m)
    sd = sd / np.sqrt(np.mean(sd ** 2))
    hits, widths = 0, []
    for _ in range(draws):
        y = 1.0 + 2.0 * t + sd * rng.standard_normal(m)
        beta, *_ = np.linalg.lstsq(X, y, rcond=None)
        rep = analyze(X, y - X @ beta, ["a", "b"], beta, log_mask=False, scale=[1.0, 1.0], robust=robust)
        lo, hi = rep.ci95[1]
        hits += lo <= 2.0 <= hi
        widths.append(hi - lo)
    return hits / draws, float(np.median(widths))


def test_robust_intervals_cover_when_the_noise_level_varies_and_match_when_it_does_not():
    """Classical intervals take one noise variance: with the noise loud where the slope is decided they cover
    far less than 95 %; the sandwich-widened ones (``robust=True``) cover about 95 %. Under one variance the
    robust intervals are the classical ones up to the sandwich's scatter (never narrower)."""
    cov_classical, _ = _coverage(loud=True, robust=False)
    cov_robust, _ = _coverage(loud=True, robust=True)
    assert cov_classical < 0.87, cov_classical  # measured 0.82
    assert 0.92 <= cov_robust <= 0.98, cov_robust  # measured 0.94
    cov_white, w_classical = _coverage(loud=False, robust=False)
    cov_white_r, w_robust = _coverage(loud=False, robust=True)
    assert 0.92 <= cov_white <= 0.98 and 0.92 <= cov_white_r <= 0.98
    assert 1.0 <= w_robust / w_classical <= 1.1, (w_robust, w_classical)


def test_robust_report_names_its_covariance_and_ratio():
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 1.0, 300)
    X = np.column_stack([np.ones_like(t), t])
    r = (0.05 + 3.0 * t ** 2) * rng.standard_normal(t.size)
    r = r - X @ np.linalg.lstsq(X, r, rcond=None)[0]
    d = analyze(X, r, ["a", "b"], [1.0, 2.0], log_mask=False, scale=[1.0, 1.0], robust=True).to_dict()
    assert d["covariance"].startswith("classical and HC3")
    assert d["hc_ratio"]["b"] > 1.5
    plain = analyze(X, r, ["a", "b"], [1.0, 2.0], log_mask=False, scale=[1.0, 1.0]).to_dict()
    assert plain["covariance"] == "classical" and plain["hc_ratio"] is None
    assert d["std_log"]["b"] > plain["std_log"]["b"]
