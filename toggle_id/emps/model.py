"""EMPS plant model, its effect registry and a batched closed-loop simulator (numba).

Plant (load side, SI units), between samples continuous:

    M q̈ = gtau·ν − f(q̇)
    f(v) = Fv·v + Fc·s + offset + Fs·s·exp(−(v/vs)²) + Fc_asym·|s| + Fv_asym·v·s,    s = tanh(v/eps)

so that for v > 0 the friction is (Fv+Fv_asym)·v + (Fc+Fc_asym) and for v < 0 it is (Fv−Fv_asym)·v − (Fc−Fc_asym),
i.e. Fv± = Fv ± Fv_asym and Fc± = Fc ± Fc_asym in the notation of the benchmark's eq. (12). ``Fs`` is the Stribeck
*excess* over Coulomb (friction at standstill = Fc + Fs), so every effect parameter is zero when its effect is off.
``Fs`` ≥ 0: the Stribeck effect is static friction in excess of Coulomb friction. (Left signed, the EMPS data
choose Fs ≈ −6 N, vs ≈ 17 mm/s — friction that rises to Fc over a few vs — which is not a Stribeck effect and
blurs the meaning of Fv and Fc; we keep the physical definition.) The
sign function is smoothed as tanh(v/eps) with eps = 1e-4 m/s by default (two velocity quanta of the encoder,
5e-8 m per 1 ms sample); with eps → 0 the published parameters give 0.00120 % instead of 0.00107 %.

Controller (benchmark eq. 6), evaluated at the samples k with the *simulated* position q(k), held (zero-order hold)
over [t_k, t_k + dt):

    qf(k) = 0.5 q(k) + 0.5 q(k−1),  q̇(k) = (qf(k) − qf(k−1))/dt = (q(k) − q(k−2))/(2 dt)
    ν(k) = sat_{±v_sat}( kp·kv·(qg(k) − q(k)) − kv·q̇(k) + p(k) )

where p(k) is the validation record's pulse train ``pulses_N`` (zero otherwise), times ``pulse_gain`` (default 1).
The pulses enter at the controller output in the unit of ν (V): in DATA_EMPS_PULSES the logged ``vir`` minus the
control law recomputed from ``qg`` and ``qm`` is a train of rectangular pulses on the same samples as ``pulses_N``
(shifting them by one sample raises the rms mismatch from 0.05 V to 0.23 V), so the drive force is
gtau·(law + pulse), about 178 N per pulse. The logged pulses are 1.014·``pulses_N`` (5.07 V for 5); the
simulator keeps the file's value unless ``pulse_gain`` says otherwise.

Integration: classical RK4 with n_sub substeps per sample, n_sub chosen per parameter row so that
h·λ ≤ ``h_lambda`` with λ a bound on |∂q̈/∂v| (the smoothed Coulomb term is stiff for small eps).
Initial state: q(0) = qm(0), q̇(0) from a second-order forward difference of qm, and the controller history
q(−1), q(−2) extrapolated linearly with that velocity.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numba
import numpy as np

from ..errors import ConfigError
from ..kernels import kernel_array
from .data import EmpsRecord


@dataclass(frozen=True)
class EmpsParam:
    """One EMPS model parameter: name, unit, value when its effect is off, feasible domain, description."""

    name: str
    unit: str
    off: float
    lower: float
    upper: float
    description: str


#: Parameters in the canonical order of the simulator's θ vector.
PARAMS: tuple[EmpsParam, ...] = (
    EmpsParam("M", "kg", 95.0, 1.0, 1000.0, "moving mass (inertia seen at the load)"),
    EmpsParam("Fv", "N·s/m", 200.0, 0.0, 2000.0, "viscous friction coefficient (mean of both directions)"),
    EmpsParam("Fc", "N", 0.0, 0.0, 200.0, "Coulomb friction (mean of both directions)"),
    EmpsParam("offset", "N", 0.0, -100.0, 100.0, "constant force opposing the drive (IDM offset term)"),
    EmpsParam("Fs", "N", 0.0, 0.0, 100.0, "Stribeck excess: static friction minus Coulomb friction (≥ 0)"),
    EmpsParam("vs", "m/s", 0.0, 1e-4, 0.02, "Stribeck velocity"),
    EmpsParam("Fc_asym", "N", 0.0, -50.0, 50.0, "Coulomb asymmetry: Fc± = Fc ± Fc_asym"),
    EmpsParam("Fv_asym", "N·s/m", 0.0, -500.0, 500.0, "viscous asymmetry: Fv± = Fv ± Fv_asym"),
)
PARAM_NAMES: tuple[str, ...] = tuple(p.name for p in PARAMS)
N_PARAMS = len(PARAMS)
INDEX: dict[str, int] = {p.name: i for i, p in enumerate(PARAMS)}
LOWER = np.array([p.lower for p in PARAMS])
UPPER = np.array([p.upper for p in PARAMS])
#: θ with every effect off (nominal inertia + viscous model at round starting values).
OFF = np.array([p.off for p in PARAMS])
#: Parameters of the nominal model (always identified).
NOMINAL_NAMES: tuple[str, ...] = ("M", "Fv")

#: IDIM-LS values printed in EMPS_Description.pdf §3.4 (symmetric model, estimated from DATA_EMPS.mat).
PUBLISHED: dict[str, float] = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648}
#: Relative standard deviations printed with them, %.
PUBLISHED_REL_SIGMA_PCT: dict[str, float] = {"M": 0.114, "Fv": 0.563, "Fc": 0.496, "offset": 1.40}
#: Asymmetric-friction IDIM-LS values of the PDF (no offset term), in its ± notation: Fv±, Fc± for q̇ ≷ 0.
PUBLISHED_ASYM_PM: dict[str, float] = {"M": 95.1540, "Fv+": 166.7061, "Fv-": 240.4236, "Fc+": 20.1440,
                                       "Fc-": 20.6277}
#: The same in this module's parameterisation (Fv = mean, Fv_asym = half difference, likewise Fc).
PUBLISHED_ASYM: dict[str, float] = {
    "M": PUBLISHED_ASYM_PM["M"],
    "Fv": 0.5 * (PUBLISHED_ASYM_PM["Fv+"] + PUBLISHED_ASYM_PM["Fv-"]),
    "Fv_asym": 0.5 * (PUBLISHED_ASYM_PM["Fv+"] - PUBLISHED_ASYM_PM["Fv-"]),
    "Fc": 0.5 * (PUBLISHED_ASYM_PM["Fc+"] + PUBLISHED_ASYM_PM["Fc-"]),
    "Fc_asym": 0.5 * (PUBLISHED_ASYM_PM["Fc+"] - PUBLISHED_ASYM_PM["Fc-"]),
}


@dataclass(frozen=True)
class Effect:
    """A switchable model effect: the parameters it owns, their bounds and their starting values when switched on."""

    name: str
    params: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    default: tuple[float, ...]
    description: str
    requires: tuple[str, ...] = ()


def _effect(name: str, params: tuple[str, ...], default: tuple[float, ...], description: str,
            requires: tuple[str, ...] = ()) -> Effect:
    return Effect(name, params, tuple(float(LOWER[INDEX[p]]) for p in params),
                  tuple(float(UPPER[INDEX[p]]) for p in params), default, description, requires)


#: Candidate effects for the EMPS, as data (name → Effect); the nominal model has none of them. ``requires``
#: names effects that must already be in the model: the Stribeck bump and the Coulomb asymmetry refine Coulomb
#: friction (without it a wide Stribeck bump Fs·sign(q̇)·exp(−(q̇/vs)²) merely imitates Coulomb + viscous).
EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        _effect("coulomb_friction", ("Fc",), (10.0,), "Coulomb friction Fc·sign(q̇)"),
        _effect("offset", ("offset",), (0.0,), "constant force (gravity/cable/bias of the drive)"),
        _effect("stribeck_friction", ("Fs", "vs"), (5.0, 0.005), "Stribeck bump Fs·sign(q̇)·exp(−(q̇/vs)²)",
                ("coulomb_friction",)),
        _effect("asymmetric_friction", ("Fc_asym", "Fv_asym"), (0.0, 0.0),
                "direction-dependent Coulomb and viscous coefficients (eq. 12)", ("coulomb_friction",)),
    )
}


def theta_from_dict(values: Mapping[str, float], base: np.ndarray | None = None) -> np.ndarray:
    """θ vector (order :data:`PARAM_NAMES`) from ``values``; unspecified entries from ``base`` (default :data:`OFF`)."""
    theta = np.array(OFF if base is None else base, dtype=float, copy=True)
    for name, val in values.items():
        if name not in INDEX:
            raise ConfigError(f"unknown EMPS parameter {name!r}; known: {list(PARAM_NAMES)}")
        theta[INDEX[name]] = float(val)
    return theta


def theta_to_dict(theta: np.ndarray) -> dict[str, float]:
    """Plain dict name → float of one θ vector."""
    theta = np.asarray(theta, dtype=float).reshape(-1)
    if theta.size != N_PARAMS:
        raise ConfigError(f"EMPS θ must have {N_PARAMS} entries, got {theta.size}")
    return {n: float(v) for n, v in zip(PARAM_NAMES, theta)}


#: Published symmetric model as a θ vector.
PUBLISHED_THETA = theta_from_dict(PUBLISHED)


# ----------------------------------------------------------------------------------------------------------------
# numba kernel
# ----------------------------------------------------------------------------------------------------------------

STATUS_OK, STATUS_MODEL_FAILURE, STATUS_SOLVER_FAILURE, STATUS_INVALID = 0, 1, 2, 3


@numba.njit(cache=True, inline="always")
def _accel(v: float, force: float, M: float, Fv: float, Fc: float, off: float, Fs: float, vs: float,
           dFc: float, dFv: float, inv_eps: float) -> float:
    """q̈ (m/s²) at velocity v (m/s) under drive + external force ``force`` (N)."""
    s = np.tanh(v * inv_eps)
    f = Fv * v + Fc * s + off + dFc * abs(s) + dFv * v * s
    if Fs != 0.0:
        r = v / vs
        f += Fs * s * np.exp(-r * r)
    return (force - f) / M


@numba.njit(cache=True)
def _simulate_row(th: np.ndarray, qg: np.ndarray, u_ext: np.ndarray, init: np.ndarray, dt: float, gtau: float,
                  kp: float, kv: float, v_sat: float, eps: float, h_lambda: float, n_sub_min: int,
                  n_sub_max: int, q_out: np.ndarray, nu_out: np.ndarray) -> int:
    """Simulate one parameter row in closed loop; fills q_out (m) and nu_out (V); returns the status code."""
    n = qg.shape[0]
    M, Fv, Fc, off, Fs, vs, dFc, dFv = th[0], th[1], th[2], th[3], th[4], th[5], th[6], th[7]
    for j in range(th.shape[0]):
        if not np.isfinite(th[j]):
            q_out[:] = np.nan
            nu_out[:] = np.nan
            return 3
    if M <= 0.0 or Fv < 0.0 or Fc < 0.0 or (Fs != 0.0 and vs <= 0.0):
        q_out[:] = np.nan
        nu_out[:] = np.nan
        return 3
    inv_eps = 1.0 / eps
    # bound on |d q̈ / d v| → number of RK4 substeps
    lam = abs(Fv) + 2.0 * abs(dFv) + (abs(Fc) + abs(dFc) + abs(Fs)) * inv_eps
    if Fs != 0.0:
        lam += abs(Fs) * 0.8577638849607068 / vs  # max |d/dv exp(-(v/vs)^2)| = sqrt(2/e)/vs
    lam /= M
    n_sub = int(np.ceil(dt * lam / h_lambda))
    if n_sub < n_sub_min:
        n_sub = n_sub_min
    if n_sub > n_sub_max:
        q_out[:] = np.nan
        nu_out[:] = np.nan
        return 2
    h = dt / n_sub
    x = init[0]
    v = init[1]
    q_km1 = init[2]
    q_km2 = init[3]
    for k in range(n):
        q_out[k] = x
        qd = (x - q_km2) / (2.0 * dt)
        nu = kp * kv * (qg[k] - x) - kv * qd + u_ext[k]
        if nu > v_sat:
            nu = v_sat
        elif nu < -v_sat:
            nu = -v_sat
        nu_out[k] = nu
        q_km2 = q_km1
        q_km1 = x
        if k == n - 1:
            break
        force = gtau * nu
        for _ in range(n_sub):
            a1 = _accel(v, force, M, Fv, Fc, off, Fs, vs, dFc, dFv, inv_eps)
            v2 = v + 0.5 * h * a1
            a2 = _accel(v2, force, M, Fv, Fc, off, Fs, vs, dFc, dFv, inv_eps)
            v3 = v + 0.5 * h * a2
            a3 = _accel(v3, force, M, Fv, Fc, off, Fs, vs, dFc, dFv, inv_eps)
            v4 = v + h * a3
            a4 = _accel(v4, force, M, Fv, Fc, off, Fs, vs, dFc, dFv, inv_eps)
            x += h * (v + 2.0 * v2 + 2.0 * v3 + v4) / 6.0
            v += h * (a1 + 2.0 * a2 + 2.0 * a3 + a4) / 6.0
        if not (np.isfinite(x) and np.isfinite(v)) or abs(x) > 1e6:
            q_out[k + 1:] = np.nan
            nu_out[k + 1:] = np.nan
            return 1
    return 0


@numba.njit(cache=True, parallel=True)
def simulate_kernel(theta: np.ndarray, qg: np.ndarray, u_ext: np.ndarray, init: np.ndarray, dt: float,
                    gtau: float, kp: float, kv: float, v_sat: float, eps: float, h_lambda: float,
                    n_sub_min: int, n_sub_max: int, q_out: np.ndarray, nu_out: np.ndarray,
                    status: np.ndarray) -> None:
    """Batched closed-loop simulation: rows of θ (P, 8) → q_out (P, N) m, nu_out (P, N) V, status (P,) int8.

    ``u_ext`` (N,) V is added to the control law before the saturation (the validation record's pulses).

    Status: 0 ok, 1 model failure (non-finite / diverged state), 2 solver failure (needs more than n_sub_max RK4
    substeps per sample), 3 invalid parameters (non-finite, M ≤ 0, Fv < 0, Fc < 0, Fs ≠ 0 with vs ≤ 0).
    Pure: no allocation besides locals, no Python objects; rows run in parallel (prange).
    """
    for p in numba.prange(theta.shape[0]):
        status[p] = _simulate_row(theta[p], qg, u_ext, init, dt, gtau, kp, kv, v_sat, eps, h_lambda,
                                  n_sub_min, n_sub_max, q_out[p], nu_out[p])


# ----------------------------------------------------------------------------------------------------------------
# Python wrapper
# ----------------------------------------------------------------------------------------------------------------

@dataclass
class EmpsSimResult:
    """Simulated positions ``q`` (P, N) m, controller outputs ``nu`` (P, N) V and per-row ``status`` (P,) int8."""

    q: np.ndarray
    nu: np.ndarray
    status: np.ndarray


def initial_state(qm: np.ndarray, dt: float) -> np.ndarray:
    """[q(0), q̇(0), q(−1), q(−2)] from the first three measured positions (m, m/s, m, m)."""
    q0, q1, q2 = float(qm[0]), float(qm[1]), float(qm[2])
    v0 = (-3.0 * q0 + 4.0 * q1 - q2) / (2.0 * dt)
    return np.array([q0, v0, q0 - v0 * dt, q0 - 2.0 * v0 * dt])


def as_theta_batch(theta: np.ndarray | Mapping[str, float]) -> np.ndarray:
    """θ as the kernel's (P, 8) array (:func:`~toggle_id.kernels.kernel_array`); a dict or a single vector gives
    P = 1. Raises ConfigError on shape."""
    if isinstance(theta, Mapping):
        theta = theta_from_dict(theta)
    arr = np.asarray(theta, dtype=float)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != N_PARAMS:
        raise ConfigError(f"EMPS θ must have shape (P, {N_PARAMS}) in the order {list(PARAM_NAMES)}, got {arr.shape}")
    return kernel_array(arr)


def simulate_emps(theta: np.ndarray | Mapping[str, float], record: EmpsRecord, *, eps: float = 1e-4,
                  h_lambda: float = 0.5, n_sub_min: int = 2, n_sub_max: int = 5000, pulse_gain: float = 1.0,
                  init: np.ndarray | None = None) -> EmpsSimResult:
    """Simulate the EMPS closed loop for each row of θ on ``record``'s reference ``qg`` (and its pulse train).

    ``eps`` (m/s) smooths sign(q̇); ``h_lambda`` bounds h·λ of the RK4 substeps; ``pulse_gain`` multiplies the
    record's ``pulses`` before they are added to the controller output ν (V, before the saturation; 0 ignores
    them); ``init`` overrides :func:`initial_state`. Bad settings raise :class:`ConfigError`; bad rows are reported in ``status``.
    """
    th = as_theta_batch(theta)
    if not (np.isfinite(eps) and eps > 0):
        raise ConfigError(f"eps (sign smoothing, m/s) must be positive, got {eps}")
    if not (np.isfinite(h_lambda) and h_lambda > 0):
        raise ConfigError(f"h_lambda must be positive, got {h_lambda}")
    if not (1 <= int(n_sub_min) <= int(n_sub_max)):
        raise ConfigError(f"need 1 <= n_sub_min <= n_sub_max, got {n_sub_min}, {n_sub_max}")
    init = initial_state(record.qm, record.dt) if init is None else np.asarray(init, dtype=float).reshape(4)
    if not np.isfinite(pulse_gain):
        raise ConfigError(f"pulse_gain must be finite, got {pulse_gain}")
    u_ext = np.ascontiguousarray(float(pulse_gain) * record.pulses)
    p, n = th.shape[0], record.n
    q = np.empty((p, n))
    nu = np.empty((p, n))
    status = np.zeros(p, dtype=np.int8)
    simulate_kernel(th, kernel_array(record.qg), u_ext, kernel_array(init), record.dt, record.gtau,
                    record.kp, record.kv, record.v_sat, float(eps), float(h_lambda), int(n_sub_min), int(n_sub_max),
                    q, nu, status)
    return EmpsSimResult(q=q, nu=nu, status=status)


def controller_law(record: EmpsRecord, q: np.ndarray | None = None, pulse_gain: float = 1.0) -> np.ndarray:
    """ν(k) (V) of the documented controller driven by the positions ``q`` (default the measured ``qm``), with
    ``pulse_gain``·``record.pulses`` added before the saturation, as in the simulator.

    The first two samples use the velocity from :func:`initial_state`. On DATA_EMPS the law reproduces the
    recorded ``vir`` to 0.004 V rms (signal rms 1.54 V); applied one sample late it would be off by 0.054 V rms.
    """
    q = record.qm if q is None else np.asarray(q, dtype=float)
    init = initial_state(q, record.dt)
    hist = np.concatenate(([init[3], init[2]], q))
    qd = (hist[2:] - hist[:-2]) / (2.0 * record.dt)
    nu = record.kp * record.kv * (record.qg - q) - record.kv * qd + float(pulse_gain) * record.pulses
    return np.clip(nu, -record.v_sat, record.v_sat)


def friction_force(theta: np.ndarray | Mapping[str, float], v: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    """Model friction f(v) (N) at velocities ``v`` (m/s) for one θ (dict or vector): the same expression as the
    simulator's kernel, Fv·v + Fc·s + offset + Fs·s·exp(−(v/vs)²) + Fc_asym·|s| + Fv_asym·v·s, s = tanh(v/eps)."""
    M, Fv, Fc, off, Fs, vs, dFc, dFv = as_theta_batch(theta)[0]
    v = np.asarray(v, dtype=float)
    s = np.tanh(v / eps)
    f = Fv * v + Fc * s + off + dFc * np.abs(s) + dFv * v * s
    if Fs != 0.0 and vs > 0.0:
        f = f + Fs * s * np.exp(-(v / vs) ** 2)
    return f


def position_rel_error_pct(qm: np.ndarray, q_sim: np.ndarray) -> np.ndarray | float:
    """100·‖qm − q_sim‖/‖qm‖ (%), per row for a (P, N) ``q_sim``; NaN rows give NaN."""
    q_sim = np.asarray(q_sim, dtype=float)
    err = np.linalg.norm(q_sim - qm, axis=-1)
    return 100.0 * err / np.linalg.norm(qm)
