"""The exact symmetries of x_B(t): one parameter held per symmetry in the polishes, and the representative of a
fit nearest the reference values for the report."""
from __future__ import annotations

from collections.abc import Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager

import numpy as np

from .. import params as P
from ..effects import ALL_INDEX, ALL_NAMES, EFFECT_PARAMS, Effect, effect_bounds
from ..identify import stage_bounds
from .model import Model


#: Parameters that scale together with every force of the mechanism: multiplying all of them (and every effect
#: parameter whose unit is a force, torque, damping or stiffness) by c leaves x_B(t) and i_q(t) unchanged.
MECHANICAL = ("m_2", "m_3", "m_5", "m_B", "m_C", "J_m", "B_m", "K_t", "K_l", "D")


#: The current scale: i_q → i_q/c with K_i → K_i/c, λ_d → λ_d/c, K_t → c·K_t leaves x_B(t) unchanged.
ELECTRICAL = {"K_t": 1.0, "K_i": -1.0, "lambda_d": -1.0}


#: The parameter held at its value to fix each symmetry in the uncertainty analysis (one per symmetry).
GAUGE_HELD = {"mechanical": "K_l", "current": "K_i", "inertia_split": "m_C"}


def gauge_symmetries(free: Collection[str], broken: Collection[str] = ()) -> list[str]:
    """The exact symmetries of x_B whose parameters are all in ``free`` and that no effect in the model breaks."""
    f = set(free)
    members = {"mechanical": MECHANICAL, "current": tuple(ELECTRICAL), "inertia_split": ("m_C", "J_m")}
    return [s for s, names in members.items() if s not in broken and set(names) <= f]


def freed_with(base_free: Sequence[str], effect: Effect, held: Collection[str]) -> tuple[str, ...]:
    """The parameters of a refit with ``effect`` on: the base fit's, the gauge parameters ``effect`` makes
    determined again (held so far), and the effect's own."""
    back = tuple(GAUGE_HELD[s] for s in effect.breaks if GAUGE_HELD[s] in held and GAUGE_HELD[s] not in base_free)
    return tuple(base_free) + back + effect.names


#: The unit of every effect parameter (the current and mechanism scales follow from it).
_UNITS = {name: p.unit for name, p in EFFECT_PARAMS.items()}


def _force_like(name: str) -> bool:
    """An effect parameter in newtons (force, torque, damping, stiffness) scales with the mechanism."""
    return _UNITS.get(name, "").startswith("N")


def current_power(name: str) -> int:
    """The power of the current scale an effect parameter follows: a limit on the drive voltage K_i·v (unit 1/V)
    scales as c, a torque saturation c_kt·i_q² (unit 1/A²) as c² (so c_kt·K_i² is unchanged along it); 0 for
    the rest."""
    return {"1/V": 1, "1/A²": 2}.get(_UNITS.get(name, ""), 0)


def scale_type(name: str) -> bool:
    """Whether x_B fixes effect parameter ``name`` only relative to the mechanism's or the current's scale (a
    force-type magnitude, :func:`_force_like`, or one that follows the current, :func:`current_power`)."""
    return _force_like(name) or current_power(name) != 0


def _scale(theta: np.ndarray, c_m: float, c_e: float) -> None:
    """Move ``theta`` in place along the mechanical scale (every parameter of :data:`MECHANICAL` and every force-type
    effect × ``c_m``) and the current scale (:data:`ELECTRICAL`'s powers of ``c_e``; drive limits and torque
    saturation follow it, :func:`current_power`)."""
    for n in MECHANICAL:
        theta[ALL_INDEX[n]] *= c_m
    for n, k in ELECTRICAL.items():
        theta[ALL_INDEX[n]] *= c_e ** k
    for n in ALL_NAMES[P.N_PARAMS:]:
        theta[ALL_INDEX[n]] *= (c_m if _force_like(n) else 1.0) * c_e ** current_power(n)


def gauge_scales(theta: np.ndarray, free: Collection[str], reference: np.ndarray, broken: Collection[str] = ()
                 ) -> tuple[float, float] | None:
    """The mechanical and current scales (c_m, c_e) that move ``theta`` along the symmetries ``free`` leaves open to
    the representative nearest ``reference`` in log space (:func:`_scale`; 1 for a symmetry not open); None where no
    scale symmetry is open, the inertia split alone (a move with no scale), or a value of either is not positive."""
    sym = gauge_symmetries(free, broken)
    use_m, use_e = "mechanical" in sym, "current" in sym
    if not (use_m or use_e or "inertia_split" in sym):
        return None
    names = sorted(set(MECHANICAL if use_m else ()) | set(ELECTRICAL if use_e else ()))
    if not names:
        return 1.0, 1.0
    x = np.array([theta[ALL_INDEX[n]] for n in names])
    ref = np.array([reference[ALL_INDEX[n]] for n in names])
    if np.any(x <= 0) or np.any(ref <= 0):
        return None
    cols = []
    if use_m:
        cols.append([1.0 if n in MECHANICAL else 0.0 for n in names])
    if use_e:
        cols.append([ELECTRICAL.get(n, 0.0) for n in names])
    logc = np.linalg.lstsq(np.array(cols).T, np.log(ref) - np.log(x), rcond=None)[0]
    return (float(np.exp(logc[0])) if use_m else 1.0), (float(np.exp(logc[-1])) if use_e else 1.0)


def _factor(name: str, c_m: float, c_e: float) -> float:
    """What :func:`_scale` multiplies effect parameter ``name`` by along the scales (``c_m``, ``c_e``)."""
    return (c_m if _force_like(name) else 1.0) * c_e ** current_power(name)


def _scales_to(start: np.ndarray, at: np.ndarray) -> tuple[float, float] | None:
    """The mechanical and current scales that move ``start`` nearest ``at`` in log space (None: not readable)."""
    return gauge_scales(start, set(MECHANICAL) | set(ELECTRICAL), at)


def carried(values: Mapping[str, float], start: np.ndarray, at: np.ndarray) -> dict[str, float]:
    """Effect values fitted at ``at`` as they read at ``start``, another point of the same gauge (its held parameters
    at ``at``'s values, :func:`in_gauge_of`) whose mechanism and current sit at other scales: each value divided by
    the factor :func:`_scale` gives it along the scales that move ``start`` nearest ``at`` in log space
    (:func:`gauge_scales`), so that the effect keeps its size relative to each start's own mechanism (a force, a
    torque, a damping) and current (a drive limit, a torque saturation); the others as they are. Where the scales
    cannot be read (a parameter not positive), the values as they are.

    Measured on the held-out record rec15_d1 (a slider viscous friction and a sensor offset; the baseline at ×0.058
    the reference mechanism, the job's reference values moved into its gauge at ×0.0093): the friction's refit,
    c_B ≈ 300 in the baseline's gauge, carried unchanged to the reference start is six times its optimum there and
    the polish stalls at 2.44 µm; from 3 to 100 it reaches 1.697 µm at c_B 37.4."""
    scales = _scales_to(start, at)
    if scales is None:
        return dict(values)
    return {n: float(v) / _factor(n, *scales) for n, v in values.items()}


def domains_at(bounds: Mapping[str, Sequence[float]], start: np.ndarray, at: np.ndarray
               ) -> dict[str, tuple[float, float]]:
    """``bounds``, the effects' domains in the gauge of ``at`` (:func:`domains_in_gauge`), widened to hold at
    ``start``'s scales too: each as it reads there (divided by :func:`carried`'s factor), the wider of the two. A
    start whose mechanism sits at a larger scale than the baseline's needs room for larger forces: on rec15_d1 the
    reference values, as a start of the baseline at ×0.058 the reference mechanism, would have the slider's
    viscous friction at 17 times the baseline's domain (docs/discovery.md)."""
    scales = _scales_to(start, at)
    out = {n: (float(lo), float(hi)) for n, (lo, hi) in bounds.items()}
    if scales is None:
        return out
    for n, (lo, hi) in out.items():
        f = _factor(n, *scales)
        if f > 0 and np.isfinite(f) and f != 1.0:
            out[n] = (min(lo, lo / f), max(hi, hi / f))
    return out


@contextmanager
def domains_of_start(model: Model, start: np.ndarray, at: np.ndarray) -> Iterator[Model]:
    """Inside the block the fits of ``model`` keep to its gauge's domains widened for ``start`` (:func:`domains_at`,
    ``at`` the point whose gauge they were read in); after it, to the domains they had."""
    before = model.gauge_bounds
    model.gauge_bounds = domains_at(before, start, at)
    try:
        yield model
    finally:
        model.gauge_bounds = before


def domains_in_gauge(c_m: float, c_e: float, given: Mapping[str, Sequence[float]] | None = None
                     ) -> dict[str, tuple[float, float]]:
    """The library's feasible domains of the effect parameters that follow the mechanical or the current scale, as
    they read in a gauge that (``c_m``, ``c_e``) move to the reference scale (:func:`gauge_scales`): each divided by
    the factor :func:`_scale` multiplies it by. A force-type magnitude is fixed by x_B only relative to the
    mechanism, and the report states it at the reference scale (:func:`gauge_fix`), so its domain holds there. The
    scales are read once, at the baseline; the fits move the mechanism's scale as they go, so the domain holds at
    the reference scale only approximately (a slider viscous friction of 8000 N·s/m on a machine 15–40 % off the
    reference: the baseline at 1.042 times the reference scale, the final fit at 1.11; docs/discovery.md).
    ``given``: effect parameters' domains a user set (``bounds``), at the reference scale like the library's, in
    their place."""
    given = dict(given or {})
    out = {}
    for n in ALL_NAMES[P.N_PARAMS:]:
        f = (c_m if _force_like(n) else 1.0) * c_e ** current_power(n)
        if (f != 1.0 or n in given) and f > 0 and np.isfinite(f):
            lo, hi = given.get(n) or tuple(float(b[0]) for b in effect_bounds([n]))
            out[n] = (float(lo) / f, float(hi) / f)
    return out


def gauge_fix(model: Model, theta: np.ndarray, free: Sequence[str], reference: np.ndarray,
              tol_m: float = 2e-8, broken: Collection[str] = (), widened: Collection[str] = ()
              ) -> tuple[np.ndarray, dict]:
    """Move ``theta`` along the exact symmetries of x_B(t) to the point closest (in log space) to ``reference``.

    The symmetries (see :data:`MECHANICAL`, :data:`ELECTRICAL`, and m_C + J_m·Z² of docs/model.md §3) leave the output
    unchanged, so the fit is the same; the representative nearest the reference values makes the parameters —
    and the magnitudes of force-type effects, which scale with the mechanism — comparable with the reference. A
    symmetry is used only if all its parameters are free, the move stays within the feasible domains, and the
    output is verified unchanged (``tol_m``); symmetries in ``broken`` (broken by an effect of the model) are
    not used; effect parameters in ``widened`` (whose domain the loop widened where the fit pressed against it) are
    held to the side of "off" they are on, not to the library's domain. Returns (theta, {"mechanical_scale",
    "current_scale", ...}).
    """
    from ..plant import GEOMETRY as G

    out = theta.copy()
    info: dict = {"mechanical_scale": 1.0, "current_scale": 1.0, "applied": False}
    sym = gauge_symmetries(free, broken)
    use_m, use_e, use_split = ("mechanical" in sym), ("current" in sym), ("inertia_split" in sym)
    scales = gauge_scales(theta, free, reference, broken)
    if scales is None:
        return out, info
    c_m, c_e = scales
    _scale(out, c_m, c_e)
    if use_split and reference[ALL_INDEX["m_C"]] > 0 and reference[ALL_INDEX["J_m"]] > 0:
        Z2 = G.Z ** 2
        total = out[ALL_INDEX["m_C"]] + out[ALL_INDEX["J_m"]] * Z2
        rc, rj = reference[ALL_INDEX["m_C"]], reference[ALL_INDEX["J_m"]]
        fr = np.linspace(1e-3, 1 - 1e-3, 2001)
        cost = (np.log(fr * total / rc)) ** 2 + (np.log((1 - fr) * total / Z2 / rj)) ** 2
        f = fr[int(np.argmin(cost))]
        out[ALL_INDEX["m_C"]], out[ALL_INDEX["J_m"]] = f * total, (1 - f) * total / Z2
    lo, hi = stage_bounds(list(ALL_NAMES))
    for nm in widened:  # the scales are positive: a magnitude stays on its side of "off" (0) along them
        lo[ALL_INDEX[nm]], hi[ALL_INDEX[nm]] = -np.inf, np.inf
    if np.any(out < lo) or np.any(out > hi):
        info["note"] = "the symmetric representative nearest the reference leaves the feasible domain; not applied"
        return theta.copy(), info
    y = model.outputs(np.array([theta, out]))
    diff = float(np.nanmax(np.abs(y[0] - y[1]))) if np.all(np.isfinite(y)) else np.inf
    if not diff <= tol_m:
        info["note"] = f"output changed by {diff:.3g} m along the symmetry; not applied"
        return theta.copy(), info
    held = ([GAUGE_HELD["mechanical"]] if use_m else []) + ([GAUGE_HELD["current"]] if use_e else [])
    if use_split:
        held.append(GAUGE_HELD["inertia_split"])
    info.update({"mechanical_scale": c_m, "current_scale": c_e, "applied": True, "output_change_m": diff,
                 "held": held})
    return out, info


def in_gauge_of(theta: np.ndarray, like: np.ndarray) -> np.ndarray | None:
    """``theta``, a vector of the nominal model, moved along its exact symmetries so that the parameter held for
    each (K_l, K_i, m_C: :data:`GAUGE_HELD`) takes ``like``'s value: the same x_B(t), in the gauge a polish holding
    ``like``'s values works in. Effect parameters follow their scales (forces with the mechanism, drive limits and
    torque saturation with the current). None where a held value is not positive or the move leaves the feasible
    domain."""
    from ..plant import GEOMETRY as G

    ix = {nm: ALL_INDEX[nm] for nm in GAUGE_HELD.values()}
    if not all(theta[i] > 0 and like[i] > 0 for i in ix.values()):
        return None
    out = np.array(theta, dtype=float, copy=True)
    _scale(out, like[ix["K_l"]] / theta[ix["K_l"]], theta[ix["K_i"]] / like[ix["K_i"]])  # K_i → K_i/c_e
    z2 = G.Z ** 2
    j_m = (out[ix["m_C"]] + out[ALL_INDEX["J_m"]] * z2 - like[ix["m_C"]]) / z2  # m_C + J_m·Z² kept
    if j_m > 0:
        out[ix["m_C"]], out[ALL_INDEX["J_m"]] = like[ix["m_C"]], j_m
    lo, hi = stage_bounds(list(ALL_NAMES))
    return out if np.all(out >= lo) and np.all(out <= hi) else None
