"""Routes of the discovery loop (toggle_id/discovery/routes.py): which route's model is reported, and when two
baselines are one basin. Stub outcomes with known residuals; the loop itself is tested in test_discover.py."""
from __future__ import annotations

import numpy as np

from toggle_id.discovery.engine import Outcome
from toggle_id.discovery.model import Fit
from toggle_id.discovery.routes import Route, choose, left_in, more_routes, same_basin

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


class _Plant:
    """A stub plant: its nominal fit is the baseline RMS it polishes to (µm); structure is left above 1.5 µm."""

    def __init__(self, rms_um: float) -> None:
        self.rms_um = rms_um
        self.baseline_fit: Fit | None = None

    def baseline(self) -> Fit:
        self.baseline_fit = Fit(np.zeros(3), ("p",), (self.rms_um * 1e-6) ** 2 * N)
        return self.baseline_fit


def _stub_loop(plant: _Plant) -> Outcome:
    diag = {"verdict": {"structure_left": plant.rms_um > 1.5}}
    return Outcome(plant.baseline_fit, [], [], [], (diag, None, None))


def _more(first_um: float, alternatives: list, restarts: list, max_ratio: float = 0.0) -> list[Route]:
    plant = _Plant(first_um)
    plant.baseline()
    routes = [Route("two_stage", plant, _stub_loop(plant))]
    more_routes(routes, alternatives, restarts, _Plant, _stub_loop, N, 1e-3, lambda msg: None, max_ratio=max_ratio)
    return routes


def test_restarts_run_only_from_a_lower_baseline_and_only_while_the_record_is_unexplained():
    made: list[str] = []

    def fit(label: str, rms_um: float):
        return label, lambda: made.append(label) or rms_um

    # a GA seed in the 8-µm basin (rec17's), the fast fit in another, then restarts: one higher (skipped), one
    # in the first route's basin (skipped), one lower that explains the record; the last one is never made
    routes = _more(8.05, [fit("fast", 9.1)], [fit("seed1", 14.6), fit("seed2", 8.0505), fit("seed3", 1.0),
                                             fit("seed4", 0.9)])
    assert made == ["fast", "seed1", "seed2", "seed3"]
    assert [r.label for r in routes] == ["two_stage", "fast", "seed1", "seed2", "seed3"]
    assert routes[1].outcome is not None and routes[1].skipped is None  # an alternative runs from a higher basin
    assert "no lower than route two_stage's (8.05 µm)" in routes[2].skipped and routes[2].outcome is None
    assert "basin of route two_stage" in routes[3].skipped
    assert routes[4].outcome is not None and not routes[4].structure_left
    # the first route explained the record: alternatives still run (as they always have), restarts are not made
    made.clear()
    routes = _more(1.0, [fit("fast", 9.1)], [fit("seed1", 0.5)])
    assert made == ["fast"] and [r.label for r in routes] == ["two_stage", "fast"]


def test_a_skipped_route_says_when_another_start_than_its_own_fit_won():
    from toggle_id.discovery.routes import _from_other_start

    fit = Fit(np.zeros(3), ("p",), 1e-12 * N)
    fit.info["starts"] = [{"start": 0, "rmse_m": 2.141e-5}, {"start": 1, "rmse_m": 1e-6}]
    assert _from_other_start(fit) == ", from another start; its own fit polished to 21.41 µm"
    fit.info["starts"][0] = {"start": 0, "error": "cannot be simulated on this record"}
    assert _from_other_start(fit).endswith("its own fit polished to nothing: it cannot be simulated")
    fit.info["starts"] = [{"start": 0, "rmse_m": 1e-6}, {"start": 1, "rmse_m": 2e-6}]  # its own fit won
    assert _from_other_start(fit) == "" and _from_other_start(Fit(np.zeros(3), ("p",), 1.0)) == ""


def test_an_alternative_far_above_the_lowest_baseline_is_skipped_and_a_near_equal_one_runs():
    def fit(label: str, rms_um: float):
        return label, rms_um

    # rec45's fast fit (29.0 against 3.045 µm) and rec22's (3.077 against 3.073 µm), at the default 1.5
    routes = _more(3.045, [fit("fast", 28.97), fit("near", 3.077)], [], max_ratio=1.5)
    assert "more than 1.5 times route two_stage's (3.045 µm): a worse optimum" in routes[1].skipped
    assert routes[1].outcome is None and routes[2].skipped is None and routes[2].outcome is not None
    # off (0): every alternative runs, as before the limit
    assert all(r.outcome is not None for r in _more(3.045, [fit("fast", 28.97)], [], max_ratio=0.0))


def test_no_route_is_started_after_the_deadline_and_its_nominal_fit_is_never_made():
    """discover.max_seconds: past the deadline every route left is listed as skipped with the budget's text, its
    nominal fit never made; before it, they run as ever."""
    import time

    made: list[str] = []

    def fit(label: str, rms_um: float):
        return label, lambda: made.append(label) or rms_um

    plant = _Plant(8.05)
    plant.baseline()
    routes = [Route("two_stage", plant, _stub_loop(plant))]
    more_routes(routes, [fit("fast", 9.1)], [fit("seed1", 1.0)], _Plant, _stub_loop, N, 1e-3, lambda msg: None,
                deadline=time.perf_counter() - 1.0, budget_text="out of time")
    assert made == [] and [(r.label, r.skipped, r.outcome) for r in routes[1:]] == [
        ("fast", "out of time", None), ("seed1", "out of time", None)]
    assert _choose(routes, {id(routes[0].outcome.final): NOISE}) == (0, [])
    assert routes[1].to_dict(N, False) == {"label": "fast", "chosen": False, "skipped": "out of time"}
    routes = routes[:1]
    more_routes(routes, [fit("fast", 9.1)], [], _Plant, _stub_loop, N, 1e-3, lambda msg: None,
                deadline=time.perf_counter() + 3600.0, budget_text="out of time")
    assert made == ["fast"] and routes[1].outcome is not None
