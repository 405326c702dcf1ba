"""Plant constants, kinematics and inertia of the motor-toggle mechanism (docs/model.md §1–4), in plain numpy.

This module is the readable statement of the model and the *independent reference* for the compiled kernel
in :mod:`toggle_id.kernels`: it computes M'(q) by differentiating M(q) numerically instead of with the
kernel's closed-form second derivatives, and its right-hand side drives ``scipy.integrate.solve_ivp`` in
tests and benchmarks.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .params import INDEX


@dataclass(frozen=True)
class Geometry:
    """Pinned plant constants of docs/model.md §1 (lengths in m, angles in rad)."""

    r1: float = 0.06
    r2: float = 0.032   # radius of gyration of the ternary link about O
    r3: float = 0.06
    r4: float = 0.068
    r5: float = 0.03
    h: float = 0.068
    phi: float = 0.4899
    pole_pairs: float = 4.0
    screw_lead: float = 0.01
    gear_ratio: float = 1.0
    g: float = 9.81
    x_B_L: float = 0.056       # clamping position
    eps_friction: float = 1e-3  # friction sign smoothing, m/s

    @property
    def Z(self) -> float:
        """Screw conversion 2π n_g / L_sd, rad/m (eq. 11)."""
        return 2.0 * np.pi * self.gear_ratio / self.screw_lead

    def as_array(self) -> np.ndarray:
        """Constants in the order the kernel reads them (see ``kernels.slots.G_*``)."""
        return np.array([self.r1, self.r2, self.r3, self.r4, self.r5, self.h, self.phi, self.pole_pairs,
                         self.Z, self.g, self.x_B_L, self.eps_friction], dtype=float)

    def q_of_xB(self, x_B: float) -> float:
        """Crank angle q = θ1 for a slider-B position (closing is q decreasing)."""
        return float(np.arccos(x_B / (self.r1 + self.r3)))


GEOMETRY = Geometry()


def kinematics(q, geo: Geometry = GEOMETRY) -> dict[str, np.ndarray]:
    """Positions and first derivatives w.r.t. q of the mechanism (docs/model.md §2). Works on arrays."""
    q = np.asarray(q, dtype=float)
    s1, c1 = np.sin(q), np.cos(q)
    sin2 = -geo.r1 * s1 / geo.r3
    cos2 = np.sqrt(1.0 - sin2**2)
    d2 = -geo.r1 * c1 / (geo.r3 * cos2)
    sp, cp = np.sin(q + geo.phi), np.cos(q + geo.phi)
    sin5 = (geo.h - geo.r4 * sp) / geo.r5
    cos5 = np.sqrt(1.0 - sin5**2)
    d5 = -geo.r4 * cp / (geo.r5 * cos5)
    x_B = geo.r1 * c1 + geo.r3 * cos2
    x_C = geo.r4 * cp + geo.r5 * cos5
    dx_B = -geo.r1 * s1 - geo.r3 * sin2 * d2
    dx_C = -geo.r4 * sp - geo.r5 * sin5 * d5
    return dict(x_B=x_B, x_C=x_C, dx_B=dx_B, dx_C=dx_C, d2=d2, d5=d5, sin5=sin5,
                A=(-geo.r1 * s1, geo.r1 * c1), E=(-geo.r4 * sp, geo.r4 * cp))


def mass_matrix(q, theta, geo: Geometry = GEOMETRY) -> np.ndarray:
    """Generalised inertia M(q) of docs/model.md §3 (kg·m²) for one parameter vector ``theta``."""
    k = kinematics(q, geo)
    g3x, g3y = 0.5 * (k["A"][0] + k["dx_B"]), 0.5 * k["A"][1]
    g5x, g5y = 0.5 * (k["E"][0] + k["dx_C"]), 0.5 * k["E"][1]
    p = {n: theta[i] for n, i in INDEX.items()}
    return (p["m_2"] * geo.r2**2
            + p["m_3"] * (g3x**2 + g3y**2 + geo.r3**2 / 12.0 * k["d2"] ** 2)
            + p["m_5"] * (g5x**2 + g5y**2 + geo.r5**2 / 12.0 * k["d5"] ** 2)
            + p["m_B"] * k["dx_B"] ** 2
            + (p["m_C"] + p["J_m"] * geo.Z**2) * k["dx_C"] ** 2)


def mass_matrix_derivative(q, theta, geo: Geometry = GEOMETRY, step: float = 1e-6) -> np.ndarray:
    """M'(q) by a fourth-order central difference of :func:`mass_matrix` (the independent reference)."""
    m = lambda x: mass_matrix(x, theta, geo)  # noqa: E731
    return (-m(q + 2 * step) + 8 * m(q + step) - 8 * m(q - step) + m(q - 2 * step)) / (12 * step)


def rhs(t: float, y: np.ndarray, theta: np.ndarray, v_in, geo: Geometry = GEOMETRY) -> np.ndarray:
    """Nominal right-hand side dy/dt for y = (q, q̇, i_q); ``v_in(t)`` gives the command in V.

    Contact is decided from the current state (z ≥ 0), so an integrator using this function must resolve
    the contact instant itself (``solve_ivp`` with an event does).
    """
    p = {n: theta[i] for n, i in INDEX.items()}
    q, w, i_q = y
    k = kinematics(q, geo)
    Z = geo.Z
    xdot_B, xdot_C = k["dx_B"] * w, k["dx_C"] * w
    F_C = Z * p["K_t"] * i_q - Z**2 * p["B_m"] * xdot_C
    F_f = -p["mu"] * p["m_B"] * geo.g * np.tanh(xdot_B / geo.eps_friction)
    z = k["x_B"] - geo.x_B_L
    F_i = p["K_l"] * z + p["D"] * xdot_B if z >= 0.0 else 0.0
    Q = F_C * k["dx_C"] + (F_f - F_i) * k["dx_B"]
    M = mass_matrix(q, theta, geo)
    dM = mass_matrix_derivative(q, theta, geo)
    wdot = (Q - 0.5 * dM * w * w) / M
    idot = (p["K_i"] * v_in(t) - p["R_s"] * i_q - geo.pole_pairs * p["lambda_d"] * Z * xdot_C) / p["L_q"]
    return np.array([w, wdot, idot])


def impulse_force(x_B: np.ndarray, xdot_B: np.ndarray, D: float, K_l: float, geo: Geometry = GEOMETRY) -> np.ndarray:
    """Clamping impulse F_i (eq. 4), N: K_l z + D ż while z = x_B − x_B^L ≥ 0, else 0."""
    z = np.asarray(x_B) - geo.x_B_L
    return np.where(z >= 0.0, K_l * z + D * np.asarray(xdot_B), 0.0)
