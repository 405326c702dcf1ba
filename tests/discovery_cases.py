"""Cases shared by the discovery tests: a simulated record with effects, fast settings, a fake model."""
from __future__ import annotations

import numpy as np

from toggle_id import discovery as D
from toggle_id.effects import ALL_INDEX, EFFECTS_BY_NAME
from toggle_id.params import ASSIGNED, PARAM_NAMES
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, extend, simulate


NOISE = 1e-6


def fake_model(**attrs):
    """A stand-in for :class:`toggle_id.discovery.model.Model` with ``attrs``, whose effects keep to the library's
    feasible domains (no gauge of its own)."""
    from types import SimpleNamespace

    from toggle_id.discovery.timing import PhaseClock
    from toggle_id.stages import stage_bounds

    def domain(name):
        lo, hi = stage_bounds([name])
        return float(lo[0]), float(hi[0])

    return SimpleNamespace(domain=domain, domains=dict, gauge_bounds={}, clock=PhaseClock(), **attrs)


def make_record(effects: dict, duration: float = 1.0, seed: int = 0, pert: float = 0.05, start_pert: float = 0.03,
                noise: float = NOISE) -> tuple[Record, np.ndarray, np.ndarray]:
    """A simulated record with ``effects`` switched on, the other parameters perturbed away from the assigned
    values (log-normal, ``pert``), noise σ = ``noise``; and a nominal start a few per cent off the truth."""
    rng = np.random.default_rng(seed)
    truth = extend(ASSIGNED * np.exp(pert * rng.standard_normal(len(PARAM_NAMES))))[0]
    for k, v in effects.items():
        truth[ALL_INDEX[k]] = v
    rec = Record.from_sweep("simulation", duration, name="test")
    sim = simulate(truth[None, :], rec, PRECISE)
    assert sim.status[0] == 0
    rec.x_B = sim.x_B[0] + noise * rng.standard_normal(rec.n)
    start = truth[:len(PARAM_NAMES)] * np.exp(start_pert * rng.standard_normal(len(PARAM_NAMES)))
    return rec, truth, start


#: Fast-test settings: a few candidates, one effect at most, small budgets.
FAST = dict(top_k=2, max_effects=1, grid_points=8, baseline_nfev=40, refit_nfev=30, null_nfev=20, noise_std=NOISE)


SUBSET = ("constant_load_force", "sensor_offset", "coulomb_friction_motor", "dead_time")


def discover_on(effects: dict, candidates=SUBSET, duration: float = 1.0, **kw) -> tuple[D.DiscoveryResult, np.ndarray]:
    rec, truth, start = make_record(effects, duration)
    settings = D.DiscoverSettings(candidates=candidates, **{**FAST, **kw})
    return D.discover(rec, nominal=start, settings=settings), truth


def with_value(theta, name, value):
    out = theta.copy()
    out[ALL_INDEX[name]] = value
    return out


def refit_case(effect: str, param: str, value: float, base_sse: float):
    """(theta, effect, base fit, scout) of a refit test: the assigned values, a baseline with μ free, and a scout
    at ``param`` = ``value``."""
    from toggle_id.discovery import refit as RF
    from toggle_id.discovery.model import Fit

    theta = extend(ASSIGNED)[0]
    eff = EFFECTS_BY_NAME[effect]
    scout = RF.Scout(eff.name, 90.0, with_value(theta, param, value), {"best_grid": {param: value}})
    return theta, eff, Fit(theta.copy(), ("mu",), sse=base_sse), scout
