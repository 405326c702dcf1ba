"""Statistics of the discovery engine."""
from __future__ import annotations

import numpy as np
from scipy import stats

def f_test(sse0: float, sse1: float, k: int, n: int, p1: int) -> tuple[float, float, float]:
    """F statistic and p-value of adding ``k`` parameters (model with ``p1`` in all, ``n`` residuals) and
    ΔBIC = n·ln(SSE1/SSE0) + k·ln n (negative: the larger model is preferred)."""
    dof2 = max(n - p1, 1)
    if not (np.isfinite(sse1) and sse1 > 0) or not np.isfinite(sse0):
        return 0.0, 1.0, float("inf")
    F = ((sse0 - sse1) / k) / (sse1 / dof2)
    p = float(stats.f.sf(F, k, dof2)) if F > 0 else 1.0
    dbic = float(n * np.log(sse1 / sse0) + k * np.log(n))
    return float(F), p, dbic

