"""Forward sensitivities of the rigid DOPRI5 solution (toggle_id/kernels/sens.py) against an independent
reference: central differences of whole simulations at steps large enough to rise above the integrator's noise
(the plant is nearly linear in most parameters over them). The contact switch is inside the record, so the
jump of the sensitivities at the switch is exercised."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from toggle_id.discovery.derivatives import sensitivities
from toggle_id.discovery.model import Model, fit_free
from toggle_id.effects import ALL_INDEX, ALL_NAMES
from toggle_id.errors import ConfigError
from toggle_id.kernels import slots as K
from toggle_id.params import ASSIGNED
from toggle_id.record import Record
from toggle_id.simulate import (ANALYTIC_SLOTS, PRECISE, PRECISE_STIFF, STATUS_INVALID, extend, simulate,
                                simulate_sensitivities)


@pytest.fixture(scope="module")
def record():
    rec = Record.from_sweep("simulation", 2.0, name="sens")
    res = simulate(extend(ASSIGNED[None, :]), rec, PRECISE)
    assert np.isfinite(res.contact[0, 0]), "the test record must reach the clamp (the switch's jump)"
    return rec


def _effects_on() -> np.ndarray:
    th = extend(ASSIGNED[None, :])[0]
    th[K.TAU_C], th[K.A_COG], th[K.N_COG] = 0.05, 0.02, 200.0
    th[K.F_S], th[K.V_S], th[K.C_B], th[K.F_LOAD] = 5.0, 0.01, 20.0, 3.0
    th[K.K3], th[K.C_KT], th[K.X_OFF] = 1e12, 1e-5, 2e-6
    th[ALL_INDEX["gx_lo"]], th[ALL_INDEX["gx_hi"]], th[ALL_INDEX["gx_w3"]] = 0.02, 0.1, -3.0
    return th


def _central(th, rec, slots, rel=3e-3, zero_step=1e-2, tier=PRECISE):
    T = np.repeat(th[None], 2 * len(slots), axis=0)
    h = np.array([rel * abs(th[c]) if th[c] != 0 else zero_step for c in slots])
    for j, c in enumerate(slots):
        T[2 * j, c] += h[j]
        T[2 * j + 1, c] -= h[j]
    R = simulate(T, rec, tier)
    return (R.x_B[0::2] - R.x_B[1::2]) / (2 * h[:, None])


def _errors(dx, th, rec, slots, steps=(1e-3, 3e-3, 1e-2), tier=PRECISE):
    """Per column, the relative distance of ``dx`` to the nearest of central differences at three steps: too short
    a step drowns in the adaptive integrator's noise, too long a one in curvature, and which wins differs by
    column."""
    err = np.full(len(slots), np.inf)
    for rel in steps:
        fd = _central(th, rec, slots, rel=rel, zero_step=10 * rel, tier=tier)
        err = np.minimum(err, np.linalg.norm(dx - fd, axis=1) / np.linalg.norm(fd, axis=1))
    return err


def test_sensitivities_match_central_differences_with_every_smooth_effect_on(record):
    th = _effects_on()
    slots = list(range(15)) + [K.TAU_C, K.F_S, K.V_S, K.C_B, K.A_COG, K.N_COG, K.PHI_COG, K.F_LOAD, K.K3,
                               K.X_OFF, K.C_KT, ALL_INDEX["gx_w3"], ALL_INDEX["gx_w4"]]
    res = simulate_sensitivities(th, record, PRECISE, slots)
    assert res.ok
    err = _errors(res.dx, th, record, slots)
    err[slots.index(K.N_COG)] = _errors(res.dx[[slots.index(K.N_COG)]], th, record, [K.N_COG],
                                        steps=(1e-5, 1e-4))[0]  # a fast phase: shorter steps
    bad = {ALL_NAMES[c]: f"{e:.2e}" for c, e in zip(slots, err) if not e < 1e-2}
    assert not bad, f"relative errors: {bad}"


def test_sensitivities_on_a_sampled_input_with_dead_time_and_a_clipped_drive():
    rec = Record.from_cycling(duration=2.0, name="cyc")
    th = extend(ASSIGNED[None, :])[0]
    th[K.TAU_D], th[K.S_SAT] = 0.003, 0.5  # the dead time shifts the input; |K_i·v_in| ≥ 2 V is clipped
    slots = [K.K_I, K.S_SAT, K.L_Q, K.R_S, K.LAMBDA_D, K.K_T, K.MB]
    res = simulate_sensitivities(th, rec, PRECISE, slots)
    assert res.ok
    err = _errors(res.dx, th, rec, slots)
    bad = {ALL_NAMES[c]: f"{e:.2e}" for c, e in zip(slots, err) if not e < 1e-2}
    assert not bad, f"relative errors: {bad}"


def test_sensitivities_along_rodas4_steps_match_central_differences(record):
    """The stiff tier (Rodas4 on the augmented system, its Jacobian's ∂(J·S)/∂y by differences), with the friction
    and the contact terms that make it stiff."""
    th = _effects_on()
    slots = list(range(15)) + [K.TAU_C, K.C_B, K.A_COG, K.F_LOAD, K.K3, K.X_OFF, K.C_KT]
    res = simulate_sensitivities(th, record, PRECISE_STIFF, slots)
    assert res.ok and not res.fell_back
    np.testing.assert_array_equal(res.x_B, simulate(th[None], record, PRECISE_STIFF).x_B[0])
    err = _errors(res.dx, th, record, slots, tier=PRECISE_STIFF)
    bad = {ALL_NAMES[c]: f"{e:.2e}" for c, e in zip(slots, err) if not e < 1e-2}
    assert not bad, f"relative errors: {bad}"


def test_a_vector_that_exhausts_dopri5s_budget_is_differentiated_on_the_fallback(record):
    th = extend(ASSIGNED[None, :])[0]
    tight = dataclasses.replace(PRECISE, max_steps=100)
    res = simulate_sensitivities(th, record, tight, [K.K_T, K.MU])
    assert res.ok and res.fell_back
    ref = simulate_sensitivities(th, record, PRECISE_STIFF, [K.K_T, K.MU])
    np.testing.assert_array_equal(res.dx, ref.dx)


def test_sensitivity_run_gives_the_simulation_bit_for_bit_and_any_thread_count_the_same(record):
    th = _effects_on()
    slots = sorted(ANALYTIC_SLOTS)
    one = simulate_sensitivities(th, record, PRECISE, slots, threads=1)
    two = simulate_sensitivities(th, record, PRECISE, slots, threads=2)
    sim = simulate(th[None], record, PRECISE)
    np.testing.assert_array_equal(one.x_B, sim.x_B[0])
    np.testing.assert_array_equal(one.i_q, sim.i_q[0])
    np.testing.assert_array_equal(one.dx, two.dx)
    assert np.all(np.isfinite(one.dx))


def test_sensitivities_refuse_what_they_cannot_differentiate_and_report_bad_values(record):
    th = extend(ASSIGNED[None, :])[0]
    with pytest.raises(ConfigError, match=str(K.TAU_D)):
        simulate_sensitivities(th, record, PRECISE, [K.TAU_D])
    lash = th.copy()
    lash[K.B_L] = 1e-4
    with pytest.raises(ConfigError, match="backlash"):
        simulate_sensitivities(lash, record, PRECISE, [K.K_T])
    bad = th.copy()
    bad[K.L_Q] = -1.0
    res = simulate_sensitivities(bad, record, PRECISE, [K.K_T])
    assert res.status == STATUS_INVALID and not res.ok and np.all(np.isnan(res.dx))


def _model(record, derivatives):
    th = _effects_on()
    x = simulate(th[None], record, PRECISE).x_B[0]
    rec = Record(t=record.t, v_in=record.v_in, x_B=x + 1e-6 * np.random.default_rng(3).standard_normal(x.size),
                 name="sens-measured", sweep=record.sweep, x_B0=record.x_B0)
    return Model(rec, PRECISE, parallel=True, derivatives=derivatives), th


def test_model_sensitivities_analytic_match_differences_with_the_hybrid_columns(record):
    """Analysis coordinates (log and affine), a dead-time column the kernel leaves to differences, and a column of
    the generic sensor error (an output map outside the kernel), with the map on."""
    fd, th = _model(record, "fd")
    an, _ = _model(record, "analytic")
    th = th.copy()
    th[ALL_INDEX["gs_lo"]], th[ALL_INDEX["gs_hi"]] = 0.019, 0.12
    th[ALL_INDEX["gs_w10"]] = 3e-6
    names = ["K_t", "m_B", "L_q", "tau_c", "x_off", "tau_d", "gs_w10", "gs_w11"]
    J_fd = sensitivities(fd, th, names, rel_step=1e-4)
    J_an = sensitivities(an, th, names, rel_step=1e-4)
    assert an.n_derivative_runs == 1
    for j, n in enumerate(names):
        err = np.linalg.norm(J_an[:, j] - J_fd[:, j]) / np.linalg.norm(J_fd[:, j])
        assert err < 2e-2, f"{n}: relative error {err:.2e}"


def test_fit_with_analytic_jacobians_reaches_the_same_optimum(record):
    fd, th = _model(record, "fd")
    an, _ = _model(record, "analytic")
    start = th.copy()
    start[K.K_T] *= 1.05
    start[K.MU] *= 0.9
    free = ("K_t", "mu", "B_m")
    f_fd = fit_free(fd, start, free, max_nfev=30)
    f_an = fit_free(an, start, free, max_nfev=30)
    assert an.n_derivative_runs > 0
    assert f_an.sse <= f_fd.sse * (1 + 1e-3)
    for n in free:
        assert f_an.theta[ALL_INDEX[n]] == pytest.approx(f_fd.theta[ALL_INDEX[n]], rel=1e-3)
