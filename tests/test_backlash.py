"""The backlash kernel (toggle_id/kernels/backlash.py) against an independent reference: the same hybrid model written
with toggle_id.plant's numpy kinematics, M(q) and finite-difference derivatives, integrated by scipy's DOP853
with its own event location."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from toggle_id.effects import ALL_INDEX
from toggle_id.params import ASSIGNED, INDEX
from toggle_id.plant import GEOMETRY as G
from toggle_id.plant import kinematics, mass_matrix, mass_matrix_derivative
from toggle_id.record import Record
from toggle_id.simulate import FAST, PRECISE, STATUS_INVALID, extend, simulate


def _d(f, q, e=1e-6):
    """Fourth-order central difference of f at q (the stencil of plant.mass_matrix_derivative)."""
    return (-f(q + 2 * e) + 8 * f(q + e) - 8 * f(q - e) + f(q - 2 * e)) / (12 * e)


class Reference:
    """Rotor and linkage as two bodies while the lash is open, one body (the nominal model) while a flank
    touches; inelastic impact when the gap closes. y = (q, q̇, i_q, δ, ẋ_r), δ ∈ [−b, 0]."""

    def __init__(self, theta: np.ndarray, b: float, v_in) -> None:
        self.p = {n: theta[i] for n, i in INDEX.items()}
        self.theta, self.b, self.v_in = theta, b, v_in
        self.jz2 = self.p["J_m"] * G.Z ** 2

    def parts(self, t, y, contact):
        p, Z = self.p, G.Z
        q, w, iq = y[:3]
        k = kinematics(q)
        M = float(mass_matrix(q, self.theta))
        dM = float(mass_matrix_derivative(q, self.theta))
        ddxC = float(_d(lambda x: kinematics(x)["dx_C"], q))
        dgC = float(_d(lambda x: kinematics(x)["dx_C"] ** 2, q))
        vB, vC = k["dx_B"] * w, k["dx_C"] * w
        F_f = -p["mu"] * p["m_B"] * G.g * np.tanh(vB / G.eps_friction)
        z = k["x_B"] - G.x_B_L
        F_i = p["K_l"] * z + p["D"] * vB if contact else 0.0
        motor = lambda v: Z * p["K_t"] * iq - Z ** 2 * p["B_m"] * v
        didt = lambda v: (p["K_i"] * self.v_in(t) - p["R_s"] * iq - G.pole_pairs * p["lambda_d"] * Z * v) / p["L_q"]
        return k, M, dM, ddxC, dgC, vC, F_f, F_i, motor, didt

    def engaged(self, t, y, contact):
        k, M, dM, ddxC, _, vC, F_f, F_i, motor, didt = self.parts(t, y, contact)
        w = y[1]
        wdot = (motor(vC) * k["dx_C"] + (F_f - F_i) * k["dx_B"] - 0.5 * dM * w * w) / M
        a_C = ddxC * w * w + k["dx_C"] * wdot
        return np.array([w, wdot, didt(vC), 0.0, a_C]), motor(vC) - self.jz2 * a_C

    def lash(self, t, y, contact):
        k, M, dM, _, dgC, vC, F_f, F_i, motor, didt = self.parts(t, y, contact)
        w, vr = y[1], y[4]
        ML = M - self.jz2 * k["dx_C"] ** 2
        wdot = ((F_f - F_i) * k["dx_B"] - 0.5 * (dM - self.jz2 * dgC) * w * w) / ML
        return np.array([w, wdot, didt(vr), vr - vC, motor(vr) / self.jz2])

    def system(self, mode: int, contact: int, q_L: float):
        """Right-hand side and terminal events of one mode."""
        def contact_ev(tt, yy):
            return q_L - yy[0]
        contact_ev.terminal, contact_ev.direction = True, (1 if contact == 0 else -1)
        if mode:
            def flank(tt, yy):
                return self.engaged(tt, yy, contact)[1]
            flank.terminal, flank.direction = True, -mode
            return (lambda tt, yy: self.engaged(tt, yy, contact)[0]), [contact_ev, flank]

        def fwd(tt, yy):
            return yy[3]

        def bwd(tt, yy):
            return yy[3] + self.b
        fwd.terminal, fwd.direction, bwd.terminal, bwd.direction = True, 1, True, -1
        return (lambda tt, yy: self.lash(tt, yy, contact)), [contact_ev, fwd, bwd]

    def run(self, t_out: np.ndarray) -> tuple[np.ndarray, int]:
        q_L = float(np.arccos(G.x_B_L / (G.r1 + G.r3)))
        y = np.array([G.q_of_xB(0.020), 0.0, 0.0, 0.0, 0.0])
        t, mode, contact, switches = float(t_out[0]), 1, 0, 0
        x = np.full(t_out.shape, np.nan)
        while t < t_out[-1] - 1e-12:
            f, events = self.system(mode, contact, q_L)
            sel = t_out >= t - 1e-12
            sol = solve_ivp(f, (t, t_out[-1]), y, method="DOP853", rtol=1e-11, atol=1e-13, events=events,
                            dense_output=True, max_step=1e-3)
            t_end = sol.t[-1]
            sel &= t_out <= t_end + 1e-12
            x[sel] = kinematics(sol.sol(t_out[sel])[0])["x_B"]
            t, y = t_end, sol.y[:, -1].copy()
            if sol.status != 1:
                break
            switches += 1
            fired = next(i for i, te in enumerate(sol.t_events) if len(te))
            if fired == 0:
                contact = 1 - contact
            elif mode:  # the flank opens
                mode, y[4] = 0, kinematics(y[0])["dx_C"] * y[1]
            else:  # the gap closes
                k = kinematics(y[0])
                M = float(mass_matrix(y[0], self.theta))
                y[1] = ((M - self.jz2 * k["dx_C"] ** 2) * y[1] + self.jz2 * k["dx_C"] * y[4]) / M
                mode = 1 if fired == 1 else -1
                y[3], y[4] = (0.0 if mode == 1 else -self.b), k["dx_C"] * y[1]
            if mode and self.engaged(t, y, contact)[1] * mode < 0:  # pulled off the flank at once
                mode, y[4] = 0, kinematics(y[0])["dx_C"] * y[1]
        return x, switches


def _theta(b: float) -> np.ndarray:
    th = extend(ASSIGNED)
    th[0, ALL_INDEX["b_l"]] = b
    return th


@pytest.fixture(scope="module")
def short():
    return Record.from_sweep("simulation", 0.6)


def test_kernel_matches_the_independent_reference(short):
    b = 5e-4
    ref, switches = Reference(ASSIGNED, b, short.sweep).run(short.t)
    assert switches >= 4, "the lash never opened: the test would not test it"
    sim = simulate(_theta(b), short, PRECISE)
    assert sim.status[0] == 0
    assert np.max(np.abs(sim.x_B[0] - ref)) < 1e-8
    rigid = simulate(_theta(0.0), short, PRECISE)
    assert np.max(np.abs(rigid.x_B[0] - ref)) > 1e-5  # and the lash changes the motion measurably


def test_fast_tier_agrees_with_the_precise_tier():
    rec = Record.from_sweep("simulation", 5.0)
    for b in (1e-5, 5e-4):
        f, p = simulate(_theta(b), rec, FAST), simulate(_theta(b), rec, PRECISE)
        assert f.status[0] == p.status[0] == 0
        assert np.max(np.abs(f.x_B[0] - p.x_B[0])) < 3e-6


def test_vanishing_lash_tends_to_the_rigid_model():
    rec = Record.from_sweep("simulation", 5.0)
    rigid = simulate(_theta(0.0), rec, PRECISE).x_B[0]
    gaps = (1e-8, 1e-7, 1e-6)
    dev = [np.max(np.abs(simulate(_theta(b), rec, PRECISE).x_B[0] - rigid)) for b in gaps]
    assert dev[0] < 1e-7 and dev[0] < dev[1] < dev[2]
    assert dev[2] / dev[1] == pytest.approx(10.0, rel=0.3)  # first order in the gap


def test_a_free_rotor_without_inertia_is_an_invalid_row(short):
    th = _theta(5e-4)
    th[0, ALL_INDEX["J_m"]] = 0.0
    res = simulate(np.vstack([th, _theta(5e-4)]), short, FAST)
    assert res.status[0] == STATUS_INVALID and res.status[1] == 0
    assert np.all(np.isnan(res.x_B[0])) and np.all(np.isfinite(res.x_B[1]))


def test_event_location_stops_where_subnormal_values_no_longer_differ():
    """A flank force at rest is subnormal noise (a probe's 0.2-mm lash refit at 1e-322 N), where the Illinois
    method's halving underflows and both ends of the bracket take the same value; the location stops there (it
    divided by zero and crashed the discover job) and returns a fraction of the step."""
    from toggle_id.kernels.backlash import N_Y, _locate_event

    y, yn, k = np.zeros(N_Y), np.zeros(N_Y), np.zeros((7, N_Y))
    y[3], yn[3] = -2.96e-322, 2.17e-322  # the gap δ (event 1) across the step, at the scale of the force's noise
    k[:, 3] = [1.09999e-318, -4.54995e-319, 1.03999e-318, 1.25e-319, 2.34997e-319, 1.484983e-318, -1.10999e-318]
    th = _locate_event(1, y[3], yn[3], 0.0, 1e-3, y, yn, k, 0, 0, 1.0, 1e-4, np.zeros(64), 1.0, np.zeros(8),
                       np.zeros((2, 2)), np.zeros(2), np.zeros(2), np.zeros(N_Y), np.zeros(N_Y))
    assert 0.0 < th <= 1.0
