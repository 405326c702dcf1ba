"""Fitness problems: which parameters are free, which samples count, and fitness = 1/ΣE² (docs/model.md §7).

A :class:`FitProblem` is the picklable *problem* of :mod:`toggle_id.evaluators`: ``setup()`` compiles the kernel
in the process that evaluates, ``evaluate(X)`` returns the fitness of each row of X (free parameters only,
physical units). Failed simulations get fitness 0 (the worst) and never stop a run.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .effects import ALL_INDEX, ALL_NAMES
from .errors import ConfigError
from .record import Record
from .simulate import FAST, STATUS_OK, SimResult, SolverSettings, extend, simulate


def free_indices(names: Sequence[str]) -> np.ndarray:
    """Positions of ``names`` in the extended parameter vector (ConfigError for an unknown name)."""
    for n in names:
        if n not in ALL_INDEX:
            raise ConfigError(f"unknown parameter {n!r}; known: {', '.join(ALL_NAMES)}")
    return np.array([ALL_INDEX[n] for n in names], dtype=np.int64)


@dataclass
class FitProblem:
    """Fit ``free`` parameters of the extended vector ``base`` to ``record`` on samples ``window = (k0, k1)``.

    ``start``/``prefix_x``/``prefix_i`` let stage 2 restart every individual from a shared state (the model's
    first contact) while the samples before it come from the shared trajectory. ``i_q_weight`` (m/A) adds the
    current as a second output when the record has it (0: x_B only, as in the paper).
    """

    record: Record
    free: tuple[str, ...]
    base: np.ndarray
    window: tuple[int, int]
    settings: SolverSettings = FAST
    start: tuple | None = None
    prefix_x: np.ndarray | None = None
    prefix_i: np.ndarray | None = None
    i_q_weight: float = 0.0
    _idx: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.free = tuple(self.free)
        self._idx = free_indices(self.free)
        self.base = extend(self.base)[0]
        k0, k1 = self.window
        if not 0 <= k0 < k1 <= self.record.n:
            raise ConfigError(f"sample window {self.window} is empty or outside the record (n = {self.record.n})")
        if self.record.x_B is None:
            raise ConfigError("the record has no measured x_B to fit")
        if self.i_q_weight and self.record.i_q is None:
            raise ConfigError("i_q is configured as a second output but the record has no i_q column")

    @property
    def n_residuals(self) -> int:
        k0, k1 = self.window
        return (k1 - k0) * (2 if self.i_q_weight else 1)

    def thetas(self, X: np.ndarray) -> np.ndarray:
        """(P, N_THETA) full vectors with the free columns set from X (P, n_free)."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        th = np.repeat(self.base[None, :], X.shape[0], axis=0)
        th[:, self._idx] = X
        return th

    def x0(self) -> np.ndarray:
        """The free parameters' values in ``base``."""
        return self.base[self._idx].copy()

    def simulate(self, X: np.ndarray, settings: SolverSettings | None = None, parallel: bool = False) -> SimResult:
        """Simulate rows of X; ``parallel`` uses the kernel's threads (not inside Ray actors)."""
        res = simulate(self.thetas(X), self.record, settings or self.settings, n_samples=self.window[1],
                       start=self.start, parallel=parallel)
        if self.start is not None and self.prefix_x is not None:
            t0 = self.start[0]
            before = self.record.t < t0 - 1e-12
            res.x_B[:, before] = self.prefix_x[before]
            res.i_q[:, before] = self.prefix_i[before]
            res.x_B[res.status != STATUS_OK] = np.nan
            res.i_q[res.status != STATUS_OK] = np.nan
        return res

    def residuals(self, X: np.ndarray, settings: SolverSettings | None = None, parallel: bool = False
                  ) -> np.ndarray:
        """(P, m) measured − model on the window (x_B in m, then weighted i_q); NaN rows for failures."""
        res = self.simulate(X, settings, parallel)
        k0, k1 = self.window
        r = self.record.x_B[k0:k1] - res.x_B[:, k0:k1]
        if self.i_q_weight:
            r = np.hstack([r, self.i_q_weight * (self.record.i_q[k0:k1] - res.i_q[:, k0:k1])])
        return r

    def sse(self, X: np.ndarray, settings: SolverSettings | None = None) -> np.ndarray:
        """(P,) ΣE² (m²); inf for failed simulations."""
        r = self.residuals(X, settings)
        s = np.einsum("ij,ij->i", r, r)
        s[~np.isfinite(s)] = np.inf
        return s

    def evaluate(self, X: np.ndarray) -> np.ndarray:
        """Fitness 1/ΣE² per row; 0 for failed simulations."""
        s = self.sse(X)
        with np.errstate(divide="ignore"):
            f = np.where(np.isfinite(s) & (s > 0), 1.0 / s, 0.0)
        f[s == 0] = np.finfo(float).max
        return f

    def setup(self) -> None:
        """Compile and warm up the kernel in this process (one short simulation)."""
        simulate(self.base[None, :], self.record, self.settings, n_samples=min(self.record.n, 3))


@dataclass
class JointProblem:
    """Several records fitted with one parameter vector (multi-experiment): residuals stack the records'
    residual vectors, SSE is the sum over records, fitness 1/ΣE² of that sum.

    Every member frees the same parameters and shares the same base vector; each keeps its own record, sample
    window and (stage 2) restart state. It is a *problem* of :mod:`toggle_id.evaluators` like a
    :class:`FitProblem` and goes wherever one goes in the pipeline (GA, polish, sensitivities).
    """

    problems: list[FitProblem]

    def __post_init__(self) -> None:
        self.problems = list(self.problems)
        if not self.problems:
            raise ConfigError("a joint fit needs at least one record")
        frees = {p.free for p in self.problems}
        if len(frees) != 1:
            raise ConfigError("all records of a joint fit must free the same parameters")
        base = self.problems[0].base
        if any(not np.array_equal(p.base, base) for p in self.problems[1:]):
            raise ConfigError("all records of a joint fit must share one parameter vector")
        self.free = self.problems[0].free

    @property
    def base(self) -> np.ndarray:
        return self.problems[0].base

    @property
    def records(self) -> list[Record]:
        return [p.record for p in self.problems]

    @property
    def windows(self) -> list[tuple[int, int]]:
        return [tuple(p.window) for p in self.problems]

    @property
    def n_residuals(self) -> int:
        return sum(p.n_residuals for p in self.problems)

    def thetas(self, X: np.ndarray) -> np.ndarray:
        return self.problems[0].thetas(X)

    def x0(self) -> np.ndarray:
        return self.problems[0].x0()

    def residuals(self, X: np.ndarray, settings: SolverSettings | None = None, parallel: bool = False
                  ) -> np.ndarray:
        """(P, Σm) the records' residual vectors side by side, in the order of ``problems``."""
        return np.hstack([p.residuals(X, settings, parallel) for p in self.problems])

    def sse(self, X: np.ndarray, settings: SolverSettings | None = None) -> np.ndarray:
        """(P,) ΣE² over all records (m²); inf where any record's simulation failed."""
        return np.sum([p.sse(X, settings) for p in self.problems], axis=0)

    def evaluate(self, X: np.ndarray) -> np.ndarray:
        """Fitness 1/ΣE² of the summed SSE per row; 0 for failed simulations."""
        s = self.sse(X)
        with np.errstate(divide="ignore"):
            f = np.where(np.isfinite(s) & (s > 0), 1.0 / s, 0.0)
        f[s == 0] = np.finfo(float).max
        return f

    def setup(self) -> None:
        for p in self.problems:
            p.setup()


def joint(problems: Sequence[FitProblem]) -> FitProblem | JointProblem:
    """One record's problem as it is; several as a :class:`JointProblem`."""
    problems = list(problems)
    return problems[0] if len(problems) == 1 else JointProblem(problems)
