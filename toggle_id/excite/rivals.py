"""The rival explanations of one record that the excite job tries to tell apart.

An *effect rival* is "effect E on" (rival A) against "the nominal model without E" (rival B, whose parameters may
absorb E). Rival B is the nominal fit of the record; rival A is the nominal fit with E switched on at the given
magnitude and the nominal parameters refitted to the record (E held), so both explain the record. An *effect pair*
is "effect E on" against "effect F on instead": rival B is then built like A, with F, and a refit of B moves F's
parameters too. Rivals come from the configuration (``excite.rivals``: effect and magnitude, optionally
``against`` another) and from a discovery result: its accepted and compensating effects, with the magnitudes it
fitted, and each *ambiguous* pair (the effect of the final model against each effect the record could not tell
from it).
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .. import params as P
from ..discovery.gauge import GAUGE_HELD
from ..discovery.model import Model, fit_free
from ..effects import ALL_INDEX, EFFECTS_BY_NAME
from ..errors import ConfigError
from ..record import Record
from ..simulate import extend
from .score import Rival, linear_separation, responses
from .settings import RivalSpec

#: Nominal parameters a refit of rival B moves: all 15 but one per exact symmetry of x_B (K_l, K_i, m_C; holding
#: them changes no fit, it removes the flat directions that stall a trust region).
FREE_B: tuple[str, ...] = tuple(n for n in P.PARAM_NAMES if n not in GAUGE_HELD.values())


def specs_from_discovery(path: str | Path) -> list[RivalSpec]:
    """Rival specs from a ``discovery.json``: its accepted (``effects_added``) and compensating effects, each with
    the parameters the loop fitted, and its ambiguous pairs (the final model's effect against each tied one)."""
    p = Path(path).expanduser()
    try:
        d = json.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError(f"excite.discovery: {p} not found") from None
    except (OSError, ValueError) as err:
        raise ConfigError(f"excite.discovery: {p} is not a discovery.json ({err})") from None
    if not isinstance(d, Mapping) or "effects_added" not in d:
        raise ConfigError(f"excite.discovery: {p} has no effects_added (not a discovery.json)")
    out: list[RivalSpec] = []
    seen = set()
    for item in list(d.get("effects_added") or []) + list(d.get("compensating") or []):
        spec = _spec(item)
        if spec is None or spec.effect in seen:
            continue
        seen.add(spec.effect)
        out.append(spec)
    for item in d.get("ambiguous") or []:
        a = _spec(item)
        for tied in (item.get("indistinguishable_from") or []) if isinstance(item, Mapping) else []:
            b = _spec(tied)
            if a is not None and b is not None and b.effect != a.effect:
                out.append(RivalSpec(a.effect, a.params, against=b))
    return out


def discovery_base(path: str | Path) -> np.ndarray | None:
    """The final model of a ``discovery.json`` (its ``final_params``) with every effect off: the nominal parameters
    fitted together with the record's effects, where the rivals of an ambiguous pair start (a nominal fit
    without them can sit far from either). None when the file has no final parameters."""
    try:
        final = json.loads(Path(path).expanduser().read_text()).get("final_params")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(final, Mapping) or any(nm not in final for nm in P.PARAM_NAMES):
        return None
    theta = extend(np.array([float(final[nm]) for nm in P.PARAM_NAMES]))[0]
    for eff in EFFECTS_BY_NAME.values():
        for p in eff.params:
            theta[ALL_INDEX[p.name]] = p.off
    return theta


def _spec(item: Any) -> RivalSpec | None:
    """A spec from a discovery.json item ({name, params}); None when it is not a library effect that is on."""
    name = item.get("name") if isinstance(item, Mapping) else None
    if name not in EFFECTS_BY_NAME:
        return None
    eff = EFFECTS_BY_NAME[name]
    params = {k: float(v) for k, v in (item.get("params") or {}).items() if k in eff.names}
    return RivalSpec(name, params) if params.get(eff.magnitude.name, eff.magnitude.off) != eff.magnitude.off else None


def effect_rival(record: Record, theta_b: np.ndarray, spec: RivalSpec, *, max_nfev: int, rounds: int = 2,
                 fd_rel_step: float = 1e-4, source: str = "config", pair_base: np.ndarray | None = None) -> Rival:
    """Rival A = ``theta_b`` with ``spec``'s effect on, nominal parameters refitted to ``record`` (effect held);
    rival B = ``theta_b`` — or, with ``spec.against``, ``theta_b`` with that effect on, built the same way, whose
    effect parameters a refit of B may move; both then start from ``pair_base`` when given (the nominal part of the
    model that found the pair, :func:`discovery_base`). Both RMS errors on the record and their first-order
    separation there are kept."""
    model = Model(record, parallel=True)
    start = pair_base if spec.against is not None and pair_base is not None else theta_b
    theta_a = _fitted_with(model, start, spec, max_nfev, rounds, fd_rel_step)
    free_b = FREE_B
    if spec.against is not None:
        theta_b = _fitted_with(model, start, spec.against, max_nfev, rounds, fd_rel_step)
        free_b = _free_with(spec.against) + EFFECTS_BY_NAME[spec.against.effect].names
    against = spec.against.effect if spec.against is not None else "nominal"
    rival = Rival(name=f"{spec.effect} vs {against}", effect=spec.effect, params=dict(spec.params),
                  theta_a=theta_a, theta_b=np.array(theta_b, float), free_b=free_b, source=source, key=spec.key,
                  against=spec.against.effect if spec.against is not None else None)
    y, _ = responses(record, np.vstack([rival.theta_a, rival.theta_b]))
    rival.rms_a_m = float(np.sqrt(np.mean((record.x_B - y[0]) ** 2)))
    rival.rms_b_m = float(np.sqrt(np.mean((record.x_B - y[1]) ** 2)))
    rival.record_separation_m = linear_separation(record, rival, y[0], y[1])
    return rival


def _free_with(spec: RivalSpec) -> tuple[str, ...]:
    """The nominal parameters refitted with ``spec``'s effect on: :data:`FREE_B` and the gauge parameters the
    effect makes determined."""
    return FREE_B + tuple(GAUGE_HELD[s] for s in EFFECTS_BY_NAME[spec.effect].breaks)


def _fitted_with(model: Model, theta: np.ndarray, spec: RivalSpec, max_nfev: int, rounds: int,
                 fd_rel_step: float) -> np.ndarray:
    """``theta`` with ``spec``'s effect on at its parameters, the nominal parameters refitted to the record."""
    start = np.array(theta, float).copy()
    for k, v in spec.params.items():
        start[ALL_INDEX[k]] = v
    return fit_free(model, start, _free_with(spec), max_nfev, fd_rel_step, rounds=rounds).theta


def build_rivals(record: Record, theta_b: np.ndarray, specs: Sequence[tuple[RivalSpec, str]], *, max_nfev: int,
                 rounds: int = 2, fd_rel_step: float = 1e-4, progress=None,
                 pair_bases: Mapping[str, np.ndarray] | None = None) -> list[Rival]:
    """One :func:`effect_rival` per (spec, source); the same rival named twice counts once (the first).
    ``pair_bases``: per source, where the rivals of an effect pair start (:func:`discovery_base`)."""
    out, seen = [], set()
    for spec, source in specs:
        if spec.key in seen:
            continue
        seen.add(spec.key)
        rv = effect_rival(record, theta_b, spec, max_nfev=max_nfev, rounds=rounds, fd_rel_step=fd_rel_step,
                          source=source, pair_base=(pair_bases or {}).get(source))
        if progress:
            progress(f"rival {rv.name} ({', '.join(f'{k} = {v:g}' for k, v in spec.params.items())}): RMS on the "
                     f"record A {1e6 * rv.rms_a_m:.3g} µm, B {1e6 * rv.rms_b_m:.3g} µm; first-order separation "
                     f"there {1e6 * rv.record_separation_m:.3g} µm")
        out.append(rv)
    return out
