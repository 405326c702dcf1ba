"""The plant's right-hand side in the compiled kernels (docs/model.md §3–5, §10): per-individual constants
(:func:`_derived`), the command v_in(t) and the drive command, the forces with every effect term, dy/dt and its
analytic 3×3 Jacobian (and a finite-difference one for the tests).

State y = (q, q̇, i_q). The parameter vector ``th`` is the extended vector of :mod:`toggle_id.effects`: the 15
physical parameters of docs/model.md §6 followed by the parameters of the candidate effects (zero = off). The
right-hand side reads the per-individual constants ``pc`` (:func:`_derived`: products and reciprocals of the
parameters, and the input's description) so that one evaluation needs a single division (by M(q)).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .geometry import _lookup, _lookup_d
from .slots import (
    GV_HI,
    GV_LO,
    GV_W0,
    GX_HI,
    GX_LO,
    GX_W0,
    N_GEN,
    PC_GEN,
    PC_GVIH,
    PC_GVLO,
    PC_GVW,
    PC_GXIH,
    PC_GXLO,
    PC_GXW,
    A_COG,
    B_M,
    C_KT,
    C_B,
    D_,
    F_LOAD,
    F_S,
    G_EPS,
    G_G,
    G_P,
    G_R2,
    G_XBL,
    G_Z,
    J_M,
    K3,
    K_I,
    K_L,
    K_T,
    L_Q,
    LAMBDA_D,
    M2,
    M3,
    M5,
    MB,
    MC,
    MU,
    N_COG,
    N_PC,
    PC_CB,
    PC_CKT,
    PC_D,
    PC_FLOAD,
    PC_FMU,
    PC_FS,
    PC_IDT,
    PC_IEPS,
    PC_ILQ,
    PC_IVS,
    PC_K3,
    PC_KI,
    PC_KL,
    PC_M0,
    PC_M3,
    PC_M5,
    PC_MB,
    PC_MC,
    PC_NZ,
    PC_PHI,
    PC_PLZL,
    PC_RSL,
    PC_SA,
    PC_SB,
    PC_SDW,
    PC_SDWT,
    PC_SIT,
    PC_ST,
    PC_SW0,
    PC_SWEEP,
    PC_T0,
    PC_TAUD,
    PC_ULIM,
    PC_XBL,
    PC_XOFF,
    PC_Z2BM,
    PC_ZACOG,
    PC_ZKT,
    PC_ZTAUC,
    PHI_COG,
    R_S,
    S_SAT,
    TAU_C,
    TAU_D,
    V_S,
    X_OFF,
)


@nb.njit(cache=True)
def _derived(th, geo, sweep, use_sweep, t0_rec, dt_rec):
    """Per-individual constants of the right-hand side (products and reciprocals computed once per simulation)
    and the description of the input: swept sine (A, B, ω0, ω1 − ω0, T, 1/T) or sampled (t0, 1/dt)."""
    pc = np.empty(N_PC)
    Z = geo[G_Z]
    pc[PC_M0] = th[M2] * geo[G_R2] * geo[G_R2]
    pc[PC_M3] = th[M3]
    pc[PC_M5] = th[M5]
    pc[PC_MB] = th[MB]
    pc[PC_MC] = th[MC] + th[J_M] * Z * Z          # slider C plus the reflected rotor inertia (eq. 10)
    pc[PC_ZKT] = Z * th[K_T]
    pc[PC_Z2BM] = Z * Z * th[B_M]
    pc[PC_FMU] = th[MU] * th[MB] * geo[G_G]
    pc[PC_IEPS] = 1.0 / geo[G_EPS]
    pc[PC_CB] = th[C_B]
    pc[PC_FLOAD] = th[F_LOAD]
    pc[PC_KL] = th[K_L]
    pc[PC_D] = th[D_]
    pc[PC_K3] = th[K3]
    pc[PC_XBL] = geo[G_XBL]
    pc[PC_KI] = th[K_I]
    pc[PC_ILQ] = 1.0 / th[L_Q]
    pc[PC_RSL] = th[R_S] / th[L_Q]
    pc[PC_PLZL] = geo[G_P] * th[LAMBDA_D] * Z / th[L_Q]
    pc[PC_ULIM] = 1.0 / th[S_SAT] if th[S_SAT] > 0.0 else np.inf
    pc[PC_ZTAUC] = Z * th[TAU_C]
    pc[PC_ZACOG] = Z * th[A_COG]
    pc[PC_NZ] = th[N_COG] * Z
    pc[PC_PHI] = th[PHI_COG]
    pc[PC_FS] = th[F_S]
    pc[PC_IVS] = 1.0 / th[V_S] if th[V_S] != 0.0 else np.inf
    pc[PC_TAUD] = th[TAU_D]
    pc[PC_SA], pc[PC_SB], pc[PC_SW0] = sweep[0], sweep[1], sweep[2]
    pc[PC_SDW] = sweep[3] - sweep[2]
    pc[PC_ST] = sweep[4]
    pc[PC_SIT] = 1.0 / sweep[4] if sweep[4] > 0.0 else 0.0
    pc[PC_SDWT] = pc[PC_SDW] * pc[PC_SIT]
    pc[PC_T0] = t0_rec
    pc[PC_IDT] = 1.0 / dt_rec
    pc[PC_SWEEP] = 1.0 if use_sweep else 0.0
    pc[PC_XOFF] = th[X_OFF]
    pc[PC_CKT] = th[C_KT]
    # the generic slider force (the discovery loop's catch-all check): knots and weights; on when a weight is not 0
    pc[PC_GEN] = 0.0
    for k in range(N_GEN):
        pc[PC_GVW + k] = th[GV_W0 + k]
        pc[PC_GXW + k] = th[GX_W0 + k]
        if th[GV_W0 + k] != 0.0 or th[GX_W0 + k] != 0.0:
            pc[PC_GEN] = 1.0
    pc[PC_GVLO], pc[PC_GXLO] = th[GV_LO], th[GX_LO]
    pc[PC_GVIH] = (N_GEN - 1) / (th[GV_HI] - th[GV_LO]) if th[GV_HI] > th[GV_LO] else 0.0
    pc[PC_GXIH] = (N_GEN - 1) / (th[GX_HI] - th[GX_LO]) if th[GX_HI] > th[GX_LO] else 0.0
    return pc


@nb.njit(cache=True, inline="always")
def _input(t, pc, v):
    """Command v_in at time t (V) and its slope (V/s): continuous swept sine (eq. 31–32) or linear interpolation
    of the samples ``v``; dead time shifts it; before the record starts (t < t0 after the shift) it is 0."""
    t = t - pc[PC_TAUD]
    if t < pc[PC_T0] - 1e-12:
        return 0.0, 0.0
    if pc[PC_SWEEP] != 0.0:
        T = pc[PC_ST]
        n = math.floor(t * pc[PC_SIT])
        tau = t - T * n                       # mod(t, T), corrected for the rounding of t·(1/T)
        if tau < 0.0:
            tau += T
        elif tau >= T:
            tau -= T
        om = pc[PC_SW0] + pc[PC_SDWT] * tau   # ω(t) = ω0 + (ω1 − ω0)·mod(t/T, 1)
        ph = om * tau
        return pc[PC_SA] + pc[PC_SB] * math.sin(ph), pc[PC_SB] * math.cos(ph) * (om + pc[PC_SDWT] * tau)
    x = (t - pc[PC_T0]) * pc[PC_IDT]
    n = v.shape[0]
    k = math.floor(x)
    if k >= n - 1:
        return v[n - 1], 0.0
    if k < 0:
        return v[0], 0.0
    f = x - k
    slope = v[k + 1] - v[k]
    return v[k] + f * slope, slope * pc[PC_IDT]


@nb.njit(cache=True, inline="always")
def _torque_current(iq, pc):
    """The current that makes torque, g(i_q) = i_q/√(1 + c_kt·i_q²) (magnetic saturation of the torque constant;
    g = i_q when c_kt = 0), and its derivative g'(i_q) = (1 + c_kt·i_q²)^(−3/2)."""
    if pc[PC_CKT] == 0.0:
        return iq, 1.0
    r = 1.0 / math.sqrt(1.0 + pc[PC_CKT] * iq * iq)
    return iq * r, r * r * r


@nb.njit(cache=True, inline="always")
def _motor_force(iq, v_rot, x_rot, pc):
    """Force of the motor on the nut (N): Z·τ, electromagnetic (K_t·g(i_q), :func:`_torque_current`) − viscous −
    Coulomb + cogging, at the rotor's speed and position in the nut's coordinate (the nut's own in the rigid
    model)."""
    F = pc[PC_ZKT] * _torque_current(iq, pc)[0] - pc[PC_Z2BM] * v_rot
    if pc[PC_ZTAUC] != 0.0:
        F -= pc[PC_ZTAUC] * math.tanh(v_rot * pc[PC_IEPS])
    if pc[PC_ZACOG] != 0.0:
        F += pc[PC_ZACOG] * math.sin(pc[PC_NZ] * x_rot + pc[PC_PHI])
    return F


@nb.njit(cache=True, inline="always")
def _hat(s, lo, ih, pc, w0):
    """Piecewise-linear interpolation at ``s`` of the N_GEN weights ``pc[w0:]`` on uniform knots from ``lo``
    with spacing 1/``ih`` (constant beyond the end knots; the first weight everywhere when ``ih`` = 0): value
    and slope."""
    u = (s - lo) * ih
    if u <= 0.0:
        return pc[w0], 0.0
    if u >= N_GEN - 1:
        return pc[w0 + N_GEN - 1], 0.0
    k = int(math.floor(u))
    a = pc[w0 + k]
    b = pc[w0 + k + 1]
    return a + (u - k) * (b - a), (b - a) * ih


@nb.njit(cache=True, inline="always")
def _forces(q, w, iq, contact, pc, geo, tab, head):
    """Geometry at q and the generalised force terms shared by the right-hand sides and the Jacobian (the last
    value, (x_C'²)', serves the backlash kernel's linkage without the rotor)."""
    ok, x_B, dxB, dxC, b3, b5, db3, db5, dgB, dgC, x_C = _lookup(q, geo, tab, head)
    M = pc[PC_M0] + pc[PC_M3] * b3 + pc[PC_M5] * b5 + pc[PC_MB] * dxB * dxB + pc[PC_MC] * dxC * dxC
    dM = pc[PC_M3] * db3 + pc[PC_M5] * db5 + pc[PC_MB] * dgB + pc[PC_MC] * dgC
    vB = dxB * w
    vC = dxC * w
    F_C = _motor_force(iq, vC, x_C, pc)
    # forces on slider B: friction (Coulomb, Stribeck, viscous) and a constant load (N)
    sg = math.tanh(vB * pc[PC_IEPS])
    F_f = -pc[PC_FMU] * sg - pc[PC_CB] * vB - pc[PC_FLOAD]
    if pc[PC_FS] != 0.0:
        r = vB * pc[PC_IVS]
        F_f -= pc[PC_FS] * math.exp(-r * r) * sg
    if pc[PC_GEN] != 0.0:  # the generic force f(ẋ_B) + g(x_B), positive opposes closing (as F_load)
        F_f -= _hat(vB, pc[PC_GVLO], pc[PC_GVIH], pc, PC_GVW)[0] + _hat(x_B, pc[PC_GXLO], pc[PC_GXIH], pc, PC_GXW)[0]
    z = x_B - pc[PC_XBL]
    F_i = 0.0
    if contact:
        F_i = pc[PC_KL] * z + pc[PC_D] * vB + pc[PC_K3] * z * z * z
    Q = F_C * dxC + (F_f - F_i) * dxB
    ok = ok and x_B > 0.0 and M > 0.0
    return ok, x_B, dxB, dxC, x_C, M, dM, vB, vC, F_C, sg, F_f, z, F_i, Q, dgC


@nb.njit(cache=True, inline="always")
def _command(t, pc, v):
    """Drive command u = K_i·v_in(t), clipped at ±1/S_SAT, and its slope du/dt (V, V/s)."""
    vin, dvin = _input(t, pc, v)
    u = pc[PC_KI] * vin
    du = pc[PC_KI] * dvin
    if abs(u) >= pc[PC_ULIM]:
        u = math.copysign(pc[PC_ULIM], u)
        du = 0.0
    return u, du


# Not inlined by Numba (its IR inlining would copy the whole right-hand side into each of the twelve stage calls of
# the DOPRI5 and Rosenbrock steps): the kernels compile cold in about half the time (90–103 s → 42–58 s), with the
# same results bit for bit and the same speed (``python -m jobs.bench``, 2026-11-28). The small terms it calls stay
# inlined.
@nb.njit(cache=True)
def _rhs_u(q, w, iq, u, contact, pc, geo, tab, head):
    """dy/dt of the plant with all effect terms for the drive command u (V); ``contact`` is the mode decided
    by event location. Returns ok (False outside the assembly range), q̇, ẇ, i̇ and ∂ẇ/∂i_q (exact: ẇ is affine
    in the torque current g(i_q))."""
    ok, _, _, dxC, _, M, dM, _, vC, _, _, _, _, _, Q, _ = _forces(q, w, iq, contact, pc, geo, tab, head)
    if not ok:
        return False, 0.0, 0.0, 0.0, 0.0
    inv_m = 1.0 / M
    wdot = (Q - 0.5 * dM * w * w) * inv_m
    idot = u * pc[PC_ILQ] - pc[PC_RSL] * iq - pc[PC_PLZL] * vC
    return True, w, wdot, idot, pc[PC_ZKT] * _torque_current(iq, pc)[1] * dxC * inv_m


@nb.njit(cache=True)
def _rhs(t, q, w, iq, contact, pc, geo, tab, head, v):
    """dy/dt at time t (see :func:`_rhs_u`)."""
    return _rhs_u(q, w, iq, _command(t, pc, v)[0], contact, pc, geo, tab, head)


@nb.njit(cache=True)
def _rhs_jac(t, q, w, iq, contact, pc, geo, tab, head, v):
    """Right-hand side at time t and its Jacobian (see :func:`_rhs_jac_u`)."""
    u, du = _command(t, pc, v)
    return _rhs_jac_u(q, w, iq, u, du, contact, pc, geo, tab, head)


@nb.njit(cache=True)
def _rhs_jac_u(q, w, iq, u, du, contact, pc, geo, tab, head):
    """Right-hand side for the command u and its analytic Jacobian J = [[0, 1, 0], [a, b, c], [d, e, g]] and
    ∂i̇/∂t (from du/dt). Returns ok, q̇, ẇ, i̇, a, b, c, d, e, g, ft."""
    ok, x_B, dxB, dxC, x_C, M, dM, vB, vC, F_C, sg, F_f, z, F_i, Q, _ = _forces(q, w, iq, contact, pc, geo, tab,
                                                                            head)
    okd, ddxB, ddxC, ddb3, ddb5, ddgB, ddgC = _lookup_d(q, geo, tab, head)
    if not (ok and okd):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    inv_m = 1.0 / M
    wdot = (Q - 0.5 * dM * w * w) * inv_m
    ft = du * pc[PC_ILQ]
    idot = u * pc[PC_ILQ] - pc[PC_RSL] * iq - pc[PC_PLZL] * vC
    # partial derivatives of the forces w.r.t. the slider speeds and q (explicit)
    dFC_dvC = -pc[PC_Z2BM]
    if pc[PC_ZTAUC] != 0.0:
        tc = math.tanh(vC * pc[PC_IEPS])
        dFC_dvC -= pc[PC_ZTAUC] * (1.0 - tc * tc) * pc[PC_IEPS]
    dFC_dq = 0.0
    if pc[PC_ZACOG] != 0.0:
        dFC_dq = pc[PC_ZACOG] * math.cos(pc[PC_NZ] * x_C + pc[PC_PHI]) * pc[PC_NZ] * dxC
    dsg = (1.0 - sg * sg) * pc[PC_IEPS]
    dFf_dvB = -pc[PC_FMU] * dsg - pc[PC_CB]
    if pc[PC_FS] != 0.0:
        r = vB * pc[PC_IVS]
        ex = math.exp(-r * r)
        dFf_dvB -= pc[PC_FS] * ex * (dsg - 2.0 * r * pc[PC_IVS] * sg)
    dFf_dx = 0.0
    if pc[PC_GEN] != 0.0:
        dFf_dvB -= _hat(vB, pc[PC_GVLO], pc[PC_GVIH], pc, PC_GVW)[1]
        dFf_dx = -_hat(x_B, pc[PC_GXLO], pc[PC_GXIH], pc, PC_GXW)[1]
    dFi_dz = 0.0
    dFi_dvB = 0.0
    if contact:
        dFi_dz = pc[PC_KL] + 3.0 * pc[PC_K3] * z * z
        dFi_dvB = pc[PC_D]
    dM2 = pc[PC_M3] * ddb3 + pc[PC_M5] * ddb5 + pc[PC_MB] * ddgB + pc[PC_MC] * ddgC
    dQ_dw = dFC_dvC * dxC * dxC + (dFf_dvB - dFi_dvB) * dxB * dxB
    dQ_dq = ((dFC_dvC * ddxC * w + dFC_dq) * dxC + F_C * ddxC
             + ((dFf_dvB - dFi_dvB) * ddxB * w + (dFf_dx - dFi_dz) * dxB) * dxB + (F_f - F_i) * ddxB)
    ja = (dQ_dq - 0.5 * dM2 * w * w - wdot * dM) * inv_m
    jb = (dQ_dw - dM * w) * inv_m
    jc = pc[PC_ZKT] * _torque_current(iq, pc)[1] * dxC * inv_m
    jd = -pc[PC_PLZL] * ddxC * w
    je = -pc[PC_PLZL] * dxC
    return True, w, wdot, idot, ja, jb, jc, jd, je, -pc[PC_RSL], ft


@nb.njit(cache=True)
def _jacobian_fd(t, q, w, iq, contact, pc, geo, tab, head, v, eps_rel=1e-5):
    """Central-difference Jacobian of :func:`_rhs` (for tests). Returns a 3×3 array and ∂f/∂t (3,)."""
    y = np.array([q, w, iq])
    J = np.zeros((3, 3))
    for c in range(3):
        e = eps_rel * max(abs(y[c]), 1e-3)
        yp = y.copy()
        ym = y.copy()
        yp[c] += e
        ym[c] -= e
        rp = _rhs(t, yp[0], yp[1], yp[2], contact, pc, geo, tab, head, v)
        rm = _rhs(t, ym[0], ym[1], ym[2], contact, pc, geo, tab, head, v)
        J[0, c] = (rp[1] - rm[1]) / (2 * e)
        J[1, c] = (rp[2] - rm[2]) / (2 * e)
        J[2, c] = (rp[3] - rm[3]) / (2 * e)
    e = 1e-7
    rp = _rhs(t + e, q, w, iq, contact, pc, geo, tab, head, v)
    rm = _rhs(t - e, q, w, iq, contact, pc, geo, tab, head, v)
    ft = np.array([(rp[1] - rm[1]) / (2 * e), (rp[2] - rm[2]) / (2 * e), (rp[3] - rm[3]) / (2 * e)])
    return J, ft
