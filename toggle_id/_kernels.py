"""Compiled kernels: the plant's right-hand side, its Jacobian, and two adaptive integrators with dense output
and exact location of the contact instant, batched over parameter vectors:

- Rodas4 (Hairer & Wanner, a linearly implicit, L-stable Rosenbrock method of order 4 with an embedded order-3
  estimate and an order-3 continuous extension) with the analytic 3×3 Jacobian: the fast tier. The clamped mode
  is stiff (contact spring: ω ≈ 1700 rad/s), which limits any explicit method to steps of about 1.4 ms; Rodas4
  steps are set by accuracy alone (about 580 steps for a 5-s record at the fast tolerances, against 3550).
- Dormand–Prince 5(4) (DOPRI5, explicit, order-4 continuous extension): the precise tier, where the steps
  are small for accuracy anyway and the cheaper explicit step wins.

Small, pure functions on float64 arrays and scalars; failures are returned as status codes, never raised.
The readable model and the independent reference for these kernels are in :mod:`toggle_id.plant`.

State y = (q, q̇, i_q). The parameter vector ``th`` is the extended vector of :mod:`toggle_id.effects`: the 15
physical parameters of docs/model.md §6 followed by the parameters of the candidate effects (zero = off). The
right-hand side reads the per-individual constants ``pc`` (:func:`_derived`: products and reciprocals of the
parameters, and the input's description) so that one evaluation needs a single division (by M(q)).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

# ---- layout of the extended parameter vector (names in toggle_id.params / toggle_id.effects) -------------
B_M, D_, J_M, K_I, K_L, K_T, L_Q, R_S, M2, M3, M5, MB, MC, MU, LAMBDA_D = range(15)
TAU_C, F_S, V_S, C_B, TAU_D, B_L, A_COG, N_COG, PHI_COG, F_LOAD, K3, S_SAT, X_OFF = range(15, 28)
N_THETA = 28

# ---- layout of the geometry array (toggle_id.plant.Geometry.as_array) --------------------------------------
G_R1, G_R2, G_R3, G_R4, G_R5, G_H, G_PHI, G_P, G_Z, G_G, G_XBL, G_EPS = range(12)

# ---- status codes ----------------------------------------------------------------------------------------
OK, MODEL_FAILURE, SOLVER_FAILURE, INVALID_PARAMS = 0, 1, 2, 3

# ---- integrator settings array -----------------------------------------------------------------------------
# S_METHOD: 0 = DOPRI5 in both modes, 1 = DOPRI5 free / Rodas4 clamped, 2 = Rodas4 in both modes
S_RTOL, S_ATOL_Q, S_ATOL_W, S_ATOL_I, S_H0, S_HMAX, S_MAXSTEPS, S_METHOD = range(8)
METHOD_DOPRI5, METHOD_MIXED, METHOD_RODAS4 = 0, 1, 2

# ---- per-individual constants (see _derived) ---------------------------------------------------------------
(PC_M0, PC_M3, PC_M5, PC_MB, PC_MC, PC_ZKT, PC_Z2BM, PC_FMU, PC_IEPS, PC_CB, PC_FLOAD, PC_KL, PC_D, PC_K3,
 PC_XBL, PC_KI, PC_ILQ, PC_RSL, PC_PLZL, PC_ULIM, PC_ZTAUC, PC_ZACOG, PC_NZ, PC_PHI, PC_FS, PC_IVS, PC_TAUD,
 PC_SA, PC_SB, PC_SW0, PC_SDW, PC_ST, PC_SIT, PC_SDWT, PC_T0, PC_IDT, PC_SWEEP, PC_XOFF) = range(38)
N_PC = 38


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


@nb.njit(cache=True)
def _geometry(q, geo):
    """Kinematics at q: x_B, x_B', x_B'', x_C', x_C'', θ5, M-basis terms. Returns ok=False outside assembly."""
    r1, r3, r4, r5, h, phi = geo[G_R1], geo[G_R3], geo[G_R4], geo[G_R5], geo[G_H], geo[G_PHI]
    s1 = math.sin(q)
    c1 = math.cos(q)
    sp = math.sin(q + phi)
    cp = math.cos(q + phi)
    sin2 = -r1 * s1 / r3
    sin5 = (h - r4 * sp) / r5
    if abs(sin5) >= 1.0 or abs(sin2) >= 1.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    cos2 = math.sqrt(1.0 - sin2 * sin2)
    cos5 = math.sqrt(1.0 - sin5 * sin5)
    d2 = -r1 * c1 / (r3 * cos2)
    d5 = -r4 * cp / (r5 * cos5)
    dd2 = (r1 / r3 * s1 + sin2 * d2 * d2) / cos2
    dd5 = (r4 * sp / r5 + sin5 * d5 * d5) / cos5
    x_B = r1 * c1 + r3 * cos2
    dxB = -r1 * s1 - r3 * sin2 * d2
    ddxB = -r1 * c1 - r3 * cos2 * d2 * d2 - r3 * sin2 * dd2
    dxC = -r4 * sp - r5 * sin5 * d5
    ddxC = -r4 * cp - r5 * cos5 * d5 * d5 - r5 * sin5 * dd5
    # centres of the slender links 3 and 5: G' and G'' (docs/model.md §3)
    g3x, g3y = 0.5 * (-r1 * s1 + dxB), 0.5 * (r1 * c1)
    g3xx, g3yy = 0.5 * (-r1 * c1 + ddxB), 0.5 * (-r1 * s1)
    g5x, g5y = 0.5 * (-r4 * sp + dxC), 0.5 * (r4 * cp)
    g5xx, g5yy = 0.5 * (-r4 * cp + ddxC), 0.5 * (-r4 * sp)
    b3 = g3x * g3x + g3y * g3y + r3 * r3 / 12.0 * d2 * d2
    db3 = 2.0 * (g3x * g3xx + g3y * g3yy) + r3 * r3 / 6.0 * d2 * dd2
    b5 = g5x * g5x + g5y * g5y + r5 * r5 / 12.0 * d5 * d5
    db5 = 2.0 * (g5x * g5xx + g5y * g5yy) + r5 * r5 / 6.0 * d5 * dd5
    return True, x_B, dxB, ddxB, dxC, ddxC, b3, db3, b5, db5, x_B, x_B - geo[G_XBL]


# ---- geometry table: cubic Hermite interpolation of the q-only functions, shared by all individuals ---------
# columns (value block, then derivative block): x_B, x_B', x_C', b3, b5, b3', b5', (x_B'²)', (x_C'²)', x_C
T_XB, T_DXB, T_DXC, T_B3, T_B5, T_DB3, T_DB5, T_DGB, T_DGC, T_XC = range(10)
N_TAB = 10
# header of the table array: q_lo, 1/dq, number of nodes
H_QLO, H_INVDQ, H_N, H_DQ = 0, 1, 2, 3


@nb.njit(cache=True)
def _geometry_exact(q, geo):
    """The tabulated quantities computed from the closed form (outside the table, and to build it)."""
    ok, x_B, dxB, ddxB, dxC, ddxC, b3, db3, b5, db5, _, _ = _geometry(q, geo)
    if not ok:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return (True, x_B, dxB, dxC, b3, b5, db3, db5, 2.0 * dxB * ddxB, 2.0 * dxC * ddxC, _xc_rel(q, geo))


@nb.njit(cache=True)
def _xc_rel(q, geo):
    """x_C(q) (m), for the rotor angle Z·x_C of the cogging term."""
    r4, r5, h, phi = geo[G_R4], geo[G_R5], geo[G_H], geo[G_PHI]
    sp = math.sin(q + phi)
    sin5 = (h - r4 * sp) / r5
    return r4 * math.cos(q + phi) + r5 * math.sqrt(max(0.0, 1.0 - sin5 * sin5))


@nb.njit(cache=True, inline="always")
def _lookup(q, geo, tab, head):
    """Geometry at q from the Hermite table (exact closed form outside it)."""
    x = (q - head[H_QLO]) * head[H_INVDQ]
    j = math.floor(x) if x >= 0.0 else -1
    if j < 0 or j >= int(head[H_N]) - 1:
        return _geometry_exact(q, geo)
    s = x - j
    d = head[H_DQ]
    s2 = s * s
    s3 = s2 * s
    h00 = 2.0 * s3 - 3.0 * s2 + 1.0
    h10 = (s3 - 2.0 * s2 + s) * d
    h01 = 1.0 - h00
    h11 = (s3 - s2) * d
    a = tab[j]
    b = tab[j + 1]
    return (True,
            h00 * a[0] + h10 * a[10] + h01 * b[0] + h11 * b[10],
            h00 * a[1] + h10 * a[11] + h01 * b[1] + h11 * b[11],
            h00 * a[2] + h10 * a[12] + h01 * b[2] + h11 * b[12],
            h00 * a[3] + h10 * a[13] + h01 * b[3] + h11 * b[13],
            h00 * a[4] + h10 * a[14] + h01 * b[4] + h11 * b[14],
            h00 * a[5] + h10 * a[15] + h01 * b[5] + h11 * b[15],
            h00 * a[6] + h10 * a[16] + h01 * b[6] + h11 * b[16],
            h00 * a[7] + h10 * a[17] + h01 * b[7] + h11 * b[17],
            h00 * a[8] + h10 * a[18] + h01 * b[8] + h11 * b[18],
            h00 * a[9] + h10 * a[19] + h01 * b[9] + h11 * b[19])


@nb.njit(cache=True)
def _lookup_d(q, geo, tab, head):
    """q-derivatives of the tabulated x_B', x_C', b3', b5', (x_B'²)', (x_C'²)' at q: the exact derivatives of
    the Hermite interpolants the right-hand side uses (central differences of the closed form outside the
    table). Returns ok, x_B'', x_C'', b3'', b5'', (x_B'²)'', (x_C'²)''."""
    x = (q - head[H_QLO]) * head[H_INVDQ]
    j = math.floor(x) if x >= 0.0 else -1
    if j < 0 or j >= int(head[H_N]) - 1:
        e = 1e-6
        rp = _geometry_exact(q + e, geo)
        rm = _geometry_exact(q - e, geo)
        ie = 0.5 / e
        return (rp[0] and rm[0], (rp[2] - rm[2]) * ie, (rp[3] - rm[3]) * ie, (rp[6] - rm[6]) * ie,
                (rp[7] - rm[7]) * ie, (rp[8] - rm[8]) * ie, (rp[9] - rm[9]) * ie)
    s = x - j
    idq = head[H_INVDQ]
    g00 = (6.0 * s * s - 6.0 * s) * idq
    g10 = 3.0 * s * s - 4.0 * s + 1.0
    g01 = -g00
    g11 = 3.0 * s * s - 2.0 * s
    a = tab[j]
    b = tab[j + 1]
    return (True,
            g00 * a[1] + g10 * a[11] + g01 * b[1] + g11 * b[11],
            g00 * a[2] + g10 * a[12] + g01 * b[2] + g11 * b[12],
            g00 * a[5] + g10 * a[15] + g01 * b[5] + g11 * b[15],
            g00 * a[6] + g10 * a[16] + g01 * b[6] + g11 * b[16],
            g00 * a[7] + g10 * a[17] + g01 * b[7] + g11 * b[17],
            g00 * a[8] + g10 * a[18] + g01 * b[8] + g11 * b[18])


@nb.njit(cache=True, inline="always")
def _motor_force(iq, v_rot, x_rot, pc):
    """Force of the motor on the nut (N): Z·τ, electromagnetic − viscous − Coulomb + cogging, at the rotor's
    speed and position in the nut's coordinate (the nut's own in the rigid model)."""
    F = pc[PC_ZKT] * iq - pc[PC_Z2BM] * v_rot
    if pc[PC_ZTAUC] != 0.0:
        F -= pc[PC_ZTAUC] * math.tanh(v_rot * pc[PC_IEPS])
    if pc[PC_ZACOG] != 0.0:
        F += pc[PC_ZACOG] * math.sin(pc[PC_NZ] * x_rot + pc[PC_PHI])
    return F


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


@nb.njit(cache=True, inline="always")
def _rhs_u(q, w, iq, u, contact, pc, geo, tab, head):
    """dy/dt of the plant with all effect terms for the drive command u (V); ``contact`` is the mode decided
    by event location. Returns ok (False outside the assembly range), q̇, ẇ, i̇ and ∂ẇ/∂i_q (exact: ẇ is affine
    in i_q)."""
    ok, _, _, dxC, _, M, dM, _, vC, _, _, _, _, _, Q, _ = _forces(q, w, iq, contact, pc, geo, tab, head)
    if not ok:
        return False, 0.0, 0.0, 0.0, 0.0
    inv_m = 1.0 / M
    wdot = (Q - 0.5 * dM * w * w) * inv_m
    idot = u * pc[PC_ILQ] - pc[PC_RSL] * iq - pc[PC_PLZL] * vC
    return True, w, wdot, idot, pc[PC_ZKT] * dxC * inv_m


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
    ok, _, dxB, dxC, x_C, M, dM, vB, vC, F_C, sg, F_f, z, F_i, Q, _ = _forces(q, w, iq, contact, pc, geo, tab,
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
    dFi_dz = 0.0
    dFi_dvB = 0.0
    if contact:
        dFi_dz = pc[PC_KL] + 3.0 * pc[PC_K3] * z * z
        dFi_dvB = pc[PC_D]
    dM2 = pc[PC_M3] * ddb3 + pc[PC_M5] * ddb5 + pc[PC_MB] * ddgB + pc[PC_MC] * ddgC
    dQ_dw = dFC_dvC * dxC * dxC + (dFf_dvB - dFi_dvB) * dxB * dxB
    dQ_dq = ((dFC_dvC * ddxC * w + dFC_dq) * dxC + F_C * ddxC
             + ((dFf_dvB - dFi_dvB) * ddxB * w - dFi_dz * dxB) * dxB + (F_f - F_i) * ddxB)
    ja = (dQ_dq - 0.5 * dM2 * w * w - wdot * dM) * inv_m
    jb = (dQ_dw - dM * w) * inv_m
    jc = pc[PC_ZKT] * dxC * inv_m
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


# Dormand–Prince 5(4) tableau, error weights and dense-output coefficients (Hairer, Nørsett & Wanner, DOPRI5)
_A21 = 1 / 5
_A31, _A32 = 3 / 40, 9 / 40
_A41, _A42, _A43 = 44 / 45, -56 / 15, 32 / 9
_A51, _A52, _A53, _A54 = 19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729
_A61, _A62, _A63, _A64, _A65 = 9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656
_A71, _A73, _A74, _A75, _A76 = 35 / 384, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84
_C2, _C3, _C4, _C5 = 1 / 5, 3 / 10, 4 / 5, 8 / 9
_E1, _E3, _E4, _E5, _E6, _E7 = 71 / 57600, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40
_D1, _D3, _D4 = -12715105075 / 11282082432, 87487479700 / 32700410799, -10690763975 / 1880347072
_D5, _D6, _D7 = 701980252875 / 199316789632, -1453857185 / 822651844, 69997945 / 29380423


# ---- Rodas4 (Hairer & Wanner, Solving ODEs II, §VI.4; coefficients of their code RODAS, 'transformed' form) --
_RG = 0.25
_RA21 = 1.544
_RA31, _RA32 = 0.9466785280815826, 0.2557011698983284
_RA41, _RA42, _RA43 = 3.314825187068521, 2.896124015972201, 0.9986419139977817
_RA51, _RA52, _RA53, _RA54 = 1.221224509226641, 6.019134481288629, 12.53708332932087, -0.687886036105895
_RC21 = -5.6688
_RC31, _RC32 = -2.430093356833875, -0.2063599157091915
_RC41, _RC42, _RC43 = -0.1073529058151375, -9.594562251023355, -20.47028614809616
_RC51, _RC52, _RC53, _RC54 = 7.496443313967647, -10.24680431464352, -33.99990352819905, 11.7089089320616
_RC61, _RC62, _RC63, _RC64, _RC65 = (8.083246795921522, -7.981132988064893, -31.52159432874371,
                                     16.31930543123136, -6.058818238834054)
_RCC2, _RCC3, _RCC4 = 0.386, 0.21, 0.63
_RD1, _RD2, _RD3, _RD4 = 0.25, -0.1043, 0.1035, -0.0362
_RH21, _RH22, _RH23, _RH24, _RH25 = (10.12623508344586, -7.487995877610167, -34.80091861555747,
                                     -7.992771707568823, 1.025137723295662)
_RH31, _RH32, _RH33, _RH34, _RH35 = (-0.6762803392801253, 6.087714651680015, 16.43084320892478,
                                     24.76722511418386, -6.594389125716872)


@nb.njit(cache=True, inline="always")
def _dense(th_, r1, r2, r3, r4, r5):
    """Continuous extension at fraction θ of the step: r1 + θ(r2 + (1−θ)(r3 + θ(r4 + (1−θ) r5))) (DOPRI5's;
    Rodas4's is the same form with r5 = 0)."""
    s = 1.0 - th_
    return r1 + th_ * (r2 + s * (r3 + th_ * (r4 + s * r5)))


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
    hg = h * _RG
    s = 1.0 / hg
    m11 = s - jb - ja * hg
    m12 = -jc
    m21 = -je - jd * hg
    m22 = s - jg
    idet = 1.0 / (m11 * m22 - m12 * m21)
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


@nb.njit(cache=True, inline="always")
def _x_of_q(q, geo):
    """x_B(q) = r1 cos q + r3 cos θ2 (m), with r3 sin θ2 = −r1 sin q: one cosine and one square root."""
    r1, r3 = geo[G_R1], geo[G_R3]
    c = math.cos(q)
    ratio = r1 / r3
    return r1 * c + r3 * math.sqrt(max(0.0, 1.0 - ratio * ratio * (1.0 - c * c)))


@nb.njit(cache=True, inline="always")
def _x_near(qs, q0, c0, s0, geo):
    """x_B(qs) as :func:`_x_of_q`, with cos qs from cos q0 = c0, sin q0 = s0 and the Taylor series of cos δ and
    sin δ (δ = qs − q0, |δ| ≤ 0.1: truncation below 3e-13 relative), which saves a cosine per output sample."""
    dl = qs - q0
    if abs(dl) > 0.1:
        return _x_of_q(qs, geo)
    d2 = dl * dl
    cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0 - d2 * (1.0 / 720.0)))
    sd = dl * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0 - d2 * (1.0 / 5040.0))))
    c = c0 * cd - s0 * sd
    r1, r3 = geo[G_R1], geo[G_R3]
    if r1 == r3:  # the plant's geometry: cos θ2 = cos q
        return (r1 + r3) * c
    ratio = r1 / r3
    return r1 * c + r3 * math.sqrt(max(0.0, 1.0 - ratio * ratio * (1.0 - c * c)))


@nb.njit(cache=True, inline="always")
def _pi_control(err, h, facold):
    """DOPRI5's PI step-size controller (beta 0.04, safety 0.9, factors in [0.2, 10]) for the scaled error
    ``err`` of a step of size h: (accepted, the next step size — the retry's after a rejection —, facold)."""
    fac11 = err ** 0.17
    if err > 1.0:
        return False, h / min(fac11 / 0.9, 5.0), facold
    fac = max(0.1, min(5.0, fac11 / facold ** 0.04 / 0.9))
    return True, h / fac, max(err, 1e-4)


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


@nb.njit(cache=True, inline="always")
def _illinois(a, b, ga, gb, side, th_, gm):
    """One bracket update of the Illinois (modified regula falsi) method: the new point th_ with value gm
    replaces the end of [a, b] with the same sign; an end kept twice in a row has its value halved."""
    if (gm < 0.0) == (ga < 0.0):
        if side == -1:
            gb *= 0.5
        return th_, b, gm, gb, -1
    if side == 1:
        ga *= 0.5
    return a, th_, ga, gm, 1


@nb.njit(cache=True)
def _first_sample(q, iq, t_start, t_out, n_out, geo, xoff, out_x, out_i):
    """(ok, k): k the first output sample after ``t_start``; the sample at ``t_start`` itself, if there is one,
    is written from the start state (ok False: that state lies outside the assembly range)."""
    k = 0
    while k < n_out and t_out[k] < t_start - 1e-12:
        k += 1
    if k < n_out and abs(t_out[k] - t_start) <= 1e-12:
        if not _geometry(q, geo)[0]:
            return False, k
        out_x[k] = _x_of_q(q, geo) + xoff
        out_i[k] = iq
        k += 1
    return True, k


@nb.njit(cache=True)
def _simulate_one(th, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                  out_x, out_i):
    """Integrate one parameter vector from ``t_start`` (state y0, contact mode contact0) and write x_B and i_q
    at the samples t_out[k] ≥ t_start for k < n_out. Samples before t_start are left untouched.

    The method (settings[S_METHOD]) is Rodas4, DOPRI5, or DOPRI5 in free motion and Rodas4 while clamped. The
    contact switch (q crossing q_L, i.e. x_B crossing x_B^L, either way) is located on the dense output and
    the step is retaken to end exactly there, so every step integrates a smooth right-hand side.
    Returns (status, n_steps, t_contact, q_c, w_c, i_c): the first closing contact after t_start and the
    state there (t_contact = inf if none), from which stage 2 restarts. n_steps counts accepted and rejected
    steps; beyond settings[S_MAXSTEPS] the simulation is a solver failure.
    """
    rtol = settings[S_RTOL]
    atq, atw, ati = settings[S_ATOL_Q], settings[S_ATOL_W], settings[S_ATOL_I]
    hmax = settings[S_HMAX]
    max_steps = int(settings[S_MAXSTEPS])
    method = int(settings[S_METHOD])
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
    while t < t_end - 1e-13:
        if n_steps >= max_steps:
            return SOLVER_FAILURE, n_steps, t_c, qc, wc, ic
        if h < 1e-14 * max(1.0, abs(t)) + 1e-15:
            return (MODEL_FAILURE if geom_fail else SOLVER_FAILURE), n_steps, t_c, qc, wc, ic
        if t + h > t_end:
            h = t_end - t
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


@nb.njit(cache=True)
def _geometry_into(q, geo, out):
    """Write the tabulated quantities at q into out[0:N_TAB]; False outside the assembly range."""
    r = _geometry_exact(q, geo)
    out[0], out[1], out[2], out[3], out[4] = r[1], r[2], r[3], r[4], r[5]
    out[5], out[6], out[7], out[8], out[9] = r[6], r[7], r[8], r[9], r[10]
    return r[0]


@nb.njit(cache=True)
def _build_table(geo, q_lo, dq, n):
    """Values and q-derivatives (4th-order central differences, step dq/1000) of the tabulated geometry at
    the nodes q_lo + j·dq; rows outside the assembly range are NaN."""
    tab = np.full((n, 2 * N_TAB), np.nan)
    e = dq * 1e-3
    f0 = np.empty(N_TAB)
    fp1 = np.empty(N_TAB)
    fm1 = np.empty(N_TAB)
    fp2 = np.empty(N_TAB)
    fm2 = np.empty(N_TAB)
    for j in range(n):
        q = q_lo + j * dq
        ok = _geometry_into(q, geo, f0)
        ok &= _geometry_into(q + e, geo, fp1)
        ok &= _geometry_into(q - e, geo, fm1)
        ok &= _geometry_into(q + 2 * e, geo, fp2)
        ok &= _geometry_into(q - 2 * e, geo, fm2)
        if not ok:
            continue
        for c in range(N_TAB):
            tab[j, c] = f0[c]
            tab[j, N_TAB + c] = (-fp2[c] + 8.0 * fp1[c] - 8.0 * fm1[c] + fm2[c]) / (12.0 * e)
    return tab


from ._backlash import simulate_lash as _simulate_lash  # (it uses the kernels above)


@nb.njit(cache=True)
def _simulate_row(thetas, r, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                  out_x, out_i, status, n_steps, events):
    """Simulate row r of ``thetas`` into row r of the outputs; samples not simulated (before ``t_start``, from
    ``n_out`` on, or all of them when the simulation failed) are NaN."""
    xr = out_x[r]
    ir = out_i[r]
    if thetas[r, B_L] > 0.0:  # backlash: a second mechanical degree of freedom while the lash is open
        st, ns, tc, qc, wc, ic = _simulate_lash(thetas[r], geo, tab, head, t_out, n_out, v, sweep, use_sweep,
                                                t_start, y0, contact0, settings, xr, ir)
    else:
        st, ns, tc, qc, wc, ic = _simulate_one(thetas[r], geo, tab, head, t_out, n_out, v, sweep, use_sweep,
                                               t_start, y0, contact0, settings, xr, ir)
    n = t_out.shape[0]
    if st != OK:
        for k in range(n):
            xr[k] = np.nan
            ir[k] = np.nan
    else:
        for k in range(n):
            if k >= n_out or t_out[k] < t_start - 1e-12:
                xr[k] = np.nan
                ir[k] = np.nan
    status[r] = st
    n_steps[r] = ns
    events[r, 0], events[r, 1], events[r, 2], events[r, 3] = tc, qc, wc, ic


@nb.njit(cache=True)
def _simulate_batch_serial(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0,
                           settings, out_x, out_i, status, n_steps, events):
    """Serial loop over the rows ``rows`` of ``thetas`` (one Ray actor = one core)."""
    for p in range(rows.shape[0]):
        _simulate_row(thetas, rows[p], geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0,
                      settings, out_x, out_i, status, n_steps, events)


@nb.njit(cache=True, parallel=True)
def _simulate_batch_parallel(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0,
                             contact0, settings, out_x, out_i, status, n_steps, events):
    """Threaded loop over the rows ``rows`` of ``thetas`` (standalone use: jobs.simulate, benchmarks)."""
    for p in nb.prange(rows.shape[0]):
        _simulate_row(thetas, rows[p], geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0,
                      settings, out_x, out_i, status, n_steps, events)
