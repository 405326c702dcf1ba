"""Kinematics of the toggle in the compiled kernels (docs/model.md §2–3.1): the closed form (:func:`_geometry`),
the cubic Hermite table of the q-only quantities shared by all individuals (:func:`build_table`, read by
:func:`_lookup` and :func:`_lookup_d`), x_C(q) for the cogging term and x_B(q) for the output samples.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .slots import G_H, G_PHI, G_R1, G_R3, G_R4, G_R5, G_XBL, H_DQ, H_INVDQ, H_N, H_QLO, N_TAB


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
def _x_of_q(q, geo):
    """x_B(q) = r1 cos q + r3 cos θ2 (m), with r3 sin θ2 = −r1 sin q: one cosine and one square root."""
    r1, r3 = geo[G_R1], geo[G_R3]
    c = math.cos(q)
    ratio = r1 / r3
    return r1 * c + r3 * math.sqrt(max(0.0, 1.0 - ratio * ratio * (1.0 - c * c)))


@nb.njit(cache=True)  # once per output sample: a call costs nothing measurable, and not inlined it compiles sooner
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


@nb.njit(cache=True)
def _geometry_into(q, geo, out):
    """Write the tabulated quantities at q into out[0:N_TAB]; False outside the assembly range."""
    r = _geometry_exact(q, geo)
    out[0], out[1], out[2], out[3], out[4] = r[1], r[2], r[3], r[4], r[5]
    out[5], out[6], out[7], out[8], out[9] = r[6], r[7], r[8], r[9], r[10]
    return r[0]


@nb.njit(cache=True)
def build_table(geo, q_lo, dq, n):
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
