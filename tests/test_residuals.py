"""Residual diagnostics: whiteness, input and state correlation, spectrum — on signals with known answers."""
from __future__ import annotations

import json

import numpy as np
import pytest

from toggle_id import residuals as R
from toggle_id.errors import DataError
from toggle_id.plant import GEOMETRY
from toggle_id.record import Record

N = 5001
T = np.arange(N) * 1e-3


def _white(seed: int = 0, sigma: float = 1e-6) -> np.ndarray:
    return sigma * np.random.default_rng(seed).standard_normal(N)


def _ar1(phi: float, seed: int = 0, sigma: float = 1e-6) -> np.ndarray:
    e = _white(seed, sigma)
    out = np.empty_like(e)
    out[0] = e[0]
    for k in range(1, e.size):
        out[k] = phi * out[k - 1] + e[k]
    return out


def test_autocorrelation_of_white_noise_stays_in_the_band_and_lag0_is_one():
    r = _white(1)
    acf = R.autocorrelation(r, 30)
    assert acf.shape == (31,) and acf[0] == pytest.approx(1.0)
    band = R.significance_band(N, 0.01)
    assert band == pytest.approx(2.5758 / np.sqrt(N), rel=1e-3)
    assert np.sum(np.abs(acf[1:]) > band) <= 2


def test_autocorrelation_matches_direct_sum():
    r = _ar1(0.5, 2)
    e = r - r.mean()
    direct = [float(e[: N - k] @ e[k:]) / float(e @ e) for k in range(6)]
    np.testing.assert_allclose(R.autocorrelation(r, 5), direct, atol=1e-12)


def test_ljung_box_accepts_white_noise_rejects_coloured_noise():
    # white noise: p-values roughly uniform; over 40 seeds only a few fall below 0.05
    ps = [R.ljung_box(_white(s), 20)["p_value"] for s in range(40)]
    assert sum(p < 0.05 for p in ps) <= 6 and 0.3 < np.median(ps) < 0.7
    lb = R.ljung_box(_ar1(0.3, 3), 20, alpha=0.01)
    assert lb["p_value"] < 1e-10 and not lb["white"] and lb["dof"] == 20
    assert lb["acf_lag1"] == pytest.approx(0.3, abs=0.05)


def test_ljung_box_statistic_formula():
    r = _ar1(0.1, 4)
    rho = R.autocorrelation(r, 5)
    q = N * (N + 2) * sum(rho[k] ** 2 / (N - k) for k in range(1, 6))
    assert R.ljung_box(r, 5)["statistic"] == pytest.approx(q, rel=1e-12)


def test_cross_correlation_finds_the_lag_of_a_delayed_input():
    rng = np.random.default_rng(5)
    u = rng.standard_normal(N)
    r = np.r_[np.zeros(7), u[:-7]] * 1e-6 + _white(6, 1e-7)  # residual follows the input by 7 samples
    lags, ccf = R.cross_correlation(r, u, 20)
    assert lags[np.argmax(np.abs(ccf))] == 7 and ccf.max() > 0.9
    assert lags.tolist() == list(range(-20, 21))


def test_input_correlation_test_independent_vs_dependent():
    rec = Record.from_sweep("simulation")
    u = rec.v_in
    ps = [R.input_correlation_test(_white(s), u, 50, 5)["p_value"] for s in range(20)]
    assert sum(p < 0.01 for p in ps) <= 2
    # a residual that is a filtered copy of the swept input (slowly varying model error)
    dep = 1e-6 * np.convolve(u - u.mean(), np.ones(20) / 20, mode="same") / u.std() + _white(7, 1e-6)
    res = R.input_correlation_test(dep, u, 50, 5, alpha=0.01)
    assert res["p_value"] < 1e-6 and not res["independent"] and res["dof"] >= 1


def test_spectrum_peak_at_a_sinusoid_frequency():
    r = 1e-6 * np.sin(2 * np.pi * 37.0 * T) + _white(8, 1e-7)
    f, p = R.spectrum(r, 1000.0)
    peaks = R.dominant_frequencies(f, p, 2)
    assert abs(peaks[0]["frequency_hz"] - 37.0) <= 2 * (f[1] - f[0])
    assert peaks[0]["ratio_to_median"] > 100
    # white noise: the Welch level matches 2σ²/fs
    f, p = R.spectrum(_white(9), 1000.0)
    assert np.median(p) == pytest.approx(R.white_noise_psd(1e-12, 1000.0), rel=0.3)


def test_state_correlations_flag_the_right_state():
    rng = np.random.default_rng(10)
    a, b = rng.standard_normal(N), rng.standard_normal(N)
    r = 0.5 * a + 0.1 * rng.standard_normal(N)
    out = R.state_correlations(r, {"a": a, "b": b, "const": np.ones(N)}, alpha=0.01)
    assert out["a"]["significant"] and out["a"]["corr"] > 0.9
    assert not out["b"]["significant"] and abs(out["b"]["corr"]) < 0.05
    assert out["const"] == {"corr": 0.0, "p_value": 1.0, "significant": False}


def test_plant_states_of_a_model_trajectory():
    x = np.linspace(0.02, 0.0575, N)
    s = R.plant_states(T, x, np.ones(N), x_off=0.0)
    assert set(s) == {"x_B", "xdot_B", "xdot_C", "motor_angle", "i_q", "contact"}
    np.testing.assert_allclose(s["xdot_B"], (0.0575 - 0.02) / 5.0, rtol=1e-9)
    assert np.all(s["xdot_C"] > 0)  # closing: x_C increases with x_B
    assert s["contact"][-1] == 1.0 and s["contact"][0] == 0.0
    assert s["contact"].sum() == np.sum(x >= GEOMETRY.x_B_L)
    # an offset is removed before the kinematics
    s2 = R.plant_states(T, x + 1e-3, None, x_off=1e-3)
    np.testing.assert_allclose(s2["motor_angle"], s["motor_angle"])
    assert "i_q" not in s2


def test_diagnose_is_json_ready_and_gives_a_verdict():
    rec = Record.from_sweep("simulation")
    d = R.diagnose(rec.t, _white(11), rec.v_in, {"x_B": np.linspace(0, 1, N)}, split_index=362, noise_std=1e-6)
    json.dumps(d)
    assert d["verdict"] == {"white": True, "input_independent": True, "structure_left": False}
    assert d["rms_over_noise"] == pytest.approx(1.0, abs=0.05)
    assert d["phases"]["free_n"] == 362 and d["phases"]["clamped_n"] == N - 362
    bad = R.diagnose(rec.t, _ar1(0.8, 12), rec.v_in)
    assert bad["verdict"]["structure_left"] and not bad["verdict"]["white"]


def test_bad_input_raises_data_error():
    with pytest.raises(DataError, match="non-finite"):
        R.ljung_box(np.r_[np.nan, np.zeros(10)])
    with pytest.raises(DataError, match="samples"):
        R.cross_correlation(np.zeros(10), np.zeros(11))
    with pytest.raises(DataError, match="1-D"):
        R.autocorrelation(np.zeros((3, 3)))


def test_figures_render(tmp_path):
    from toggle_id import figures

    rec = Record.from_sweep("simulation")
    r = _ar1(0.5, 13)
    states = R.plant_states(rec.t, np.linspace(0.02, 0.0575, N), np.zeros(N))
    paths = [figures.save(R.diagnostics_figure(rec.t, r), tmp_path / "d.png"),
             figures.save(R.states_figure(r, states, rec.v_in), tmp_path / "s.png"),
             figures.save(R.comparison_figure(rec.t, {"before": r, "after": _white(1)}, noise_std=1e-6,
                                              split_time=0.36), tmp_path / "c.png"),
             figures.save(R.glitches_figure(rec.t, r, [40, 2000]), tmp_path / "g.png")]
    for p in paths:
        assert (tmp_path / p.split("/")[-1]).stat().st_size > 10_000


def test_glitches_are_jumps_no_mechanism_makes_not_noise_counts_or_structure():
    """A sample that jumps away from its neighbours is a glitch of the measurement; Gaussian, coloured, quantised
    noise and noise that is loud at speed, a steep smooth residual (a missing effect), the ringing of a contact
    and the kink of an impact at another time than the model's are not."""
    from scipy.signal import lfilter

    from toggle_id.residuals import glitch_report, glitches

    rng = np.random.default_rng(3)
    n = 5001
    t = np.arange(n) / 1000.0
    smooth = 50e-6 * np.sin(2 * np.pi * 8 * t)  # 2.5 µm per sample at its steepest
    speed = np.abs(np.sin(0.5 * t + 3.95 * t ** 2)) * t / t[-1]  # the paper's sweep, 0.5 → 40 rad/s, growing
    level = (0.1 + speed ** 2) / np.sqrt(np.mean((0.1 + speed ** 2) ** 2))  # 0.1–3× its rms, loud at speed
    loud = 1e-6 * level * rng.standard_normal(n)
    clean = {"white": 1e-6 * rng.standard_normal(n),
             "ar1_0.9": lfilter([1.0], [1.0, -0.9], np.sqrt(1 - 0.81) * 1e-6 * rng.standard_normal(n)),
             "smooth_plus_noise": smooth + 1e-6 * rng.standard_normal(n),
             "contact_ringing": 30e-6 * np.exp(-np.clip(t - 0.7, 0, None) / 0.02) * np.sin(2 * np.pi * 180 * t)
             * (t >= 0.7) + 1e-6 * rng.standard_normal(n),
             "encoder_counts": np.round((5e-3 * np.sin(2 * np.pi * 1.3 * t)) / 1e-6) * 1e-6
             - 5e-3 * np.sin(2 * np.pi * 1.3 * t),
             "loud_at_speed": loud}
    for name, r in clean.items():
        assert not glitches(r).any(), name
    bad = smooth + 1e-6 * rng.standard_normal(n)
    where = [100, 2000, 3000, 4500]
    bad[where] += np.array([30, -30, 25, -40]) * 1e-6
    bad[[1000, 1001]] += 30e-6  # two in a row: not alone, not flagged
    mask = glitches(bad)
    assert np.flatnonzero(mask).tolist() == where
    assert not glitches(bad, k=0).any()
    quiet = int(np.argmin(level[4000:4500])) + 4000
    spiked = loud.copy()
    spiked[quiet] += 20e-6  # a glitch where the loud noise is quiet is still one
    assert quiet in np.flatnonzero(glitches(spiked)).tolist()
    from toggle_id.residuals import near_changes

    contact = (t >= 2.0).astype(float)  # a clamp entry between samples 1999 and 2000: an impact may jump there
    protect = near_changes(contact, np.zeros(n))
    assert np.flatnonzero(protect).tolist() == list(range(1995, 2005))
    assert np.flatnonzero(glitches(bad, protect=protect)).tolist() == [100, 3000, 4500]
    kink = np.where(t < 1.0, 0.4 * (t - 1.0), 0.0) - np.where(t < 1.0003, 0.4 * (t - 1.0003), 0.0)
    assert not glitches(kink + 1e-6 * rng.standard_normal(n)).any()  # two impacts 0.3 ms apart: not a glitch
    rep = glitch_report(t, bad, mask, 8.0)
    assert rep["count"] == 4 and rep["times_s"][0] == pytest.approx(0.1) and rep["residual_m"][-1] < -30e-6
