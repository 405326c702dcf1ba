"""Real-coded genetic algorithm (RGA) with an ask / tell interface.

The algorithm knows nothing of the plant, of Ray or of how fitness is computed: :meth:`RGA.ask` hands out a
population in physical units, the caller evaluates it however it likes and hands the fitness back with
:meth:`RGA.tell`, which breeds the next generation. :func:`run_ga` is the thin loop around it.

Conventions
-----------
* Fitness is **maximised**. The project uses ``fitness = 1 / SSE``; a failed simulation has fitness 0.
  NaN, negative and ``-inf`` fitness are treated as 0; ``+inf`` (a perfect fit) as the largest float.
* Internally the population lives scaled to the unit box ``[0, 1]^n`` (``x = lower + u (upper - lower)``),
  so every operator is bound-agnostic. Each operator is a pure function of arrays that receives its
  :class:`numpy.random.Generator`; nothing draws random numbers behind the caller's back.
* ``generations`` counts evaluated populations, the initial one included: a run with the paper's settings
  evaluates ``population × generations = 1000 × 100`` individuals.

Operators (selection, crossover, mutation, elitism): :mod:`toggle_id.ga_operators`.

Reproducibility: the same ``seed`` gives the same run, and :meth:`RGA.state_dict` / :meth:`RGA.from_state`
capture everything (population, best, history, the generator's state) so that a run interrupted after k
generations and resumed is bit-identical to an uninterrupted one.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np

from toggle_id.errors import CheckpointError, ConfigError, DataError
from toggle_id.ga_operators import next_generation, sanitize_fitness

#: Version of the layout of :meth:`RGA.state_dict`; bumped when it changes.
STATE_VERSION = 1


# --------------------------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------------------------


@dataclass
class GAConfig:
    """Settings of the RGA; the defaults are the paper's (§5: population 1000, 100 generations, p_c 0.7, p_m 0.05).

    Attributes:
        population: individuals per generation (≥ 2).
        generations: evaluated populations per run, the initial one included (≥ 1).
        crossover_prob: probability that a parent pair is crossed, in [0, 1].
        mutation_prob: probability that one gene is mutated, in [0, 1].
        tournament_size: individuals per selection tournament (≥ 1; 1 is random selection).
        blend_alpha: α of BLX-α (≥ 0; 0 draws children between the parents).
        mutation_shape: b of the non-uniform mutation (> 0; larger shrinks the steps faster).
        n_elite: fittest individuals copied unchanged each generation (0 ≤ n_elite < population).
        stall_generations: stop after this many generations without improvement (None: never stop early).
        stall_tol: relative improvement of the best fitness that counts as improvement (≥ 0).
    """

    population: int = 1000
    generations: int = 100
    crossover_prob: float = 0.7
    mutation_prob: float = 0.05
    tournament_size: int = 2
    blend_alpha: float = 0.5
    mutation_shape: float = 2.0
    n_elite: int = 2
    stall_generations: Optional[int] = None
    stall_tol: float = 1e-9

    def validate(self) -> "GAConfig":
        """Raise :class:`ConfigError` naming the first unusable setting; return ``self`` when all are usable."""
        for name in ("population", "generations", "tournament_size", "n_elite"):
            _check_int(name, getattr(self, name))
        if self.population < 2:
            raise ConfigError(f"GA population must be >= 2, got {self.population}")
        if self.generations < 1:
            raise ConfigError(f"GA generations must be >= 1, got {self.generations}")
        for name in ("crossover_prob", "mutation_prob"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0.0 <= value <= 1.0):
                raise ConfigError(f"GA {name} must be a probability in [0, 1], got {value!r}")
        if self.tournament_size < 1:
            raise ConfigError(f"GA tournament_size must be >= 1, got {self.tournament_size}")
        if not (isinstance(self.blend_alpha, (int, float)) and math.isfinite(self.blend_alpha)
                and self.blend_alpha >= 0.0):
            raise ConfigError(f"GA blend_alpha must be finite and >= 0, got {self.blend_alpha!r}")
        if not (isinstance(self.mutation_shape, (int, float)) and math.isfinite(self.mutation_shape)
                and self.mutation_shape > 0.0):
            raise ConfigError(f"GA mutation_shape must be finite and > 0, got {self.mutation_shape!r}")
        if not 0 <= self.n_elite < self.population:
            raise ConfigError(f"GA n_elite must be in [0, population), got {self.n_elite} "
                              f"for population {self.population}")
        if self.stall_generations is not None:
            _check_int("stall_generations", self.stall_generations)
            if self.stall_generations < 1:
                raise ConfigError(f"GA stall_generations must be >= 1 or None, got {self.stall_generations}")
        if not (isinstance(self.stall_tol, (int, float)) and math.isfinite(self.stall_tol)
                and self.stall_tol >= 0.0):
            raise ConfigError(f"GA stall_tol must be finite and >= 0, got {self.stall_tol!r}")
        return self

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "GAConfig":
        """Build and validate a config from a mapping (e.g. a Hydra node); unknown keys raise ConfigError."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown GA setting(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
        return cls(**dict(values)).validate()


def _check_int(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"GA {name} must be an integer, got {value!r}")


def _check_bounds(lower: Sequence[float], upper: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Bounds as float arrays; ConfigError unless 1-D, same length, finite and lower < upper everywhere."""
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    if lo.ndim != 1 or hi.ndim != 1 or lo.shape != hi.shape or lo.size == 0:
        raise ConfigError(f"GA bounds must be two non-empty 1-D arrays of one length, got shapes "
                          f"{lo.shape} and {hi.shape}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ConfigError("GA bounds must be finite")
    bad = np.flatnonzero(~(lo < hi))
    if bad.size:
        i = int(bad[0])
        raise ConfigError(f"GA bound {i} is empty or inverted: lower {lo[i]!r} >= upper {hi[i]!r}")
    return lo, hi


# --------------------------------------------------------------------------------------------------------------
# The algorithm
# --------------------------------------------------------------------------------------------------------------


class RGA:
    """Ask / tell real-coded GA over the box ``[lower, upper]`` (physical units), maximising fitness.

    Args:
        lower, upper: bounds (n,), finite, ``lower < upper``.
        config: settings (validated here); default :class:`GAConfig()` (the paper's).
        seed: seed of the generator (int); ``None`` draws fresh entropy (not reproducible).
        x0: optional initial individuals (k, n) or (n,) in physical units inside the bounds, k ≤ population;
            they replace the first k rows of the uniform initial population.

    One generation is ``X = ga.ask()`` → evaluate → ``ga.tell(fitness)``; ``ask`` is idempotent until ``tell``.
    """

    def __init__(self, lower: Sequence[float], upper: Sequence[float], config: Optional[GAConfig] = None,
                 seed: Optional[int] = None, x0: Optional[np.ndarray] = None) -> None:
        self._lower, self._upper = _check_bounds(lower, upper)
        self._config = (config if config is not None else GAConfig()).validate()
        self._rng = np.random.default_rng(seed)
        n = self._lower.size
        pop = self._rng.random((self._config.population, n))
        if x0 is not None:
            rows = np.atleast_2d(np.asarray(x0, dtype=float))
            if rows.ndim != 2 or rows.shape[1] != n:
                raise ConfigError(f"GA x0 must have {n} columns, got shape {np.shape(x0)}")
            if rows.shape[0] > self._config.population:
                raise ConfigError(f"GA x0 has {rows.shape[0]} rows, more than the population "
                                  f"{self._config.population}")
            if not np.all(np.isfinite(rows)) or np.any(rows < self._lower) or np.any(rows > self._upper):
                raise ConfigError("GA x0 rows must be finite and inside [lower, upper]")
            pop[: rows.shape[0]] = self._to_unit(rows)
        self._pop = pop
        self._fitness: Optional[np.ndarray] = None  # of the last evaluated population
        self._generation = 0
        self._n_evaluations = 0
        self._best_u: Optional[np.ndarray] = None
        self._best_fitness = -math.inf
        self._history: list[float] = []
        self._stall = 0
        self._stopped = False

    # ---- unit box <-> physical units ------------------------------------------------------------------------

    def _to_unit(self, x: np.ndarray) -> np.ndarray:
        return np.clip((x - self._lower) / (self._upper - self._lower), 0.0, 1.0)

    def _to_physical(self, u: np.ndarray) -> np.ndarray:
        return np.clip(self._lower + u * (self._upper - self._lower), self._lower, self._upper)

    # ---- ask / tell -----------------------------------------------------------------------------------------

    def ask(self) -> np.ndarray:
        """The population to evaluate, (population, n) in physical units (a fresh copy each call)."""
        return self._to_physical(self._pop)

    def tell(self, fitness: np.ndarray) -> None:
        """Record the fitness (population,) of the population from :meth:`ask` and breed the next one.

        NaN and negative values count as 0 (failed evaluations). Raises :class:`DataError` on a wrong shape
        and ``RuntimeError`` when the run is already done.
        """
        if self.done:
            raise RuntimeError("tell() called on a finished GA run")
        f = np.asarray(fitness)
        if f.shape != (self._config.population,):
            raise DataError(f"GA fitness must have shape ({self._config.population},), got {f.shape}")
        f = sanitize_fitness(f)
        self._fitness = f
        self._n_evaluations += f.size
        i = int(np.argmax(f))
        previous = self._best_fitness
        if self._best_u is None or f[i] > self._best_fitness:
            self._best_u = self._pop[i].copy()
            self._best_fitness = float(f[i])
        improved = not math.isfinite(previous) or (
            self._best_fitness > previous + self._config.stall_tol * abs(previous))
        if improved:
            self._stall = 0
        else:
            self._stall += 1
        self._history.append(self._best_fitness)
        self._generation += 1
        if not self.done:
            self._pop = next_generation(self._pop, f, self._config, self._generation, self._rng)

    def stop(self) -> None:
        """Mark the run as done (e.g. a callback asked to stop); not saved: a resumed run goes on."""
        self._stopped = True

    # ---- read-only views ------------------------------------------------------------------------------------

    @property
    def config(self) -> GAConfig:
        """The (validated) settings."""
        return self._config

    @property
    def lower(self) -> np.ndarray:
        """Lower bounds (n,), physical units."""
        return self._lower.copy()

    @property
    def upper(self) -> np.ndarray:
        """Upper bounds (n,), physical units."""
        return self._upper.copy()

    @property
    def generation(self) -> int:
        """Number of populations evaluated so far (0 before the first :meth:`tell`)."""
        return self._generation

    @property
    def n_evaluations(self) -> int:
        """Number of individuals evaluated so far."""
        return self._n_evaluations

    @property
    def best_x(self) -> Optional[np.ndarray]:
        """The fittest individual seen so far (n,), physical units; None before the first :meth:`tell`."""
        return None if self._best_u is None else self._to_physical(self._best_u)

    @property
    def best_fitness(self) -> float:
        """The best fitness seen so far (-inf before the first :meth:`tell`)."""
        return self._best_fitness

    @property
    def history(self) -> list[float]:
        """Best fitness so far after each evaluated generation."""
        return list(self._history)

    @property
    def last_fitness(self) -> Optional[np.ndarray]:
        """Sanitized fitness of the last evaluated population (None before the first :meth:`tell`)."""
        return None if self._fitness is None else self._fitness.copy()

    @property
    def stalled(self) -> bool:
        """True when early stopping is on and the best fitness has stalled for ``stall_generations``."""
        n = self._config.stall_generations
        return n is not None and self._stall >= n

    @property
    def done(self) -> bool:
        """True after ``generations`` evaluated populations, a stall, or :meth:`stop`."""
        return self._stopped or self._generation >= self._config.generations or self.stalled

    # ---- checkpointing --------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume exactly: plain Python values (JSON-able) plus numpy arrays.

        Arrays: ``population`` (unit box), ``fitness`` (or None), ``best_u`` (or None), ``lower``, ``upper``.
        The generator state ``rng_state`` is numpy's ``bit_generator.state`` dict (Python ints, JSON-able).
        """
        return {
            "version": STATE_VERSION,
            "config": asdict(self._config),
            "lower": self._lower.copy(),
            "upper": self._upper.copy(),
            "population": self._pop.copy(),
            "fitness": None if self._fitness is None else self._fitness.copy(),
            "generation": self._generation,
            "n_evaluations": self._n_evaluations,
            "best_u": None if self._best_u is None else self._best_u.copy(),
            "best_fitness": self._best_fitness,
            "history": list(self._history),
            "stall": self._stall,
            "rng_state": _copy_plain(self._rng.bit_generator.state),
        }

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> "RGA":
        """Rebuild a GA from :meth:`state_dict` output (arrays may have become lists); CheckpointError if unusable."""
        try:
            if state["version"] != STATE_VERSION:
                raise CheckpointError(f"GA state version {state['version']!r} is not {STATE_VERSION}")
            config = GAConfig.from_dict(state["config"])
            ga = cls.__new__(cls)
            ga._lower, ga._upper = _check_bounds(state["lower"], state["upper"])
            ga._config = config
            n = ga._lower.size
            ga._pop = np.array(state["population"], dtype=float).reshape(-1, n)
            if ga._pop.shape != (config.population, n) or not np.all((ga._pop >= 0) & (ga._pop <= 1)):
                raise CheckpointError(f"GA state population has shape {ga._pop.shape} or values outside "
                                      f"[0, 1]; expected ({config.population}, {n})")
            ga._fitness = None if state["fitness"] is None else np.array(state["fitness"], dtype=float)
            ga._generation = int(state["generation"])
            ga._n_evaluations = int(state["n_evaluations"])
            ga._best_u = None if state["best_u"] is None else np.array(state["best_u"], dtype=float)
            best = state["best_fitness"]  # -inf before the first tell; JSON writers may have turned it into None
            ga._best_fitness = -math.inf if best is None else float(best)
            ga._history = [float(v) for v in state["history"]]
            ga._stall = int(state["stall"])
            ga._stopped = False  # stop() is the driver's decision, not part of the state
            if len(ga._history) != ga._generation:
                raise CheckpointError(f"GA state history has {len(ga._history)} entries for generation "
                                      f"{ga._generation}")
            rng_state = dict(state["rng_state"])
            bit_generator = getattr(np.random, str(rng_state["bit_generator"]))()
            bit_generator.state = rng_state
            ga._rng = np.random.Generator(bit_generator)
        except CheckpointError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise CheckpointError(f"unusable GA state: {type(err).__name__}: {err}") from err
        return ga


def split_state(state: Mapping[str, Any]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Split :meth:`RGA.state_dict` output into (numeric arrays for an npz, JSON-able rest)."""
    arrays = {k: v for k, v in state.items() if isinstance(v, np.ndarray)}
    meta = {k: v for k, v in state.items() if not isinstance(v, np.ndarray)}
    return arrays, meta


def join_state(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> dict[str, Any]:
    """Inverse of :func:`split_state`: one state mapping for :meth:`RGA.from_state`."""
    return {**dict(meta), **dict(arrays)}


def _copy_plain(value: Any) -> Any:
    """Deep copy of nested dicts / lists of plain values (the generator state)."""
    if isinstance(value, dict):
        return {k: _copy_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_copy_plain(v) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    return value


# --------------------------------------------------------------------------------------------------------------
# Thin driver
# --------------------------------------------------------------------------------------------------------------


@dataclass
class GAResult:
    """Outcome of :func:`run_ga`: best individual (physical units), its fitness, the per-generation best."""

    best_x: np.ndarray
    best_fitness: float
    history: list[float]
    generations_run: int
    n_evaluations: int


def run_ga(evaluate: Callable[[np.ndarray], np.ndarray], lower: Sequence[float], upper: Sequence[float],
           config: Optional[GAConfig] = None, seed: Optional[int] = None,
           callback: Optional[Callable[[int, float, RGA], Optional[bool]]] = None,
           x0: Optional[np.ndarray] = None, ga: Optional[RGA] = None) -> GAResult:
    """Maximise ``evaluate`` ((P, n) physical units → (P,) fitness) over ``[lower, upper]``.

    ``callback(generation, best_fitness, ga)`` runs after each generation; returning True stops the run (it may
    also save ``ga.state_dict()``). Pass ``ga`` (e.g. from :meth:`RGA.from_state`) to resume a run; then
    ``lower``, ``upper``, ``config``, ``seed`` and ``x0`` are ignored.
    """
    if ga is None:
        ga = RGA(lower, upper, config, seed=seed, x0=x0)
    while not ga.done:
        ga.tell(evaluate(ga.ask()))
        if callback is not None and callback(ga.generation, ga.best_fitness, ga):
            ga.stop()
    if ga.best_x is None:
        raise RuntimeError("GA finished without evaluating any generation")
    return GAResult(best_x=ga.best_x, best_fitness=ga.best_fitness, history=ga.history,
                    generations_run=ga.generation, n_evaluations=ga.n_evaluations)
