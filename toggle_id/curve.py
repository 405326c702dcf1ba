"""The curve every method shares: the best whole-record RMS error so far against the simulations spent.

Each identification stage has its own objective on its own window (stage 1: free motion, stage 2: the clamped
part, one-stage: everything), so their fitness histories cannot be laid over each other. This curve can: at
every point the current best model — the GA's best individual each generation, the result of each polish —
is simulated once on the WHOLE record(s) (PRECISE tier, x_B only, exactly as the reported ``rmse_m``) and
the best RMS error so far is recorded against the cumulative number of simulations the method has spent
(GA individuals, polish residuals and Jacobian columns; the monitoring simulation itself is not counted) and
the seconds since the start. One-stage, two-stage (across its stages and polishes) and the discovery loop
all give this curve, so MLflow's *Compare* overlays them on one axis (``best_rmse_um`` with ``step`` = the
simulation count; the metric's timestamps give the wall-time axis).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Callable, Sequence

import numpy as np

from .record import Record
from .simulate import PRECISE, SolverSettings, simulate


@dataclass(frozen=True)
class CurvePoint:
    """One point: ``simulations`` spent so far, ``seconds`` since the start, the ``stage`` that produced it, the
    current model's whole-record RMS error ``rmse_m`` (m; inf when it cannot be simulated) and the best so far."""

    simulations: int
    seconds: float
    stage: str
    rmse_m: float
    best_rmse_m: float

    def to_dict(self) -> dict:
        return asdict(self)


class RmseCurve:
    """Best whole-record RMS error against cumulative simulations (see the module's docstring).

    ``on_point`` is called with every new :class:`CurvePoint` (e.g. to log it live to MLflow); ``t0`` is the
    start of the clock (``time.perf_counter()``; default now).
    """

    def __init__(self, records: Record | Sequence[Record], *, settings: SolverSettings = PRECISE,
                 on_point: Callable[[CurvePoint], None] | None = None, t0: float | None = None) -> None:
        self.records = [records] if isinstance(records, Record) else list(records)
        self.settings = settings
        self.on_point = on_point
        self.t0 = time.perf_counter() if t0 is None else float(t0)
        self.points: list[CurvePoint] = []
        self._n = sum(r.n for r in self.records)
        self._last_theta: np.ndarray | None = None
        self._last_rmse = math.inf

    @property
    def best_rmse_m(self) -> float:
        return self.points[-1].best_rmse_m if self.points else math.inf

    @property
    def simulations(self) -> int:
        return self.points[-1].simulations if self.points else 0

    def rmse(self, theta: np.ndarray) -> float:
        """Whole-record x_B RMS error of the extended vector ``theta`` over all records (one simulation each;
        the last vector's value is remembered, so an unchanged best costs nothing)."""
        theta = np.asarray(theta, float)
        if self._last_theta is not None and np.array_equal(theta, self._last_theta):
            return self._last_rmse
        sse = 0.0
        for rec in self.records:
            x = simulate(theta[None, :], rec, self.settings).x_B[0]
            e = rec.x_B - x
            sse += float(np.dot(e, e))
        value = math.sqrt(sse / self._n) if math.isfinite(sse) else math.inf
        self._last_theta, self._last_rmse = theta.copy(), value
        return value

    def add(self, stage: str, simulations: int, *, theta: np.ndarray | None = None, rmse_m: float | None = None,
            notify: bool = True) -> CurvePoint:
        """A point for the model ``theta`` (simulated here) or of known error ``rmse_m``, after ``simulations``."""
        if rmse_m is None:
            if theta is None:
                raise ValueError("give theta or rmse_m")
            rmse_m = self.rmse(theta)
        rmse_m = float(rmse_m) if math.isfinite(float(rmse_m)) else math.inf
        point = CurvePoint(int(simulations), time.perf_counter() - self.t0, stage, rmse_m,
                           min(self.best_rmse_m, rmse_m))
        self.points.append(point)
        if notify and self.on_point is not None and math.isfinite(point.best_rmse_m):
            self.on_point(point)
        return point

    def to_list(self) -> list[dict]:
        return [p.to_dict() for p in self.points]
