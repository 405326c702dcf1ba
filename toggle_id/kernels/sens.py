"""Forward sensitivities of the rigid plant's solution, ∂x_B(t_k)/∂θ_c: the accepted steps of a simulation
(:func:`toggle_id.kernels.rigid._simulate_one`'s ``steplog``) are retraced with the variational equations
Ṡ = J(y) S + ∂f/∂θ, the step sizes held fixed. A DOPRI5 step integrates them by its own stages (internal
differentiation: the exact derivative of the numerical solution on those steps — no differencing error, no
step-size jitter); a Rodas4 step (the stiff tier) is Rodas4 on the augmented system (y, S), whose Jacobian needs
∂(J·S)/∂y, taken by forward differences of the analytic Jacobian (three state directions, whatever the number of
columns). Where the contact switch (q crossing q_L) ends a step the sensitivities jump by (f⁻ − f⁺)·∂τ/∂θ with
∂τ/∂θ = −S_q/q̇ (the switch time moves with θ).

:data:`SENS_SLOTS` are the parameters this differentiates: the 15 physical ones and every smooth effect term. Not
here — the caller differentiates them otherwise: the dead time (it moves the input's kinks and its start), the
backlash (another integrator), the generic force's knot positions and the generic sensor error (an output map
outside the kernels).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .geometry import _geometry, _lookup
from .rhs import _command, _derived, _input, _rhs, _rhs_jac_u, _torque_current
from .slots import (
    A_COG, B_M, C_B, C_KT, D_, F_LOAD, F_S, G_G, G_R1, G_R2, G_R3, G_XBL, G_Z, GV_W0, GX_W0, J_M, K3, K_I, K_L,
    K_T, L_Q, LAMBDA_D, M2, M3, M5, MB, MC, MODEL_FAILURE, MU, N_COG, N_GEN, OK, PC_GVIH, PC_GVLO, PC_GXIH,
    PC_GXLO, PC_IEPS, PC_ILQ, PC_IVS, PC_M0, PC_M3, PC_M5, PC_MB, PC_MC, PC_NZ, PC_PHI, PC_ULIM, PC_XBL,
    PHI_COG, R_S, S_SAT,
    SOLVER_FAILURE, TAU_C, V_S, X_OFF, G_P,
)
from .rigid import _wmatrix, _wsolve
from .tableaus import (
    _RA21, _RA31, _RA32, _RA41, _RA42, _RA43, _RA51, _RA52, _RA53, _RA54, _RC21, _RC31, _RC32, _RC41, _RC42,
    _RC43, _RC51, _RC52, _RC53, _RC54, _RC61, _RC62, _RC63, _RC64, _RC65, _RCC2, _RCC3, _RCC4, _RD1, _RD2, _RD3,
    _RD4, _RH21, _RH22, _RH23, _RH24, _RH25, _RH31, _RH32, _RH33, _RH34, _RH35,
    _A21, _A31, _A32, _A41, _A42, _A43, _A51, _A52, _A53, _A54, _A61, _A62, _A63, _A64, _A65, _A71, _A73, _A74,
    _A75, _A76, _C2, _C3, _C4, _C5, _D1, _D3, _D4, _D5, _D6, _D7,
)
from .stepping import _dense

#: parameter slots :func:`sens_replay` differentiates
SENS_SLOTS = frozenset((B_M, D_, J_M, K_I, K_L, K_T, L_Q, R_S, M2, M3, M5, MB, MC, MU, LAMBDA_D, TAU_C, F_S, V_S,
                        C_B, A_COG, N_COG, PHI_COG, F_LOAD, K3, S_SAT, X_OFF, C_KT)
                       + tuple(range(GV_W0, GV_W0 + N_GEN)) + tuple(range(GX_W0, GX_W0 + N_GEN)))


@nb.njit(cache=True, inline="always")
def _hat_basis(s, lo, ih, k):
    """Weight k's share in the piecewise-linear interpolation of :func:`toggle_id.kernels.rhs._hat` at ``s``."""
    u = (s - lo) * ih
    if u <= 0.0:
        return 1.0 if k == 0 else 0.0
    if u >= N_GEN - 1:
        return 1.0 if k == N_GEN - 1 else 0.0
    j = int(math.floor(u))
    if k == j:
        return 1.0 - (u - j)
    if k == j + 1:
        return u - j
    return 0.0


@nb.njit(cache=True)
def _dfdp(t, q, w, iq, contact, pc, th, geo, tab, head, v, cols, wdot, idot, dw, di):
    """∂ẇ/∂θ_c and ∂i̇/∂θ_c (into ``dw``, ``di``) for the slots ``cols`` at time t and state (q, w, iq) in the
    contact mode ``contact``, where ẇ = ``wdot`` and i̇ = ``idot`` (:func:`toggle_id.kernels.rhs._rhs_u`:
    ẇ = (Q − ½ M' q̇²)/M, i̇ = (u − R_s i_q − pλ_d Z ẋ_C)/L_q); False outside the assembly range."""
    ok, x_B, dxB, dxC, b3, b5, db3, db5, dgB, dgC, x_C = _lookup(q, geo, tab, head)
    if not ok:
        return False
    Z = geo[G_Z]
    M = pc[PC_M0] + pc[PC_M3] * b3 + pc[PC_M5] * b5 + pc[PC_MB] * dxB * dxB + pc[PC_MC] * dxC * dxC
    inv_m = 1.0 / M
    vB = dxB * w
    vC = dxC * w
    sg = math.tanh(vB * pc[PC_IEPS])
    z = x_B - pc[PC_XBL]
    vin = _input(t, pc, v)[0]
    u_raw = th[K_I] * vin
    clipped = abs(u_raw) >= pc[PC_ULIM]
    ilq = pc[PC_ILQ]
    gi = _torque_current(iq, pc)[0]
    ex = 0.0  # the Stribeck term's exp(−(ẋ_B/v_s)²) and (ẋ_B/v_s)², 0 when v_s = 0 (the term vanishes)
    r2 = 0.0
    if math.isfinite(pc[PC_IVS]):
        r = vB * pc[PC_IVS]
        r2 = r * r
        ex = math.exp(-r2)
    arg = pc[PC_NZ] * x_C + pc[PC_PHI]
    for j in range(cols.shape[0]):
        c = cols[j]
        dQ = 0.0    # ∂Q/∂θ_c
        dMp = 0.0   # ∂M/∂θ_c
        ddMp = 0.0  # ∂M'/∂θ_c
        dI = 0.0    # ∂i̇/∂θ_c
        if c == M2:
            dMp = geo[G_R2] * geo[G_R2]
        elif c == M3:
            dMp, ddMp = b3, db3
        elif c == M5:
            dMp, ddMp = b5, db5
        elif c == MB:
            dMp, ddMp = dxB * dxB, dgB
            dQ = -th[MU] * geo[G_G] * sg * dxB
        elif c == MC:
            dMp, ddMp = dxC * dxC, dgC
        elif c == J_M:
            dMp, ddMp = Z * Z * dxC * dxC, Z * Z * dgC
        elif c == K_T:
            dQ = Z * gi * dxC
        elif c == B_M:
            dQ = -Z * Z * vC * dxC
        elif c == MU:
            dQ = -th[MB] * geo[G_G] * sg * dxB
        elif c == K_L:
            dQ = -z * dxB if contact else 0.0
        elif c == D_:
            dQ = -vB * dxB if contact else 0.0
        elif c == K3:
            dQ = -z * z * z * dxB if contact else 0.0
        elif c == TAU_C:
            dQ = -Z * math.tanh(vC * pc[PC_IEPS]) * dxC
        elif c == A_COG:
            dQ = Z * math.sin(arg) * dxC
        elif c == N_COG:
            dQ = Z * th[A_COG] * math.cos(arg) * Z * x_C * dxC
        elif c == PHI_COG:
            dQ = Z * th[A_COG] * math.cos(arg) * dxC
        elif c == C_B:
            dQ = -vB * dxB
        elif c == F_LOAD:
            dQ = -dxB
        elif c == F_S:
            dQ = -ex * sg * dxB
        elif c == V_S:
            dQ = -th[F_S] * sg * ex * 2.0 * r2 * pc[PC_IVS] * dxB if th[V_S] != 0.0 else 0.0
        elif c == C_KT:
            dQ = -0.5 * Z * th[K_T] * iq * iq * iq * (1.0 + th[C_KT] * iq * iq) ** -1.5 * dxC
        elif GV_W0 <= c < GV_W0 + N_GEN:
            dQ = -_hat_basis(vB, pc[PC_GVLO], pc[PC_GVIH], c - GV_W0) * dxB
        elif GX_W0 <= c < GX_W0 + N_GEN:
            dQ = -_hat_basis(x_B, pc[PC_GXLO], pc[PC_GXIH], c - GX_W0) * dxB
        elif c == L_Q:
            dI = -idot * ilq
        elif c == R_S:
            dI = -iq * ilq
        elif c == LAMBDA_D:
            dI = -geo[G_P] * Z * vC * ilq
        elif c == K_I:
            dI = 0.0 if clipped else vin * ilq
        elif c == S_SAT:
            dI = -math.copysign(1.0, u_raw) / (th[S_SAT] * th[S_SAT]) * ilq if clipped else 0.0
        dw[j] = (dQ - 0.5 * ddMp * w * w - wdot * dMp) * inv_m
        di[j] = dI
    return True


@nb.njit(cache=True)
def _stage(t, q, w, iq, contact, pc, th, geo, tab, head, v, cols, S, K, s, dw, di, jac):
    """Stage ``s`` of a step: f at (t, y) into K[s, 0:3, 0] … as (q̇, ẇ, i̇), and the sensitivities' derivatives
    J·S + ∂f/∂θ of the stage's S (3, P) into K[s, :, 1:]; the Jacobian J = [[0, 1, 0], [a, b, c], [d, e, g]] and
    ∂i̇/∂t into ``jac`` (a, b, c, d, e, g, ∂i̇/∂t). False outside the assembly range."""
    u, du = _command(t, pc, v)
    ok, fq, fw, fi, ja, jb, jc, jd, je, jg, ft = _rhs_jac_u(q, w, iq, u, du, contact, pc, geo, tab, head)
    if not ok or not _dfdp(t, q, w, iq, contact, pc, th, geo, tab, head, v, cols, fw, fi, dw, di):
        return False
    jac[0], jac[1], jac[2], jac[3], jac[4], jac[5], jac[6] = ja, jb, jc, jd, je, jg, ft
    K[s, 0, 0], K[s, 1, 0], K[s, 2, 0] = fq, fw, fi
    for j in range(cols.shape[0]):
        sq, sw, si = S[0, j], S[1, j], S[2, j]
        K[s, 0, j + 1] = sw
        K[s, 1, j + 1] = ja * sq + jb * sw + jc * si + dw[j]
        K[s, 2, j + 1] = jd * sq + je * sw + jg * si + di[j]
    return True


@nb.njit(cache=True)
def _dfdp_dt(t, pc, th, cols, v, out):
    """∂/∂t of ∂i̇/∂θ_c at time t, into ``out`` (through the command only: ∂ẇ/∂θ and the Jacobian do not depend
    on t). Rodas4's stages need it as they need ∂f/∂t."""
    vin, dvin = _input(t, pc, v)
    clipped = abs(th[K_I] * vin) >= pc[PC_ULIM]
    ilq = pc[PC_ILQ]
    for j in range(cols.shape[0]):
        c = cols[j]
        out[j] = 0.0
        if not clipped:
            if c == K_I:
                out[j] = dvin * ilq
            elif c == L_Q:
                out[j] = -th[K_I] * dvin * ilq * ilq


@nb.njit(cache=True)
def _ros_tables():
    """Rodas4's stage tables in the transformed form of :func:`~.rigid._ros_step`: a (stage state), c (the
    1/h-weighted earlier increments), d (the f_t weights), the stage times and the dense-output weights."""
    a = np.zeros((6, 6))
    a[1, 0] = _RA21
    a[2, 0], a[2, 1] = _RA31, _RA32
    a[3, 0], a[3, 1], a[3, 2] = _RA41, _RA42, _RA43
    a[4, 0], a[4, 1], a[4, 2], a[4, 3] = _RA51, _RA52, _RA53, _RA54
    a[5, 0], a[5, 1], a[5, 2], a[5, 3], a[5, 4] = _RA51, _RA52, _RA53, _RA54, 1.0  # y6 = y5 + k5
    c = np.zeros((6, 6))
    c[1, 0] = _RC21
    c[2, 0], c[2, 1] = _RC31, _RC32
    c[3, 0], c[3, 1], c[3, 2] = _RC41, _RC42, _RC43
    c[4, 0], c[4, 1], c[4, 2], c[4, 3] = _RC51, _RC52, _RC53, _RC54
    c[5, 0], c[5, 1], c[5, 2], c[5, 3], c[5, 4] = _RC61, _RC62, _RC63, _RC64, _RC65
    d = np.array([_RD1, _RD2, _RD3, _RD4, 0.0, 0.0])
    ct = np.array([0.0, _RCC2, _RCC3, _RCC4, 1.0, 1.0])
    hd = np.zeros((2, 5))
    hd[0, 0], hd[0, 1], hd[0, 2], hd[0, 3], hd[0, 4] = _RH21, _RH22, _RH23, _RH24, _RH25
    hd[1, 0], hd[1, 1], hd[1, 2], hd[1, 3], hd[1, 4] = _RH31, _RH32, _RH33, _RH34, _RH35
    return a, c, d, ct, hd


@nb.njit(cache=True)
def _ros_sens_step(h, t, q, w, iq, contact, pc, th, geo, tab, head, v, cols, S, Snew, R3, R4, U, Z, Kt, M, fts,
                   dw, di, jac, ra, rc, rd, rt, rh):
    """One Rodas4 step of the state and its sensitivities together: Rodas4 on the augmented system
    (y, S)' = (f, J·S + ∂f/∂θ), whose Jacobian [[J, 0], [M, J]] is block triangular — M = ∂(J·S + ∂f/∂θ)/∂y by
    forward differences of the analytic terms — so each stage solves the plant's 3×3 system once for y and once
    per column. Writes S(t+h) into Snew and the dense-output coefficients of S_q into R3, R4; returns ok, y(t+h)
    and those of q."""
    P = cols.shape[0]
    if not _stage(t, q, w, iq, contact, pc, th, geo, tab, head, v, cols, S, Kt, 0, dw, di, jac):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    ja, jb, jc, jd, je, jg, fti = jac[0], jac[1], jac[2], jac[3], jac[4], jac[5], jac[6]
    y = (q, w, iq)
    for b in range(3):  # M by forward differences: it only corrects the stages by O(h)
        e = 1e-7 * max(abs(y[b]), 1.0)
        if not _stage(t, q + (e if b == 0 else 0.0), w + (e if b == 1 else 0.0), iq + (e if b == 2 else 0.0),
                      contact, pc, th, geo, tab, head, v, cols, S, Kt, 1, dw, di, jac):
            return False, 0.0, 0.0, 0.0, 0.0, 0.0
        for r in range(1, 3):  # the q-row, S_w, does not depend on y
            for j in range(P):
                M[r, b, j] = (Kt[1, r, j + 1] - Kt[0, r, j + 1]) / e
    _dfdp_dt(t, pc, th, cols, v, fts)
    hg, m11, m12, m21, m22, idet = _wmatrix(h, ja, jb, jc, jd, je, jg)
    ih = 1.0 / h
    for i in range(6):
        # the stage's state and sensitivities: Z = (y, S) + Σ a_il U_l
        for r in range(3):
            for c in range(P + 1):
                Z[r, c] = (y[r] if c == 0 else S[r, c - 1])
                for l in range(i):
                    if ra[i, l] != 0.0:
                        Z[r, c] += ra[i, l] * U[l, r, c]
        if i > 0 and not _stage(t + rt[i] * h, Z[0, 0], Z[1, 0], Z[2, 0], contact, pc, th, geo, tab, head, v,
                                cols, Z[:, 1:], Kt, 3, dw, di, jac):
            return False, 0.0, 0.0, 0.0, 0.0, 0.0
        src = 0 if i == 0 else 3
        # right-hand sides: F(Z) + (1/h) Σ c_il U_l + d_i h F_t
        for r in range(3):
            for c in range(P + 1):
                acc = Kt[src, r, c]
                for l in range(i):
                    acc += ih * rc[i, l] * U[l, r, c]
                if r == 2 and rd[i] != 0.0:
                    acc += rd[i] * h * (fti if c == 0 else fts[c - 1])
                U[i, r, c] = acc
        uq, uw, ui = _wsolve(U[i, 0, 0], U[i, 1, 0], U[i, 2, 0], hg, ja, jd, m11, m12, m21, m22, idet)
        U[i, 0, 0], U[i, 1, 0], U[i, 2, 0] = uq, uw, ui
        for j in range(P):
            c = j + 1
            r0 = U[i, 0, c] + M[0, 0, j] * uq + M[0, 1, j] * uw + M[0, 2, j] * ui
            r1 = U[i, 1, c] + M[1, 0, j] * uq + M[1, 1, j] * uw + M[1, 2, j] * ui
            r2 = U[i, 2, c] + M[2, 0, j] * uq + M[2, 1, j] * uw + M[2, 2, j] * ui
            U[i, 0, c], U[i, 1, c], U[i, 2, c] = _wsolve(r0, r1, r2, hg, ja, jd, m11, m12, m21, m22, idet)
    # the new point: the sixth stage's state plus its increment
    qn, wn, inn = Z[0, 0] + U[5, 0, 0], Z[1, 0] + U[5, 1, 0], Z[2, 0] + U[5, 2, 0]
    for r in range(3):
        for j in range(P):
            Snew[r, j] = Z[r, j + 1] + U[5, r, j + 1]
    d1q = 0.0
    d2q = 0.0
    for l in range(5):
        d1q += rh[0, l] * U[l, 0, 0]
        d2q += rh[1, l] * U[l, 0, 0]
    for j in range(P):
        a1 = 0.0
        a2 = 0.0
        for l in range(5):
            a1 += rh[0, l] * U[l, 0, j + 1]
            a2 += rh[1, l] * U[l, 0, j + 1]
        R3[j] = a1
        R4[j] = a2
    return True, qn, wn, inn, d1q, d2q


@nb.njit(cache=True)
def _dopri_sens_stages(h, t, q, w, iq, contact, pc, th, geo, tab, head, v, cols, S, Y, K, A, C, ys, dw, di, jac):
    """DOPRI5's stages 2–7 of the state and the sensitivities together from stage 1 in K[0]: y + h Σ a K and
    S + h Σ a KS; the new point into ``ys`` and ``Y``, its derivatives into K[6]. False outside the assembly
    range."""
    P = cols.shape[0]
    for s in range(1, 7):
        ys[0], ys[1], ys[2] = q, w, iq
        for r in range(3):
            for j in range(P):
                Y[r, j] = S[r, j]
            for l in range(s):  # stages 1 … s (a zero coefficient would still carry a NaN of a stage not made)
                a = h * A[s, l]
                if a != 0.0:
                    ys[r] += a * K[l, r, 0]
                    for j in range(P):
                        Y[r, j] += a * K[l, r, j + 1]
        if not _stage(t + C[s] * h, ys[0], ys[1], ys[2], contact, pc, th, geo, tab, head, v, cols, Y, K, s, dw, di,
                      jac):
            return False
    return True


@nb.njit(cache=True)
def sens_replay(th, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, steplog, cols,
                out_dx):
    """∂x_B/∂θ_c at the samples t_out[k] ≥ t_start, k < n_out, into out_dx[j, k] for the slots ``cols`` (all in
    :data:`SENS_SLOTS`), by retracing the DOPRI5 and Rodas4 steps ``steplog`` that :func:`~.rigid._simulate_one`
    took for the same arguments (starting state independent of θ). Returns a status: OK, MODEL_FAILURE (a stage left the
    assembly range) or SOLVER_FAILURE (the log ends before the record)."""
    P = cols.shape[0]
    pc = _derived(th, geo, sweep, use_sweep, t_out[0], t_out[1] - t_out[0])
    q_L = math.acos(geo[G_XBL] / (geo[G_R1] + geo[G_R3]))
    xcol = np.zeros(P)  # ∂x_off: 1 at every sample
    for j in range(P):
        if cols[j] == X_OFF:
            xcol[j] = 1.0
    S = np.zeros((3, P))
    Y = np.full((3, P), np.nan)  # a stage's S
    K = np.full((7, 3, P + 1), np.nan)  # the stages' (f, J·S + ∂f/∂θ)
    dw = np.full(P, np.nan)
    di = np.full(P, np.nan)
    jac = np.empty(7)  # a stage's Jacobian entries and ∂i̇/∂t
    t = t_start
    q, w, iq = y0[0], y0[1], y0[2]
    contact = contact0
    k = 0
    while k < n_out and t_out[k] < t_start - 1e-12:
        k += 1
    if k < n_out and abs(t_out[k] - t_start) <= 1e-12:
        for j in range(P):
            out_dx[j, k] = xcol[j]
        k += 1
    t_end = t_out[n_out - 1]
    n = 0
    have_f = False
    ys = np.empty(3)
    qn = wn = inn = 0.0
    A = np.zeros((7, 6))  # DOPRI5's a_{s+1, l+1}; row 6: the weights of the new point
    A[1, 0] = _A21
    A[2, 0], A[2, 1] = _A31, _A32
    A[3, 0], A[3, 1], A[3, 2] = _A41, _A42, _A43
    A[4, 0], A[4, 1], A[4, 2], A[4, 3] = _A51, _A52, _A53, _A54
    A[5, 0], A[5, 1], A[5, 2], A[5, 3], A[5, 4] = _A61, _A62, _A63, _A64, _A65
    A[6, 0], A[6, 2], A[6, 3], A[6, 4], A[6, 5] = _A71, _A73, _A74, _A75, _A76
    C = np.array([0.0, _C2, _C3, _C4, _C5, 1.0, 1.0])
    ra, rc, rd, rt, rh = _ros_tables()
    R3 = np.zeros(P)  # the dense output's coefficients of S_q in the current step
    R4 = np.zeros(P)
    R5 = np.zeros(P)
    U = np.full((6, 3, P + 1), np.nan)  # Rodas4's stage increments of (y, S)
    Z = np.full((3, P + 1), np.nan)  # a Rodas4 stage's (y, S)
    Kt = np.full((4, 3, P + 1), np.nan)
    M = np.zeros((3, 3, P))
    fts = np.zeros(P)
    while t < t_end - 1e-13:
        if n >= steplog.shape[0]:
            return SOLVER_FAILURE
        h = steplog[n, 0]
        mode = steplog[n, 1]
        n += 1
        ros = mode >= 4.0
        if ros:
            mode -= 4.0
        crossed = mode >= 2.0
        contact = int(mode) % 2
        if ros:
            ok, qn, wn, inn, r3q, r4q = _ros_sens_step(h, t, q, w, iq, contact, pc, th, geo, tab, head, v, cols, S,
                                                       Y, R3, R4, U, Z, Kt, M, fts, dw, di, jac, ra, rc, rd, rt, rh)
            if not ok:
                return MODEL_FAILURE
            r5q = 0.0
            R5[:] = 0.0
            have_f = False
        else:
            if not have_f and not _stage(t, q, w, iq, contact, pc, th, geo, tab, head, v, cols, S, K, 0, dw, di,
                                         jac):
                return MODEL_FAILURE
            if not _dopri_sens_stages(h, t, q, w, iq, contact, pc, th, geo, tab, head, v, cols, S, Y, K, A, C, ys,
                                      dw, di, jac):
                return MODEL_FAILURE
            qn, wn, inn = ys[0], ys[1], ys[2]
            dq = qn - q
            r3q = h * K[0, 0, 0] - dq
            r4q = dq - h * K[6, 0, 0] - r3q
            r5q = h * (_D1 * K[0, 0, 0] + _D3 * K[2, 0, 0] + _D4 * K[3, 0, 0] + _D5 * K[4, 0, 0]
                       + _D6 * K[5, 0, 0] + _D7 * K[6, 0, 0])
            for j in range(P):
                c = j + 1
                dS = Y[0, j] - S[0, j]
                R3[j] = h * K[0, 0, c] - dS
                R4[j] = dS - h * K[6, 0, c] - R3[j]
                R5[j] = h * (_D1 * K[0, 0, c] + _D3 * K[2, 0, c] + _D4 * K[3, 0, c] + _D5 * K[4, 0, c]
                             + _D6 * K[5, 0, c] + _D7 * K[6, 0, c])
        # dense output of q and of S_q at the samples inside (t, t + h]; ∂x_B = x_B'(q)·S_q (+1 for x_off)
        t_new = t + h
        if k < n_out and t_out[k] <= t_new + 1e-12:
            ih = 1.0 / h
            dq = qn - q
            while k < n_out and t_out[k] <= t_new + 1e-12:
                fr = min((t_out[k] - t) * ih, 1.0)
                okg, _, dxdq, _, _, _, _, _, _, _, _, _ = _geometry(_dense(fr, q, dq, r3q, r4q, r5q), geo)
                if not okg:
                    return MODEL_FAILURE
                for j in range(P):
                    out_dx[j, k] = dxdq * _dense(fr, S[0, j], Y[0, j] - S[0, j], R3[j], R4[j], R5[j]) + xcol[j]
                k += 1
        t = t_new
        old_mode = contact
        q, w, iq = qn, wn, inn
        for r in range(3):
            for j in range(P):
                S[r, j] = Y[r, j]
        if crossed:  # the switch time τ moves with θ: S⁺ = S⁻ + (f⁻ − f⁺)·∂τ/∂θ, ∂τ/∂θ = −S_q/q̇ (only ẇ jumps)
            ok_o, _, fw_old, _, _ = _rhs(t, q, w, iq, old_mode, pc, geo, tab, head, v)
            contact = 1 - contact
            ok, _, fw_new, _, _ = _rhs(t, q, w, iq, contact, pc, geo, tab, head, v)
            if not (ok and ok_o) or w == 0.0:
                return MODEL_FAILURE
            for j in range(P):
                S[1, j] += (fw_old - fw_new) * (-S[0, j] / w)
            have_f = False
        elif not ros:  # first same as last
            for r in range(3):
                for c in range(P + 1):
                    K[0, r, c] = K[6, r, c]
            have_f = True
    return OK

