"""EMPS plant: loaders, closed-loop simulator, IDIM-LS recipe, output-error fit and the effect-discovery loop.

Most tests run on records simulated from the published EMPS model (:mod:`toggle_id.emps.synthetic`). The ones
marked ``needs_records`` use the benchmark's own records, found where the job finds them (``$TOGGLE_ID_EMPS_DIR``
or the official loader's cache, sha256-checked); they skip, with the job's one-line reason, only when the records
are absent (a wrong file is an error, not a skip).
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.linalg import expm

from toggle_id.emps import (
    EFFECTS,
    PARAM_NAMES,
    PUBLISHED,
    PUBLISHED_THETA,
    EmpsRecord,
    EmpsRecordsNotFound,
    controller_law,
    find_benchmark_files,
    fit_output_error,
    idim_ls,
    load_emps_csv,
    load_emps_mat,
    make_jacobian,
    make_residual,
    position_rel_error_pct,
    run_emps_loop,
    simulate_emps,
    theta_from_dict,
)
from toggle_id.emps.fit import FAIL_RESIDUAL, judge_effect
from toggle_id.emps.model import INDEX, LOWER, OFF, UPPER, initial_state
from toggle_id.emps.synthetic import back_and_forth, pulse_train, simulated_record, write_record
from toggle_id.errors import ConfigError, DataError


def _benchmark():
    try:
        return find_benchmark_files(require_validation=True), None
    except EmpsRecordsNotFound as err:  # absent: skip with the job's own one-line reason
        return None, str(err)


FILES, MISSING = _benchmark()
needs_records = pytest.mark.skipif(FILES is None, reason=MISSING or "")

#: README's independent Python check of the IDIM-LS recipe.
README_IDIM = {"M": 95.104, "Fv": 203.13, "Fc": 20.438, "offset": -3.180}


@pytest.fixture(scope="module")
def sim() -> EmpsRecord:
    """8 s of the published model tracking a back-and-forth reference, positions quantised like the encoder."""
    return simulated_record(PUBLISHED_THETA, 8000, name="sim")


@pytest.fixture(scope="module")
def rec() -> EmpsRecord:
    if FILES is None:
        pytest.skip(MISSING)
    return load_emps_mat(FILES.estimation.path)


@pytest.fixture(scope="module")
def val() -> EmpsRecord:
    if FILES is None:
        pytest.skip(MISSING)
    return load_emps_mat(FILES.validation.path)


# ---------------------------------------------------------------------------------------------------- loading
@needs_records
def test_mat_loads_the_benchmark_record(rec, tmp_path):
    assert rec.n == 24841
    assert (rec.kp, rec.kv, rec.dt) == (160.18, 243.45, 1e-3)
    assert rec.gtau == pytest.approx(35.15065188, rel=1e-9)  # the file's value, not the README's rounding
    assert load_emps_mat(FILES.estimation.path, gtau=35.1507).gtau == 35.1507
    assert np.all(rec.pulses == 0.0)
    assert rec.qm.max() == pytest.approx(0.24638, abs=1e-5)
    assert np.abs(rec.vir).max() == pytest.approx(4.326, abs=1e-3)
    # the CSV loader reads the same record written with %.17g (a scratch copy, never kept)
    csv = load_emps_csv(write_record(rec, str(tmp_path / "rec.csv")))
    for key in ("t", "vir", "qm", "qg", "pulses"):
        np.testing.assert_array_equal(getattr(csv, key), getattr(rec, key))


@needs_records
def test_validation_record_has_the_pulse_train(val, rec):
    assert val.n == rec.n and set(np.unique(val.pulses)) == {0.0, 5.0}
    np.testing.assert_allclose(val.qg, rec.qg, rtol=0, atol=1e-12)  # the same reference trajectory
    edges = np.flatnonzero(np.diff(val.pulses) != 0)
    assert np.all(np.diff(edges) == 500)  # 0.5 s on, 0.5 s off


def test_mat_and_csv_round_trip_with_pulses(tmp_path, sim):
    pulses = pulse_train(sim.n)
    r = simulated_record(PUBLISHED_THETA, sim.n, pulses=pulses)
    for suffix in ("mat", "csv"):
        path = write_record(r, str(tmp_path / f"r.{suffix}"))
        back = load_emps_mat(path) if suffix == "mat" else load_emps_csv(path)
        for key in ("t", "vir", "qm", "qg", "pulses"):
            np.testing.assert_array_equal(getattr(back, key), getattr(r, key))
    from scipy.io import savemat

    savemat(tmp_path / "nokv.mat", {"t": r.t[:, None], "vir": r.vir[:, None], "qm": r.qm[:, None],
                                    "qg": r.qg[:, None], "kp": 160.18})
    assert load_emps_mat(tmp_path / "nokv.mat").kv == 243.45  # README default when the file lacks the key


def test_bad_input_raises_data_error(tmp_path, sim):
    with pytest.raises(DataError, match="not found"):
        load_emps_csv(tmp_path / "missing.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,vir,qm\n0,1,2\n")
    with pytest.raises(DataError, match="qg"):
        load_emps_csv(bad)
    r = sim.slice(0, 100)
    qm = r.qm.copy()
    qm[10] = np.nan
    with pytest.raises(DataError, match="NaN"):
        EmpsRecord(t=r.t, vir=r.vir, qm=qm, qg=r.qg)
    with pytest.raises(DataError, match="samples"):
        EmpsRecord(t=r.t, vir=r.vir[:99], qm=r.qm, qg=r.qg)
    with pytest.raises(DataError, match="uniform"):
        EmpsRecord(t=r.t * 2, vir=r.vir, qm=r.qm, qg=r.qg)
    with pytest.raises(DataError, match="increasing"):
        EmpsRecord(t=r.t[::-1], vir=r.vir, qm=r.qm, qg=r.qg)
    with pytest.raises(DataError, match="gtau"):
        EmpsRecord(t=r.t, vir=r.vir, qm=r.qm, qg=r.qg, gtau=-1.0)


# ---------------------------------------------------------------------------------------------------- model
def test_simulated_record_is_reproduced_by_its_model(sim):
    assert np.abs(sim.vir).max() < 10.0 and np.abs(np.diff(sim.qg)).max() / sim.dt < 0.26  # m/s
    res = simulate_emps(PUBLISHED_THETA, sim)
    assert res.status[0] == 0
    assert np.max(np.abs(res.q[0] - sim.qm)) < 2e-7  # m: the encoder quantum and the initial velocity estimate
    assert np.sqrt(np.mean((controller_law(sim) - sim.vir)[2:] ** 2)) < 0.01  # V
    no_friction = simulate_emps(theta_from_dict({"M": PUBLISHED["M"], "Fv": PUBLISHED["Fv"]}), sim).q[0]
    assert position_rel_error_pct(sim.qm, no_friction) > 100 * position_rel_error_pct(sim.qm, res.q[0])


@needs_records
def test_controller_law_matches_recorded_vir(rec, val):
    err = rec.vir - controller_law(rec)
    assert np.sqrt(np.mean(err[2:] ** 2)) < 0.01  # V, against a signal rms of 1.54 V
    # validation record: the pulses are in the logged controller output, on the same samples as pulses_N
    with_p = np.sqrt(np.mean((val.vir - controller_law(val))[2:] ** 2))
    without = np.sqrt(np.mean((val.vir - controller_law(val, pulse_gain=0.0))[2:] ** 2))
    late = val.vir - controller_law(val, pulse_gain=0.0) - np.roll(val.pulses, 1)
    assert with_p < 0.06 and np.sqrt(np.mean(late[2:] ** 2)) > 0.2 and without > 2.0


@needs_records
def test_published_model_reproduces_record(rec):
    res = simulate_emps(PUBLISHED, rec)
    assert res.status[0] == 0
    err = position_rel_error_pct(rec.qm, res.q[0])
    assert err < 0.0011  # README: ≈ 0.001 %; here 0.00107 %
    nominal_only = simulate_emps(theta_from_dict({"M": PUBLISHED["M"], "Fv": PUBLISHED["Fv"]}), rec)
    assert position_rel_error_pct(rec.qm, nominal_only.q[0]) > 3 * err  # friction matters


@needs_records
def test_published_model_predicts_the_validation_record_with_its_pulses(val):
    """The pulses enter at the controller output (V): the published model predicts the record to 0.0016 %;
    left out they cost 0.06 %, and added as newtons to the force (the old reading) they do not help."""
    err = position_rel_error_pct(val.qm, simulate_emps(PUBLISHED_THETA, val).q[0])
    without = position_rel_error_pct(val.qm, simulate_emps(PUBLISHED_THETA, val, pulse_gain=0.0).q[0])
    as_newtons = position_rel_error_pct(val.qm, simulate_emps(PUBLISHED_THETA, val,
                                                              pulse_gain=1.0 / val.gtau).q[0])
    assert err < 0.002 and without > 0.05 and as_newtons > 0.05


def test_linear_case_matches_exact_zoh_discretisation(sim):
    """Without Coulomb friction the plant is linear: compare with the exact matrix-exponential ZOH update, the
    pulses (V) added to the controller output before the saturation."""
    r = simulated_record(PUBLISHED_THETA, 3000, pulses=pulse_train(3000, amplitude=12.0))
    M, Fv, off = 90.0, 250.0, -2.0
    res = simulate_emps(theta_from_dict({"M": M, "Fv": Fv, "offset": off}), r)
    A = np.array([[0.0, 1.0, 0.0], [0.0, -Fv / M, 1.0 / M], [0.0, 0.0, 0.0]])
    Phi = expm(A * r.dt)
    x0, v0, qm1, qm2 = initial_state(r.qm, r.dt)
    state = np.array([x0, v0])
    hist = [qm2, qm1]
    q_ref = np.empty(r.n)
    nu_ref = np.empty(r.n)
    for k in range(r.n):
        q_ref[k] = state[0]
        nu = r.kp * r.kv * (r.qg[k] - state[0]) - r.kv * (state[0] - hist[0]) / (2 * r.dt) + r.pulses[k]
        nu_ref[k] = nu = np.clip(nu, -10, 10)
        hist = [hist[1], state[0]]
        state = (Phi @ np.array([state[0], state[1], r.gtau * nu - off]))[:2]
    assert np.max(np.abs(res.q[0] - q_ref)) < 1e-10  # m
    assert np.max(np.abs(res.nu[0] - nu_ref)) < 1e-6  # V
    assert np.max(np.abs(res.nu[0])) == 10.0  # 12 V pulses drive the controller output into saturation


def test_pulses_enter_at_the_controller_output_causally(sim):
    n = 3000
    pulses = np.zeros(n)
    pulses[1000:1100] = 5.0
    base = simulated_record(PUBLISHED_THETA, n)
    r = EmpsRecord(t=base.t, vir=base.vir, qm=base.qm, qg=base.qg, pulses=pulses)
    with_p = simulate_emps(PUBLISHED_THETA, r)
    without = simulate_emps(PUBLISHED_THETA, r, pulse_gain=0.0)
    np.testing.assert_array_equal(with_p.q[0][:1001], without.q[0][:1001])  # nothing before the pulse acts
    np.testing.assert_array_equal(with_p.nu[0][:1000], without.nu[0][:1000])
    assert with_p.nu[0][1000] - without.nu[0][1000] == pytest.approx(5.0, abs=1e-12)  # V, on its own sample
    assert np.max(np.abs(with_p.q[0] - without.q[0])) > 1e-5  # 5 V = 176 N moves the axis by > 10 µm
    law = controller_law(r, q=with_p.q[0])  # the documented law on the simulated positions, pulses included
    np.testing.assert_allclose(with_p.nu[0][2:], law[2:], atol=1e-9)
    half = simulate_emps(PUBLISHED_THETA, r, pulse_gain=0.5).q[0]
    assert 0 < np.max(np.abs(half - without.q[0])) < np.max(np.abs(with_p.q[0] - without.q[0]))
    with pytest.raises(ConfigError):
        simulate_emps(PUBLISHED_THETA, r, pulse_gain=float("nan"))


def test_batched_equals_single_rows_and_invalid_rows_are_flagged(sim):
    r = sim.slice(0, 2000)
    good = np.array([PUBLISHED_THETA,
                     theta_from_dict({"M": 80.0, "Fv": 150.0, "Fc": 15.0, "Fs": 3.0, "vs": 0.01,
                                      "Fc_asym": 1.0, "Fv_asym": -20.0})])
    bad = np.array([theta_from_dict({"M": -1.0, "Fv": 200.0}),
                    theta_from_dict({"M": 95.0, "Fv": 200.0, "Fs": 2.0, "vs": 0.0}),
                    np.where(np.arange(len(PARAM_NAMES)) == 1, np.nan, PUBLISHED_THETA)])
    batch = simulate_emps(np.vstack([good[0], bad[0], good[1], bad[1], bad[2]]), r)
    np.testing.assert_array_equal(batch.status, [0, 3, 0, 3, 3])
    assert np.all(np.isnan(batch.q[[1, 3, 4]]))
    for row, theta in ((0, good[0]), (2, good[1])):
        single = simulate_emps(theta, r)
        np.testing.assert_array_equal(batch.q[row], single.q[0])
        np.testing.assert_array_equal(batch.nu[row], single.nu[0])
    assert simulate_emps(PUBLISHED_THETA, r, n_sub_max=3).status[0] == 2  # needs more substeps than allowed


def test_bad_settings_raise_config_error(sim):
    with pytest.raises(ConfigError):
        simulate_emps(np.zeros((2, 3)), sim)
    with pytest.raises(ConfigError):
        simulate_emps(PUBLISHED_THETA, sim, eps=0.0)
    with pytest.raises(ConfigError):
        theta_from_dict({"mass": 1.0})
    with pytest.raises(ConfigError):
        run_emps_loop(sim.slice(0, 500), candidates=["no_such_effect"])
    for bad in ({"noise_max_order": -1}, {"cv_block": 0}, {"cv_folds": 1}, {"cv_folds": 2.0},
                {"structure_bins": 1}, {"structure_alpha": 1.0}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            run_emps_loop(sim.slice(0, 500), **bad)
    with pytest.raises(ConfigError):
        fit_output_error(sim.slice(0, 500), ["M"], PUBLISHED_THETA, solver="newton")
    with pytest.raises(ConfigError):
        back_and_forth(2)


def test_effect_registry_is_consistent():
    assert set(EFFECTS) == {"coulomb_friction", "offset", "stribeck_friction", "asymmetric_friction"}
    for eff in EFFECTS.values():
        assert len(eff.params) == len(eff.lower) == len(eff.upper) == len(eff.default)
        for p, lo, hi, d in zip(eff.params, eff.lower, eff.upper, eff.default):
            assert OFF[INDEX[p]] == 0.0  # effects are off in the nominal model
            assert LOWER[INDEX[p]] == lo and UPPER[INDEX[p]] == hi and lo <= d <= hi
        assert all(req in EFFECTS for req in eff.requires)


# ---------------------------------------------------------------------------------------------------- IDIM-LS
@needs_records
def test_idim_ls_reproduces_readme(rec):
    out = idim_ls(rec)
    for name, ref in README_IDIM.items():
        assert out["params"][name] == pytest.approx(ref, rel=5e-3)
    assert out["cond"] == pytest.approx(25.99, abs=0.01)
    assert out["rel_error_pct"] == pytest.approx(4.12, abs=0.01)
    asym = idim_ls(rec, terms=("M", "Fv+", "Fc+", "Fv-", "Fc-"))["params"]
    for name, ref in {"M": 95.147, "Fv+": 166.71, "Fc+": 20.144, "Fv-": 239.68, "Fc-": 20.716}.items():
        assert asym[name] == pytest.approx(ref, rel=5e-3)


def test_idim_ls_on_a_simulated_record():
    """The inverse-model recipe on a record with known truth and no standstill: close to it (its filters and the
    smoothed sign bias it a little; standstills, where friction sticks below Fc, would bias Fc and Fv more)."""
    r = simulated_record(PUBLISHED_THETA, 8000, qg=back_and_forth(8000, dwell_s=0.0))
    out = idim_ls(r)["params"]
    for name in ("M", "Fv", "Fc", "offset"):
        assert out[name] == pytest.approx(PUBLISHED[name], rel=0.05, abs=0.3)


# ---------------------------------------------------------------------------------------------------- output error
def test_residual_and_jacobian(sim):
    r = sim.slice(0, 3000)
    free = ["M", "Fc", "offset"]
    res_fn = make_residual(r, free, PUBLISHED_THETA)
    x = PUBLISHED_THETA[[INDEX[n] for n in free]]
    resid = res_fn(x)
    q = simulate_emps(PUBLISHED_THETA, r).q[0]
    np.testing.assert_array_equal(resid, r.qm - q)
    assert np.all(res_fn(np.array([-1.0, 20.0, 0.0])) == FAIL_RESIDUAL)  # failure is data, not a crash
    J = make_jacobian(r, free, PUBLISHED_THETA, LOWER[[INDEX[n] for n in free]], UPPER[[INDEX[n] for n in free]])(x)
    h = 1e-3  # central difference in the offset (N)
    num = (res_fn(x + [0, 0, h]) - res_fn(x - [0, 0, h])) / (2 * h)
    assert np.linalg.norm(J[:, 2] - num) < 1e-3 * np.linalg.norm(num)


@pytest.mark.parametrize("solver", ["polish", "scipy"])
def test_output_error_fit_recovers_the_truth_of_a_simulated_record(sim, solver):
    start = theta_from_dict({"M": 80.0, "Fv": 250.0, "Fc": 10.0, "offset": 0.0})
    fit = fit_output_error(sim, ["M", "Fv", "Fc", "offset"], start, solver=solver)
    assert fit.rel_error_pct <= 1.01 * position_rel_error_pct(sim.qm, simulate_emps(PUBLISHED_THETA, sim).q[0])
    for name in ("M", "Fv", "Fc", "offset"):
        assert fit.params[name] == pytest.approx(PUBLISHED[name], rel=1e-3)


@needs_records
def test_output_error_fit_recovers_published_structure(rec):
    r = rec.slice(0, 8000)
    start = theta_from_dict({"M": 80.0, "Fv": 250.0, "Fc": 10.0, "offset": 0.0})
    fit = fit_output_error(r, ["M", "Fv", "Fc", "offset"], start)
    pub = simulate_emps(PUBLISHED_THETA, r).q[0]
    assert fit.rel_error_pct <= position_rel_error_pct(r.qm, pub)  # at least as good as the published values
    assert fit.params["M"] == pytest.approx(PUBLISHED["M"], rel=0.02)
    assert fit.params["Fc"] == pytest.approx(PUBLISHED["Fc"], rel=0.1)


def _fit(residual: np.ndarray, J: np.ndarray, free: tuple[str, ...]):
    """An OEFitResult holding only what :func:`judge_effect` reads (residual, Jacobian, correlations)."""
    from toggle_id.emps.fit import OEFitResult

    n = residual.size
    cov = np.linalg.inv(J.T @ J)
    d = np.sqrt(np.diag(cov))
    return OEFitResult(theta=PUBLISHED_THETA.copy(), free=free, sse=float(residual @ residual), n=n,
                       rel_error_pct=0.0, corr=cov / np.outer(d, d), residual=residual, jacobian=J)


def _ar1(n: int, rho: float, sigma: float, seed: int) -> np.ndarray:
    from scipy.signal import lfilter

    return lfilter([1.0], [1.0, -rho], np.random.default_rng(seed).normal(0.0, sigma, n))


def test_judge_effect_is_noise_aware():
    """Linear stand-ins for output-error fits under AR(1) noise (ρ = 0.95, ≈ N/39 independent samples): a
    regressor made of slow blocks that explains noise-sized wiggles passes the naive F-test but not the
    prewhitened one; a real effect passes every check; a collinear one fails the identifiability gate. The verdict
    is the discovery engine's Evidence, the gate one of its checks."""
    from scipy.stats import f as f_dist

    from toggle_id.discovery.validation import Evidence
    from toggle_id.emps.fit import new_params_corr

    n, rho, sigma = 20000, 0.95, 1e-6
    t = np.linspace(0.0, 1.0, n)
    base = np.column_stack([np.sin(2 * np.pi * t), np.ones(n)])
    effect = np.sign(np.sin(2 * np.pi * 7 * t))
    rejected_naive = rejected_white = 0
    for seed in range(10):
        noise = _ar1(n, rho, sigma, seed)
        slow = np.random.default_rng(100 + seed).normal(size=n // 1000).repeat(1000)  # 20 blocks of 1 s
        y = noise.copy()
        r0 = y - base @ np.linalg.lstsq(base, y, rcond=None)[0]
        X = np.column_stack([base, slow])
        r1 = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
        small, large = _fit(r0, base, ("a", "b")), _fit(r1, X, ("a", "b", "c"))
        ev = judge_effect(small, large, alpha=0.01)
        F_naive = (small.sse - large.sse) / (large.sse / (n - 3))
        rejected_naive += f_dist.sf(F_naive, 1, n - 3) >= 0.01
        assert isinstance(ev, Evidence)
        rejected_white += not ev.passed
        assert ev.noise.order >= 1 and abs(ev.noise.a[0] - rho) < 0.05
        assert ev.noise.to_dict()["effective_samples"] < n / 20
    assert rejected_white >= 9 and rejected_naive <= 5  # the naive test is fooled at least half of the time

    y = _ar1(n, rho, sigma, 1) + 2 * sigma * effect  # a real effect: every check passes
    r0 = y - base @ np.linalg.lstsq(base, y, rcond=None)[0]
    X = np.column_stack([base, effect])
    r1 = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
    small, large = _fit(r0, base, ("a", "b")), _fit(r1, X, ("a", "b", "c"))
    ev = judge_effect(small, large, alpha=0.01)
    assert ev.passed and all(ev.checks.values()) and ev.p_value < 1e-6 and ev.delta_bic < 0
    assert ev.cv1 < ev.cv0 and ev.sse1_w < ev.sse0_w
    assert ev.reason.startswith("significant in sample")
    d = ev.to_dict()
    json.dumps(d)
    assert d["checks"] == ev.checks and d["passed"] and d["p_value"] == ev.p_value
    corr = new_params_corr(small, large)
    assert 0 < corr < 1
    ev = judge_effect(small, large, alpha=0.01, max_corr=0.5 * corr)
    assert not ev.passed and ev.checks == {"f_test": True, "robust_f_test": True, "bic": True,
                                           "cross_validation": True, "identifiable": False}
    assert 1.0 <= ev.hc_ratio < 1.5 and ev.F_robust == pytest.approx(ev.F / ev.hc_ratio)
    assert ev.reason == "a new parameter is not identifiable (|correlation| > max_corr)"
    white = judge_effect(small, large, noise_max_order=0)
    assert white.noise.white and white.F > ev.F
    broken = judge_effect(small, _fit(np.full(n, np.nan), X, ("a", "b", "c")))
    assert not broken.passed and broken.checks["f_test"] is False and broken.noise.white


# ---------------------------------------------------------------------------------------------------- discovery loop
def test_loop_finds_the_simulated_friction_and_predicts_a_pulsed_record(sim):
    """On a record of the published model (Coulomb friction and an offset), the loop adds exactly those, recovers
    the values and predicts a held-out record with pulses to the quantisation level."""
    val = simulated_record(PUBLISHED_THETA, 3000, qg=back_and_forth(3000, waypoints=(0.0, 0.15, 0.05, 0.0)),
                           pulses=pulse_train(3000), name="sim_pulses")
    report = run_emps_loop(sim.slice(0, 5000), val, reference_fit=False,
                           candidates=["coulomb_friction", "offset", "asymmetric_friction"])
    assert [e["name"] for e in report["effects_added"]] == ["coulomb_friction", "offset"]
    assert [c["name"] for c in report["rejected"]] == ["asymmetric_friction"] and report["compensating"] == []
    assert all(a["evidence"]["passed"] and a["reason"] for a in report["effects_added"])
    for c in report["candidates"]:  # every verdict by the prewhitened tests and the cross-validation
        assert {"noise_model", "F", "p_value", "delta_bic", "in_sample_rms_w_after", "out_of_sample_rms_w_after",
                "verdict", "reason"} <= set(c)
    assert report["noise_model"]["n"] == 5000
    for name in ("M", "Fv", "Fc", "offset"):
        assert report["identified"][name] == pytest.approx(PUBLISHED[name], rel=2e-3)
    v = report["validation"]
    assert v["has_pulses"] and v["status"] == 0 and v["pulse_gain"] == 1.0
    assert v["logged_pulse_gain"] == pytest.approx(1.0, abs=0.01)
    assert v["position_rel_error_pct"] < 1e-4  # quantisation level
    assert v["models"]["final"]["without_pulses_rel_error_pct"] > 100 * v["position_rel_error_pct"]
    json.dumps(report)


@needs_records
def test_loop_finds_coulomb_on_short_record(rec):
    report = run_emps_loop(rec.slice(0, 6000), validation=rec.slice(6000, 9000), reference_fit=False)
    names = [e["name"] for e in report["effects_added"]]
    assert names[0] == "coulomb_friction"
    assert report["position_rel_error_pct_after"] < 0.5 * report["position_rel_error_pct_before"]
    assert report["position_rel_error_pct_after"] < 0.0011
    assert abs(report["pct_diff_vs_published"]["M"]) < 2.0
    assert report["validation"]["status"] == 0
    assert report["validation"]["position_rel_error_pct"] < report["validation"]["published_model_rel_error_pct"]
    assert {c["name"] for c in report["candidates"] if c["round"] == 1} == {"coulomb_friction", "offset"}
    assert sum(c["accepted"] for c in report["candidates"]) == len(names)
    listed = [c["name"] for key in ("effects_added", "compensating", "rejected") for c in report[key]]
    assert sorted(listed) == sorted(EFFECTS)
    assert isinstance(report["structure_left"], bool) and report["localisation"]["text"]
    json.dumps(report)


@pytest.mark.slow
@needs_records
def test_loop_on_full_record(rec):
    report = run_emps_loop(rec)
    assert report["position_rel_error_pct_after"] <= 0.0011
    assert "coulomb_friction" in [e["name"] for e in report["effects_added"]]
    assert abs(report["pct_diff_vs_published"]["M"]) < 2.0
    ref = report["reference"]["pct_diff_vs_published"]
    assert abs(ref["M"]) < 2.0 and abs(ref["Fv"]) < 5.0 and abs(ref["Fc"]) < 5.0
    assert report["seconds"] < 120
