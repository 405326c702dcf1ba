"""The rival explanations of one record that the excite job tries to tell apart.

An *effect rival* is "effect E on" (rival A) against "the nominal model without E" (rival B, whose parameters may
absorb E). Rival B is the nominal fit of the record; rival A is the nominal fit with E switched on at the given
magnitude and the nominal parameters refitted to the record (E held), so both explain the record. Rivals come
from the configuration (``excite.rivals``: effect and magnitude) and from a discovery result (its accepted and
compensating effects, with the magnitudes it fitted).
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .. import params as P
from ..discovery.gauge import GAUGE_HELD
from ..discovery.model import Model, fit_free
from ..effects import ALL_INDEX, EFFECTS_BY_NAME
from ..errors import ConfigError
from ..record import Record
from .score import Rival, linear_separation, responses
from .settings import RivalSpec

#: Nominal parameters a refit of rival B moves: all 15 but one per exact symmetry of x_B (K_l, K_i, m_C; holding
#: them changes no fit, it removes the flat directions that stall a trust region).
FREE_B: tuple[str, ...] = tuple(n for n in P.PARAM_NAMES if n not in GAUGE_HELD.values())


def specs_from_discovery(path: str | Path) -> list[RivalSpec]:
    """Rival specs from a ``discovery.json``: its accepted (``effects_added``) and compensating effects, each with
    the parameters the loop fitted."""
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
        name = item.get("name") if isinstance(item, Mapping) else None
        if name not in EFFECTS_BY_NAME or name in seen:
            continue
        params = {k: float(v) for k, v in (item.get("params") or {}).items() if k in EFFECTS_BY_NAME[name].names}
        mag = EFFECTS_BY_NAME[name].magnitude
        if params.get(mag.name, mag.off) == mag.off:
            continue
        seen.add(name)
        out.append(RivalSpec(name, params))
    return out


def effect_rival(record: Record, theta_b: np.ndarray, spec: RivalSpec, *, max_nfev: int, rounds: int = 2,
                 fd_rel_step: float = 1e-4, source: str = "config") -> Rival:
    """Rival A = ``theta_b`` with ``spec``'s effect on, nominal parameters refitted to ``record`` (effect held);
    rival B = ``theta_b``. Both RMS errors on the record and their first-order separation there are kept."""
    theta_a = np.array(theta_b, float).copy()
    for k, v in spec.params.items():
        theta_a[ALL_INDEX[k]] = v
    free_a = FREE_B + tuple(GAUGE_HELD[s] for s in EFFECTS_BY_NAME[spec.effect].breaks)
    model = Model(record, parallel=True)
    fit = fit_free(model, theta_a, free_a, max_nfev, fd_rel_step, rounds=rounds)
    rival = Rival(name=f"{spec.effect} vs nominal", effect=spec.effect, params=dict(spec.params),
                  theta_a=fit.theta, theta_b=np.array(theta_b, float), free_b=FREE_B, source=source)
    y, _ = responses(record, np.vstack([rival.theta_a, rival.theta_b]))
    rival.rms_a_m = float(np.sqrt(np.mean((record.x_B - y[0]) ** 2)))
    rival.rms_b_m = float(np.sqrt(np.mean((record.x_B - y[1]) ** 2)))
    rival.record_separation_m = linear_separation(record, rival, y[0], y[1])
    return rival


def build_rivals(record: Record, theta_b: np.ndarray, specs: Sequence[tuple[RivalSpec, str]], *, max_nfev: int,
                 rounds: int = 2, fd_rel_step: float = 1e-4, progress=None) -> list[Rival]:
    """One :func:`effect_rival` per (spec, source); the same effect named twice counts once (the first)."""
    out, seen = [], set()
    for spec, source in specs:
        if spec.effect in seen:
            continue
        seen.add(spec.effect)
        rv = effect_rival(record, theta_b, spec, max_nfev=max_nfev, rounds=rounds, fd_rel_step=fd_rel_step,
                          source=source)
        if progress:
            progress(f"rival {rv.name} ({', '.join(f'{k} = {v:g}' for k, v in spec.params.items())}): RMS on the "
                     f"record A {1e6 * rv.rms_a_m:.3g} µm, B {1e6 * rv.rms_b_m:.3g} µm; first-order separation "
                     f"there {1e6 * rv.record_separation_m:.3g} µm")
        out.append(rv)
    return out
