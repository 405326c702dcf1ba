"""The library of candidate effects the nominal model (docs/model.md) lacks.

Each effect is a physically meaningful term of the compiled right-hand side with its own parameters, bounds
and an *off* value at which the term vanishes (the nominal model). An effect's parameters live in the
extended parameter vector after the 15 physical ones (slots fixed in :mod:`toggle_id.kernels.slots`), so
switching an effect on is choosing which extended parameters are free; the discovery pipeline never names an
effect. Adding an effect = adding its term to the kernel's right-hand side (:mod:`toggle_id.kernels.rhs`) and
one :class:`Effect` entry here.

Parameters that only shape an effect (a Stribeck velocity, a cogging order) are *nuisance* parameters: they
have no influence while the effect is off, so the score test probes them on a small grid (``probe``).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .kernels import slots as K
from .params import N_PARAMS, PARAM_NAMES


@dataclass(frozen=True)
class EffectParam:
    """One parameter of an effect: kernel slot, unit, feasible domain and the value that switches it off."""

    name: str
    slot: int
    unit: str
    lower: float
    upper: float
    off: float = 0.0
    nuisance: bool = False


@dataclass(frozen=True)
class Effect:
    """A candidate effect: its parameters and the probe values used to score it from the nominal fit.

    ``probe`` lists parameter settings (name → value) at which the effect is 'small but on'; the score test
    linearises the output around the nominal fit in the direction of each probe and keeps the best.
    ``breaks`` names the exact symmetries of the rigid model's x_B (``mechanical``, ``current``,
    ``inertia_split``; see :mod:`toggle_id.discovery.gauge`) that the effect breaks: with it on, the parameter
    that fixes such a symmetry becomes determined by the data and is fitted again.
    ``grid`` (threshold effects): the magnitudes a global screening tries on a given record, as a function of
    the current parameters, the record's input and the number of points — a threshold acts only where the
    record crosses it, so a grid fixed in advance misses it on a record whose drive levels differ.
    """

    name: str
    description: str
    params: tuple[EffectParam, ...]
    probe: tuple[dict, ...] = field(default_factory=tuple)
    breaks: tuple[str, ...] = ()
    grid: Callable[[np.ndarray, np.ndarray, int], np.ndarray] | None = None
    acts_on: str = ""

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    @property
    def magnitude(self) -> EffectParam:
        """The parameter that measures the effect's size (the first non-nuisance one)."""
        return next(p for p in self.params if not p.nuisance)


def saturation_grid(theta: np.ndarray, v_in: np.ndarray, points: int) -> np.ndarray:
    """s_sat values that clip the record's peak drive command max|K_i·v_in| by 0.2 % to 60 % (geometric in the
    clipped fraction: a limit just below the peak acts on the few samples at the peak only)."""
    peak = float(np.max(np.abs(theta[PARAM_NAMES.index("K_i")] * np.asarray(v_in, float))))
    if not np.isfinite(peak) or peak <= 0.0:
        return np.zeros(0)
    clipped = np.geomspace(0.002, 0.6, max(int(points), 2))
    return 1.0 / ((1.0 - clipped) * peak)


EFFECTS: tuple[Effect, ...] = (
    Effect("coulomb_friction_motor", "Coulomb torque on the motor/screw side, −τ_c·sgn(ω_r)",
           (EffectParam("tau_c", K.TAU_C, "N·m", 0.0, 20.0),), ({"tau_c": 0.1},),
           acts_on="slider"),  # through the mechanism, a force on slider B of its position and direction
    Effect("stribeck_friction", "Stribeck excess friction on slider B, −F_s·exp(−(ẋ_B/v_s)²)·sgn(ẋ_B)",
           (EffectParam("F_s", K.F_S, "N", 0.0, 500.0), EffectParam("v_s", K.V_S, "m/s", 1e-4, 0.5, 0.01, True)),
           ({"F_s": 1.0, "v_s": 0.003}, {"F_s": 1.0, "v_s": 0.01}, {"F_s": 1.0, "v_s": 0.03},
            {"F_s": 1.0, "v_s": 0.1}), acts_on="slider"),
    Effect("viscous_friction_slider", "viscous friction on slider B, −c_B·ẋ_B",
           (EffectParam("c_B", K.C_B, "N·s/m", 0.0, 1e4),), ({"c_B": 10.0},), acts_on="slider"),
    Effect("dead_time", "transport delay of the drive input, v_in(t − τ_d)",
           (EffectParam("tau_d", K.TAU_D, "s", 0.0, 0.05),), ({"tau_d": 1e-4},)),
    Effect("backlash", "dead band b_l in the screw–nut: rotor and linkage move apart while the flank force is "
           "reversed and meet again in an inelastic impact (toggle_id/kernels/backlash.py)",
           (EffectParam("b_l", K.B_L, "m", 0.0, 2e-3),), ({"b_l": 1e-5},),
           breaks=("inertia_split",)),  # in the lash the rotor's inertia J_m acts apart from m_C
    Effect("cogging_torque", "torque ripple a·sin(n·θ_r + φ) periodic in the rotor angle θ_r = Z·x_C",
           (EffectParam("a_cog", K.A_COG, "N·m", 0.0, 20.0),
            EffectParam("n_cog", K.N_COG, "1/rev", 1.0, 48.0, 6.0, True),
            EffectParam("phi_cog", K.PHI_COG, "rad", -np.pi, np.pi, 0.0, True)),
           tuple({"a_cog": 0.1, "n_cog": float(n), "phi_cog": ph} for n in (1, 2, 3, 4, 6, 8, 12, 16, 24)
                 for ph in (0.0, np.pi / 2))),
    Effect("constant_load_force", "constant external force on slider B, −F_load (positive opposes closing)",
           (EffectParam("F_load", K.F_LOAD, "N", -2000.0, 2000.0),), ({"F_load": 1.0},), acts_on="slider"),
    Effect("contact_nonlinear_stiffness", "hardening contact, F_i += k3·z³ while clamped",
           (EffectParam("k3", K.K3, "N/m³", -1e15, 1e15),), ({"k3": 1e10},), acts_on="slider"),
    Effect("voltage_saturation", "drive output limit |K_i·v_in| ≤ 1/s_sat (s_sat = 0: no limit)",
           (EffectParam("s_sat", K.S_SAT, "1/V", 0.0, 1.0),),
           tuple({"s_sat": s} for s in (0.12, 0.15, 0.17, 0.2, 0.25, 0.35, 0.5)), grid=saturation_grid),
    Effect("sensor_offset", "constant offset of the measured x_B",
           (EffectParam("x_off", K.X_OFF, "m", -5e-3, 5e-3),), ({"x_off": 1e-6},), acts_on="reading"),
    Effect("torque_constant_saturation", "magnetic saturation of the motor: torque K_t·i_q/√(1 + c_kt·i_q²), so "
           "the torque constant falls at high current (i_sat = 1/√c_kt); the back-EMF is unchanged",
           (EffectParam("c_kt", K.C_KT, "1/A²", 0.0, 1e-4),), ({"c_kt": 1e-9},)),
)

EFFECTS_BY_NAME: dict[str, Effect] = {e.name: e for e in EFFECTS}
#: every parameter of the library's effects by name (the generic terms' aside)
EFFECT_PARAMS: dict[str, EffectParam] = {p.name: p for e in EFFECTS for p in e.params}


def _generic_params(prefix: str, lo: int, w0: int, unit: str, n: int = K.N_GEN, weight: str = "N",
                    bound: float = 5e3) -> tuple[EffectParam, ...]:
    knots = (EffectParam(f"{prefix}_lo", lo, unit, -1e3, 1e3, 0.0, True),
             EffectParam(f"{prefix}_hi", lo + 1, unit, -1e3, 1e3, 0.0, True))
    return knots + tuple(EffectParam(f"{prefix}_w{k}", w0 + k, weight, -bound, bound) for k in range(n))


#: Not a library effect, never named: a force on slider B of any shape in its speed and position,
#: f(ẋ_B) + g(x_B), each piecewise linear on ``N_GEN`` uniform knots over the range the record covers
#: (``gv_lo``…``gv_hi`` m/s, ``gx_lo``…``gx_hi`` m; set from the record, not fitted). The discovery loop fits
#: it when structure is left, to ask whether an accepted effect does anything such a force would not do
#: (:mod:`toggle_id.discovery.catchall`).
GENERIC_FORCE = Effect(
    "generic_slider_force", "a force on slider B, any piecewise-linear function of its speed plus one of its "
    "position, −f(ẋ_B) − g(x_B)",
    _generic_params("gv", K.GV_LO, K.GV_W0, "m/s") + _generic_params("gx", K.GX_LO, K.GX_W0, "m"),
    # the probes give the fits the weights' typical size (finite-difference steps, trust region): a force that
    # moves x_B well above the integrator's error
    tuple({f"{p}_w{k}": 100.0} for p in ("gv", "gx") for k in range(K.N_GEN)))

#: Not a library effect, never named: an error of the position reading of any shape, h(x_B), piecewise linear on
#: ``N_GS`` uniform knots from ``gs_lo`` to ``gs_hi`` (m; set from the record, not fitted) with weights ``gs_w*`` (m),
#: added to the model's x_B at the model's position (an interpolation error of a linear scale, a misaligned or bent
#: scale; at the measured position its slope would fit the noise of a slider at rest). An output map, not a kernel
#: term: :class:`toggle_id.discovery.model.Model` adds it, and a batch whose rows differ only in it costs one
#: simulation. The catch-all check fits it beside :data:`GENERIC_FORCE`.
GENERIC_SENSOR = Effect(
    "generic_sensor_error", "an error of the position reading, any piecewise-linear function of the position x_B",
    _generic_params("gs", K.GS_LO, K.GS_W0, "m", K.N_GS, "m", 1e-3),
    tuple({f"gs_w{k}": 1e-6} for k in range(K.N_GS)))

#: Every term of the extended parameter vector beyond the 15 physical parameters: the library, then the generic
#: force and the generic sensor error.
TERMS: tuple[Effect, ...] = EFFECTS + (GENERIC_FORCE, GENERIC_SENSOR)

#: Names of the library effects' parameters (kernel order); the extended parameter vector holds the 15 physical
#: ones, then these, then the generic force's and the generic sensor error's (which no report lists: they are never
#: part of a reported model).
EXTRA_NAMES: tuple[str, ...] = ("tau_c", "F_s", "v_s", "c_B", "tau_d", "b_l", "a_cog", "n_cog", "phi_cog",
                                "F_load", "k3", "s_sat", "x_off", "c_kt")
ALL_NAMES: tuple[str, ...] = PARAM_NAMES + EXTRA_NAMES + GENERIC_FORCE.names + GENERIC_SENSOR.names
ALL_INDEX: dict[str, int] = {n: i for i, n in enumerate(ALL_NAMES)}
assert len(ALL_NAMES) == K.N_THETA
for _e in TERMS:
    for _p in _e.params:
        assert ALL_INDEX[_p.name] == _p.slot, _p

#: Values of the effect parameters in the nominal model (all effects off; nuisance ones at their defaults).
EXTRA_DEFAULTS = np.zeros(K.N_THETA - N_PARAMS)
for _e in TERMS:
    for _p in _e.params:
        EXTRA_DEFAULTS[_p.slot - N_PARAMS] = _p.off


def effect(name: str) -> Effect:
    """The effect called ``name``; ValueError listing the known ones otherwise."""
    if name not in EFFECTS_BY_NAME:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECTS_BY_NAME)}")
    return EFFECTS_BY_NAME[name]


def effect_bounds(names) -> tuple[np.ndarray, np.ndarray]:
    """Feasible domain of extended (effect) parameter names."""
    lookup = {p.name: p for e in TERMS for p in e.params}
    return (np.array([lookup[n].lower for n in names], float), np.array([lookup[n].upper for n in names], float))


def sensor_error(thetas: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(P, N) generic error of the position reading (:data:`GENERIC_SENSOR`) of extended vectors ``thetas`` at the
    positions ``x`` ((N,), or (P, N): one row per vector), interpolated linearly between its knots and constant
    beyond them; zeros for rows with all its weights at 0."""
    thetas = np.atleast_2d(thetas)
    x = np.asarray(x, float)
    W = thetas[:, K.GS_W0:K.GS_W0 + K.N_GS]
    out = np.zeros((thetas.shape[0], x.shape[-1]))
    for i in np.flatnonzero(np.any(W != 0.0, axis=1)):
        lo, hi = thetas[i, K.GS_LO], thetas[i, K.GS_HI]
        if not hi > lo:
            raise ValueError(f"the generic sensor error's knots need gs_hi > gs_lo, got {lo!r} … {hi!r}")
        out[i] = np.interp(x if x.ndim == 1 else x[i], np.linspace(lo, hi, K.N_GS), W[i])
    return out
