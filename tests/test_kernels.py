"""Tests of the compiled kernels (toggle_id.kernels) against the independent numpy reference in toggle_id.plant:
geometry, inertia, right-hand side, the analytic Jacobian (against finite differences) and the input."""
from __future__ import annotations

import numpy as np
import pytest

from toggle_id import plant
from toggle_id.kernels import geometry as KG
from toggle_id.kernels import rhs as KR
from toggle_id.kernels import slots as K
from toggle_id.params import ASSIGNED
from toggle_id.plant import GEOMETRY
from toggle_id.record import SWEEPS
from toggle_id.simulate import extend, geometry_table

GEO = GEOMETRY.as_array()
TAB, HEAD = geometry_table()
Q_L = GEOMETRY.q_of_xB(GEOMETRY.x_B_L)
NO_SAMPLES = np.zeros(2)


def consts(theta: np.ndarray, sweep: str = "simulation") -> np.ndarray:
    return KR._derived(theta, GEO, SWEEPS[sweep].as_array(), True, 0.0, 1e-3)


def with_effects(theta: np.ndarray) -> np.ndarray:
    th = theta.copy()
    th[K.TAU_C], th[K.A_COG], th[K.N_COG], th[K.PHI_COG] = 0.05, 0.02, 3.0, 0.4
    th[K.F_S], th[K.V_S], th[K.K3], th[K.C_B], th[K.F_LOAD] = 5.0, 0.01, 1e9, 30.0, 20.0
    th[K.C_KT] = 4e-6  # the torque constant down by 1/√2 at 500 A
    return th


def with_generic_force(theta: np.ndarray, f_v, g_x, v_range=(-0.5, 0.5), x_range=(0.01, 0.09)) -> np.ndarray:
    """``theta`` with the generic slider force f(ẋ_B) + g(x_B) interpolating ``f_v`` and ``g_x`` at its knots."""
    th = theta.copy()
    th[K.GV_LO], th[K.GV_HI] = v_range
    th[K.GX_LO], th[K.GX_HI] = x_range
    th[K.GV_W0:K.GV_W0 + K.N_GEN] = f_v(np.linspace(*v_range, K.N_GEN))
    th[K.GX_W0:K.GX_W0 + K.N_GEN] = g_x(np.linspace(*x_range, K.N_GEN))
    return th


# q from near the singular end of link 5 (closed-form fallback) through the table to beyond the clamp
Q_GRID = np.concatenate([np.linspace(0.105, 1.5, 301), [Q_L - 1e-9, Q_L + 1e-9]])


def test_table_lookup_matches_closed_form_geometry():
    for q in Q_GRID:
        ref = KG._geometry_exact(q, GEO)
        got = KG._lookup(q, GEO, TAB, HEAD)
        assert got[0] == ref[0]
        if ref[0]:
            np.testing.assert_allclose(got[1:], ref[1:], rtol=1e-8, atol=1e-11)  # cubic Hermite, dq = 5e-4


def test_kinematics_match_plant_reference():
    k = plant.kinematics(Q_GRID)
    for j, q in enumerate(Q_GRID):
        ok, x_B, dxB, _, dxC, _, _, _, _, _, _, _ = KG._geometry(q, GEO)
        assert ok
        assert x_B == pytest.approx(k["x_B"][j], abs=1e-15)
        assert dxB == pytest.approx(k["dx_B"][j], abs=1e-14)
        assert dxC == pytest.approx(k["dx_C"][j], abs=1e-14)
        assert KG._xc_rel(q, GEO) == pytest.approx(k["x_C"][j], abs=1e-15)


@pytest.mark.parametrize("seed", [0, 1])
def test_mass_matrix_and_derivative_match_plant_reference(seed):
    th = extend(ASSIGNED * np.random.default_rng(seed).uniform(0.5, 1.5, ASSIGNED.size))[0]
    pc = consts(th)
    M_ref = plant.mass_matrix(Q_GRID, th[:15])
    for j, q in enumerate(Q_GRID):
        out = KR._forces(q, 0.0, 0.0, 0, pc, GEO, TAB, HEAD)
        M, dM = out[5], out[6]
        assert M == pytest.approx(M_ref[j], rel=1e-9)
        assert dM == pytest.approx(plant.mass_matrix_derivative(q, th[:15]), rel=1e-6, abs=1e-9)


def test_rhs_matches_plant_rhs_in_both_modes():
    rng = np.random.default_rng(3)
    th = extend(ASSIGNED)[0]
    pc = consts(th)
    sweep = SWEEPS["simulation"]
    for _ in range(100):
        q = rng.uniform(0.3, 1.4)
        y = np.array([q, rng.uniform(-3.0, 3.0), rng.uniform(-50.0, 400.0)])
        t = rng.uniform(0.0, 5.0)
        contact = int(q <= Q_L)  # plant.rhs decides the mode from the state
        ok, qd, wd, idot, _ = KR._rhs(t, y[0], y[1], y[2], contact, pc, GEO, TAB, HEAD, NO_SAMPLES)
        ref = plant.rhs(t, y, th[:15], sweep)
        assert ok
        assert qd == y[1]
        assert wd == pytest.approx(ref[1], rel=1e-7, abs=1e-6)
        assert idot == pytest.approx(ref[2], rel=1e-10, abs=1e-8)


@pytest.mark.parametrize("effects", [False, True, "generic force"])
@pytest.mark.parametrize("contact", [0, 1])
def test_analytic_jacobian_matches_finite_differences(effects, contact):
    rng = np.random.default_rng(7 + contact)
    th = extend(ASSIGNED)[0]
    th = with_effects(th) if effects else th
    if effects == "generic force":  # kinks at the knots: a random point lies within the FD step of one rarely
        th = with_generic_force(th, lambda v: 400.0 * v * np.abs(v) + 15.0, lambda x: 3e3 * (x - 0.05) ** 2)
    pc = consts(th)
    for _ in range(60):
        q = rng.uniform(0.2, 1.4)
        w = rng.uniform(-3.0, 3.0) * rng.choice([1.0, 1e-3])  # also inside the friction's tanh layer
        iq, t = rng.uniform(-50.0, 400.0), rng.uniform(0.0, 5.0)
        r = KR._rhs_jac(t, q, w, iq, contact, pc, GEO, TAB, HEAD, NO_SAMPLES)
        f = KR._rhs(t, q, w, iq, contact, pc, GEO, TAB, HEAD, NO_SAMPLES)
        assert r[0] and f[0]
        np.testing.assert_array_equal(r[1:4], f[1:4])
        J, ft = KR._jacobian_fd(t, q, w, iq, contact, pc, GEO, TAB, HEAD, NO_SAMPLES)
        Ja = np.array([[0.0, 1.0, 0.0], r[4:7], r[7:10]])
        dy = np.array([1e-3, max(abs(w), 1e-2), 1.0])  # typical state perturbations, to compare across units
        err = np.abs((Ja - J) * dy)
        scale = np.sum(np.abs(J * dy), axis=1, keepdims=True)
        assert np.all(err <= 1e-5 * scale), (q, w, iq, Ja, J)
        assert r[10] == pytest.approx(ft[2], rel=1e-5, abs=1e-6 * abs(pc[K.PC_KI] * pc[K.PC_ILQ]))


@pytest.mark.parametrize("contact", [0, 1])
def test_generic_force_reproduces_the_library_forces_it_can_take_the_shape_of(contact):
    """A constant f (or g) is the constant load force, a linear f on the knots' range the slider's viscous
    friction: the same right-hand side and Jacobian to rounding."""
    rng = np.random.default_rng(11)
    base = extend(ASSIGNED)[0]
    pairs = []
    for F in (-40.0, 25.0):
        load = base.copy()
        load[K.F_LOAD] = F
        pairs.append((load, with_generic_force(base, lambda v: 0 * v + F, lambda x: 0 * x)))
        pairs.append((load, with_generic_force(base, lambda v: 0 * v, lambda x: 0 * x + F)))
    visc = base.copy()
    visc[K.C_B] = 300.0
    pairs.append((visc, with_generic_force(base, lambda v: 300.0 * v, lambda x: 0 * x, v_range=(-5.0, 5.0))))
    for lib, gen in pairs:
        pc_lib, pc_gen = consts(lib), consts(gen)
        assert pc_gen[K.PC_GEN] == 1.0 and pc_lib[K.PC_GEN] == 0.0
        for _ in range(40):
            q = rng.uniform(0.2, 1.4)
            w, iq, t = rng.uniform(-3.0, 3.0), rng.uniform(-50.0, 400.0), rng.uniform(0.0, 5.0)
            a = KR._rhs_jac(t, q, w, iq, contact, pc_lib, GEO, TAB, HEAD, NO_SAMPLES)
            b = KR._rhs_jac(t, q, w, iq, contact, pc_gen, GEO, TAB, HEAD, NO_SAMPLES)
            np.testing.assert_allclose(b[1:], a[1:], rtol=1e-9, atol=1e-9)


def test_generic_force_is_off_at_zero_weights_and_constant_beyond_its_end_knots():
    base = extend(ASSIGNED)[0]
    assert consts(base)[K.PC_GEN] == 0.0
    gen = with_generic_force(base, lambda v: 10.0 + 100.0 * v, lambda x: 0 * x, v_range=(-0.1, 0.1))
    pc = consts(gen)
    for v, want in ((-0.1, 0.0), (-1.0, 0.0), (0.1, 20.0), (2.0, 20.0), (0.05, 15.0)):
        assert KR._hat(v, pc[K.PC_GVLO], pc[K.PC_GVIH], pc, K.PC_GVW)[0] == pytest.approx(want, abs=1e-12)
    assert KR._hat(2.0, pc[K.PC_GVLO], pc[K.PC_GVIH], pc, K.PC_GVW)[1] == 0.0
    assert KR._hat(0.0, pc[K.PC_GVLO], pc[K.PC_GVIH], pc, K.PC_GVW)[1] == pytest.approx(100.0)


def test_input_matches_sweep_and_its_slope():
    for name, sweep in SWEEPS.items():
        pc = consts(extend(ASSIGNED)[0], name)
        t = np.concatenate([np.linspace(0.0, 5.0, 2001), [4.999999, 5.0]])
        got = np.array([KR._input(x, pc, NO_SAMPLES)[0] for x in t])
        np.testing.assert_allclose(got, sweep(t), rtol=0, atol=1e-12)
        e = 1e-6
        for x in np.linspace(0.01, 4.99, 97):
            fd = (KR._input(x + e, pc, NO_SAMPLES)[0] - KR._input(x - e, pc, NO_SAMPLES)[0]) / (2 * e)
            assert KR._input(x, pc, NO_SAMPLES)[1] == pytest.approx(fd, rel=1e-5, abs=1e-7)


def test_sampled_input_interpolates_linearly_and_dead_time_shifts():
    th = extend(ASSIGNED)[0]
    th[K.TAU_D] = 0.0025
    v = np.array([0.0, 1.0, 3.0, 3.0])
    pc = KR._derived(th, GEO, np.zeros(5), False, 0.0, 1e-3)
    assert KR._input(0.0, pc, v) == (0.0, 0.0)  # before the record starts (shifted)
    val, slope = KR._input(0.0025 + 1.5e-3, pc, v)
    assert val == pytest.approx(2.0)
    assert slope == pytest.approx(2000.0)
    assert KR._input(1.0, pc, v)[0] == 3.0  # held after the last sample


def test_output_position_from_taylor_series_matches_closed_form():
    rng = np.random.default_rng(11)
    for q0 in np.linspace(0.25, 1.45, 25):
        c0, s0 = np.cos(q0), np.sin(q0)
        for dl in np.concatenate([rng.uniform(-0.1, 0.1, 20), [0.0, 0.1, -0.1, 0.3]]):
            x = KG._x_near(q0 + dl, q0, c0, s0, GEO)
            assert x == pytest.approx(plant.kinematics(q0 + dl)["x_B"], abs=5e-14)  # δ⁸/8! truncation
    other = GEO.copy()
    other[K.G_R3] = 0.08  # r1 ≠ r3: the general formula
    q = 0.7
    assert KG._x_near(q + 0.05, q, np.cos(q), np.sin(q), other) == pytest.approx(KG._x_of_q(q + 0.05, other), abs=1e-14)
    k = plant.kinematics(q + 0.05, plant.Geometry(r3=0.08))
    assert KG._x_of_q(q + 0.05, other) == pytest.approx(float(k["x_B"]), abs=1e-14)


def test_an_edit_of_any_kernel_source_empties_numbas_cache_of_the_package(tmp_path):
    """cache=True tracks only the defining file; the package's guard tracks them all (on a copy, not the real
    cache)."""
    from toggle_id.kernels import _drop_stale_caches

    (tmp_path / "rhs.py").write_text("A = 1\n")
    (tmp_path / "rigid.py").write_text("B = 2\n")
    cache = tmp_path / "__pycache__"
    _drop_stale_caches(tmp_path)
    for name in ("rigid._simulate_one-10.py311.nbi", "rigid._simulate_one-10.py311.1.nbc", "rigid.cpython-311.pyc"):
        (cache / name).write_bytes(b"x")
    _drop_stale_caches(tmp_path)  # nothing edited: the cache stays
    assert len(list(cache.glob("*.nb*"))) == 2
    (tmp_path / "rhs.py").write_text("A = 3\n")  # an edit of another file than the cached function's
    _drop_stale_caches(tmp_path)
    assert not list(cache.glob("*.nb*")) and (cache / "rigid.cpython-311.pyc").exists()
