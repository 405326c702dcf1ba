"""Routes of the discovery loop (toggle_id/discovery/routes.py): which route's model is reported, and when two
baselines are one basin. Stub outcomes with known residuals; the loop itself is tested in test_discover.py."""
from __future__ import annotations

import numpy as np

from toggle_id.discovery.engine import Outcome
from toggle_id.discovery.model import Fit
from toggle_id.discovery.routes import Route, choose, left_in, same_basin

N = 4000
RNG = np.random.default_rng(7)
NOISE = 1e-6 * RNG.standard_normal(N)
JITTER = 2e-8 * RNG.standard_normal(N)  # two fits the record cannot tell apart (Vuong z ≈ 0.6)
BUMP = 1e-6 * np.exp(-0.5 * ((np.arange(N) - 2000) / 150.0) ** 2)  # structure a white-noise test would flag


def _route(label: str, residual: np.ndarray, n_free: int, left: bool, registry: dict) -> Route:
    fit = Fit(np.full(3, float(len(registry))), tuple(f"p{i}" for i in range(n_free)), float(residual @ residual))
    registry[id(fit)] = residual
    diag = {"verdict": {"structure_left": left}}
    return Route(label, plant=None, outcome=Outcome(fit, [], [], [], (diag, residual, None)))


def _choose(routes: list[Route], registry: dict, alpha: float = 0.05) -> tuple[int, list[dict]]:
    return choose(routes, lambda f: registry[id(f)], N, noise_max_order=2, alpha=alpha)


def test_a_route_that_fits_clearly_better_is_reported_even_if_it_leaves_structure():
    reg: dict = {}
    worse = _route("two_stage", NOISE + 3.0 * BUMP + 0.8e-6 * np.sin(np.arange(N) / 30.0), 13, False, reg)
    better = _route("fast", NOISE + 0.2 * BUMP, 13, True, reg)
    pick, compared = _choose([worse, better], reg)
    assert pick == 1
    assert compared and compared[0]["a"] == "fast" and compared[0]["z"] > 0 and not compared[0]["tied"]


def test_among_routes_the_record_cannot_tell_apart_the_one_that_explains_it_wins():
    reg: dict = {}
    unexplained = _route("two_stage", NOISE, 13, True, reg)  # the lower error, structure flagged
    explained = _route("fast", NOISE + JITTER, 13, False, reg)
    pick, compared = _choose([unexplained, explained], reg)
    assert compared[0]["tied"] and pick == 1


def test_of_two_routes_that_explain_the_record_equally_well_the_one_with_fewer_parameters_wins():
    reg: dict = {}
    more = _route("two_stage", NOISE, 14, False, reg)
    fewer = _route("fast", NOISE + JITTER, 13, False, reg)
    pick, compared = _choose([more, fewer], reg)
    assert pick == 1 and compared[0]["z"] < 0  # the Schwarz correction: one parameter more buys nothing here
    # tied, both explaining, as many parameters: the earlier route (the job's own nominal fit) is kept
    first = _route("two_stage", NOISE + JITTER, 13, False, reg)
    assert _choose([first, _route("fast", NOISE, 13, False, reg)], reg)[0] == 0
    # with the ambiguity test off the lowest error wins
    assert _choose([more, fewer], reg, alpha=0.0)[0] == 0


def test_a_route_that_was_not_run_is_never_reported_and_one_route_needs_no_test():
    reg: dict = {}
    only = _route("two_stage", NOISE, 13, True, reg)
    skipped = Route("fast", plant=None, skipped="same basin")
    assert _choose([only, skipped], reg) == (0, [])
    assert left_in(only.outcome) and not left_in(Outcome(None, [], [], [], None))


def test_baselines_are_one_basin_when_their_errors_agree_to_the_tolerance():
    a = Fit(np.zeros(3), ("p",), 1.000e-12 * N)
    b = Fit(np.zeros(3), ("p",), 1.0015e-12 * N)  # RMS 1 µm against 1.00075 µm
    c = Fit(np.zeros(3), ("p",), 1.01e-12 * N)
    assert same_basin(a, b, N, 1e-3) and not same_basin(a, c, N, 1e-3) and same_basin(a, c, N, 1e-2)
