"""Compiled kernel of the plant with backlash (a dead band b_l in the screw–nut), the `backlash` effect.

The nominal model is rigid: the rotor's inertia is reflected onto slider C (m_C + J_m·Z², eq. 10). With a
dead band the rotor and the nut are one body only while a flank is in contact; in between, the rotor turns
freely across the gap. In the nut's coordinate (x_r = θ_rotor/Z) the lash is δ = x_r − x_C ∈ [−b_l, 0]:

- engaged forward (δ = 0) or backward (δ = −b_l): the nominal rigid dynamics (q, q̇, i_q); the flank force
  the rotor transmits to the nut is F_s = F_motor − J_m·Z²·ẍ_C. The flank opens when F_s changes sign
  against it (F_s < 0 forward, F_s > 0 backward).
- in the lash: two bodies. The linkage (inertia M(q) − J_m·Z²·x_C'², no motor force) and the rotor
  (J_m·Z²·ẍ_r = F_motor(i_q, ẋ_r, rotor angle); the back-EMF follows the rotor, ẋ_r). States
  (q, q̇, i_q, δ, ẋ_r).
- the gap closes (δ reaches 0 or −b_l): a perfectly inelastic impact that conserves the generalised momentum,
  M·q̇⁺ = (M − J_m·Z²·x_C'²)·q̇⁻ + J_m·Z²·x_C'·ẋ_r⁻; engaged from there.

The simulation starts engaged forward (the nut rests on the driving flank; a stage-2 restart from a contact
state assumes the same). Integration: DOPRI5 in both modes with the contact switch, the flank opening and the
gap closing located on the dense output (the step is retaken to end at the event), so every step integrates a
smooth right-hand side. As b_l → 0 the trajectory tends to the rigid model's. Only parameter vectors with
b_l > 0 come here (see :func:`toggle_id.kernels.driver._simulate_row`).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .geometry import _geometry, _lookup, _lookup_d, _x_of_q
from .rhs import _command, _derived, _forces, _motor_force
from .slots import (
    B_L,
    G_R1,
    G_R3,
    G_XBL,
    G_Z,
    INVALID_PARAMS,
    J_M,
    MODEL_FAILURE,
    OK,
    PC_ILQ,
    PC_PLZL,
    PC_RSL,
    PC_XOFF,
    S_ATOL_I,
    S_ATOL_Q,
    S_ATOL_W,
    S_H0,
    S_HMAX,
    S_MAXSTEPS,
    S_RTOL,
    S_STOPS,
    SOLVER_FAILURE,
)
from .stepping import _dense, _first_sample, _illinois, _next_stop, _pi_control, _stops_on
from .tableaus import (
    _A21,
    _A31,
    _A32,
    _A41,
    _A42,
    _A43,
    _A51,
    _A52,
    _A53,
    _A54,
    _A61,
    _A62,
    _A63,
    _A64,
    _A65,
    _A71,
    _A73,
    _A74,
    _A75,
    _A76,
    _C2,
    _C3,
    _C4,
    _C5,
    _D1,
    _D3,
    _D4,
    _D5,
    _D6,
    _D7,
    _E1,
    _E3,
    _E4,
    _E5,
    _E6,
    _E7,
)

N_Y = 5  # q, q̇, i_q, δ, ẋ_r
ENGAGED_FWD, LASH, ENGAGED_BWD = 1, 0, -1

# DOPRI5 as a table: stage nodes, stage coefficients (row s: the weights of k_0..k_{s-1}), error and dense weights
_C = np.array([0.0, _C2, _C3, _C4, _C5, 1.0, 1.0])
_A = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
               [_A21, 0.0, 0.0, 0.0, 0.0, 0.0],
               [_A31, _A32, 0.0, 0.0, 0.0, 0.0],
               [_A41, _A42, _A43, 0.0, 0.0, 0.0],
               [_A51, _A52, _A53, _A54, 0.0, 0.0],
               [_A61, _A62, _A63, _A64, _A65, 0.0],
               [_A71, 0.0, _A73, _A74, _A75, _A76]])
_E = np.array([_E1, 0.0, _E3, _E4, _E5, _E6, _E7])
_DD = np.array([_D1, 0.0, _D3, _D4, _D5, _D6, _D7])


@nb.njit(cache=True)
def lash_rhs(y, u, mode, contact, pc, jz2, geo, tab, head, out):
    """dy/dt into ``out`` for y = (q, q̇, i_q, δ, ẋ_r) in ``mode`` (engaged ±1 or lash 0) and the command u (V).
    Returns ok (False outside the assembly range) and the flank force F_s (N; 0 in the lash)."""
    q, w, iq, d, vr = y[0], y[1], y[2], y[3], y[4]
    ok, _, dxB, dxC, x_C, M, dM, _, vC, _, _, F_f, _, F_i, _, dgC = _forces(q, w, iq, contact, pc, geo, tab, head)
    if not ok:
        return False, 0.0
    v_rot = vC if mode != LASH else vr  # the back-EMF and the motor's friction follow the rotor
    F_rot = _motor_force(iq, v_rot, x_C + d, pc)
    out[0] = w
    out[2] = u * pc[PC_ILQ] - pc[PC_RSL] * iq - pc[PC_PLZL] * v_rot
    if mode != LASH:
        wdot = (F_rot * dxC + (F_f - F_i) * dxB - 0.5 * dM * w * w) / M
        okd, _, ddxC, _, _, _, _ = _lookup_d(q, geo, tab, head)
        a_C = ddxC * w * w + dxC * wdot
        out[1], out[3], out[4] = wdot, 0.0, a_C
        return okd, F_rot - jz2 * a_C
    ML = M - jz2 * dxC * dxC
    if not ML > 0.0:
        return False, 0.0
    out[1] = ((F_f - F_i) * dxB - 0.5 * (dM - jz2 * dgC) * w * w) / ML
    out[3] = vr - vC
    out[4] = F_rot / jz2
    return True, 0.0


@nb.njit(cache=True)
def _rotor_with_nut(y, geo, tab, head):
    """The rotor's speed set to the nut's, ẋ_r = x_C'(q)·q̇ (engaged, or just separated)."""
    y[4] = _lookup(y[0], geo, tab, head)[3] * y[1]


@nb.njit(cache=True)
def _step(h, t, y, k, mode, contact, pc, jz2, geo, tab, head, v, ytmp, yn):
    """One DOPRI5 step from (t, y) with k[0] = f(t, y); fills k[1..6] and yn = y(t + h) (k[6] = f(t+h, yn)).
    Returns ok (False when a stage leaves the assembly range); the caller forms the error estimate from k."""
    for s in range(1, 7):
        for j in range(N_Y):
            acc = 0.0
            for m in range(s):
                acc += _A[s, m] * k[m, j]
            ytmp[j] = y[j] + h * acc
        ok, _ = lash_rhs(ytmp, _command(t + _C[s] * h, pc, v)[0], mode, contact, pc, jz2, geo, tab, head, k[s])
        if not ok:
            return False
    for j in range(N_Y):
        yn[j] = ytmp[j]
    return True


@nb.njit(cache=True)
def _dense_at(th_, h, y, yn, k, j):
    """Component j of DOPRI5's continuous extension at fraction th_ of the step."""
    r2 = yn[j] - y[j]
    r3 = h * k[0, j] - r2
    r5 = 0.0
    for m in range(7):
        r5 += _DD[m] * k[m, j]
    return _dense(th_, y[j], r2, r3, r2 - h * k[6, j] - r3, h * r5)


@nb.njit(cache=True)
def _event_value(kind, th_, t, h, y, yn, k, mode, contact, q_L, b, pc, jz2, geo, tab, head, v, ytmp, ftmp):
    """Event function ``kind`` on the dense output: 0 contact (q_L − q), 1 gap closing forward (δ), 2 gap
    closing backward (δ + b), 3 flank force F_s."""
    if kind == 0:
        return q_L - _dense_at(th_, h, y, yn, k, 0)
    if kind == 1:
        return _dense_at(th_, h, y, yn, k, 3)
    if kind == 2:
        return _dense_at(th_, h, y, yn, k, 3) + b
    for j in range(N_Y):
        ytmp[j] = _dense_at(th_, h, y, yn, k, j)
    return lash_rhs(ytmp, _command(t + th_ * h, pc, v)[0], mode, contact, pc, jz2, geo, tab, head, ftmp)[1]


@nb.njit(cache=True)
def _locate_event(kind, g0, g1, t, h, y, yn, k, mode, contact, q_L, b, pc, jz2, geo, tab, head, v, ytmp, ftmp):
    """Fraction of the step (far side of the root) where event ``kind`` changes sign (Illinois method)."""
    a, bb, ga, gb = 0.0, 1.0, g0, g1
    side = 0
    for _ in range(100):
        if gb == ga:  # values too small to tell apart (a flank force at rest is subnormal; halving underflows)
            break
        th_ = (a * gb - bb * ga) / (gb - ga)
        gm = _event_value(kind, th_, t, h, y, yn, k, mode, contact, q_L, b, pc, jz2, geo, tab, head, v, ytmp, ftmp)
        a, bb, ga, gb, side = _illinois(a, bb, ga, gb, side, th_, gm)
        if (bb - a) * h < 1e-13 or gm == 0.0:
            break
    return bb


@nb.njit(cache=True)
def _crossed(kind, g0, g1, mode, contact):
    """Did event ``kind`` fire between step start (g0) and end (g1) in the current mode?"""
    if kind == 0:
        return (g0 < 0.0 and g1 >= 0.0) if contact == 0 else (g0 >= 0.0 and g1 < 0.0)
    if kind == 1:
        return mode == LASH and g0 <= 0.0 and g1 > 0.0
    if kind == 2:
        return mode == LASH and g0 >= 0.0 and g1 < 0.0
    if mode == ENGAGED_FWD:
        return g0 >= 0.0 and g1 < 0.0
    if mode == ENGAGED_BWD:
        return g0 <= 0.0 and g1 > 0.0
    return False


@nb.njit(cache=True)
def simulate_lash(th, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                  out_x, out_i):
    """As :func:`toggle_id.kernels.rigid._simulate_one` (same arguments, outputs and return value) for a parameter
    vector with backlash b_l = th[B_L] > 0. DOPRI5 whatever settings[S_METHOD] says."""
    t_c, qc, wc, ic = np.inf, 0.0, 0.0, 0.0
    b = th[B_L]
    Z = geo[G_Z]
    jz2 = th[J_M] * Z * Z
    if not (b > 0.0 and jz2 > 0.0):  # a free rotor needs inertia
        return INVALID_PARAMS, 0, t_c, qc, wc, ic
    rtol = settings[S_RTOL]
    R = geo[G_R1] + geo[G_R3]
    atol = np.array([settings[S_ATOL_Q], settings[S_ATOL_W], settings[S_ATOL_I], settings[S_ATOL_Q] * R,
                     settings[S_ATOL_W] * R])
    hmax = settings[S_HMAX]
    max_steps = int(settings[S_MAXSTEPS])
    stops = _stops_on(settings[S_STOPS], use_sweep)
    pc = _derived(th, geo, sweep, use_sweep, t_out[0], t_out[1] - t_out[0])
    q_L = math.acos(geo[G_XBL] / (geo[G_R1] + geo[G_R3]))
    xoff = pc[PC_XOFF]

    y = np.empty(N_Y)
    yn = np.empty(N_Y)
    ytmp = np.empty(N_Y)
    ftmp = np.empty(N_Y)
    k = np.empty((7, N_Y))
    y[0], y[1], y[2] = y0[0], y0[1], y0[2]
    y[3] = 0.0
    _rotor_with_nut(y, geo, tab, head)
    mode = ENGAGED_FWD
    contact = contact0
    t = t_start
    ok, kk = _first_sample(y[0], y[2], t_start, t_out, n_out, geo, xoff, out_x, out_i)
    if not ok:
        return MODEL_FAILURE, 0, t_c, qc, wc, ic
    if kk >= n_out:
        return OK, 0, t_c, qc, wc, ic
    t_end = t_out[n_out - 1]

    h = min(settings[S_H0], hmax)
    facold = 1e-4
    n_steps = 0
    last_reject = False
    need_f = True
    g_now = np.zeros(4)
    g_new = np.zeros(4)
    while t < t_end - 1e-13:
        if n_steps >= max_steps:
            return SOLVER_FAILURE, n_steps, t_c, qc, wc, ic
        if h < 1e-14 * max(1.0, abs(t)) + 1e-15:
            return SOLVER_FAILURE, n_steps, t_c, qc, wc, ic
        if t + h > t_end:
            h = t_end - t
        if stops:
            h = min(h, _next_stop(t, pc, use_sweep) - t)
        if need_f:
            ok, F_s = lash_rhs(y, _command(t, pc, v)[0], mode, contact, pc, jz2, geo, tab, head, k[0])
            if not ok:
                return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
            # an engaged flank that pulls the wrong way opens at once (after an impact or a restart)
            if (mode == ENGAGED_FWD and F_s < 0.0) or (mode == ENGAGED_BWD and F_s > 0.0):
                mode = LASH
                _rotor_with_nut(y, geo, tab, head)
                ok, F_s = lash_rhs(y, _command(t, pc, v)[0], mode, contact, pc, jz2, geo, tab, head, k[0])
                if not ok:
                    return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
            g_now[0] = q_L - y[0]
            g_now[1] = y[3]
            g_now[2] = y[3] + b
            g_now[3] = F_s
            need_f = False
        n_steps += 1
        if not _step(h, t, y, k, mode, contact, pc, jz2, geo, tab, head, v, ytmp, yn):
            h *= 0.25
            last_reject = True
            continue
        err = 0.0
        for j in range(N_Y):
            e = 0.0
            for m in range(7):
                e += _E[m] * k[m, j]
            sc = (h * e) / (atol[j] + rtol * max(abs(y[j]), abs(yn[j])))
            err += sc * sc
        err = math.sqrt(err / N_Y)
        if not err <= 1e300:
            h *= 0.25
            last_reject = True
            continue
        accepted, h_prop, facold = _pi_control(err, h, facold)
        if not accepted:
            h = h_prop
            last_reject = True
            continue
        h_new = min(h_prop, hmax)
        if last_reject:
            h_new = min(h_new, h)
        last_reject = False
        # --- events: the first one inside the step ends it ---
        ok, F_end = lash_rhs(yn, _command(t + h, pc, v)[0], mode, contact, pc, jz2, geo, tab, head, ftmp)
        g_new[0] = q_L - yn[0]
        g_new[1] = yn[3]
        g_new[2] = yn[3] + b
        g_new[3] = F_end if ok else g_now[3]
        first, th_first = -1, 2.0
        for kind in range(4):
            if _crossed(kind, g_now[kind], g_new[kind], mode, contact):
                th_e = _locate_event(kind, g_now[kind], g_new[kind], t, h, y, yn, k, mode, contact, q_L, b, pc,
                                     jz2, geo, tab, head, v, ytmp, ftmp)
                if th_e < th_first:
                    first, th_first = kind, th_e
        if first >= 0 and th_first < 1.0:  # retake the step to end at the event, in the old mode
            h = max(th_first * h, 1e-15)
            if not _step(h, t, y, k, mode, contact, pc, jz2, geo, tab, head, v, ytmp, yn):
                return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
        # --- dense output at the samples inside (t, t + h] ---
        t_new = t + h
        while kk < n_out and t_out[kk] <= t_new + 1e-12:
            s = min((t_out[kk] - t) / h, 1.0)
            out_x[kk] = _x_of_q(_dense_at(s, h, y, yn, k, 0), geo) + xoff
            out_i[kk] = _dense_at(s, h, y, yn, k, 2)
            kk += 1
        t = t_new
        for j in range(N_Y):
            y[j] = yn[j]
            k[0, j] = k[6, j]  # first same as last
        if not (math.isfinite(y[0]) and math.isfinite(y[1]) and math.isfinite(y[2]) and math.isfinite(y[4])):
            return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
        g_now[0] = q_L - y[0]
        g_now[1] = y[3]
        g_now[2] = y[3] + b
        g_now[3] = g_new[3]
        if first >= 0:
            need_f = True
            h_new = min(h_new, max(h, 1e-6))
            if first == 0:
                if contact == 0 and t_c == np.inf:
                    t_c, qc, wc, ic = t, y[0], y[1], y[2]
                contact = 1 - contact
            elif first == 3:  # the flank opens: the rotor leaves the nut with the same speed
                mode = LASH
                _rotor_with_nut(y, geo, tab, head)
            else:  # the gap closes: inelastic impact, generalised momentum conserved
                _, _, _, dxC, _, M, _, _, _, _, _, _, _, _, _, _ = _forces(y[0], y[1], y[2], contact, pc, geo, tab,
                                                                          head)
                y[1] = ((M - jz2 * dxC * dxC) * y[1] + jz2 * dxC * y[4]) / M
                y[3] = 0.0 if first == 1 else -b
                y[4] = dxC * y[1]
                mode = ENGAGED_FWD if first == 1 else ENGAGED_BWD
        h = h_new
    if not (_geometry(y[0], geo)[0] and _x_of_q(y[0], geo) > 0.0):
        return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
    return OK, n_steps, t_c, qc, wc, ic
