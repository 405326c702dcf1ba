"""The rigid plant's adaptive integrators with dense output and exact location of the contact instant:

- Rodas4 (Hairer & Wanner, a linearly implicit, L-stable Rosenbrock method of order 4 with an embedded order-3
  estimate and an order-3 continuous extension) with the analytic 3×3 Jacobian: the fast tier. The clamped mode
  is stiff (contact spring: ω ≈ 1700 rad/s), which limits any explicit method to steps of about 1.4 ms; Rodas4
  steps are set by accuracy alone (about 580 steps for a 5-s record at the fast tolerances, against 3550).
- Dormand–Prince 5(4) (DOPRI5, explicit, order-4 continuous extension): the precise tier, where the steps
  are small for accuracy anyway and the cheaper explicit step wins.

:func:`_simulate_one` integrates one parameter vector with either (or DOPRI5 free and Rodas4 clamped).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .geometry import _geometry, _x_near, _x_of_q
from .rhs import _command, _derived, _rhs_jac_u, _rhs_u
from .slots import (
    G_R1,
    G_R3,
    G_XBL,
    METHOD_MIXED,
    METHOD_RODAS4,
    MODEL_FAILURE,
    OK,
    PC_XOFF,
    S_ATOL_I,
    S_ATOL_Q,
    S_ATOL_W,
    S_H0,
    S_HMAX,
    S_MAXSTEPS,
    S_METHOD,
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
    _RA21,
    _RA31,
    _RA32,
    _RA41,
    _RA42,
    _RA43,
    _RA51,
    _RA52,
    _RA53,
    _RA54,
    _RC21,
    _RC31,
    _RC32,
    _RC41,
    _RC42,
    _RC43,
    _RC51,
    _RC52,
    _RC53,
    _RC54,
    _RC61,
    _RC62,
    _RC63,
    _RC64,
    _RC65,
    _RCC2,
    _RCC3,
    _RCC4,
    _RD1,
    _RD2,
    _RD3,
    _RD4,
    _RG,
    _RH21,
    _RH22,
    _RH23,
    _RH24,
    _RH25,
    _RH31,
    _RH32,
    _RH33,
    _RH34,
    _RH35,
)


@nb.njit(cache=True)
def _dopri_step(h, t, q, w, iq, k1q, k1w, k1i, contact, pc, geo, tab, head, v):
    """One Dormand–Prince step of size h from (t, y) with k1 = f(t, y). Returns ok, y(t+h), k7 = f(t+h, y(t+h))
    (first same as last), the error estimate, the dense-output coefficients (r3, r4, r5) of q and i_q, and the
    command and its slope at t+h."""
    u2 = _command(t + _C2 * h, pc, v)[0]
    u3 = _command(t + _C3 * h, pc, v)[0]
    u4 = _command(t + _C4 * h, pc, v)[0]
    u5 = _command(t + _C5 * h, pc, v)[0]
    uh, duh = _command(t + h, pc, v)  # stages 6 and 7
    ok2, k2q, k2w, k2i, _ = _rhs_u(q + h * _A21 * k1q, w + h * _A21 * k1w, iq + h * _A21 * k1i, u2, contact, pc, geo, tab, head)
    ok3, k3q, k3w, k3i, _ = _rhs_u(q + h * (_A31 * k1q + _A32 * k2q), w + h * (_A31 * k1w + _A32 * k2w),
                                 iq + h * (_A31 * k1i + _A32 * k2i), u3, contact, pc, geo, tab, head)
    ok4, k4q, k4w, k4i, _ = _rhs_u(q + h * (_A41 * k1q + _A42 * k2q + _A43 * k3q),
                                 w + h * (_A41 * k1w + _A42 * k2w + _A43 * k3w),
                                 iq + h * (_A41 * k1i + _A42 * k2i + _A43 * k3i), u4, contact, pc, geo, tab, head)
    ok5, k5q, k5w, k5i, _ = _rhs_u(q + h * (_A51 * k1q + _A52 * k2q + _A53 * k3q + _A54 * k4q),
                                 w + h * (_A51 * k1w + _A52 * k2w + _A53 * k3w + _A54 * k4w),
                                 iq + h * (_A51 * k1i + _A52 * k2i + _A53 * k3i + _A54 * k4i), u5, contact, pc, geo, tab, head)
    ok6, k6q, k6w, k6i, _ = _rhs_u(q + h * (_A61 * k1q + _A62 * k2q + _A63 * k3q + _A64 * k4q + _A65 * k5q),
                                 w + h * (_A61 * k1w + _A62 * k2w + _A63 * k3w + _A64 * k4w + _A65 * k5w),
                                 iq + h * (_A61 * k1i + _A62 * k2i + _A63 * k3i + _A64 * k4i + _A65 * k5i), uh, contact, pc, geo, tab, head)
    qn = q + h * (_A71 * k1q + _A73 * k3q + _A74 * k4q + _A75 * k5q + _A76 * k6q)
    wn = w + h * (_A71 * k1w + _A73 * k3w + _A74 * k4w + _A75 * k5w + _A76 * k6w)
    inn = iq + h * (_A71 * k1i + _A73 * k3i + _A74 * k4i + _A75 * k5i + _A76 * k6i)
    ok7, k7q, k7w, k7i, k7c = _rhs_u(qn, wn, inn, uh, contact, pc, geo, tab, head)
    ok = ok2 and ok3 and ok4 and ok5 and ok6 and ok7
    eq = h * (_E1 * k1q + _E3 * k3q + _E4 * k4q + _E5 * k5q + _E6 * k6q + _E7 * k7q)
    ew = h * (_E1 * k1w + _E3 * k3w + _E4 * k4w + _E5 * k5w + _E6 * k6w + _E7 * k7w)
    ei = h * (_E1 * k1i + _E3 * k3i + _E4 * k4i + _E5 * k5i + _E6 * k6i + _E7 * k7i)
    dq = qn - q
    di = inn - iq
    r3q = h * k1q - dq
    r4q = dq - h * k7q - r3q
    r5q = h * (_D1 * k1q + _D3 * k3q + _D4 * k4q + _D5 * k5q + _D6 * k6q + _D7 * k7q)
    r3i = h * k1i - di
    r4i = di - h * k7i - r3i
    r5i = h * (_D1 * k1i + _D3 * k3i + _D4 * k4i + _D5 * k5i + _D6 * k6i + _D7 * k7i)
    return ok, qn, wn, inn, k7q, k7w, k7i, k7c, eq, ew, ei, r3q, r4q, r5q, r3i, r4i, r5i, uh, duh


@nb.njit(cache=True, inline="always")
def _wmatrix(h, ja, jb, jc, jd, je, jg):
    """hγ and the reduced 2×2 block of I/(hγ) − J with its inverse determinant, for :func:`_wsolve`."""
    hg = h * _RG
    s = 1.0 / hg
    m11 = s - jb - ja * hg
    m12 = -jc
    m21 = -je - jd * hg
    m22 = s - jg
    return hg, m11, m12, m21, m22, 1.0 / (m11 * m22 - m12 * m21)


@nb.njit(cache=True, inline="always")
def _wsolve(r0, r1, r2, hg, a, d, m11, m12, m21, m22, idet):
    """Solve (I/(hγ) − J) x = r for the plant's Jacobian J = [[0, 1, 0], [a, b, c], [d, e, g]] (the reduced 2×2
    block m, its inverse determinant idet and hγ prepared by the caller)."""
    s1 = r1 + a * hg * r0
    s2 = r2 + d * hg * r0
    x1 = (m22 * s1 - m12 * s2) * idet
    x2 = (m11 * s2 - m21 * s1) * idet
    return (r0 + x1) * hg, x1, x2


@nb.njit(cache=True)
def _ros_step(h, t, q, w, iq, f0w, f0i, ja, jb, jc, jd, je, jg, fti, contact, pc, geo, tab, head, v):
    """One Rodas4 step of size h from (t, y) with f(t, y) = (w, f0w, f0i), the Jacobian (a…g) and ∂i̇/∂t.
    Returns ok, y(t+h), the error estimate, the dense-output coefficients (K1, K2) of q and i_q, and the command
    and its slope at t+h (stages 5 and 6 and the next step's Jacobian share them)."""
    u2 = _command(t + _RCC2 * h, pc, v)[0]
    u3 = _command(t + _RCC3 * h, pc, v)[0]
    u4 = _command(t + _RCC4 * h, pc, v)[0]
    uh, duh = _command(t + h, pc, v)
    hg, m11, m12, m21, m22, idet = _wmatrix(h, ja, jb, jc, jd, je, jg)
    ih = 1.0 / h
    k1q, k1w, k1i = _wsolve(w, f0w, f0i + _RD1 * h * fti, hg, ja, jd, m11, m12, m21, m22, idet)
    ok2, f2q, f2w, f2i, _ = _rhs_u(q + _RA21 * k1q, w + _RA21 * k1w, iq + _RA21 * k1i, u2, contact, pc, geo, tab, head)
    k2q, k2w, k2i = _wsolve(f2q + ih * _RC21 * k1q, f2w + ih * _RC21 * k1w, f2i + _RD2 * h * fti + ih * _RC21 * k1i,
                            hg, ja, jd, m11, m12, m21, m22, idet)
    ok3, f3q, f3w, f3i, _ = _rhs_u(q + _RA31 * k1q + _RA32 * k2q, w + _RA31 * k1w + _RA32 * k2w,
                                 iq + _RA31 * k1i + _RA32 * k2i, u3, contact, pc, geo, tab, head)
    k3q, k3w, k3i = _wsolve(f3q + ih * (_RC31 * k1q + _RC32 * k2q), f3w + ih * (_RC31 * k1w + _RC32 * k2w),
                            f3i + _RD3 * h * fti + ih * (_RC31 * k1i + _RC32 * k2i),
                            hg, ja, jd, m11, m12, m21, m22, idet)
    ok4, f4q, f4w, f4i, _ = _rhs_u(q + _RA41 * k1q + _RA42 * k2q + _RA43 * k3q,
                                 w + _RA41 * k1w + _RA42 * k2w + _RA43 * k3w,
                                 iq + _RA41 * k1i + _RA42 * k2i + _RA43 * k3i, u4, contact, pc, geo, tab, head)
    k4q, k4w, k4i = _wsolve(f4q + ih * (_RC41 * k1q + _RC42 * k2q + _RC43 * k3q),
                            f4w + ih * (_RC41 * k1w + _RC42 * k2w + _RC43 * k3w),
                            f4i + _RD4 * h * fti + ih * (_RC41 * k1i + _RC42 * k2i + _RC43 * k3i),
                            hg, ja, jd, m11, m12, m21, m22, idet)
    y5q = q + _RA51 * k1q + _RA52 * k2q + _RA53 * k3q + _RA54 * k4q
    y5w = w + _RA51 * k1w + _RA52 * k2w + _RA53 * k3w + _RA54 * k4w
    y5i = iq + _RA51 * k1i + _RA52 * k2i + _RA53 * k3i + _RA54 * k4i
    ok5, f5q, f5w, f5i, _ = _rhs_u(y5q, y5w, y5i, uh, contact, pc, geo, tab, head)
    k5q, k5w, k5i = _wsolve(f5q + ih * (_RC51 * k1q + _RC52 * k2q + _RC53 * k3q + _RC54 * k4q),
                            f5w + ih * (_RC51 * k1w + _RC52 * k2w + _RC53 * k3w + _RC54 * k4w),
                            f5i + ih * (_RC51 * k1i + _RC52 * k2i + _RC53 * k3i + _RC54 * k4i),
                            hg, ja, jd, m11, m12, m21, m22, idet)
    y6q, y6w, y6i = y5q + k5q, y5w + k5w, y5i + k5i
    ok6, f6q, f6w, f6i, _ = _rhs_u(y6q, y6w, y6i, uh, contact, pc, geo, tab, head)
    k6q, k6w, k6i = _wsolve(f6q + ih * (_RC61 * k1q + _RC62 * k2q + _RC63 * k3q + _RC64 * k4q + _RC65 * k5q),
                            f6w + ih * (_RC61 * k1w + _RC62 * k2w + _RC63 * k3w + _RC64 * k4w + _RC65 * k5w),
                            f6i + ih * (_RC61 * k1i + _RC62 * k2i + _RC63 * k3i + _RC64 * k4i + _RC65 * k5i),
                            hg, ja, jd, m11, m12, m21, m22, idet)
    ok = ok2 and ok3 and ok4 and ok5 and ok6
    d1q = _RH21 * k1q + _RH22 * k2q + _RH23 * k3q + _RH24 * k4q + _RH25 * k5q
    d2q = _RH31 * k1q + _RH32 * k2q + _RH33 * k3q + _RH34 * k4q + _RH35 * k5q
    d1i = _RH21 * k1i + _RH22 * k2i + _RH23 * k3i + _RH24 * k4i + _RH25 * k5i
    d2i = _RH31 * k1i + _RH32 * k2i + _RH33 * k3i + _RH34 * k4i + _RH35 * k5i
    return ok, y6q + k6q, y6w + k6w, y6i + k6i, k6q, k6w, k6i, d1q, d2q, d1i, d2i, uh, duh


@nb.njit(cache=True)
def _locate(q, q_L, h, g0, g1, r2, r3, r4, r5):
    """Fraction b ∈ (0, 1] of the step at which the dense output of q reaches q_L (Illinois method; the returned
    point lies on the far side of the switching surface)."""
    a, b, ga, gb = 0.0, 1.0, g0, g1
    side = 0
    for _ in range(100):
        th_ = (a * gb - b * ga) / (gb - ga)
        gm = q_L - _dense(th_, q, r2, r3, r4, r5)
        a, b, ga, gb, side = _illinois(a, b, ga, gb, side, th_, gm)
        if (b - a) * h < 1e-13 or gm == 0.0:
            break
    return b


@nb.njit(cache=True)
def _simulate_one(th, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                  out_x, out_i, steplog):
    """Integrate one parameter vector from ``t_start`` (state y0, contact mode contact0) and write x_B and i_q
    at the samples t_out[k] ≥ t_start for k < n_out. Samples before t_start are left untouched.

    The method (settings[S_METHOD]) is Rodas4, DOPRI5, or DOPRI5 in free motion and Rodas4 while clamped. The
    contact switch (q crossing q_L, i.e. x_B crossing x_B^L, either way) is located on the dense output and
    the step is retaken to end exactly there, so every step integrates a smooth right-hand side.
    Returns (status, n_steps, t_contact, q_c, w_c, i_c): the first closing contact after t_start and the
    state there (t_contact = inf if none), from which stage 2 restarts. n_steps counts accepted and rejected
    steps; beyond settings[S_MAXSTEPS] the simulation is a solver failure.

    ``steplog`` (M, 2), when M > 0, receives the accepted steps in order: their size and their mode (contact before
    the step, plus 2 when the step ends at a contact switch, plus 4 for a Rodas4 step) — what
    :func:`toggle_id.kernels.sens.sens_replay` retraces to differentiate the solution. M ≥ settings[S_MAXSTEPS] holds them all; an empty one costs nothing.
    """
    rtol = settings[S_RTOL]
    atq, atw, ati = settings[S_ATOL_Q], settings[S_ATOL_W], settings[S_ATOL_I]
    hmax = settings[S_HMAX]
    max_steps = int(settings[S_MAXSTEPS])
    method = int(settings[S_METHOD])
    stops = _stops_on(settings[S_STOPS], use_sweep)
    pc = _derived(th, geo, sweep, use_sweep, t_out[0], t_out[1] - t_out[0])
    q_L = math.acos(geo[G_XBL] / (geo[G_R1] + geo[G_R3]))  # contact iff q ≤ q_L (x_B ≥ x_B^L)
    xoff = pc[PC_XOFF]
    t_c, qc, wc, ic = np.inf, 0.0, 0.0, 0.0

    t = t_start
    q, w, iq = y0[0], y0[1], y0[2]
    contact = contact0
    ok, k = _first_sample(q, iq, t_start, t_out, n_out, geo, xoff, out_x, out_i)  # k: next output sample
    if not ok:
        return MODEL_FAILURE, 0, t_c, qc, wc, ic
    if k >= n_out:
        return OK, 0, t_c, qc, wc, ic
    t_end = t_out[n_out - 1]

    h = min(settings[S_H0], hmax)
    facold = 1e-4
    n_steps = 0
    last_reject = False
    geom_fail = False
    have_f = False   # f(t, y) = (w, fw, fi) known
    have_j = False   # Jacobian at (t, y) known
    fw = fi = ja = jb = jc = jd = je = jg = fti = 0.0
    ut, dut = _command(t, pc, v)  # command and its slope at t
    h_acc = 0.0  # last accepted Rodas4 step and its error (predictive step-size control)
    err_acc = 1.0
    n_acc = 0  # accepted steps (steplog's rows)
    while t < t_end - 1e-13:
        if n_steps >= max_steps:
            return SOLVER_FAILURE, n_steps, t_c, qc, wc, ic
        if h < 1e-14 * max(1.0, abs(t)) + 1e-15:
            return (MODEL_FAILURE if geom_fail else SOLVER_FAILURE), n_steps, t_c, qc, wc, ic
        if t + h > t_end:
            h = t_end - t
        if stops:
            h = min(h, _next_stop(t, pc, use_sweep) - t)
        use_ros = method == METHOD_RODAS4 or (method == METHOD_MIXED and contact == 1)
        if use_ros and not have_j:
            ok, _, fw, fi, ja, jb, jc, jd, je, jg, fti = _rhs_jac_u(q, w, iq, ut, dut, contact, pc, geo, tab, head)
            if not ok:
                return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
            have_f = have_j = True
        elif not have_f:
            ok, _, fw, fi, _ = _rhs_u(q, w, iq, ut, contact, pc, geo, tab, head)
            if not ok:
                return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
            have_f = True
        n_steps += 1
        if use_ros:
            ok, qn, wn, inn, eq, ew, ei, r3q, r4q, r3i, r4i, un, dun = _ros_step(h, t, q, w, iq, fw, fi, ja, jb, jc,
                                                                                jd, je, jg, fti, contact, pc, geo,
                                                                                tab, head, v)
            r5q = r5i = 0.0
            k7w = k7i = 0.0
        else:
            (ok, qn, wn, inn, _, k7w, k7i, _, eq, ew, ei, r3q, r4q, r5q, r3i, r4i,
             r5i, un, dun) = _dopri_step(h, t, q, w, iq, w, fw, fi, contact, pc, geo, tab, head, v)
        if not ok:  # a stage left the assembly range: shrink; if it persists the model has failed
            geom_fail = True
            h *= 0.25
            last_reject = True
            continue
        sq = eq / (atq + rtol * max(abs(q), abs(qn)))
        sw = ew / (atw + rtol * max(abs(w), abs(wn)))
        si = ei / (ati + rtol * max(abs(iq), abs(inn)))
        err = math.sqrt((sq * sq + sw * sw + si * si) / 3.0)
        if not err <= 1e300:  # NaN or overflow
            geom_fail = False
            h *= 0.25
            last_reject = True
            continue
        geom_fail = False
        if use_ros:  # predictive controller of Gustafsson (as in Hairer & Wanner's RODAS), factors in [0.2, 6]
            fac = max(1.0 / 6.0, min(5.0, err ** 0.25 / 0.9))
            if err > 1.0:
                h = h / fac
                last_reject = True
                continue
            if h_acc > 0.0:
                facgus = max(1.0 / 6.0, min(5.0, (h_acc / h) * (err * err / err_acc) ** 0.25 / 0.9))
                fac = max(fac, facgus)
            h_acc = h
            err_acc = max(1e-2, err)
            h_prop = h / fac
        else:
            accepted, h_prop, facold = _pi_control(err, h, facold)
            if not accepted:
                h = h_prop
                last_reject = True
                continue
        h_new = min(h_prop, hmax)
        if last_reject:
            h_new = min(h_new, h)
        last_reject = False
        # --- contact event: does q cross q_L inside this step? ---
        g0 = q_L - q
        g1 = q_L - qn
        if contact == 0:
            crossed = (g0 < 0.0) and (g1 >= 0.0)
        else:
            crossed = (g0 >= 0.0) and (g1 < 0.0)
        if crossed:  # retake the step to the far side of the event, in the old mode
            h = max(_locate(q, q_L, h, g0, g1, qn - q, r3q, r4q, r5q) * h, 1e-15)
            if use_ros:
                ok, qn, wn, inn, _, _, _, r3q, r4q, r3i, r4i, un, dun = _ros_step(h, t, q, w, iq, fw, fi, ja, jb, jc,
                                                                                  jd, je, jg, fti, contact, pc, geo,
                                                                                  tab, head, v)
            else:
                (ok, qn, wn, inn, _, k7w, k7i, _, _, _, _, r3q, r4q, r5q, r3i, r4i,
                 r5i, un, dun) = _dopri_step(h, t, q, w, iq, w, fw, fi, contact, pc, geo, tab, head, v)
            if not ok:
                return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
        # --- dense output at the samples inside (t, t + h] ---
        t_new = t + h
        if k < n_out and t_out[k] <= t_new + 1e-12:
            dq = qn - q
            di = inn - iq
            ih = 1.0 / h
            c0 = math.cos(q)
            s0 = math.sin(q)
            while k < n_out and t_out[k] <= t_new + 1e-12:
                s = min((t_out[k] - t) * ih, 1.0)
                out_x[k] = _x_near(_dense(s, q, dq, r3q, r4q, r5q), q, c0, s0, geo) + xoff
                out_i[k] = _dense(s, iq, di, r3i, r4i, r5i)
                k += 1
        if n_acc < steplog.shape[0]:
            steplog[n_acc, 0] = h
            steplog[n_acc, 1] = contact + (2.0 if crossed else 0.0) + (4.0 if use_ros else 0.0)
        n_acc += 1
        t = t_new
        q, w, iq = qn, wn, inn
        ut, dut = un, dun
        if not (math.isfinite(q) and math.isfinite(w) and math.isfinite(iq)):
            return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
        have_j = False
        have_f = not (use_ros or crossed)  # DOPRI5: first same as last
        fw, fi = k7w, k7i
        if crossed:
            if contact == 0 and t_c == np.inf:
                t_c, qc, wc, ic = t, q, w, iq
            contact = 1 - contact
            h_new = min(h_new, max(h, 1e-6))
        h = h_new
    if not (_geometry(q, geo)[0] and _x_of_q(q, geo) > 0.0):
        return MODEL_FAILURE, n_steps, t_c, qc, wc, ic
    return OK, n_steps, t_c, qc, wc, ic
