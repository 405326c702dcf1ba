"""The independent scipy plant of tests/outside_plant.py: with its outside-the-library effects off it is the
project's simulator (PRECISE tier) to far below the 1-µm encoder resolution; each effect moves x_B clearly."""
from __future__ import annotations

import numpy as np
import pytest
from outside_plant import Outside, Plant, _dmass, _mass, simulate_outside

from toggle_id.params import ASSIGNED, INDEX
from toggle_id.plant import mass_matrix, mass_matrix_derivative
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, extend, simulate


@pytest.fixture(scope="module")
def paper():
    """The paper's record (Table 1 sweep, 5 s): the reference's and the kernel's x_B, i_q with nothing added."""
    rec = Record.from_sweep("simulation", 5.0)
    x, i, info = simulate_outside(ASSIGNED, rec)
    return rec, x, i, info


def test_inertia_agrees_with_the_plant_module():
    p = {n: ASSIGNED[k] for n, k in INDEX.items()}
    for q in np.linspace(0.9, 1.45, 7):
        assert _mass(q, p) == pytest.approx(float(mass_matrix(q, ASSIGNED)), rel=1e-13)
        assert _dmass(q, p) == pytest.approx(float(mass_matrix_derivative(q, ASSIGNED)), rel=1e-7)


def test_without_its_effects_it_is_the_projects_simulator_on_the_papers_record(paper):
    rec, x, i, info = paper
    assert info["status"] == 0 and info["contacts"] == 1
    sim = simulate(extend(ASSIGNED), rec, PRECISE)
    assert sim.status[0] == 0
    assert np.max(np.abs(x - sim.x_B[0])) < 1e-9  # m: a thousandth of the encoder's micrometre
    assert np.max(np.abs(i - sim.i_q[0])) < 1e-6 * np.ptp(sim.i_q[0])
    assert abs(rec.t[np.argmax(x >= 0.056)] - rec.t[np.argmax(sim.x_B[0] >= 0.056)]) == 0.0


def test_without_its_effects_it_is_the_projects_simulator_on_the_cycling_command():
    """The sampled command (linear interpolation) with several contacts and releases."""
    rec = Record.from_cycling(duration=5.0)
    theta = ASSIGNED * np.exp(0.1 * np.random.default_rng(3).standard_normal(ASSIGNED.size))
    x, _, info = simulate_outside(theta, rec)
    assert info["status"] == 0 and info["contacts"] >= 3 and info["releases"] >= 3
    sim = simulate(extend(theta), rec, PRECISE)
    assert sim.status[0] == 0
    assert np.max(np.abs(x - sim.x_B[0])) < 2e-8


def test_each_outside_effect_moves_x_B_clearly_and_vanishes_when_off(paper):
    rec, x0, _, _ = paper
    bump, _, info_b = simulate_outside(ASSIGNED, rec, Outside(bump=(50.0, 0.040, 0.003)))
    sat, _, info_s = simulate_outside(ASSIGNED, rec, Outside(i_sat=2000.0))
    assert info_b["status"] == info_s["status"] == 0
    assert np.max(np.abs(bump - x0)) > 5e-6  # the slider is slowed where it passes x_c …
    before = rec.t < rec.t[np.argmax(x0 >= 0.028)]  # 4 widths from x_c
    assert np.max(np.abs(bump - x0)[before]) < 1e-9  # … and not before it gets near
    assert np.max(np.abs(sat - x0)) > 1e-5  # less clamping force at the ~350-A stall current
    free = rec.t < rec.t[np.argmax(x0 >= 0.05)]
    assert np.max(np.abs(sat - x0)[free]) < 0.1 * np.max(np.abs(sat - x0))  # the free motion draws less current
    drag, _, info_d = simulate_outside(ASSIGNED, rec, Outside(drag=5000.0))
    assert info_d["status"] == 0 and np.max(np.abs(drag - x0)) > 5e-6  # the fast strokes are slowed
    off, _, _ = simulate_outside(ASSIGNED, rec, Outside(bump=(0.0, 0.040, 0.003), i_sat=1e12, drag=0.0))
    assert np.max(np.abs(off - x0)) < 1e-12


def test_the_scale_error_is_in_the_reading_only():
    rec = Record.from_sweep("simulation", 1.0)
    x0, i0, _ = simulate_outside(ASSIGNED, rec)
    x, i, info = simulate_outside(ASSIGNED, rec, Outside(scale=(2e-6, 0.005, 0.3)))
    assert info["status"] == 0
    np.testing.assert_array_equal(i, i0)  # the motion is unchanged …
    np.testing.assert_allclose(x - x0, 2e-6 * np.sin(2 * np.pi * x0 / 0.005 + 0.3), rtol=0, atol=1e-15)


def test_the_scale_factor_error_is_in_the_reading_only():
    rec = Record.from_sweep("experiment", 1.0)
    x0, i0, _ = simulate_outside(ASSIGNED, rec)
    x, i, info = simulate_outside(ASSIGNED, rec, Outside(scale_factor=5e-4))
    assert info["status"] == 0
    np.testing.assert_array_equal(i, i0)  # the motion is unchanged …
    np.testing.assert_allclose(x - x0, 5e-4 * x0, rtol=0, atol=1e-15)  # … the reading 0.05 % long


@pytest.mark.parametrize("term", [{"pin_mu": 0.01}, {"hc_damping": 1e7}])
def test_pin_friction_and_penetration_damping_act_only_in_the_clamp(term):
    """Pin friction grows with the clamping force, Hunt–Crossley damping with the penetration: neither acts in free
    motion; both move x_B once the clamp closes, and vanish at zero."""
    rec = Record.from_cycling(duration=2.0)
    x0, _, info0 = simulate_outside(ASSIGNED, rec)
    x, _, info = simulate_outside(ASSIGNED, rec, Outside(**term))
    assert info0["status"] == info["status"] == 0 and info["contacts"] >= 1
    first = np.argmax(x0 >= 0.056)
    assert np.max(np.abs(x - x0)[:first]) < 1e-12  # free motion: no clamping force, no penetration
    assert np.max(np.abs(x - x0)[first:]) > 2e-6  # in the clamp and after it
    off, _, _ = simulate_outside(ASSIGNED, rec, Outside(**{k: 0.0 for k in term}))
    assert np.max(np.abs(off - x0)) < 1e-12


def test_the_drive_dead_band_ignores_small_commands_and_shifts_the_rest_towards_zero():
    band = Outside(deadband=2e-3)
    assert [band.drive(v) for v in (5e-3, -5e-3, 1.5e-3, -1.5e-3, 0.0)] == pytest.approx([3e-3, -3e-3, 0, 0, 0])
    assert Outside().drive(1.5e-3) == 1.5e-3
    rec = Record.from_sweep("simulation", 1.0)
    small = Record(rec.t, 1.9e-3 * np.sin(2 * np.pi * 3.0 * rec.t), x_B0=rec.x_B0, name="inside the band")
    x, i, info = simulate_outside(ASSIGNED, small, band)
    assert info["status"] == 0
    np.testing.assert_array_equal(i, 0.0)  # no current, no motion: the command never leaves the band
    np.testing.assert_array_equal(x, x[0])
    moved, _, _ = simulate_outside(ASSIGNED, small)
    assert np.ptp(moved) > 1e-6  # without the band the same command moves the slider
    x0, _, _ = simulate_outside(ASSIGNED, rec)
    x, _, info = simulate_outside(ASSIGNED, rec, band)
    assert info["status"] == 0 and np.max(np.abs(x - x0)) > 2e-6  # on the paper's sweep, clearly


def test_a_drifting_torque_constant_falls_linearly_in_time_and_its_effect_grows_along_the_record():
    kt = ASSIGNED[INDEX["K_t"]]
    plant = Plant(ASSIGNED, lambda t: 0.0, Outside(kt_drift=(0.1, 5.0)))
    assert [plant.torque_constant(50.0, t) for t in (0.0, 2.5, 5.0)] == pytest.approx([kt, 0.95 * kt, 0.9 * kt],
                                                                                      rel=1e-15)
    both = Plant(ASSIGNED, lambda t: 0.0, Outside(kt_drift=(0.1, 5.0), i_sat=100.0))
    assert both.torque_constant(100.0, 2.5) == pytest.approx(0.95 * kt / np.sqrt(2.0), rel=1e-15)
    rec = Record.from_sweep("simulation", 2.0)
    x0, _, _ = simulate_outside(ASSIGNED, rec)
    x, _, info = simulate_outside(ASSIGNED, rec, Outside(kt_drift=(0.01, 5.0)))
    off, _, _ = simulate_outside(ASSIGNED, rec, Outside(kt_drift=(0.0, 5.0)))
    assert info["status"] == 0 and np.max(np.abs(off - x0)) < 1e-12
    dev = np.abs(x - x0)
    assert np.max(dev[rec.t < 0.2]) < 0.05 * np.max(dev) and np.max(dev) > 1e-6


def test_leaving_the_assembly_range_is_a_failed_simulation():
    rec = Record.from_cycling(duration=2.0)
    theta = ASSIGNED.copy()
    theta[INDEX["K_i"]] *= 4.0  # opens far beyond x_B = 0
    x, i, info = simulate_outside(theta, rec)
    assert info["status"] == 1 and "x_B" in info["message"]
    assert np.isnan(x[-1]) and np.isnan(i[-1]) and np.isfinite(x[0])


@pytest.mark.parametrize("command", ["simulation", "cycling"])
def test_the_librarys_torque_saturation_is_the_independent_plants_saturating_torque_constant(command):
    """The library's ``torque_constant_saturation`` (kernel term K_t·i_q/√(1 + c_kt·i_q²), with its analytic
    Jacobian in the implicit clamped-mode integrator) against this plant's K_t/√(1 + (i_q/i_sat)²) at
    c_kt = 1/i_sat²: the same x_B and i_q, on the sweep (one clamp) and the cycling command (several)."""
    from toggle_id.effects import ALL_INDEX

    rec = Record.from_sweep("simulation", 5.0) if command == "simulation" else Record.from_cycling(duration=5.0)
    theta = ASSIGNED * np.exp(0.1 * np.random.default_rng(5).standard_normal(ASSIGNED.size))
    i_sat = 800.0
    x, i, info = simulate_outside(theta, rec, Outside(i_sat=i_sat))
    assert info["status"] == 0
    th = extend(theta)
    th[0, ALL_INDEX["c_kt"]] = 1.0 / i_sat ** 2
    sim = simulate(th, rec, PRECISE)
    x0 = simulate(extend(theta), rec, PRECISE).x_B[0]
    assert sim.status[0] == 0
    assert np.max(np.abs(x - x0)) > 5e-6  # the saturation moves x_B by micrometres …
    assert np.max(np.abs(x - sim.x_B[0])) < 2e-8  # … and both simulators agree far below the encoder's resolution
    assert np.max(np.abs(i - sim.i_q[0])) < 1e-6 * np.ptp(i)


@pytest.mark.parametrize("effect", ["cogging", "coulomb"])
def test_the_librarys_cogging_and_coulomb_torques_are_the_independent_plants(effect):
    """The kernel's cogging torque Z·a_cog·sin(n_cog·Z·x_C + φ_cog) and motor Coulomb torque −Z·τ_c·tanh(ẋ_C/ε)
    against this plant's, written from docs/model.md §7 alone, on the cycling command (contacts and releases):
    the same x_B and i_q far below the encoder's resolution, where the term itself moves x_B by micrometres."""
    from toggle_id.effects import ALL_INDEX

    rec = Record.from_cycling(duration=5.0)
    theta = ASSIGNED * np.exp(0.1 * np.random.default_rng(7).standard_normal(ASSIGNED.size))
    outside, library = ((Outside(cogging=(0.1, 6.0, 0.5)), {"a_cog": 0.1, "n_cog": 6.0, "phi_cog": 0.5})
                        if effect == "cogging" else (Outside(tau_c=0.3), {"tau_c": 0.3}))
    x, i, info = simulate_outside(theta, rec, outside)
    assert info["status"] == 0 and info["contacts"] >= 3
    th = extend(theta)
    for k, v in library.items():
        th[0, ALL_INDEX[k]] = v
    sim = simulate(th, rec, PRECISE)
    x0 = simulate(extend(theta), rec, PRECISE).x_B[0]
    assert sim.status[0] == 0
    assert np.max(np.abs(x - x0)) > 5e-6
    assert np.max(np.abs(x - sim.x_B[0])) < 2e-8
    assert np.max(np.abs(i - sim.i_q[0])) < 1e-6 * np.ptp(i)


def test_a_compliant_transmission_is_felt_and_tends_to_the_rigid_coupling_as_it_stiffens():
    """The rotor drives the nut through a spring: x_B moves by 10 µm at k_s = 1e8 N/m on 0.3 s of the sweep, and the
    difference to the rigid plant falls as 1/k_s (a tenfold stiffer spring: a tenth); the rigid path is untouched."""
    rec = Record.from_sweep("simulation", 0.3)
    x0, i0, _ = simulate_outside(ASSIGNED, rec)
    dev = {}
    for k_s in (1e8, 1e9):
        x, i, info = simulate_outside(ASSIGNED, rec, Outside(compliance=(k_s, 0.1)))
        assert info["status"] == 0 and np.all(np.isfinite(x)) and np.all(np.isfinite(i))
        dev[k_s] = np.max(np.abs(x - x0))
    assert dev[1e8] > 5e-6
    assert 8.0 < dev[1e8] / dev[1e9] < 13.0
    sim = simulate(extend(ASSIGNED), rec, PRECISE)
    assert np.max(np.abs(x0 - sim.x_B[0])) < 1e-9
