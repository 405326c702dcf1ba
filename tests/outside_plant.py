"""An independent reference of the motor-toggle plant (docs/model.md §1–5) with effects the library does NOT have.

Written from docs/model.md alone — scalar kinematics and inertia, M'(q) by the complex-step derivative of M(q),
scipy's DOP853 with its own location of the contact instant — and shares no code with the compiled kernels
(``toggle_id/kernels/``) or with ``toggle_id/plant.py``. It is used by the tests (``tests/test_outside_plant.py``
checks it against :func:`toggle_id.simulate.simulate`) and by ``jobs/bench_adversarial.py`` to make records
with physics outside the discovery library (``toggle_id/effects.py``):

* **friction bump** (``bump=(F_b, x_c, w)``): an extra force on slider B localised on its stroke,
  −F_b·exp(−((x_B − x_c)/w)²)·tanh(ẋ_B/ε) (N, m, m; ε = 1e-3 m/s as for the slider's Coulomb friction) — a
  worn or dirty spot of the guide, felt only while B passes x_c;
* **quadratic drag** (``drag = c_q``, N·s²/m²): −c_q·ẋ_B·|ẋ_B| on slider B — a fluid or air resistance that
  grows with the square of the speed (the library has only friction linear in, or independent of, the speed);
* **saturating torque constant** (``i_sat``, A): K_t,eff = K_t / √(1 + (i_q/i_sat)²), so the torque
  K_t,eff·i_q tends to K_t·i_sat at high current (magnetic saturation of the motor); the back-EMF (λ_d) is
  unchanged. The library has had this effect since (``torque_constant_saturation``, c_kt = 1/i_sat²): here it
  is the independent reference of that kernel term;
* **periodic scale error** (``scale = (a, p, φ)``: m, m, rad): the sensor reads x_B + a·sin(2π·x_B/p + φ) — the
  interpolation error of a magnetic or optical linear scale of pitch p, a property of the measurement only (the
  motion is unchanged; the library's only sensor effect is a constant offset);
* **scale factor error** (``scale_factor = e``, dimensionless): the sensor reads x_B·(1 + e) — a linear scale's
  resolution set wrong, or its thermal expansion against the machine's frame; the motion is unchanged;
* **pin friction under the clamping load** (``pin_mu``, dimensionless): an extra force
  −pin_mu·|F_i|·tanh(ẋ_B/ε) on slider B while it is in contact — the toggle's pins and the platen's guides carry
  the clamping force F_i, and their friction grows with it, so the clamp's force–stroke curve becomes a
  hysteresis loop (the library's contact terms are a spring and a damper);
* **drive dead band** (``deadband = v_db``, V): the drive ignores commands smaller than v_db and passes the rest
  shifted towards zero, sign(v_in)·max(|v_in| − v_db, 0) — a threshold effect of the power stage or of an analogue
  input's offset compensation (the library's drive effects are a delay and a saturation at large commands);
* **drifting torque constant** (``kt_drift = (d, T)``: dimensionless, s): K_t(t) = K_t·(1 − d·t/T), the torque
  constant falling by the fraction d over T seconds — a motor warming up during the record (its magnets lose
  about 0.1 % of their flux per kelvin); every parameter of the library is constant in time;
* **compliant transmission** (``compliance = (k_s, ζ)``: N/m, dimensionless): the rotor drives the nut through
  a spring k_s and a damper c_s = 2ζ·√(k_s·J_m·Z²) (a timing belt or a screw's torsion, in the nut's coordinate)
  instead of rigidly — two bodies with a resonance: the rotor (J_m·Z², the motor's force, its damping B_m and the
  back-EMF at its own speed) and the linkage (M(q) without the rotor), states (q, q̇, i_q, x_r, ẋ_r). The
  library's backlash is a rigid dead band; nothing in it is elastic;
* **contact damping that grows with the penetration** (``hc_damping = λ``, N·s/m²): the clamp's force
  K_l·z + D·ż + λ·z·ż in contact (z = x_B − x_B^L ≥ 0) — Hunt and Crossley's form, where the damping vanishes
  at first touch instead of jumping to D (the library's contact terms are a constant damper and a cubic spring).

Two terms of the library are here too, written from docs/model.md §7, so that a record can hold a library
effect and one outside the library at once (the adversarial set's *mixed* records) and as independent references of
those kernel terms: a **cogging torque** (``cogging = (a_cog, n_cog, φ_cog)``: N·m, 1/rev, rad),
+Z·a_cog·sin(n_cog·Z·x_C + φ_cog) on slider C, and a motor-side **Coulomb torque** (``tau_c``, N·m),
−Z·τ_c·tanh(ẋ_C/ε) on slider C.

All are off by default; then this is the nominal plant of docs/model.md.
"""
from __future__ import annotations

import cmath
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

# docs/model.md §1 (pinned constants)
R1 = R3 = 0.06
R2 = 0.032
R4 = 0.068
R5 = 0.03
H = 0.068
PHI = 0.4899
POLES = 4.0
Z = 2.0 * math.pi * 1.0 / 0.01
G = 9.81
X_B_L = 0.056
X_B0 = 0.020
EPS = 1e-3

#: docs/model.md §6 order of the 15 physical parameters
NAMES = ("B_m", "D", "J_m", "K_i", "K_l", "K_t", "L_q", "R_s", "m_2", "m_3", "m_5", "m_B", "m_C", "mu", "lambda_d")


class OutOfRange(Exception):
    """The mechanism left its assembly range (|sin θ5| ≥ 1 or x_B ≤ 0): a failed simulation (docs/model.md §6)."""


def _kin(q, lib):
    """x_B, x_C, x_B', x_C', θ2', θ5', sin θ2, sin θ5 at q (docs/model.md §2); ``lib`` is math or cmath."""
    s1, c1 = lib.sin(q), lib.cos(q)
    sp, cp = lib.sin(q + PHI), lib.cos(q + PHI)
    sin2 = -R1 * s1 / R3
    cos2 = lib.sqrt(1.0 - sin2 * sin2)
    sin5 = (H - R4 * sp) / R5
    cos5 = lib.sqrt(1.0 - sin5 * sin5)
    d2 = -R1 * c1 / (R3 * cos2)
    d5 = -R4 * cp / (R5 * cos5)
    x_B = R1 * c1 + R3 * cos2
    x_C = R4 * cp + R5 * cos5
    dx_B = -R1 * s1 - R3 * sin2 * d2
    dx_C = -R4 * sp - R5 * sin5 * d5
    return x_B, x_C, dx_B, dx_C, d2, d5, s1, c1, sp, cp, sin5


def _mass(q, p, lib=math, rotor=True):
    """M(q) of docs/model.md §3 (kg·m²); with ``lib=cmath`` it accepts a complex q (complex-step derivative);
    without the ``rotor`` (J_m·Z²·x_C'²) it is the linkage's alone."""
    _, _, dx_B, dx_C, d2, d5, s1, c1, sp, cp, _ = _kin(q, lib)
    g3x, g3y = 0.5 * (-R1 * s1 + dx_B), 0.5 * R1 * c1
    g5x, g5y = 0.5 * (-R4 * sp + dx_C), 0.5 * R4 * cp
    return (p["m_2"] * R2 ** 2
            + p["m_3"] * (g3x * g3x + g3y * g3y + R3 ** 2 / 12.0 * d2 * d2)
            + p["m_5"] * (g5x * g5x + g5y * g5y + R5 ** 2 / 12.0 * d5 * d5)
            + p["m_B"] * dx_B * dx_B
            + (p["m_C"] + (p["J_m"] * Z * Z if rotor else 0.0)) * dx_C * dx_C)


def _dmass(q, p, h=1e-20, rotor=True):
    """M'(q) by the complex-step derivative (exact to rounding)."""
    return _mass(complex(q, h), p, cmath, rotor).imag / h


def x_B_of_q(q):
    return R1 * np.cos(q) + R3 * np.sqrt(1.0 - (R1 * np.sin(q) / R3) ** 2)


@dataclass(frozen=True)
class Outside:
    """Effects of this plant (all off by default): ``bump = (F_b N, x_c m, w m)``, ``drag`` N·s²/m², ``i_sat``
    A, ``scale = (a m, p m, φ rad)``, ``scale_factor`` and ``pin_mu`` (dimensionless), ``deadband`` V,
    ``kt_drift = (d, T s)``, ``compliance = (k_s N/m, ζ)``, ``hc_damping`` N·s/m²; and the library's
    ``cogging = (a_cog N·m, n_cog 1/rev, φ_cog rad)`` and ``tau_c`` N·m."""

    bump: tuple[float, float, float] | None = None
    i_sat: float | None = None
    drag: float | None = None
    scale: tuple[float, float, float] | None = None
    pin_mu: float | None = None
    scale_factor: float | None = None
    deadband: float | None = None
    cogging: tuple[float, float, float] | None = None
    tau_c: float | None = None
    kt_drift: tuple[float, float] | None = None
    compliance: tuple[float, float] | None = None
    hc_damping: float | None = None

    def to_dict(self) -> dict:
        out: dict = {}
        if self.bump is not None:
            out["friction_bump"] = dict(zip(("F_b", "x_c", "w"), map(float, self.bump)))
        if self.i_sat is not None:
            out["saturating_torque_constant"] = {"i_sat": float(self.i_sat)}
        if self.drag is not None:
            out["quadratic_drag"] = {"c_q": float(self.drag)}
        if self.scale is not None:
            out["periodic_scale_error"] = dict(zip(("a", "pitch", "phase"), map(float, self.scale)))
        if self.pin_mu is not None:
            out["pin_friction_under_load"] = {"pin_mu": float(self.pin_mu)}
        if self.scale_factor is not None:
            out["scale_factor_error"] = {"e": float(self.scale_factor)}
        if self.deadband is not None:
            out["drive_dead_band"] = {"v_db": float(self.deadband)}
        if self.cogging is not None:  # the library's terms, by the library's names
            out["cogging_torque"] = dict(zip(("a_cog", "n_cog", "phi_cog"), map(float, self.cogging)))
        if self.tau_c is not None:
            out["coulomb_friction_motor"] = {"tau_c": float(self.tau_c)}
        if self.kt_drift is not None:
            out["drifting_torque_constant"] = dict(zip(("d", "T"), map(float, self.kt_drift)))
        if self.compliance is not None:
            out["compliant_transmission"] = dict(zip(("k_s", "zeta"), map(float, self.compliance)))
        if self.hc_damping is not None:
            out["penetration_damping"] = {"lambda": float(self.hc_damping)}
        return out

    def drive(self, v: float) -> float:
        """The command the drive acts on (its dead band, if any)."""
        if self.deadband is None:
            return v
        return math.copysign(max(abs(v) - self.deadband, 0.0), v)


class Plant:
    """The plant of docs/model.md for one parameter vector (15 values, docs/model.md §6 order or a name → value mapping)
    and one command ``v_in(t)`` (V), with the :class:`Outside` effects."""

    def __init__(self, theta, v_in: Callable[[float], float], outside: Outside = Outside()) -> None:
        if isinstance(theta, dict):
            self.p = {n: float(theta[n]) for n in NAMES}
        else:
            self.p = {n: float(v) for n, v in zip(NAMES, np.asarray(theta, float)[:15])}
        self.v_in = v_in
        self.out = outside

    def torque_constant(self, i_q: float, t: float = 0.0) -> float:
        k_t = self.p["K_t"]
        if self.out.kt_drift is not None:
            d, period = self.out.kt_drift
            k_t = k_t * (1.0 - d * t / period)
        if self.out.i_sat is None:
            return k_t
        return k_t / math.sqrt(1.0 + (i_q / self.out.i_sat) ** 2)

    def motor_force(self, t: float, i_q: float, v_rot: float, x_rot: float) -> float:
        """The motor's force on the nut's coordinate (N) at the rotor's speed and position there."""
        p = self.p
        F = Z * self.torque_constant(i_q, t) * i_q - Z * Z * p["B_m"] * v_rot
        if self.out.cogging is not None:
            a_cog, n_cog, phi_cog = self.out.cogging
            F += Z * a_cog * math.sin(n_cog * Z * x_rot + phi_cog)
        if self.out.tau_c is not None:
            F -= Z * self.out.tau_c * math.tanh(v_rot / EPS)
        return F

    def slider_force(self, x_B: float, vB: float, contact: int) -> float:
        """The forces on slider B (N): friction, the outside terms on it and the clamp's spring–damper."""
        p = self.p
        F_f = -p["mu"] * p["m_B"] * G * math.tanh(vB / EPS)
        if self.out.bump is not None:
            F_b, x_c, width = self.out.bump
            F_f -= F_b * math.exp(-((x_B - x_c) / width) ** 2) * math.tanh(vB / EPS)
        if self.out.drag is not None:
            F_f -= self.out.drag * vB * abs(vB)
        F_i = p["K_l"] * (x_B - X_B_L) + p["D"] * vB if contact else 0.0
        if self.out.hc_damping is not None and contact:
            F_i += self.out.hc_damping * (x_B - X_B_L) * vB
        if self.out.pin_mu is not None and contact:
            F_f -= self.out.pin_mu * abs(F_i) * math.tanh(vB / EPS)
        return F_f - F_i

    def rhs(self, t: float, y, contact: int):
        p = self.p
        q, w, i_q = float(y[0]), float(y[1]), float(y[2])
        sin5 = (H - R4 * math.sin(q + PHI)) / R5
        if abs(sin5) >= 1.0 or abs(R1 * math.sin(q) / R3) >= 1.0:
            raise OutOfRange(f"link 5 cannot be assembled at t = {t:.6g} s")
        x_B, x_C, dx_B, dx_C, *_ = _kin(q, math)
        if x_B <= 0.0:
            raise OutOfRange(f"x_B = {x_B:.6g} m at t = {t:.6g} s")
        vB, vC = dx_B * w, dx_C * w
        drive = p["K_i"] * self.out.drive(self.v_in(t))
        if self.out.compliance is not None:  # two bodies: the rotor (x_r, v_r) and the linkage without it
            x_r, v_r = float(y[3]), float(y[4])
            k_s, zeta = self.out.compliance
            m_r = p["J_m"] * Z * Z
            F_s = k_s * (x_r - x_C) + 2.0 * zeta * math.sqrt(k_s * m_r) * (v_r - vC)  # on the nut, forwards
            Q = F_s * dx_C + self.slider_force(x_B, vB, contact) * dx_B
            wdot = (Q - 0.5 * _dmass(q, p, rotor=False) * w * w) / _mass(q, p, rotor=False)
            idot = (drive - p["R_s"] * i_q - POLES * p["lambda_d"] * Z * v_r) / p["L_q"]
            return [w, wdot, idot, v_r, (self.motor_force(t, i_q, v_r, x_r) - F_s) / m_r]
        Q = self.motor_force(t, i_q, vC, x_C) * dx_C + self.slider_force(x_B, vB, contact) * dx_B
        wdot = (Q - 0.5 * _dmass(q, p) * w * w) / _mass(q, p)
        idot = (drive - p["R_s"] * i_q - POLES * p["lambda_d"] * Z * vC) / p["L_q"]
        return [w, wdot, idot]

    def run(self, t_out: np.ndarray, rtol: float = 1e-11, atol=(1e-13, 1e-10, 1e-8), max_step: float = 1e-3,
            x_B0: float = X_B0) -> tuple[np.ndarray, np.ndarray, dict]:
        """x_B (m) and i_q (A) at the samples ``t_out`` and a summary (contacts, steps, status). A failure
        (out of the assembly range, or the integrator gives up) leaves NaN from there on and ``status != 0``."""
        q_L = math.acos(X_B_L / (R1 + R3))  # contact iff q ≤ q_L
        y = np.array([math.acos(x_B0 / (R1 + R3)), 0.0, 0.0])
        if self.out.compliance is not None:  # the rotor at rest where the rigid coupling would put it
            y = np.array([y[0], 0.0, 0.0, _kin(y[0], math)[1], 0.0])
            atol = tuple(atol) + (1e-13, 1e-10)
            # steps well inside DOP853's stability bound at the resonance (twice the rotor's own frequency), so
            # that no trial stage is thrown out of the assembly range
            max_step = min(max_step, 0.5 / math.sqrt(self.out.compliance[0] / (self.p["J_m"] * Z * Z)))
        t, contact = float(t_out[0]), int(x_B0 >= X_B_L)
        x = np.full(t_out.shape, np.nan)
        i = np.full(t_out.shape, np.nan)
        info = {"contacts": 0, "releases": 0, "steps": 0, "status": 0, "message": ""}

        def event(tt, yy, _contact):  # x_B crosses x_B^L
            return yy[0] - q_L

        event.terminal = True
        while t < t_out[-1] - 1e-12:
            event.direction = -1 if contact == 0 else 1
            try:
                sol = solve_ivp(self.rhs, (t, float(t_out[-1])), y, method="DOP853", args=(contact,),
                                rtol=rtol, atol=atol, events=event, dense_output=True, max_step=max_step)
            except OutOfRange as err:
                info.update(status=1, message=str(err))
                break
            info["steps"] += int(sol.t.size - 1)
            sel = (t_out >= t - 1e-12) & (t_out <= sol.t[-1] + 1e-12)
            if np.any(sel):
                Y = sol.sol(t_out[sel])
                x[sel] = x_B_of_q(Y[0])
                i[sel] = Y[2]
            if sol.status == -1:
                info.update(status=2, message=sol.message)
                break
            t, y = float(sol.t[-1]), sol.y[:, -1].copy()
            if sol.status == 1:  # the contact switched
                info["contacts" if contact == 0 else "releases"] += 1
                contact = 1 - contact
        if info["status"]:
            bad = ~np.isfinite(x)
            x[bad] = np.nan
            i[bad] = np.nan
        return x, i, info


def command_of(record) -> Callable[[float], float]:
    """The record's v_in(t) as docs/model.md §5 defines it: the swept sine in continuous time, or the samples
    interpolated linearly (held at the ends; 0 V before the record starts)."""
    if record.sweep is not None:
        sw = record.sweep
        return lambda t: float(sw(t))
    tt, vv = np.asarray(record.t, float), np.asarray(record.v_in, float)
    t0, dt, n = float(tt[0]), float(tt[1] - tt[0]), tt.size

    def v(t: float) -> float:
        u = (t - t0) / dt
        k = math.floor(u)
        if k < 0:
            return float(vv[0]) if t >= t0 - 1e-12 else 0.0
        if k >= n - 1:
            return float(vv[-1])
        f = u - k
        return float(vv[k] + f * (vv[k + 1] - vv[k]))

    return v


def simulate_outside(theta, record, outside: Outside = Outside(), **kw) -> tuple[np.ndarray, np.ndarray, dict]:
    """x_B, i_q and the summary of :meth:`Plant.run` for ``theta`` (15 physical parameters) on ``record``."""
    plant = Plant(theta, command_of(record), outside)
    x, i, info = plant.run(np.asarray(record.t, float), x_B0=float(record.x_B0), **kw)
    if outside.scale is not None:  # what the sensor reads; the motion itself is unchanged
        a, pitch, phase = outside.scale
        x = x + a * np.sin(2.0 * math.pi * x / pitch + phase)
    if outside.scale_factor is not None:  # likewise
        x = x * (1.0 + outside.scale_factor)
    return x, i, info
