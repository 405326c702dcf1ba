"""EMPS plant: loaders, closed-loop simulator, IDIM-LS recipe, output-error fit and the effect-discovery loop.

Uses the real benchmark record in /work/shared/data/emps (skipped where it is absent).
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.io import savemat
from scipy.linalg import expm

from toggle_id.emps import (EFFECTS, PARAM_NAMES, PUBLISHED, PUBLISHED_THETA, EmpsRecord, controller_law,
                            fit_output_error, idim_ls, load_emps_csv, load_emps_mat, make_jacobian, make_residual,
                            position_rel_error_pct, run_emps_loop, simulate_emps, theta_from_dict)
from toggle_id.emps.data import DEFAULT_CSV, DEFAULT_MAT
from toggle_id.emps.fit import FAIL_RESIDUAL, f_test_pvalue
from toggle_id.emps.model import INDEX, LOWER, OFF, UPPER, initial_state
from toggle_id.errors import ConfigError, DataError

pytestmark = pytest.mark.skipif(not DEFAULT_CSV.is_file(), reason="EMPS benchmark data not available")

#: README's independent Python check of the IDIM-LS recipe.
README_IDIM = {"M": 95.104, "Fv": 203.13, "Fc": 20.438, "offset": -3.180}


@pytest.fixture(scope="module")
def rec() -> EmpsRecord:
    return load_emps_csv()


# ---------------------------------------------------------------------------------------------------- loading
def test_csv_loads_the_benchmark_record(rec):
    assert rec.n == 24841
    assert (rec.gtau, rec.kp, rec.kv, rec.dt) == (35.1507, 160.18, 243.45, 1e-3)
    assert np.all(rec.pulses == 0.0)
    assert rec.qm.max() == pytest.approx(0.24638, abs=1e-5)
    assert np.abs(rec.vir).max() == pytest.approx(4.326, abs=1e-3)


def test_mat_equals_csv_and_takes_constants_from_file(rec):
    m = load_emps_mat(DEFAULT_MAT)
    for key in ("t", "vir", "qm", "qg"):
        np.testing.assert_array_equal(getattr(m, key), getattr(rec, key))
    assert m.gtau == pytest.approx(35.15065188, rel=1e-9)  # the file's value, not the README's rounding
    assert load_emps_mat(DEFAULT_MAT, gtau=35.1507).gtau == 35.1507


def test_mat_with_pulses(tmp_path, rec):
    n = 3000
    pulses = np.zeros(n)
    pulses[1000:1100] = 50.0
    path = tmp_path / "pulses.mat"
    savemat(path, {"t": rec.t[:n, None], "vir": rec.vir[:n, None], "qm": rec.qm[:n, None],
                   "qg": rec.qg[:n, None], "pulses_N": pulses[:, None], "kp": 160.18})
    m = load_emps_mat(path)
    np.testing.assert_array_equal(m.pulses, pulses)
    assert m.kv == 243.45  # README default when the file lacks the key
    with_p = simulate_emps(PUBLISHED_THETA, m).q[0]
    without = simulate_emps(PUBLISHED_THETA, rec.slice(0, n)).q[0]
    np.testing.assert_array_equal(with_p[:1001], without[:1001])  # causal: nothing before the pulse starts
    assert np.max(np.abs(with_p - without)) > 1e-6  # a 50 N pulse moves the axis by micrometres


def test_bad_input_raises_data_error(tmp_path, rec):
    with pytest.raises(DataError, match="not found"):
        load_emps_csv(tmp_path / "missing.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,vir,qm\n0,1,2\n")
    with pytest.raises(DataError, match="qg"):
        load_emps_csv(bad)
    qm = rec.qm[:100].copy()
    qm[10] = np.nan
    with pytest.raises(DataError, match="NaN"):
        EmpsRecord(t=rec.t[:100], vir=rec.vir[:100], qm=qm, qg=rec.qg[:100])
    with pytest.raises(DataError, match="samples"):
        EmpsRecord(t=rec.t[:100], vir=rec.vir[:99], qm=rec.qm[:100], qg=rec.qg[:100])
    with pytest.raises(DataError, match="uniform"):
        EmpsRecord(t=rec.t[:100] * 2, vir=rec.vir[:100], qm=rec.qm[:100], qg=rec.qg[:100])
    with pytest.raises(DataError, match="increasing"):
        EmpsRecord(t=rec.t[:100][::-1], vir=rec.vir[:100], qm=rec.qm[:100], qg=rec.qg[:100])
    with pytest.raises(DataError, match="gtau"):
        EmpsRecord(t=rec.t[:100], vir=rec.vir[:100], qm=rec.qm[:100], qg=rec.qg[:100], gtau=-1.0)


# ---------------------------------------------------------------------------------------------------- model
def test_controller_law_matches_recorded_vir(rec):
    err = rec.vir - controller_law(rec)
    assert np.sqrt(np.mean(err[2:] ** 2)) < 0.01  # V, against a signal rms of 1.54 V


def test_published_model_reproduces_record(rec):
    res = simulate_emps(PUBLISHED, rec)
    assert res.status[0] == 0
    err = position_rel_error_pct(rec.qm, res.q[0])
    assert err < 0.0011  # README: ≈ 0.001 %; here 0.00107 %
    nominal_only = simulate_emps(theta_from_dict({"M": PUBLISHED["M"], "Fv": PUBLISHED["Fv"]}), rec)
    assert position_rel_error_pct(rec.qm, nominal_only.q[0]) > 3 * err  # friction matters


def test_linear_case_matches_exact_zoh_discretisation(rec):
    """Without Coulomb friction the plant is linear: compare with the exact matrix-exponential ZOH update."""
    r = rec.slice(0, 3000)
    M, Fv, off = 90.0, 250.0, -2.0
    q_sim = simulate_emps(theta_from_dict({"M": M, "Fv": Fv, "offset": off}), r).q[0]
    A = np.array([[0.0, 1.0, 0.0], [0.0, -Fv / M, 1.0 / M], [0.0, 0.0, 0.0]])
    Phi = expm(A * r.dt)
    x0, v0, qm1, qm2 = initial_state(r.qm, r.dt)
    state = np.array([x0, v0])
    hist = [qm2, qm1]
    q_ref = np.empty(r.n)
    for k in range(r.n):
        q_ref[k] = state[0]
        nu = np.clip(r.kp * r.kv * (r.qg[k] - state[0]) - r.kv * (state[0] - hist[0]) / (2 * r.dt), -10, 10)
        hist = [hist[1], state[0]]
        state = (Phi @ np.array([state[0], state[1], r.gtau * nu - off]))[:2]
    assert np.max(np.abs(q_sim - q_ref)) < 1e-10  # m


def test_batched_equals_single_rows_and_invalid_rows_are_flagged(rec):
    r = rec.slice(0, 2000)
    good = np.array([PUBLISHED_THETA,
                     theta_from_dict({"M": 80.0, "Fv": 150.0, "Fc": 15.0, "Fs": -3.0, "vs": 0.01,
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


def test_bad_settings_raise_config_error(rec):
    with pytest.raises(ConfigError):
        simulate_emps(np.zeros((2, 3)), rec)
    with pytest.raises(ConfigError):
        simulate_emps(PUBLISHED_THETA, rec, eps=0.0)
    with pytest.raises(ConfigError):
        theta_from_dict({"mass": 1.0})
    with pytest.raises(ConfigError):
        run_emps_loop(rec.slice(0, 500), candidates=["no_such_effect"])
    with pytest.raises(ConfigError):
        fit_output_error(rec.slice(0, 500), ["M"], PUBLISHED_THETA, solver="newton")


def test_effect_registry_is_consistent():
    assert set(EFFECTS) == {"coulomb_friction", "offset", "stribeck_friction", "asymmetric_friction"}
    for eff in EFFECTS.values():
        assert len(eff.params) == len(eff.lower) == len(eff.upper) == len(eff.default)
        for p, lo, hi, d in zip(eff.params, eff.lower, eff.upper, eff.default):
            assert OFF[INDEX[p]] == 0.0  # effects are off in the nominal model
            assert LOWER[INDEX[p]] == lo and UPPER[INDEX[p]] == hi and lo <= d <= hi
        assert all(req in EFFECTS for req in eff.requires)


# ---------------------------------------------------------------------------------------------------- IDIM-LS
def test_idim_ls_reproduces_readme(rec):
    out = idim_ls(rec)
    for name, ref in README_IDIM.items():
        assert out["params"][name] == pytest.approx(ref, rel=5e-3)
    assert out["cond"] == pytest.approx(25.99, abs=0.01)
    assert out["rel_error_pct"] == pytest.approx(4.12, abs=0.01)
    asym = idim_ls(rec, terms=("M", "Fv+", "Fc+", "Fv-", "Fc-"))["params"]
    for name, ref in {"M": 95.147, "Fv+": 166.71, "Fc+": 20.144, "Fv-": 239.68, "Fc-": 20.716}.items():
        assert asym[name] == pytest.approx(ref, rel=5e-3)


# ---------------------------------------------------------------------------------------------------- output error
def test_residual_and_jacobian(rec):
    r = rec.slice(0, 3000)
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
def test_output_error_fit_recovers_published_structure(rec, solver):
    r = rec.slice(0, 8000)
    start = theta_from_dict({"M": 80.0, "Fv": 250.0, "Fc": 10.0, "offset": 0.0})
    fit = fit_output_error(r, ["M", "Fv", "Fc", "offset"], start, solver=solver)
    pub = simulate_emps(PUBLISHED_THETA, r).q[0]
    assert fit.rel_error_pct <= position_rel_error_pct(r.qm, pub)  # at least as good as the published values
    assert fit.params["M"] == pytest.approx(PUBLISHED["M"], rel=0.02)
    assert fit.params["Fc"] == pytest.approx(PUBLISHED["Fc"], rel=0.1)


def test_f_test_pvalue():
    assert f_test_pvalue(1.0, 2, 1.0, 3, 1000) == 1.0
    assert f_test_pvalue(1.0, 2, 0.5, 3, 1000) < 1e-10
    assert 0.01 < f_test_pvalue(1.0, 2, 0.999, 3, 1000) < 1.0


# ---------------------------------------------------------------------------------------------------- discovery loop
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
    json.dumps(report)  # plain data for the Hydra job's result files


@pytest.mark.slow
def test_loop_on_full_record(rec):
    report = run_emps_loop(rec)
    assert report["position_rel_error_pct_after"] <= 0.0011
    assert "coulomb_friction" in [e["name"] for e in report["effects_added"]]
    assert abs(report["pct_diff_vs_published"]["M"]) < 2.0
    ref = report["reference"]["pct_diff_vs_published"]
    assert abs(ref["M"]) < 2.0 and abs(ref["Fv"]) < 5.0 and abs(ref["Fc"]) < 5.0
    assert report["seconds"] < 120
