"""Operators of the real-coded GA (:mod:`toggle_id.ga`): pure functions on populations scaled to the unit box
``[0, 1]^n``. Each receives its :class:`numpy.random.Generator`; nothing draws random numbers behind the caller's
back.

Operators (the paper, §4, names only "reproduction, crossover and mutation" on real-valued genes; these are
the standard choices for an RGA and each has a default that matches the paper's probabilities):

* **Selection** — tournament of ``tournament_size`` (default 2) individuals drawn with replacement; the
  fittest wins (ties go to the first drawn). Tournament needs no fitness scaling and tolerates zeros.
* **Crossover** — blend crossover BLX-α (Eshelman & Schaffer 1993, default α = 0.5): the selected parents are
  paired in order; with probability ``crossover_prob`` a pair produces two children drawn per gene uniformly
  from ``[min - α d, max + α d]`` (``d = |p1 - p2|``), otherwise the parents pass unchanged. Children that leave
  the unit box are reflected back into it (reflection keeps the density near a bound instead of piling
  individuals onto it, as clipping would).
* **Mutation** — Michalewicz's non-uniform mutation, applied to each gene with probability ``mutation_prob``:
  ``u ← u + Δ(t, 1 - u)`` or ``u ← u - Δ(t, u)`` (each with probability ½), with
  ``Δ(t, y) = y (1 - r^((1 - t/T)^b))``, ``r ~ U(0, 1)``, ``t`` the generation, ``T = generations`` and
  ``b = mutation_shape`` (default 2). Steps are large early and shrink as the run ends; they never leave the box.
* **Elitism** — the ``n_elite`` (default 2) fittest individuals are copied unchanged into the next generation.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # for the annotation only: ga imports this module
    from .ga import GAConfig

_LARGEST = float(np.finfo(np.float64).max)


def sanitize_fitness(fitness: np.ndarray) -> np.ndarray:
    """Fitness as float64 with NaN, negative and -inf replaced by 0 and +inf by the largest float."""
    f = np.array(fitness, dtype=float, copy=True)
    f[np.isnan(f) | (f < 0.0)] = 0.0
    f[np.isposinf(f)] = _LARGEST
    return f


def reflect_unit(u: np.ndarray) -> np.ndarray:
    """Fold values back into [0, 1] by mirror reflection at the bounds (…, -0.2 → 0.2, 1.3 → 0.7, 2.4 → 0.4)."""
    v = np.mod(np.abs(u), 2.0)
    return np.where(v > 1.0, 2.0 - v, v)


def tournament_select(fitness: np.ndarray, n_select: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n_select`` winners of tournaments of ``size`` individuals drawn with replacement."""
    entrants = rng.integers(0, fitness.shape[0], size=(n_select, size))
    winner = np.argmax(fitness[entrants], axis=1)  # argmax: the first drawn wins ties
    return entrants[np.arange(n_select), winner]


def blend_crossover(parents: np.ndarray, prob: float, alpha: float, rng: np.random.Generator) -> np.ndarray:
    """BLX-α on consecutive pairs of ``parents`` (m, n) in the unit box; each pair crossed with ``prob``.

    Returns children (m, n) reflected into [0, 1]; an odd last parent passes unchanged.
    """
    children = parents.copy()
    n_pairs = parents.shape[0] // 2
    if n_pairs == 0:
        return children
    p1 = parents[0:2 * n_pairs:2]
    p2 = parents[1:2 * n_pairs:2]
    crossed = rng.random(n_pairs) < prob
    low = np.minimum(p1, p2)
    span = np.abs(p1 - p2)
    low = low - alpha * span
    width = (1.0 + 2.0 * alpha) * span
    draws = rng.random((2, n_pairs, parents.shape[1]))
    c1 = reflect_unit(low + draws[0] * width)
    c2 = reflect_unit(low + draws[1] * width)
    children[0:2 * n_pairs:2][crossed] = c1[crossed]
    children[1:2 * n_pairs:2][crossed] = c2[crossed]
    return children


def nonuniform_mutation(pop: np.ndarray, prob: float, generation: int, max_generations: int, shape: float,
                        rng: np.random.Generator) -> np.ndarray:
    """Michalewicz's non-uniform mutation of each gene of ``pop`` (m, n) in the unit box with probability ``prob``.

    The step ``Δ(t, y) = y (1 - r^((1 - t/T)^b))`` shrinks to 0 as ``generation`` t reaches ``max_generations`` T;
    mutated genes stay in [0, 1].
    """
    mutate = rng.random(pop.shape) < prob
    upward = rng.random(pop.shape) < 0.5
    r = rng.random(pop.shape)
    progress = min(max(generation / max_generations, 0.0), 1.0)
    factor = 1.0 - r ** ((1.0 - progress) ** shape)
    up = pop + (1.0 - pop) * factor
    down = pop - pop * factor
    out = np.where(mutate, np.where(upward, up, down), pop)
    return np.clip(out, 0.0, 1.0)  # rounding guard only: up/down are in [0, 1] mathematically


def elite_indices(fitness: np.ndarray, n_elite: int) -> np.ndarray:
    """Indices of the ``n_elite`` fittest individuals, fittest first; ties keep population order."""
    if n_elite == 0:
        return np.zeros(0, dtype=np.intp)
    return np.argsort(-fitness, kind="stable")[:n_elite]


def next_generation(pop: np.ndarray, fitness: np.ndarray, config: GAConfig, generation: int,
                    rng: np.random.Generator) -> np.ndarray:
    """The next unit-box population from the evaluated ``pop`` (P, n) and its sanitized ``fitness`` (P,).

    Elites first (unchanged), then ``P - n_elite`` children: tournament → BLX-α → non-uniform mutation.
    ``generation`` is the number of populations already evaluated (the mutation's t).
    """
    n_children = config.population - config.n_elite
    elites = pop[elite_indices(fitness, config.n_elite)]
    parents = pop[tournament_select(fitness, n_children, config.tournament_size, rng)]
    children = blend_crossover(parents, config.crossover_prob, config.blend_alpha, rng)
    children = nonuniform_mutation(children, config.mutation_prob, generation, config.generations,
                                   config.mutation_shape, rng)
    return np.concatenate([elites, children], axis=0)
