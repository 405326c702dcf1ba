"""The real-coded GA: operators stay in the box, runs are reproducible and resumable, and it optimises."""
from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest

from toggle_id.errors import CheckpointError, ConfigError, DataError
from toggle_id.ga import (
    GAConfig,
    RGA,
    join_state,
    run_ga,
    split_state,
)
from toggle_id.ga_operators import (
    blend_crossover,
    elite_indices,
    next_generation,
    nonuniform_mutation,
    reflect_unit,
    sanitize_fitness,
    tournament_select,
)

LOWER = np.array([-5.0, 0.0, 1e-4, -1e3, 10.0])
UPPER = np.array([5.0, 1.0, 1e-3, 1e3, 11.0])
CENTRE = np.array([1.0, 0.25, 4e-4, -200.0, 10.9])


def sphere_fitness(X: np.ndarray) -> np.ndarray:
    """1 / (SSE + tiny): maximum at CENTRE, with the error scaled per coordinate to the box width."""
    z = (X - CENTRE) / (UPPER - LOWER)
    return 1.0 / (1e-30 + np.sum(z * z, axis=1))


def small(**kw) -> GAConfig:
    return GAConfig(**{"population": 30, "generations": 12, **kw})


# ---- operators -------------------------------------------------------------------------------------------------


def _populations(seed: int) -> list[np.ndarray]:
    """Random, degenerate (all equal), at-the-bounds and two-valued unit-box populations."""
    rng = np.random.default_rng(seed)
    m, n = 2 * int(rng.integers(1, 20)) + int(rng.integers(0, 2)), int(rng.integers(1, 6))
    return [rng.random((m, n)), np.full((m, n), rng.random()), np.zeros((m, n)), np.ones((m, n)),
            rng.integers(0, 2, size=(m, n)).astype(float)]


@pytest.mark.parametrize("seed", range(40))
def test_operators_stay_in_unit_box(seed):
    rng = np.random.default_rng(1000 + seed)
    config = GAConfig(population=9, generations=10, blend_alpha=float(rng.uniform(0, 3)), n_elite=1)
    for pop in _populations(seed):
        for alpha in (0.0, 0.5, config.blend_alpha):
            c = blend_crossover(pop, 1.0, alpha, rng)
            assert c.shape == pop.shape and np.all((c >= 0) & (c <= 1))
        for t in (0, 5, 9, 10):
            m = nonuniform_mutation(pop, 1.0, t, 10, 2.0, rng)
            assert m.shape == pop.shape and np.all((m >= 0) & (m <= 1))
        if pop.shape[0] == config.population:
            f = rng.random(pop.shape[0])
            nxt = next_generation(pop, f, config, 3, rng)
            assert np.all((nxt >= 0) & (nxt <= 1))


def test_degenerate_population_is_a_fixed_point_of_crossover():
    pop = np.full((10, 3), 0.4)
    np.testing.assert_array_equal(blend_crossover(pop, 1.0, 0.5, np.random.default_rng(0)), pop)


def test_reflect_unit():
    np.testing.assert_allclose(reflect_unit(np.array([-0.2, 0.0, 0.3, 1.0, 1.3, 2.4, -1.5])),
                               [0.2, 0.0, 0.3, 1.0, 0.7, 0.4, 0.5])


def test_crossover_probability_zero_and_alpha_zero():
    rng = np.random.default_rng(1)
    pop = rng.random((20, 4))
    np.testing.assert_array_equal(blend_crossover(pop, 0.0, 0.5, rng), pop)
    kids = blend_crossover(pop, 1.0, 0.0, rng)  # children between their parents, gene by gene
    lo = np.minimum(pop[0::2], pop[1::2])
    hi = np.maximum(pop[0::2], pop[1::2])
    for k in (kids[0::2], kids[1::2]):
        assert np.all((k >= lo) & (k <= hi))


def test_mutation_rate_and_shrinking_steps():
    rng = np.random.default_rng(2)
    pop = np.full((2000, 10), 0.5)
    m = nonuniform_mutation(pop, 0.05, 0, 100, 2.0, rng)
    assert 0.04 < np.mean(m != pop) < 0.06
    early = np.abs(nonuniform_mutation(pop, 1.0, 0, 100, 2.0, rng) - 0.5).mean()
    late = np.abs(nonuniform_mutation(pop, 1.0, 95, 100, 2.0, rng) - 0.5).mean()
    final = nonuniform_mutation(pop, 1.0, 100, 100, 2.0, rng)
    assert late < 0.1 * early
    np.testing.assert_array_equal(final, pop)  # t = T: no step left


def test_tournament_prefers_fitter():
    rng = np.random.default_rng(3)
    f = np.arange(100, dtype=float)
    winners = tournament_select(f, 10_000, 2, rng)
    assert f[winners].mean() > 60  # E[max of two uniform picks] ≈ 66, random selection ≈ 49.5
    assert np.all(tournament_select(f, 50, 3000, rng) == 99)


def test_sanitize_and_elites():
    f = sanitize_fitness(np.array([np.nan, -1.0, 2.0, np.inf, -np.inf, 0.5]))
    assert f[0] == f[1] == f[4] == 0.0 and f[2] == 2.0 and f[3] == np.finfo(float).max
    np.testing.assert_array_equal(elite_indices(np.array([1.0, 3.0, 3.0, 2.0]), 3), [1, 2, 3])
    assert elite_indices(np.ones(3), 0).size == 0


# ---- configuration -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad, match", [
    ({"population": 1}, "population"),
    ({"population": 10.0}, "integer"),
    ({"generations": 0}, "generations"),
    ({"crossover_prob": 1.5}, "crossover_prob"),
    ({"mutation_prob": -0.1}, "mutation_prob"),
    ({"mutation_prob": float("nan")}, "mutation_prob"),
    ({"tournament_size": 0}, "tournament_size"),
    ({"blend_alpha": -1.0}, "blend_alpha"),
    ({"mutation_shape": 0.0}, "mutation_shape"),
    ({"n_elite": 30}, "n_elite"),
    ({"n_elite": -1}, "n_elite"),
    ({"stall_generations": 0}, "stall_generations"),
    ({"stall_tol": -1.0}, "stall_tol"),
])
def test_config_validation(bad, match):
    with pytest.raises(ConfigError, match=match):
        small(**bad).validate()
    with pytest.raises(ConfigError, match=match):
        RGA(LOWER, UPPER, small(**bad), seed=0)


def test_config_defaults_are_the_papers_and_from_dict():
    c = GAConfig().validate()
    assert (c.population, c.generations, c.crossover_prob, c.mutation_prob) == (1000, 100, 0.7, 0.05)
    assert GAConfig.from_dict({"population": 50}).population == 50
    with pytest.raises(ConfigError, match="unknown GA setting"):
        GAConfig.from_dict({"popsize": 50})


@pytest.mark.parametrize("lower, upper, match", [
    ([0.0, 1.0], [1.0, 1.0], "bound 1"),
    ([0.0, 2.0], [1.0, 1.0], "inverted"),
    ([0.0, -np.inf], [1.0, 1.0], "finite"),
    ([0.0, np.nan], [1.0, 1.0], "finite"),
    ([0.0], [1.0, 2.0], "1-D"),
    ([], [], "non-empty"),
])
def test_bounds_validation(lower, upper, match):
    with pytest.raises(ConfigError, match=match):
        RGA(lower, upper, small(), seed=0)


def test_x0_is_inserted_and_checked():
    x0 = np.array([CENTRE, LOWER])
    ga = RGA(LOWER, UPPER, small(), seed=0, x0=x0)
    np.testing.assert_allclose(ga.ask()[:2], x0, rtol=1e-15, atol=1e-12)
    np.testing.assert_array_equal(ga.ask()[2:], RGA(LOWER, UPPER, small(), seed=0).ask()[2:])
    with pytest.raises(ConfigError, match="inside"):
        RGA(LOWER, UPPER, small(), seed=0, x0=UPPER + 1.0)
    with pytest.raises(ConfigError, match="columns"):
        RGA(LOWER, UPPER, small(), seed=0, x0=np.zeros(3))
    with pytest.raises(ConfigError, match="more than the population"):
        RGA(LOWER, UPPER, small(), seed=0, x0=np.tile(CENTRE, (31, 1)))


# ---- ask / tell ----------------------------------------------------------------------------------------------------


def test_ask_in_bounds_and_idempotent_and_tell_checks_shape():
    ga = RGA(LOWER, UPPER, small(), seed=4)
    X = ga.ask()
    assert X.shape == (30, 5) and np.all((X >= LOWER) & (X <= UPPER))
    np.testing.assert_array_equal(ga.ask(), X)
    assert ga.best_x is None and ga.best_fitness == -math.inf and ga.generation == 0
    with pytest.raises(DataError, match="shape"):
        ga.tell(np.ones(29))
    ga.tell(sphere_fitness(X))
    assert ga.generation == 1 and ga.n_evaluations == 30 and len(ga.history) == 1
    assert np.all((ga.ask() >= LOWER) & (ga.ask() <= UPPER))


def test_elitism_keeps_the_best_and_history_is_monotone():
    ga = RGA(LOWER, UPPER, small(generations=20, n_elite=2), seed=5)
    while not ga.done:
        X = ga.ask()
        f = sphere_fitness(X)
        ga.tell(f)
        if not ga.done:
            order = np.argsort(-f, kind="stable")[:2]
            np.testing.assert_array_equal(ga.ask()[:2], X[order])  # the two fittest, unchanged, in front
    assert all(b >= a for a, b in zip(ga.history, ga.history[1:]))
    assert ga.best_fitness == max(ga.history)


def test_failed_evaluations_count_as_zero():
    ga = RGA(LOWER, UPPER, small(), seed=6)
    f = np.full(30, np.nan)
    f[3] = -5.0
    ga.tell(f)
    assert ga.best_fitness == 0.0 and ga.history == [0.0]
    np.testing.assert_array_equal(ga.last_fitness, np.zeros(30))


def test_tell_after_done_raises():
    ga = RGA(LOWER, UPPER, small(generations=1), seed=0)
    ga.tell(sphere_fitness(ga.ask()))
    assert ga.done
    with pytest.raises(RuntimeError, match="finished"):
        ga.tell(np.ones(30))


# ---- reproducibility ---------------------------------------------------------------------------------------------


def test_same_seed_same_run_different_seed_different_run():
    a = run_ga(sphere_fitness, LOWER, UPPER, small(), seed=42)
    b = run_ga(sphere_fitness, LOWER, UPPER, small(), seed=42)
    c = run_ga(sphere_fitness, LOWER, UPPER, small(), seed=43)
    np.testing.assert_array_equal(a.best_x, b.best_x)
    assert a.history == b.history
    assert not np.array_equal(a.best_x, c.best_x)
    assert a.history != c.history


def _jsonify(state: dict) -> str:
    """state_dict → JSON text (arrays as lists), as a checkpoint writer might store it."""
    def plain(v):
        if isinstance(v, np.ndarray):
            return v.tolist()
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v
    return json.dumps(plain(state))


@pytest.mark.parametrize("k", [0, 1, 7])
def test_state_round_trip_resumes_bit_identically(k):
    config = small(generations=15)
    reference = RGA(LOWER, UPPER, config, seed=9)
    populations = []
    while not reference.done:
        populations.append(reference.ask())
        reference.tell(sphere_fitness(populations[-1]))

    ga = RGA(LOWER, UPPER, config, seed=9)
    for _ in range(k):
        ga.tell(sphere_fitness(ga.ask()))
    text = _jsonify(ga.state_dict())
    del ga
    resumed = RGA.from_state(json.loads(text))
    assert resumed.generation == k
    while not resumed.done:
        X = resumed.ask()
        np.testing.assert_array_equal(X, populations[resumed.generation])
        resumed.tell(sphere_fitness(X))
    np.testing.assert_array_equal(resumed.best_x, reference.best_x)
    assert resumed.history == reference.history
    assert resumed.n_evaluations == reference.n_evaluations


def _npz_json_round_trip(state: dict) -> dict:
    """Arrays through an in-memory npz (no pickle), the rest through strict JSON with -inf → null."""
    arrays, meta = split_state(state)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    buf.seek(0)
    with np.load(buf, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    meta = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in meta.items()}
    return join_state(arrays, json.loads(json.dumps(meta, allow_nan=False)))


@pytest.mark.parametrize("k", [0, 3])
def test_state_round_trip_through_npz_and_json(k):
    config = small(generations=8)
    reference = run_ga(sphere_fitness, LOWER, UPPER, config, seed=21)
    ga = RGA(LOWER, UPPER, config, seed=21)
    for _ in range(k):
        ga.tell(sphere_fitness(ga.ask()))
    resumed = run_ga(sphere_fitness, None, None, ga=RGA.from_state(_npz_json_round_trip(ga.state_dict())))
    np.testing.assert_array_equal(resumed.best_x, reference.best_x)
    assert resumed.history == reference.history


def test_state_dict_keeps_arrays_and_does_not_alias():
    ga = RGA(LOWER, UPPER, small(), seed=1)
    ga.tell(sphere_fitness(ga.ask()))
    state = ga.state_dict()
    assert isinstance(state["population"], np.ndarray) and state["population"].shape == (30, 5)
    state["population"][:] = 0.0
    assert not np.all(ga.ask() == LOWER)
    resumed = RGA.from_state(ga.state_dict())  # arrays kept as arrays also work
    np.testing.assert_array_equal(resumed.ask(), ga.ask())


def test_from_state_rejects_bad_state():
    state = RGA(LOWER, UPPER, small(), seed=1).state_dict()
    with pytest.raises(CheckpointError, match="version"):
        RGA.from_state({**state, "version": 99})
    with pytest.raises(CheckpointError, match="population"):
        RGA.from_state({**state, "population": state["population"][:5]})
    with pytest.raises(CheckpointError, match="unusable"):
        RGA.from_state({k: v for k, v in state.items() if k != "rng_state"})
    with pytest.raises(CheckpointError, match="population must be >= 2"):
        RGA.from_state({**state, "config": {**state["config"], "population": 1}})


def test_resume_through_run_ga_with_callback_checkpoint():
    config = small(generations=10)
    full = run_ga(sphere_fitness, LOWER, UPPER, config, seed=3)
    saved = {}

    def stop_at_4(generation, best, ga):
        if generation == 4:
            saved["state"] = _jsonify(ga.state_dict())
            return True
        return False

    first = run_ga(sphere_fitness, LOWER, UPPER, config, seed=3, callback=stop_at_4)
    assert first.generations_run == 4
    ga = RGA.from_state(json.loads(saved["state"]))
    assert not ga.done
    second = run_ga(sphere_fitness, None, None, ga=ga)
    np.testing.assert_array_equal(second.best_x, full.best_x)
    assert second.history == full.history and second.n_evaluations == full.n_evaluations


# ---- optimisation --------------------------------------------------------------------------------------------------


def test_converges_on_5d_sphere():
    result = run_ga(sphere_fitness, LOWER, UPPER, GAConfig(population=100, generations=80), seed=0)
    assert result.generations_run == 80 and result.n_evaluations == 8000
    rel_err = np.abs(result.best_x - CENTRE) / (UPPER - LOWER)
    assert np.all(rel_err < 2e-4), rel_err
    assert result.history[-1] > 100 * result.history[0]


def test_stall_stops_early():
    flat = lambda X: np.ones(X.shape[0])  # noqa: E731 - nothing ever improves
    result = run_ga(flat, LOWER, UPPER, small(generations=50, stall_generations=5), seed=0)
    assert result.generations_run == 6  # the first generation sets the best, five more stall
    never = run_ga(flat, LOWER, UPPER, small(generations=8), seed=0)
    assert never.generations_run == 8
