"""The discovery engine's statistics on plain arrays: noise model, prewhitened tests, cross-validation, the
structure test and its localisation — against independent references and known distributions."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import linalg, signal, stats

from toggle_id.discovery.localise import level_basis, locate, noise_level
from toggle_id.discovery.noise import (NoiseModel, autocovariance, fit_noise, start_factor,
                                      stationary_autocovariance, whitened_sse)
from toggle_id.discovery.stats import (
    block_cv,
    compare,
    f_test,
    fold_of,
    lagged_basis,
    out_of_sample,
    piecewise_basis,
    robust_f,
    robust_portmanteau,
    separation,
    structure_test,
    vuong_power,
    vuong,
)
from toggle_id.residuals import ljung_box

N = 5001


def ar1(rho: float, n: int = N, sigma: float = 1.0, seed: int = 0) -> np.ndarray:
    """Stationary AR(1) with marginal σ, generated independently of the module (scipy.signal.lfilter)."""
    rng = np.random.default_rng(seed)
    w = rng.standard_normal(n) * sigma * np.sqrt(1 - rho ** 2)
    zi = np.array([rho * rng.standard_normal() * sigma])
    return signal.lfilter([1.0], [1.0, -rho], w, zi=zi)[0]


def trajectory(n: int = N) -> dict[str, np.ndarray]:
    t = np.arange(n) / 1000.0
    x = 0.02 + 0.015 * (1 - np.cos(2 * np.pi * t / t[-1])) + 0.002 * np.sin(7 * t)
    return {"x_B": x, "xdot_B": np.gradient(x, t), "i_q": 100 * np.sin(3 * t),
            "v_in": 0.05 + 0.01 * np.sin((0.5 + 7.9 * t) * t), "t": t}


# ------------------------------------------------------------------------------------------ noise model
@pytest.mark.parametrize("rho", [0.5, 0.9])
def test_ar1_noise_is_recovered_and_whitened(rho):
    e = ar1(rho, sigma=1e-6, seed=1)
    nm = fit_noise(e)
    assert nm.order >= 1 and nm.a[0] == pytest.approx(rho, abs=0.05)
    assert np.sqrt(nm.sigma2) == pytest.approx(1e-6, rel=0.1)
    assert nm.effective_fraction == pytest.approx((1 - rho) / (1 + rho), rel=0.35)
    w = nm.whiten(e)[nm.order:]
    lag1 = np.corrcoef(w[:-1], w[1:])[0, 1]
    assert abs(lag1) < 3 / np.sqrt(N)
    d = nm.to_dict()
    assert d["kind"].startswith("AR(") and d["effective_samples"] < N


def test_the_robust_order_keeps_the_colour_of_steady_noise_and_finds_none_in_white_noise_loud_at_times():
    """White noise whose level grows steeply with the slider's speed: BIC picks a spurious order in many draws (the
    sample autocorrelations scatter far more than 1/√N; measured 9 of 30), the robust criterion in none; AR(1)
    noise of a steady level keeps BIC's order and coefficient under both."""
    speed = np.abs(trajectory()["xdot_B"])
    level = 0.05 + (speed / speed.mean()) ** 3
    bic = robust = 0
    for seed in range(30):
        e = level * np.random.default_rng(seed).standard_normal(N)
        bic += fit_noise(e).order > 0
        robust += fit_noise(e, robust=True).order > 0
    assert bic >= 5 and robust <= 1, (bic, robust)
    for rho in (0.5, 0.9):
        e = ar1(rho, sigma=1e-6, seed=4)
        nm, nm_r = fit_noise(e), fit_noise(e, robust=True)
        assert nm_r.order == nm.order and nm_r.a[0] == pytest.approx(nm.a[0], abs=1e-12)
        assert "robust" in nm_r.to_dict()["method"] and "robust" not in nm.to_dict()["method"]


def test_white_noise_gives_the_white_model_and_leaves_signals_alone():
    e = np.random.default_rng(2).standard_normal(N)
    nm = fit_noise(e)
    assert nm.white and nm.effective_fraction == 1.0
    x = np.arange(10.0)
    assert nm.whiten(x) is not None and np.array_equal(nm.whiten(x), x)
    assert whitened_sse(nm, e)[0] == pytest.approx(float(e @ e))


def test_autocovariance_matches_the_direct_sum():
    e = np.random.default_rng(3).standard_normal(300)
    c = autocovariance(e, 5)
    d = e - e.mean()
    assert np.allclose(c, [d[: d.size - k] @ d[k:] / d.size for k in range(6)])


def test_burg_recovers_a_sharp_spectral_peak_that_yule_walker_flattens():
    """Resonant AR(2) noise (poles at radius 0.97, 20 Hz at 1 kHz): Burg's lattice finds its two coefficients and
    whitens it; Yule–Walker's biased autocovariance gives a third lag and a residual still coloured (the default is
    unchanged). On AR(1) noise the two agree."""
    r2, th = 0.97, 2 * np.pi * 0.02
    truth = np.array([2 * r2 * np.cos(th), -r2 * r2])
    rng = np.random.default_rng(8)
    e = signal.lfilter([1.0], [1.0, -truth[0], -truth[1]], rng.standard_normal(N + 2000))[2000:]
    nb, ny = fit_noise(e, method="burg"), fit_noise(e)
    assert nb.order == 2 and np.allclose(nb.a, truth, atol=0.01) and nb.method == "burg"
    assert np.all(np.abs(np.roots(nb.filter)) < 1.0)  # stable
    assert ny.method == "yule_walker" and np.max(np.abs(np.r_[ny.a, 0.0][:2] - truth)) > 0.1
    c = autocovariance(e, ny.order)
    assert np.allclose(ny.a, np.linalg.solve(
        [[c[abs(i - j)] for j in range(ny.order)] for i in range(ny.order)], c[1:ny.order + 1]))

    def lag_corr(nm):
        w = nm.whiten(e)[nm.order:]
        return max(abs(np.corrcoef(w[:-k], w[k:])[0, 1]) for k in range(1, 6))
    assert lag_corr(nb) < 3 / np.sqrt(N) < lag_corr(ny)
    assert "Burg" in nb.to_dict()["method"] and "Yule-Walker" in ny.to_dict()["method"]
    a1 = signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(N))
    assert fit_noise(a1, method="burg").a == pytest.approx(fit_noise(a1).a, abs=2e-3)
    with pytest.raises(ValueError, match="one of yule_walker, burg"):
        fit_noise(e, method="levinson")


def test_whitening_starts_from_the_stationary_law_so_an_offset_is_not_fitted_to_the_filters_transient():
    """With zero initial conditions the first p whitened samples were r(0), r(1) − a₁r(0), …: under resonant AR(2)
    noise each outweighed hundreds of innovations and a constant regressor fitted them (the prewhitened F-test of an
    offset fired on 92 % of draws at 1 %). Whitened by their stationary covariance (the exact likelihood) each has
    the innovations' variance: the F-test keeps its level, and no sample is left out."""
    r2, th = 0.97, 2 * np.pi * 0.02
    rng = np.random.default_rng(12)
    fired, heads = 0, []
    for _ in range(40):
        e = signal.lfilter([1.0], [1.0, -2 * r2 * np.cos(th), r2 * r2], rng.standard_normal(N + 2000))[2000:]
        nm = fit_noise(e)
        J, rw, _ = nm.prewhiten(np.ones((N, 1)), e)
        beta = float(J[:, 0] @ rw) / float(J[:, 0] @ J[:, 0])
        sse0, sse1 = whitened_sse(nm, np.vstack([e, e - beta]))
        fired += f_test(float(sse0), float(sse1), 1, N, 1 + nm.order)[1] < 0.01
        heads.append(nm.whiten(e)[0] / np.sqrt(nm.sigma2_e))
    assert fired <= 4  # 10 % of 40 draws at most (Yule-Walker's bias leaves 2-4 %; with the raw transient in: 92 %)
    # the first whitened sample is a standardised innovation, not r(0) (≈ 21 innovations' standard deviations)
    assert np.std(heads) == pytest.approx(1.0, abs=0.35)
    w = nm.whiten(e)
    assert nm.order >= 2 and np.all(w != 0.0)


def _acov_by_impulse_response(a, lags: int, n: int = 60_000) -> np.ndarray:
    """γ(0 … lags) of AR noise with unit innovations, independently: Σ ψⱼψⱼ₊ₖ over the impulse response ψ of 1/A."""
    psi = signal.lfilter([1.0], np.r_[1.0, -np.asarray(a, float)], np.r_[1.0, np.zeros(n - 1)])
    return np.array([psi[: n - k] @ psi[k:] for k in range(lags + 1)])


@pytest.mark.parametrize("a", [(0.9,), (0.6, 0.25), (2 * 0.97 * np.cos(2 * np.pi * 0.02), -0.97 ** 2),
                               (0.433, -0.0792, 0.267, 0.23, -0.0525, 0.0422, 0.0942)])
def test_whitening_is_the_exact_gaussian_likelihood(a):
    """Whitening W (r ↦ e) of an AR(p) noise model satisfies WᵀW = σ_e²·Σ⁻¹, Σ the noise's covariance — checked
    against Σ from the impulse response of 1/A(q) (an independent reference); AR(1)'s first sample is
    Prais–Winsten's √(1 − ρ²)·r(0)."""
    n = 30
    nm = NoiseModel(a=tuple(a), sigma2_e=1.0, sigma2=1.0, n=n)
    gamma = _acov_by_impulse_response(a, n - 1)
    np.testing.assert_allclose(stationary_autocovariance(a), gamma[: len(a) + 1], rtol=1e-9)
    Wt = nm.whiten(np.eye(n))  # row i: W applied to the i-th unit vector, i.e. Wᵀ
    np.testing.assert_allclose(Wt @ Wt.T @ linalg.toeplitz(gamma), np.eye(n), atol=1e-8)
    if len(a) == 1:
        assert nm.whiten(np.r_[2.0, np.zeros(n - 1)])[0] == pytest.approx(2.0 * np.sqrt(1 - a[0] ** 2))
    # a failed simulation's residual (not finite) stays not finite, row by row, and raises nothing
    bad = np.vstack([np.ones(n), np.r_[np.nan, np.ones(n - 1)], np.r_[np.ones(n - 1), np.inf]])
    w = nm.whiten(bad)
    assert np.all(np.isfinite(w[0])) and not np.all(np.isfinite(w[1])) and not np.all(np.isfinite(w[2]))
    assert not np.isfinite(whitened_sse(nm, bad)[1])
    # a record shorter than the model's order: its samples whitened by the leading block of the start's factor
    short = nm.whiten(np.eye(n)[:1, :1])
    assert short.shape == (1, 1) and short[0, 0] == pytest.approx(1.0 / np.sqrt(gamma[0]))


def test_a_noise_model_that_is_not_stationary_whitens_without_its_first_samples():
    """No stationary law to start from (a unit root): the conditional likelihood, the first p samples at 0."""
    assert stationary_autocovariance((1.0,)) is None and start_factor((0.5, 0.6)) is None
    w = NoiseModel(a=(1.0,), sigma2_e=1.0, sigma2=1.0, n=5).whiten(np.arange(1.0, 6.0))
    np.testing.assert_array_equal(w, [0.0, 1.0, 1.0, 1.0, 1.0])


def test_the_noise_benchmark_prints_each_estimators_whitening_and_false_alarms(capsys, tmp_path):
    from jobs import bench_noise

    assert bench_noise.main(["--draws", "2", "--json", str(tmp_path / "n.json")]) == 0
    out = capsys.readouterr().out
    assert "| resonant AR(2), 20 Hz | burg |" in out and "| white | yule_walker |" in out
    rows = json.loads((tmp_path / "n.json").read_text())
    assert len(rows) == 10
    by = {(r["noise"], r["method"]): r for r in rows}
    for (noise, method), r in by.items():  # white and AR(1) noise: the order found and the residual whitened
        if noise == "white" or noise.startswith("AR(1)"):
            assert r["median_order"] == (0 if noise == "white" else 1) and r["ljung_box_rejects"] <= 0.5, r
    assert by[("resonant AR(2), 20 Hz", "burg")]["median_order"] == 2
    assert bench_noise.main(["--draws", "0"]) == 2


def test_a_nonfinite_residual_gives_white_with_a_note():
    nm = fit_noise(np.r_[np.ones(50), np.nan])
    assert nm.white and "white" in nm.note


# ------------------------------------------------------------------------------------------ tests
def test_prewhitened_f_test_is_calibrated_under_ar1_noise():
    """A regressor that is pure (smooth) nonsense: the white F-test rejects far too often under AR(1) ρ = 0.9
    noise, the prewhitened one at about its level."""
    t = np.arange(N) / 1000.0
    x = np.sin(2 * np.pi * t / 2.3)  # a slow signal the noise can mimic
    naive, white = 0, 0
    for seed in range(60):
        e = ar1(0.9, seed=seed)
        c = float(x @ e) / float(x @ x)
        r1 = e - c * x
        nm = fit_noise(r1)
        res = compare(nm, e, r1, 1, 1)
        white += res["p_value"] < 0.01
        F = (e @ e - r1 @ r1) / (r1 @ r1 / (N - 1))
        naive += stats.f.sf(F, 1, N - 1) < 0.01
    assert naive >= 20 and white <= 4


def heteroscedastic_case(seed: int, n: int = N) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise whose level grows with a swept 'speed' v, and a regressor (v³) that lives where it is large: the
    base columns X0, the new column z and the noise e."""
    t = np.arange(n) / 1000.0
    v = np.sin(2 * np.pi * (0.5 + 4.0 * t) * t)
    sig = 0.1 + np.abs(v) ** 2
    sig /= np.sqrt(np.mean(sig ** 2))
    X0 = np.column_stack([np.ones(n), t, np.cos(3 * t)])
    return X0, v ** 3, sig * np.random.default_rng(seed).standard_normal(n)


def test_robust_f_matches_the_textbook_hc3_sandwich_for_one_new_column():
    X0, z, e = heteroscedastic_case(1, 800)
    X = np.column_stack([X0, z])
    r1 = e - X @ np.linalg.lstsq(X, e, rcond=None)[0]
    n, p = X.shape
    inv = np.linalg.inv(X.T @ X)
    h = np.einsum("ij,jk,ik->i", X, inv, X)
    v_hc = inv @ (X.T * (r1 / (1 - h)) ** 2) @ X @ inv
    v_0 = r1 @ r1 / (n - p) * inv
    out = robust_f(10.0, NoiseModel(), r1, X, [3])
    assert out["ratio"] == pytest.approx(max(v_hc[3, 3] / v_0[3, 3], 1.0), rel=1e-8)
    assert out["F"] == pytest.approx(10.0 / out["ratio"], rel=1e-12)
    assert out["p_value"] == pytest.approx(stats.f.sf(out["F"], 1, n - p), rel=1e-10)
    # along the change of the fit: the noise's level where the fit moved over its mean, here all in one sample
    w = np.zeros(800)
    w[17] = 1.0
    along = robust_f(10.0, NoiseModel(), r1, X, [3], change=w)
    assert along["ratio_change"] == pytest.approx(r1[17] ** 2 / np.mean(r1 ** 2), rel=1e-10)
    assert along["ratio"] == pytest.approx(max(out["ratio"], along["ratio_change"], 1.0), rel=1e-10)


@pytest.mark.parametrize("form", ["per sample", "level"])
def test_robust_f_keeps_its_level_under_heteroscedastic_noise_and_its_power_under_white_noise(form):
    """Nonsense regressor where the noise is loud: the F-test rejects far too often, the robust one at about its
    level; a real effect under white noise is found as often by both. The same with the variance from the level
    (bins of the 'speed' and of time, ``discover.level_min_count``) as per sample."""
    naive, robust, power_f, power_robust = 0, 0, 0, 0
    for seed in range(200):
        X0, z, e = heteroscedastic_case(seed)
        X = np.column_stack([X0, z])
        level = level_basis({"xdot_B": np.cbrt(z), "t": np.arange(N) / 1000.0}) if form == "level" else None
        effect = np.random.default_rng(1000 + seed).standard_normal(N) + 0.045 * z / z.std()
        for y, real in ((e, False), (effect, True)):
            r0 = y - X0 @ np.linalg.lstsq(X0, y, rcond=None)[0]
            r1 = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
            res = compare(NoiseModel(), r0, r1, 1, 4)
            rob = robust_f(res["F"], NoiseModel(), r1, X, [3], change=r0 - r1, level=level)
            assert rob["variance"] == form
            if real:
                power_f += res["p_value"] < 0.01
                power_robust += rob["p_value"] < 0.01
            else:
                naive += res["p_value"] < 0.01
                robust += rob["p_value"] < 0.01
    assert naive >= 12 and robust <= 6, (naive, robust)  # 1 % of 200 is 2
    assert power_f >= 100 and power_robust >= power_f - 6, (power_f, power_robust)


def test_robust_f_from_the_level_is_not_set_by_a_few_large_residuals():
    """A new column whose influence sits in three samples where the residual is 12 σ (a model error at an impact,
    not louder noise): the per-sample sandwich divides F by about that 12², the level's by what the three raise
    their bins' mean by (3·12² over ~400 samples: about 2.5); with one constant level both ratios are exactly 1."""
    rng = np.random.default_rng(3)
    t = np.arange(N) / 1000.0
    X0 = np.column_stack([np.ones(N), t])
    z = np.zeros(N)
    z[[1200, 1201, 1202]] = 1.0
    X = np.column_stack([X0, z])
    y = rng.standard_normal(N)
    y[[1200, 1201, 1202]] += 12.0 * np.array([1.0, -1.0, 1.0])
    r1 = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
    change = np.zeros(N)
    change[[1200, 1201, 1202]] = 1.0
    level = level_basis({"xdot_B": np.sin(2 * np.pi * 2.0 * t), "t": t})
    per_sample = robust_f(50.0, NoiseModel(), r1, X, [2], change=change)
    by_level = robust_f(50.0, NoiseModel(), r1, X, [2], change=change, level=level)
    assert per_sample["variance"] == "per sample" and per_sample["ratio"] > 40.0, per_sample
    assert by_level["variance"] == "level" and by_level["ratio"] < 4.0, by_level
    flat = robust_f(50.0, NoiseModel(), r1, X, [2], change=change, level=np.ones((N, 1)))
    assert flat["ratio_linear"] == pytest.approx(1.0, rel=1e-9) and flat["ratio_change"] == pytest.approx(1.0)
    assert flat["F"] == pytest.approx(50.0, rel=1e-9)


def test_block_cv_equals_exact_cross_validation_for_a_linear_model():
    rng = np.random.default_rng(4)
    X = rng.standard_normal((400, 3))
    y = X @ np.array([1.0, -2.0, 0.5]) + 0.1 * rng.standard_normal(400)
    beta = np.linalg.lstsq(X, y, rcond=None)[0]
    r = y - X @ beta
    out = block_cv(NoiseModel(), r, X, block=20, folds=4)
    fold = fold_of(400, 20, 4)
    exact = 0.0
    for k in range(4):
        b = np.linalg.lstsq(X[fold != k], y[fold != k], rcond=None)[0]
        exact += float(np.sum((y[fold == k] - X[fold == k] @ b) ** 2))
    assert out["cv_sse_w"] == pytest.approx(exact, rel=1e-9)
    assert out["cv_sse_w"] > out["in_sse_w"]


def _nested_fits(y: np.ndarray, X0: np.ndarray, x_new: np.ndarray):
    """Least-squares residuals and design matrices of a model and of the model with one more column."""
    X1 = np.column_stack([X0, x_new])
    r0 = y - X0 @ np.linalg.lstsq(X0, y, rcond=None)[0]
    r1 = y - X1 @ np.linalg.lstsq(X1, y, rcond=None)[0]
    return r0, X0, r1, X1


def test_out_of_sample_p_below_one_half_is_exactly_the_sign_rule():
    rng = np.random.default_rng(11)
    X0 = np.column_stack([np.ones(N), np.linspace(-1, 1, N)])
    for seed in range(40):
        g = np.random.default_rng(seed)
        y = X0 @ np.array([0.3, 1.0]) + g.standard_normal(N)
        r0, J0, r1, J1 = _nested_fits(y, X0, rng.standard_normal(N))
        oos = out_of_sample(NoiseModel(), r0, J0, r1, J1, block=10, folds=5)
        assert oos["cv0"] == block_cv(NoiseModel(), r0, J0, 10, 5)["cv_sse_w"]
        assert (oos["p_value"] < 0.5) == (oos["cv1"] < oos["cv0"])


def test_out_of_sample_test_holds_its_level_where_the_sign_rule_does_not():
    """A column of pure noise added to a linear model: its cross-validated SSE drops by chance on about a fifth
    of the records (the sign rule; 22 % of 600 measured), the paired test passes it at most at its level (0 of
    600 at 5 %: conservative for nested models); a column in the data at 1.3 σ of the record's RMS passes it
    every time."""
    X0 = np.column_stack([np.ones(N), np.sin(np.linspace(0, 9, N))])
    drops = passes = found = 0
    for seed in range(200):
        g = np.random.default_rng(1000 + seed)
        y = X0 @ np.array([0.2, 1.0]) + g.standard_normal(N)
        oos = out_of_sample(NoiseModel(), *_nested_fits(y, X0, g.standard_normal(N)), block=10, folds=5)
        drops += oos["cv1"] < oos["cv0"]
        passes += oos["p_value"] < 0.05
        if seed < 20:
            effect = np.cos(np.linspace(0, 23, N))
            y_eff = y + 1.17 * effect  # RMS of the model without it: sqrt(1 + 1.17² / 2) ≈ 1.3
            real = out_of_sample(NoiseModel(), *_nested_fits(y_eff, X0, effect), block=10, folds=5)
            found += real["p_value"] < 1e-6
    assert 25 <= drops <= 65, drops
    assert passes <= 10, passes  # 5 % of 200 is 10; the test is conservative for nested models
    assert found == 20


def test_out_of_sample_test_refuses_a_gain_of_a_tenth_of_a_percent():
    """rec12 (backlash, cycling) with the fast nominal fit: a Coulomb friction on top lowered the
    cross-validated error by 0.07 %; a drop that small is one the noise makes."""
    g = np.random.default_rng(5)
    e = g.standard_normal(N)
    tiny = 0.03 * np.sin(np.linspace(0, 40, N))  # |tiny|² / |e|² ≈ 0.05 %
    r0 = e + tiny
    J = np.zeros((N, 0))
    oos = out_of_sample(NoiseModel(), r0, J, e, J)
    assert oos["cv1"] < oos["cv0"] and oos["cv0"] / oos["cv1"] - 1 < 2e-3
    assert oos["p_value"] > 0.05
    same = out_of_sample(NoiseModel(), e, J, e, J)
    assert (same["z"], same["p_value"]) == (0.0, 1.0)


def test_every_fold_spans_the_record():
    f = fold_of(1000, 100, 5)
    for k in range(5):
        idx = np.flatnonzero(f == k)
        assert idx.min() < 500 < idx.max()


def test_bases():
    B, edges = piecewise_basis(np.linspace(0, 1, 240), 12)
    assert B.shape == (240, 12) and np.all(B.sum(axis=1) == 1) and edges.size == 13
    assert piecewise_basis(np.ones(10), 4)[0].shape[1] == 0
    # a record that sits mostly at one end keeps equal widths over the stroke; sparse bins are merged
    v = np.r_[np.linspace(0.02, 0.056, 360), np.full(4600, 0.0575)]
    B, edges = piecewise_basis(v, 12)
    counts = B.sum(axis=0)
    assert counts.min() >= 20 and B.shape[1] >= 10 and np.all(np.diff(edges) > 0)
    L = lagged_basis(np.arange(10.0), 4, 2)
    assert L.shape == (10, 3) and L[5, 1] == L[3, 0]


def test_structure_test_rejects_at_its_level_for_coloured_noise_and_finds_a_bump():
    sig = trajectory()
    hits = {0.0: 0, 0.9: 0}
    for rho in hits:
        for seed in range(40):
            e = ar1(rho, sigma=1e-6, seed=100 + seed)
            hits[rho] += locate(None, e, sig)["structure_left"]
    assert hits[0.0] <= 3 and hits[0.9] <= 3
    bump = 2e-6 * np.exp(-((sig["x_B"] - 0.03) / 0.002) ** 2) * np.sign(sig["xdot_B"])
    loc = locate(None, ar1(0.0, sigma=1e-6, seed=7) + bump, sig)
    assert loc["structure_left"] and loc["strongest"] in ("x_B_dir", "x_B")
    fam = loc["families"][loc["strongest"]]
    lo, hi = fam["range"]
    assert lo - 0.004 <= 0.03 <= hi + 0.004
    assert "slider B position" in loc["text"]


def test_structure_test_does_not_read_noise_that_is_loud_at_speed_as_structure_and_keeps_its_power():
    """Noise whose level grows with the slider's speed spreads the bin means of the velocity family: the classical
    statistic calls that structure in about a quarter of the draws, the robust one (local variances from first
    differences, ``robust=True``) at most at its level; a bump on the stroke is found as often by both."""
    tr = trajectory()
    sig = {k: tr[k] for k in ("x_B", "xdot_B", "i_q", "v_in", "t")}
    speed = np.abs(tr["xdot_B"])
    level = (0.2 + speed / speed.mean()) / np.sqrt(np.mean((0.2 + speed / speed.mean()) ** 2))
    bump = 0.5e-6 * np.exp(-((tr["x_B"] - 0.03) / 0.002) ** 2)
    classical = robust = found = found_classical = 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        loc = locate(None, 1e-6 * level * rng.standard_normal(N), sig, robust=True)
        robust += loc["structure_left"]
        classical += any(f["tested"] and stats.chi2.sf(f["statistic_classical"], f["dof"]) < loc["level_per_family"]
                         for f in loc["families"].values())
        loc = locate(None, 1e-6 * rng.standard_normal(N) + bump, sig, robust=True)
        found += loc["structure_left"]
        found_classical += any(f["tested"] and stats.chi2.sf(f["statistic_classical"], f["dof"])
                               < loc["level_per_family"] for f in loc["families"].values())
    assert classical >= 8 and robust <= 2, (classical, robust)
    # locate's own default is the classical verdict (the discover loop asks for the robust one:
    # DiscoverSettings.robust_structure)
    default = locate(None, 1e-6 * level * np.random.default_rng(0).standard_normal(N), sig)
    tested = [f for f in default["families"].values() if f["tested"]]
    assert tested and all(f["statistic"] == f["statistic_classical"] for f in tested)
    assert found >= found_classical - 3 and found_classical >= 20, (found, found_classical)


def test_the_robust_structure_statistic_tests_after_the_fits_sensitivities():
    """A least-squares fit carries the loud samples' noise into the quiet ones' residual through its parameters:
    tested alone, the quiet bins then look structured; tested after the sensitivities J they do not, and a bump
    is found as often."""
    tr = trajectory()
    sig = {k: tr[k] for k in ("x_B", "xdot_B", "i_q", "v_in", "t")}
    v = tr["xdot_B"]
    level = 0.05 + (np.abs(v) / np.abs(v).mean()) ** 3
    level /= np.sqrt(np.mean(level ** 2))
    J = np.column_stack([np.ones(N), tr["x_B"] - tr["x_B"].mean(), v / np.abs(v).max(),
                         np.gradient(v) / np.abs(np.gradient(v)).max(), np.sin(2 * np.pi * tr["t"] / 1.7)])
    bump = 0.5e-6 * np.exp(-((tr["x_B"] - 0.03) / 0.002) ** 2)

    def verdicts(y: np.ndarray) -> tuple[bool, bool]:
        r = y - J @ np.linalg.lstsq(J, y, rcond=None)[0]
        return (locate(None, r, sig, robust=True)["structure_left"],
                locate(None, r, sig, J=J, robust=True)["structure_left"])

    loud = np.array([verdicts(1e-6 * level * np.random.default_rng(s).standard_normal(N)) for s in range(20)])
    bumps = np.array([verdicts(1e-6 * np.random.default_rng(100 + s).standard_normal(N) + bump) for s in range(10)])
    assert loud[:, 0].sum() >= 2 and loud[:, 1].sum() == 0, loud.sum(axis=0)  # measured: 4 and 0 of 20
    assert bumps[:, 0].sum() >= 5 and bumps[:, 1].sum() >= bumps[:, 0].sum() - 1, bumps.sum(axis=0)


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_a_fit_stopped_short_of_its_minimum_is_not_read_as_noise(rho):
    """The families are tested after the fit's sensitivities, so a residual its own parameters still explain reads
    as noise to them; the convergence check, under the noise model the fit minimised under, says the fit stopped
    short — and at the fit's minimum its statistic is 0, so a converged fit is never flagged by it."""
    tr = trajectory()
    sig = {k: tr[k] for k in ("x_B", "xdot_B", "i_q", "v_in", "t")}
    v = tr["xdot_B"]
    J = np.column_stack([np.ones(N), tr["x_B"] - tr["x_B"].mean(), v / np.abs(v).max(),
                         np.gradient(v) / np.abs(np.gradient(v)).max(), np.sin(2 * np.pi * tr["t"] / 1.7)])
    nm = NoiseModel(a=(rho,)) if rho else NoiseModel()
    k0 = nm.order
    stats_at_minimum = []
    for seed in range(10):
        y = J @ np.array([3e-6, 1e-3, 2e-6, -1e-6, 1e-6]) + 1e-6 * ar1(rho, seed=seed)
        beta = np.linalg.lstsq(nm.whiten_columns(J)[k0:], nm.whiten(y)[k0:], rcond=None)[0]  # the fit's minimum
        r = y - J @ beta
        at_min = locate(None, r, sig, J=J, robust=True, fitted=J, fitted_noise=nm)
        stats_at_minimum.append(at_min["convergence"]["statistic"])
        assert at_min["convergence"]["converged"] and at_min["convergence"]["dof"] == 5
    assert max(stats_at_minimum) < 1e-6, stats_at_minimum
    short = r + J @ np.array([5e-6, 0.0, 3e-6, 0.0, 0.0])  # a step of the parameters away: ≈ 6 σ of error
    assert np.sqrt(np.mean((short - r) ** 2)) > 4e-6
    assert not locate(None, short, sig, J=J, robust=True)["structure_left"]  # the flaw the check closes
    stopped = locate(None, short, sig, J=J, robust=True, fitted=J, fitted_noise=nm)
    conv = stopped["convergence"]
    assert stopped["structure_left"] and not conv["converged"] and conv["p_value"] < 1e-10
    assert stopped["text"].startswith("structure left: the fit has not converged") and conv["share"] > 0.5
    # a significant but small share (a kink's linearisation, not a fit stopped short) is no sign of one: ≈ 4 %
    e, w4 = nm.whiten(r)[k0:], nm.whiten_columns(J[:, 4:])[k0:, 0]
    slight = r + J[:, 4] * np.sqrt(200.0 * np.mean(e ** 2) / (w4 @ w4))  # χ² 200 on 5 dof
    strict = locate(None, slight, sig, J=J, fitted=J, fitted_noise=nm, unconverged_share=0.0)["convergence"]
    assert strict["p_value"] < 1e-6 and not strict["converged"] and 0.005 < strict["share"] < 0.1, strict
    assert locate(None, slight, sig, J=J, fitted=J, fitted_noise=nm)["convergence"]["converged"]
    # no free parameter inside its bounds: nothing to test
    assert locate(None, r, sig, fitted=J[:, :0])["convergence"]["converged"]


def test_inside_bounds_leaves_out_a_parameter_at_its_bound():
    from toggle_id.discovery.model import inside_bounds
    from toggle_id.effects import ALL_INDEX
    from toggle_id.identify import stage_bounds
    from toggle_id.params import ASSIGNED
    from toggle_id.simulate import extend

    theta = extend(ASSIGNED)[0]
    free = ("B_m", "K_t", "mu")
    assert inside_bounds(theta, free).tolist() == [True, True, True]
    lo, hi = stage_bounds(list(free))
    theta[ALL_INDEX["K_t"]], theta[ALL_INDEX["mu"]] = lo[1], hi[2]
    assert inside_bounds(theta, free).tolist() == [True, False, False]


def test_a_noise_level_that_grows_with_speed_is_named_and_steady_noise_of_any_shape_is_not():
    tr = trajectory()
    sig = {k: tr[k] for k in ("x_B", "xdot_B", "i_q", "v_in", "t")}
    speed = np.abs(tr["xdot_B"])
    level = (0.2 + speed / speed.mean()) / np.sqrt(np.mean((0.2 + speed / speed.mean()) ** 2))
    steady = {"white": lambda g: g.standard_normal(N), "student_t3": lambda g: g.standard_t(3, N) / np.sqrt(3),
              "ar1_0.9": lambda g: ar1(0.9, seed=int(g.integers(1 << 30)))}
    for name, draw in steady.items():
        hits = sum(noise_level(fit_noise(r), r, sig)["varies"]
                   for r in (1e-6 * draw(np.random.default_rng(s)) for s in range(50)))
        assert hits <= 3, (name, hits)
    r = 1e-6 * level * np.random.default_rng(0).standard_normal(N)
    out = noise_level(fit_noise(r), r, sig)
    assert out["varies"] and out["strongest"] == "speed" and "slider B speed" in out["text"]
    sd = np.asarray(out["families"]["speed"]["sigma_m"])
    assert sd[-1] > 3 * sd[0]  # loud at speed, quiet at rest
    assert np.sqrt(np.mean(r ** 2)) == pytest.approx(1e-6, rel=0.05)


def test_structure_test_families_report_their_own_noise_model():
    sig = trajectory(2000)
    e = ar1(0.5, n=2000, seed=9)
    out = structure_test(None, e, {"x_B": piecewise_basis(sig["x_B"], 8)[0]})
    assert out["x_B"]["noise"]["order"] >= 1 and out["x_B"]["dof"] == 8


# ---------------------------------------------------------------------------------------------- Vuong's test
def _vuong_pair(extra_rms: float, rho: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of two fits to one record: a the noise, b the noise plus a smooth deterministic miss of RMS
    ``extra_rms`` (σ = 1)."""
    e = ar1(rho, seed=seed) if rho else np.random.default_rng(seed).standard_normal(N)
    t = np.linspace(0.0, 1.0, N)
    miss = np.sin(2 * np.pi * 3 * t) * np.exp(-((t - 0.6) / 0.2) ** 2)
    return e, e + extra_rms * miss / np.sqrt(np.mean(miss ** 2))


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_vuong_cannot_tell_apart_two_fits_that_differ_by_noise_alone(rho):
    """Two fits whose residuals differ only by noise-sized scatter of no structure: |z| below 1.96 in ~95 % of
    draws (the test's size), with white and with AR(1) noise whitened by its own model."""
    rejected = 0
    for seed in range(40):
        rng = np.random.default_rng(1000 + seed)
        e = ar1(rho, seed=seed) if rho else rng.standard_normal(N)
        a = e + 0.05 * rng.standard_normal(N)
        b = e + 0.05 * rng.standard_normal(N)
        noise = fit_noise(a, 8)
        v = vuong(noise, a, b, 1, 1)
        rejected += v["favours"] is not None
    assert rejected <= 6  # 5 % of 40 is 2; binomial 99.9 % bound ~7


@pytest.mark.parametrize("rho, miss", [(0.0, 0.15), (0.9, 0.5)])
def test_vuong_prefers_the_fit_without_a_structured_miss(rho, miss):
    """A smooth miss of 0.15 σ is told apart in white noise; in AR(1) ρ = 0.9 noise a slow miss looks much like
    the noise itself (whitening shrinks it by A(1) = 0.1 against σ_e = 0.44 σ), so it takes a larger one."""
    a, b = _vuong_pair(miss, rho)
    noise = fit_noise(a, 8)
    v = vuong(noise, a, b, 1, 1)
    assert v["favours"] == "a" and v["z"] > 3
    w = vuong(noise, b, a, 1, 1)  # symmetric
    assert w["favours"] == "b" and w["z"] == pytest.approx(-v["z"], rel=1e-9)


@pytest.mark.parametrize("rho, rms", [(0.0, 0.04), (0.9, 0.25)])
def test_separation_predicts_what_vuongs_test_does_on_the_record(rho, rms):
    """The expected z and power of a tie, from the two fits alone, against Vuong's test run on many draws of the
    noise with one of the two models true: the mean z and the share of draws that name it agree with them."""
    _, b0 = _vuong_pair(rms, rho, seed=0)
    e0 = _vuong_pair(rms, rho, seed=0)[0]
    delta = b0 - e0  # the two models' predictions differ by this (the miss of b when a is the truth)
    sep = separation(fit_noise(e0, 8), e0, b0)
    assert sep["difference_rms_m"] == pytest.approx(rms, rel=1e-9)
    assert 0.5 < sep["expected_z"] < 3.0 and 0.05 < sep["power"] < 0.9  # a case where the answer is uncertain
    zs = []
    for seed in range(1, 161):
        e = ar1(rho, seed=seed) if rho else np.random.default_rng(seed).standard_normal(N)
        zs.append(vuong(fit_noise(e, 8), e, e + delta, 1, 1)["z"])
    zs = np.asarray(zs)
    assert np.mean(zs) == pytest.approx(sep["expected_z"], abs=0.25)
    assert np.mean(np.abs(zs) > stats.norm.isf(0.025)) == pytest.approx(sep["power"], abs=0.12)
    # a difference of the needed size names the true model with the target probability (the formula's own
    # consistency, and on draws)
    grown = separation(fit_noise(e0, 8), e0, e0 + delta * sep["needed_rms_m"] / rms)
    assert grown["power"] == pytest.approx(0.8, abs=0.01)
    hits = [vuong(fit_noise(e, 8), e, e + delta * sep["needed_rms_m"] / rms, 1, 1)["p_value"] < 0.05
            for e in ((ar1(rho, seed=s) if rho else np.random.default_rng(s).standard_normal(N))
                      for s in range(200, 300))]
    assert np.mean(hits) == pytest.approx(0.8, abs=0.12)


def test_vuong_power_is_the_size_at_zero_and_grows_to_one():
    assert vuong_power(0.0) == pytest.approx(0.05)
    assert vuong_power(1.1) == pytest.approx(stats.norm.cdf(1.1 - 1.959964) + stats.norm.cdf(-1.1 - 1.959964))
    assert vuong_power(-2.0) == vuong_power(2.0) and vuong_power(6.0) > 0.9999


def test_separation_of_identical_fits_is_zero_and_of_broken_ones_unknown():
    e = np.random.default_rng(4).standard_normal(N)
    same = separation(fit_noise(e, 0), e, e.copy())
    assert same["expected_z"] == 0.0 and same["power"] == pytest.approx(0.05) and same["needed_rms_m"] == np.inf
    broken = separation(fit_noise(e, 0), e, np.full(N, np.nan))
    assert np.isnan(broken["expected_z"]) and np.isnan(broken["power"])


def test_vuong_charges_the_extra_parameters_of_the_larger_model():
    """Equal residuals: the model with more parameters loses by the Schwarz term, ln(n)/2 per parameter."""
    a, _ = _vuong_pair(0.0)
    v0 = vuong(fit_noise(a, 0), a, a.copy(), 1, 1)
    assert v0["z"] == 0.0 and v0["p_value"] == 1.0
    rng = np.random.default_rng(3)
    b = a + 0.01 * rng.standard_normal(N)
    assert vuong(fit_noise(a, 0), a, b, 3, 1)["z"] < vuong(fit_noise(a, 0), a, b, 1, 1)["z"]


def test_a_drift_is_told_from_coloured_noise_by_a_trend_under_the_detrended_noise_model():
    """A 4-µm linear drift over 5 s is a trend (a noise model fitted with the trend in would absorb it); white and
    AR(0.9) noise without one are not, at the test's level (these draws)."""
    from scipy.signal import lfilter

    from toggle_id.discovery.residual import drift_test

    rng = np.random.default_rng(0)
    t = np.arange(5001) / 1000.0
    drifting = drift_test(t, 1e-6 * rng.standard_normal(t.size) + 4e-6 * t / 5.0, 8, 0.01)
    assert drifting["drifts"] and drifting["drift_m"] == pytest.approx(4e-6, rel=0.1) and drifting["z"] > 20
    for rho in (0.0, 0.9):
        e = lfilter([1.0], [1.0, -rho], np.sqrt(1 - rho * rho) * 1e-6 * rng.standard_normal(t.size))
        assert not drift_test(t, e, 8, 0.01)["drifts"], rho


def test_a_line_in_the_noise_is_named_with_its_frequency_and_amplitude_and_coloured_noise_makes_none():
    """A 50-Hz tone of 0.3 σ on white noise is a line at 49.8 Hz (the bin's centre) of 0.3 µm; the strongest
    bin of white, AR(1) ρ 0.9 and 0.99 noise and of a quantisation error is not one (these draws); a tone of
    1.5 σ on AR(1) noise is still found (the amplitude within 20 % at 0.3 σ, 15 % at 1.5 σ), and the steep low
    end of an AR spectrum is never tested."""
    from scipy.signal import lfilter

    from toggle_id.discovery.residual import spectral_lines

    rng = np.random.default_rng(0)
    t = np.arange(5001) / 1000.0
    tone = 1e-6 * np.sin(2 * np.pi * 50.0 * t + 0.3)
    found = spectral_lines(1e-6 * rng.standard_normal(t.size) + 0.3 * tone, 1000.0, 0.01)
    assert [round(x["frequency_hz"], 1) for x in found["lines"]] == [49.8]
    assert found["lines"][0]["amplitude_m"] == pytest.approx(0.3e-6, rel=0.2) and found["dof"] > 10
    for rho in (0.0, 0.9, 0.99):
        e = lfilter([1.0], [1.0, -rho], np.sqrt(1 - rho * rho) * 1e-6 * rng.standard_normal(t.size))
        assert spectral_lines(e, 1000.0, 0.01)["lines"] == [], rho
        hum = spectral_lines(e + 1.5 * tone, 1000.0, 0.01)["lines"]
        assert hum and abs(hum[0]["frequency_hz"] - 50.0) < 1.0
        assert hum[0]["amplitude_m"] == pytest.approx(1.5e-6, rel=0.15)
    slow = 3e-6 * np.sin(2 * np.pi * 1.3 * t)
    assert spectral_lines(np.round((slow + 0.3e-6 * rng.standard_normal(t.size)) * 1e6) / 1e6 - slow, 1000.0,
                          0.01)["lines"] == []
    assert found["tested_bins"] < 513 - 2 * 14  # a whole window either side of every bin tested
    # noise that grows along the record: each Welch segment is read at its own level (averaged as they are, the
    # loud segments faked a line in 33 of 50 such draws; now none), and a tone in it is still found
    growing = (0.1 + (t / t[-1]) ** 3) / np.sqrt(np.mean((0.1 + (t / t[-1]) ** 3) ** 2))
    loud = 1e-6 * growing * rng.standard_normal(t.size)
    assert spectral_lines(loud, 1000.0, 0.01)["lines"] == []
    assert [round(x["frequency_hz"], 1) for x in spectral_lines(loud + 0.5 * tone, 1000.0, 0.01)["lines"]] == [49.8]


def test_a_hysteresis_of_the_load_is_found_by_the_current_signed_by_the_direction_of_motion():
    """A friction that grows with the load (the clamp's pins) makes the residual change sign with the direction of
    motion where the current is large: the bins of the current alone average it out, the signed bins do not."""
    sig = trajectory()
    hyst = 1.5e-6 * np.sign(sig["xdot_B"]) * np.clip(np.abs(sig["i_q"]) - 50.0, 0.0, None) / 50.0
    loc = locate(None, ar1(0.0, sigma=1e-6, seed=11) + hyst, sig)
    assert loc["structure_left"] and loc["strongest"] == "i_q_dir"
    assert loc["families"]["i_q_dir"]["p_value"] < 1e-3 * loc["families"]["i_q"]["p_value"]
    assert "model current i_q, signed by the direction of motion" in loc["text"]


def test_a_signal_and_its_signed_bins_pointing_at_one_place_are_said_once():
    from toggle_id.discovery.localise import _parts

    def fam(label, peak, level, lo=0.042, hi=0.0483):
        return {"peak_at": peak, "range": [lo, hi], "peak_level_m": level, "p_value": 1e-9,
                "text": f"a bump near {label} ≈ {peak * 1e3:.3g} mm, residual level {level * 1e6:+.3g} µm"}

    families = {"x_B": fam("slider B position", 0.0467, -17.7e-6),
                "x_B_dir": fam("slider B position, signed by the direction of motion", 0.0467, -17.7e-6),
                "xdot_B": fam("slider B velocity", -0.0006, -4.2e-6), "v_in_lags": {"p_value": 1e-9}}
    parts = _parts(families, ["x_B_dir", "x_B", "xdot_B", "v_in_lags"])
    assert parts == [families["x_B"]["text"] + " (the same with the direction of motion's sign)",
                     families["xdot_B"]["text"]]
    # elsewhere, or of another size: both are said
    families["x_B_dir"] = fam("slider B position, signed by the direction of motion", 0.0467, -8.0e-6)
    assert len(_parts(families, ["x_B_dir", "x_B"])) == 2
    families["x_B_dir"] = fam("slider B position, signed by the direction of motion", 0.0301, -17.7e-6, 0.028, 0.032)
    assert len(_parts(families, ["x_B_dir", "x_B"])) == 2
    assert _parts(families, ["x_B_dir"]) == [families["x_B_dir"]["text"]]  # the signed one alone


@pytest.mark.parametrize("levels, words", [
    ([0, 0, 0, 0, 9, 10, 9, 0, 0, 0, 0, 0], "a bump near slider B position ≈ 55 mm (bins 40–70 mm)"),
    ([0, 0, 0, 0, 0, 0, 0, 0, 0, 3, 6, 10], "grows with slider B position above 100 mm"),
    ([10, 6, 3, 0, 0, 0, 0, 0, 0, 0, 0, 0], "grows towards low slider B position, below 20 mm"),
    # large at both ends and in between: no place to name (rec28 of the adversarial set was called "a bump" over
    # the whole stroke)
    ([-9, 0, 0, 0, 0, -10, 0, 0, 0, 0, 0, -7], "spread over the whole range of slider B position (0–120 mm), "
                                               "largest near 55 mm"),
])
def test_the_localisation_names_a_place_only_where_there_is_one(levels, words):
    from toggle_id.discovery.localise import _describe

    edges = np.linspace(0.0, 0.12, 13)
    d = _describe("x_B", edges, 1e-6 * np.asarray(levels, float))
    assert d["text"].startswith(words + ", residual level")


def test_localisation_runs_with_one_blas_thread_and_gives_the_pool_back(monkeypatch):
    """locate's projections on tall, thin bases run under one BLAS thread (several times faster on a multi-threaded
    pool); the pool is as before afterwards."""
    from conftest import blas_threads

    import toggle_id.discovery.localise as localise

    seen, real = [], localise.structure_test

    def spy(*args, **kwargs):
        seen.append(blas_threads())
        return real(*args, **kwargs)

    monkeypatch.setattr(localise, "structure_test", spy)
    before = blas_threads()
    sig = trajectory(1001)
    localise.locate(None, 1e-6 * np.random.default_rng(0).standard_normal(1001), sig)
    assert seen == [[1] * len(before)] and blas_threads() == before


def test_a_noise_model_as_slow_as_the_motion_leaves_structure_and_makes_every_accepted_effect_compensating():
    """The floor on the noise model's independent samples (``discover.min_effective_fraction``, 0.02): AR(1) noise
    with ρ = 0.9 (the adversarial set's) and white noise pass; a slow error the noise model takes for noise (a
    random walk's slow wander, ρ → 1) does not, and then no effect accepted under it is called added."""
    from types import SimpleNamespace

    from toggle_id.discovery.residual import slow_noise
    from toggle_id.discovery.toggle_plant import TogglePlant

    rng = np.random.default_rng(7)
    e = rng.standard_normal(5001)
    ar09 = signal.lfilter([1.0], [1.0, -0.9], e)
    wander = np.cumsum(e) * 0.2 + e  # a slow wander under white noise: AR(8), coefficients summing to 0.98
    fast_enough = [slow_noise(fit_noise(x), 0.02) for x in (e, ar09)]
    assert [s["slow"] for s in fast_enough] == [False, False]
    assert 0.03 < fast_enough[1]["effective_fraction"] < 0.08  # (1 − ρ)/(1 + ρ) = 0.053
    slow = slow_noise(fit_noise(wander), 0.02)
    assert slow["slow"] and slow["effective_fraction"] < 0.02 and "validation.path" in slow["text"]
    assert not slow_noise(fit_noise(wander), 0.0)["slow"]  # the check off
    said: list[str] = []
    plant = SimpleNamespace(say=said.append)
    added = [{"name": "contact_nonlinear_stiffness"}, {"name": "cogging_torque"}]
    keep, demoted = TogglePlant.explains(plant, None, added, ({"slow_noise": slow}, None, None), added)
    assert keep == [] and [d["name"] for d in demoted] == ["contact_nonlinear_stiffness", "cogging_torque"]
    assert all("cannot be told apart" in d["reason"] for d in demoted) and said
    # an effect kept for its own fast signature (a ripple over many periods) is no stand-in for a slow error: it goes
    # on to the catch-all check (off here), the others are compensating as before
    plant = SimpleNamespace(say=said.append, _fitting=lambda: None, s=SimpleNamespace(catch_all=False))
    ripple = {"name": "cogging_torque", "own_signature": "repeats at its count without it"}
    keep, demoted = TogglePlant.explains(plant, None, [added[0], ripple], ({"slow_noise": slow}, None, None), added)
    assert keep == [ripple] and [d["name"] for d in demoted] == ["contact_nonlinear_stiffness"]


def _ringing(n: int) -> np.ndarray:
    """A 50-Hz ringing of 4 µm under a Gaussian envelope (a transmission's resonance on a closing stroke)."""
    t = np.arange(n) * 1e-3
    return 4e-6 * np.sin(2 * np.pi * 50.0 * t) * np.exp(-((t - 0.4) / 0.2) ** 2)


def _louder_at_speed(rng: np.random.Generator, n: int = 5001) -> np.ndarray:
    """White noise, 1 µm, three times louder on the record's first fifth (where a slider would be moving)."""
    e = 1e-6 * rng.standard_normal(n)
    e[: n // 5] *= 3.0
    return e


def test_the_robust_portmanteau_keeps_its_level_under_noise_louder_on_part_of_the_record():
    """Independent noise whose level jumps: Ljung–Box (one σ² for the record) reads the jump as correlation, the
    robust form does not; a ringing burst — an error the model lacks, on the loud part only — is no white noise."""
    rng = np.random.default_rng(5)
    p_robust, p_lb = [], []
    for _ in range(200):
        e = _louder_at_speed(rng)
        p_robust.append(robust_portmanteau(e, 20)["p_value"])
        p_lb.append(ljung_box(e, 20)["p_value"])
    assert np.mean(np.array(p_robust) < 0.01) <= 0.03
    assert np.mean(np.array(p_robust) < 0.05) <= 0.09
    assert np.mean(np.array(p_lb) < 0.01) > 0.5  # measured: 82 % of the draws (the robust form: 1 %)
    e = _louder_at_speed(rng)
    e[:800] += _ringing(800)
    assert robust_portmanteau(e, 20)["p_value"] < 1e-6


def test_an_error_louder_where_the_slider_moves_is_structure_only_when_the_noise_model_cannot_whiten_it():
    """:func:`toggle_id.discovery.residual.noise_misfit`: asked only where the level varies with the motion; white
    noise louder there passes, a ringing error there does not; a level that varies in time alone is not asked."""
    from toggle_id.discovery.residual import noise_misfit

    rng = np.random.default_rng(11)
    moving = {"families": {"speed": {"p_value": 1e-12}, "x_B": {"p_value": 0.4}, "t": {"p_value": 0.3}}}
    in_time = {"families": {"speed": {"p_value": 0.5}, "x_B": {"p_value": 0.4}, "t": {"p_value": 1e-9}}}
    loud = _louder_at_speed(rng)
    white = NoiseModel()
    assert noise_misfit(white, loud, moving, 20, 0.01)["applies"]
    assert not noise_misfit(white, loud, moving, 20, 0.01)["misfit"]
    ringing = loud.copy()
    ringing[:800] += _ringing(800)
    found = noise_misfit(white, ringing, moving, 20, 0.01)
    assert found["misfit"] and found["p_value"] < 1e-6 and "does not whiten it" in found["text"]
    assert noise_misfit(white, ringing, in_time, 20, 0.01) == {
        "applies": False, "misfit": False, "statistic": None, "dof": None, "p_value": None, "text": ""}


def test_a_prediction_error_fit_that_drifts_from_least_squares_is_refused_only_beyond_the_noise():
    """``noise.prediction_error_drift``: a linear model under AR(1) noise (ρ 0.7), fitted by least squares and by
    generalised least squares under the true noise model (the prediction-error fit). When the model holds the truth
    the excess of the second's raw SSE stays inside the bound (χ²(k) times the spectrum's peak) at 1 %:
    at most 2 of 200 (1 %); past the bound the fit is refused, and the reason gives the figures."""
    from types import SimpleNamespace

    from toggle_id.discovery.noise import prediction_error_drift

    n, rho = 2000, 0.7
    t = np.linspace(0.0, 1.0, n)
    X = np.column_stack([np.ones(n), np.sin(2 * np.pi * 3 * t), np.cos(2 * np.pi * 7 * t)])
    nm = NoiseModel((rho,), 1.0, 1.0 / (1 - rho ** 2), n)
    Xw = nm.whiten_columns(X)[1:]

    def fits(y):
        b_ls = np.linalg.lstsq(X, y, rcond=None)[0]
        b_pe = np.linalg.lstsq(Xw, nm.whiten(y)[1:], rcond=None)[0]
        sse = [float(np.sum((y - X @ b) ** 2)) for b in (b_ls, b_pe)]
        return (SimpleNamespace(sse=sse[0], raw_sse=None, free=("a", "b", "c"), minimised_under=()),
                SimpleNamespace(sse=0.0, raw_sse=sse[1], free=("a", "b", "c"), minimised_under=(rho,)))

    alarms = 0
    for seed in range(200):
        y = X @ np.array([1.0, 2.0, -1.0]) + signal.lfilter([1.0], [1.0, -rho], np.random.default_rng(seed).standard_normal(n))
        ls, pe = fits(y)
        alarms += prediction_error_drift(ls, pe, nm, 0.01) is not None
        assert prediction_error_drift(ls, pe, nm, 0.0) is None and prediction_error_drift(pe, pe, nm, 0.01) is None
    assert alarms <= 2, alarms
    # past the bound it is refused, with the figures: a linear model cannot drift so (its two fits stay close even
    # with a slow error in the data); the plant's nonlinear fits do (rec15_d1: 7e-9 m² of raw SSE against 1.5e-9)
    bound = nm.peak_spectrum * stats.chi2.isf(0.01, 3)
    for excess, refused in ((0.99 * bound, False), (1.01 * bound, True)):
        pe = SimpleNamespace(sse=0.0, raw_sse=ls.sse + excess, free=("a", "b", "c"), minimised_under=(rho,))
        why = prediction_error_drift(ls, pe, nm, 0.01)
        assert (why is not None) == refused and (not refused or "not noise" in why)


def test_serial_ratio_is_the_newey_west_sandwich_and_restores_the_f_tests_level_under_slow_noise():
    """``stats.serial_ratio``: against the Newey–West variance written out as a double sum over sample pairs (a
    small case); then a linear model with a slow column that is not in the truth, under white noise (ratio ≈ 1, the
    F-test's level kept) and under AR(1) ρ 0.7 noise, where the plain F-test rejects far too often at 5 % and F/c
    about as often as it should."""
    from toggle_id.discovery.stats import serial_ratio

    rng = np.random.default_rng(0)
    n, L = 60, 4
    X = np.column_stack([np.ones(n), rng.standard_normal(n), np.linspace(-1, 1, n)])
    e = rng.standard_normal(n)
    e -= X @ np.linalg.lstsq(X, e, rcond=None)[0]
    XtXi = np.linalg.inv(X.T @ X)
    meat = sum(max(0.0, 1 - abs(i - j) / (L + 1)) * e[i] * e[j] * np.outer(X[i], X[j])
               for i in range(n) for j in range(n))
    v_hac = (XtXi @ meat @ XtXi)[2, 2]
    v_0 = float(e @ e) / (n - 3) * XtXi[2, 2]
    assert serial_ratio(e, X, [2], lags=L)["ratio"] == pytest.approx(max(v_hac / v_0, 1.0), rel=1e-9)

    n = 1000
    t = np.linspace(0.0, 1.0, n)
    X = np.column_stack([np.ones(n), np.cos(2 * np.pi * 5 * t), np.sin(2 * np.pi * 0.7 * t)])
    rates = {}
    for rho in (0.0, 0.7):
        plain = corrected = 0
        for seed in range(300):
            y = signal.lfilter([1.0], [1.0, -rho], np.random.default_rng(seed).standard_normal(n))
            r0 = y - X[:, :2] @ np.linalg.lstsq(X[:, :2], y, rcond=None)[0]
            r1 = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
            F = float(r0 @ r0 - r1 @ r1) / (float(r1 @ r1) / (n - 3))
            c = serial_ratio(r1, X, [2])["ratio"]
            plain += stats.f.sf(F, 1, n - 3) < 0.05
            corrected += stats.f.sf(F / c, 1, n - 3) < 0.05
        rates[rho] = (plain / 300, corrected / 300)
    assert rates[0.0][1] <= 0.08 and rates[0.0][0] - rates[0.0][1] <= 0.03, rates  # white: next to no correction
    assert rates[0.7][0] >= 0.25 and rates[0.7][1] <= 0.12, rates


def test_the_block_cv_truncated_above_a_direction_the_differences_do_not_resolve_ignores_it():
    """``stats.block_cv``'s ``rcond``: a third column that differs from the second by 1e-7 of noise (what a finite
    difference gives for a direction the record hardly determines) is fitted by the default truncation, which moves
    far along it and predicts the folds differently; truncated at 1e-4 each fold is predicted as by the least-squares
    refit of the other folds with the two resolved columns alone (the reference, computed fold by fold)."""
    from toggle_id.discovery.stats import block_cv, fold_of

    rng = np.random.default_rng(5)
    n = 1200
    t = np.linspace(0, 1, n)
    X2 = np.column_stack([np.ones(n), t])
    X = np.column_stack([X2, t + 1e-7 * rng.standard_normal(n)])
    y = X2 @ np.array([1.0, -2.0]) + 0.1 * np.sin(9 * t) + 0.1 * rng.standard_normal(n)
    r = y - X2 @ np.linalg.lstsq(X2, y, rcond=None)[0]
    fold = fold_of(n, 10, 5)
    ref = np.empty(n)
    for k in range(5):
        test = fold == k
        ref[test] = y[test] - X2[test] @ np.linalg.lstsq(X2[~test], y[~test], rcond=None)[0]
    white = NoiseModel()
    cut = block_cv(white, r, X, 10, 5, rcond=1e-4)
    assert np.allclose(cut["errors_w"], ref, rtol=0, atol=1e-9)
    loose = block_cv(white, r, X, 10, 5)  # the default, 1e-8: the noise column is used
    assert np.max(np.abs(loose["errors_w"] - ref)) > 1e-3
