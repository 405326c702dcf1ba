"""What an identification returns: one :class:`StageResult` per stage (GA stage, multistart stage or joint
polish) and the :class:`IdentificationResult` of the whole run, with the dictionaries ``result.json`` is made of.
Every method (:mod:`toggle_id.identify`, :mod:`toggle_id.fast`) returns these.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from . import params as P
from .curve import CurvePoint
from .effects import ALL_INDEX, EXTRA_NAMES


@dataclass
class StageResult:
    """What one GA stage found: free names and values, fitness 1/ΣE², history, timing, diagnostics."""

    name: str
    free: tuple[str, ...]
    x: np.ndarray
    theta: np.ndarray
    window: tuple[int, int]
    fitness_ga: float
    fitness: float
    sse: float
    history: list[float]
    generations: int
    converged_generation: int
    n_evaluations: int
    seconds_ga: float
    seconds_polish: float = 0.0
    polish: dict | None = None
    identifiability: dict | None = None
    windows: tuple[tuple[int, int], ...] | None = None  # joint fits: every record's window (``window``: the first's)
    n_simulations: int = 0  # simulations the stage spent: GA individuals, polish residuals and Jacobian columns

    @property
    def n_samples(self) -> int:
        return sum(k1 - k0 for k0, k1 in (self.windows or (self.window,)))

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(self.sse / max(1, self.n_samples)))

    def to_dict(self) -> dict:
        windows = {} if self.windows is None else {"windows": [list(w) for w in self.windows]}
        return {"name": self.name, "free": list(self.free), "params": dict(zip(self.free, map(float, self.x))),
                "window": list(self.window), **windows, "fitness_ga": self.fitness_ga, "fitness": self.fitness,
                "sse_m2": self.sse, "rmse_m": self.rmse_m, "generations": self.generations,
                "converged_generation": self.converged_generation, "n_evaluations": self.n_evaluations,
                "seconds_ga": self.seconds_ga, "seconds_polish": self.seconds_polish,
                "seconds": self.seconds_ga + self.seconds_polish, "fitness_history": list(self.history),
                "n_simulations": self.n_simulations, "polish": self.polish, "identifiability": self.identifiability}


@dataclass
class IdentificationResult:
    """The identified extended parameter vector, per-stage results and the whole-record fit."""

    method: str
    theta: np.ndarray
    stages: list[StageResult]
    fitness: float
    sse: float
    n_samples: int
    seconds: float
    clamp_index: int
    extra: dict = field(default_factory=dict)
    curve: list[CurvePoint] = field(default_factory=list)  # best whole-record RMS vs simulations (toggle_id.curve)

    @property
    def params(self) -> dict[str, float]:
        return {n: float(self.theta[i]) for i, n in enumerate(P.PARAM_NAMES)}

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(self.sse / self.n_samples))

    @property
    def n_simulations(self) -> int:
        """Simulations the whole identification spent (its stages' sum)."""
        return sum(s.n_simulations for s in self.stages)

    def to_dict(self) -> dict:
        extra = {n: float(self.theta[ALL_INDEX[n]]) for n in EXTRA_NAMES}
        return {"method": self.method, "params": self.params, "effect_params": extra,
                "fitness": self.fitness, "sse_m2": self.sse, "rmse_m": self.rmse_m, "rmse_um": 1e6 * self.rmse_m,
                "n_samples": self.n_samples, "n_simulations": self.n_simulations,
                "curve": [p.to_dict() for p in self.curve],
                "clamp_index": self.clamp_index, "seconds_total": self.seconds,
                "seconds_per_stage": {s.name: s.seconds_ga + s.seconds_polish for s in self.stages},
                "stages": [s.to_dict() for s in self.stages], **self.extra}


def converged_generation(history: Sequence[float], rel: float = 0.01) -> int:
    """First generation (1-based) whose best fitness is within ``rel`` of the final best."""
    h = np.asarray(history, dtype=float)
    if h.size == 0:
        return 0
    return int(np.argmax(h >= (1.0 - rel) * h[-1])) + 1
