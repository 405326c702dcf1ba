"""Local refinement ("polish") of a fitted parameter vector by bounded least squares.

Model-agnostic: the model enters only through ``residual_fn(x) -> (m,)`` (and optionally an analytic
``jac_fn(x) -> (m, n)``), both in physical units. The optimiser is scipy's ``least_squares`` (method
``'trf'``), run in a *scaled* parameterisation so that parameters spanning many decades (a rotor inertia of
1e-5 next to a stiffness of 1e7) are equally easy to move:

- positive parameters (``log_mask`` True) live in log space, ``u = log(x)``: a unit step is a factor e, and
  a positive parameter can never cross zero;
- the others live in affine space, ``u = (x - lower) / (upper - lower)`` when both bounds are finite, else
  ``u = x / s`` with ``s = |x0|`` (or 1 when ``x0 = 0``).

Bounds map with the parameters. A log parameter whose lower bound is 0 (every entry of the paper's Table 1)
gets the floor ``x0 · log_floor_rel`` (default 1e-6, i.e. six decades below the start): a local polish that
wants to move a positive parameter further than that is not polishing, and log(0) does not exist.

Failures are data: at a trial point where ``residual_fn`` returns NaN/inf or raises one of
:data:`TRIAL_ERRORS`, the residual is replaced by a *penalty* (a constant vector far larger than the starting
residual), which the trust-region method simply rejects (a vector of the wrong length is a bug and raises).
The polished point is accepted only if it lowers the sum of squares (:attr:`PolishResult.improved`);
otherwise the start is returned unchanged (as scipy's differential evolution does with its own ``polish``).

The trust-region steps take the SVD of a tall, thin Jacobian (thousands of samples × a dozen parameters). A
multi-threaded BLAS is far slower at that than one thread, and more so beside the simulator's own threads
(``python -m jobs.bench --polish``), so :func:`polish` runs scipy with one BLAS thread (``blas_threads``).
"""
from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import least_squares
from threadpoolctl import ThreadpoolController

from .errors import ConfigError

ResidualFn = Callable[[np.ndarray], np.ndarray]
JacobianFn = Callable[[np.ndarray], np.ndarray]

#: Exceptions raised by ``residual_fn``/``jac_fn`` at a trial point that are treated as a failed evaluation
#: (penalty residual / zero Jacobian) rather than propagated. Not caught at the start point.
TRIAL_ERRORS: tuple[type[BaseException], ...] = (ArithmeticError, ValueError, np.linalg.LinAlgError)

#: Default floor of a log parameter with lower bound ≤ 0, relative to its starting value.
LOG_FLOOR_REL = 1e-6

#: Default relative decrease of the sum of squares a polished point must achieve to be accepted.
MIN_REL_IMPROVEMENT = 1e-10


# ---------------------------------------------------------------------------------------------- scaling
@dataclass(frozen=True)
class Scaling:
    """Map between physical parameters ``x`` and the optimiser's coordinates ``u``.

    ``u_i = log(x_i)`` where ``log_mask[i]``, else ``u_i = (x_i - offset_i) / scale_i``.
    ``lower``/``upper`` are the physical bounds (the log floor included), ``lower_u``/``upper_u`` their images.
    """

    log_mask: np.ndarray
    offset: np.ndarray
    scale: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    lower_u: np.ndarray
    upper_u: np.ndarray

    def to_u(self, x: np.ndarray) -> np.ndarray:
        """Optimiser coordinates of physical ``x`` (n,)."""
        x = np.asarray(x, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.log_mask, np.log(np.where(self.log_mask, x, 1.0)),
                            (x - self.offset) / self.scale)

    def to_x(self, u: np.ndarray) -> np.ndarray:
        """Physical parameters of coordinates ``u``, clipped to the physical bounds (round-off of exp/log)."""
        u = np.asarray(u, dtype=float)
        x = np.where(self.log_mask, np.exp(np.where(self.log_mask, u, 0.0)), self.offset + self.scale * u)
        return np.clip(x, self.lower, self.upper)

    def dx_du(self, x: np.ndarray) -> np.ndarray:
        """Diagonal of the Jacobian dx/du at physical ``x``: ``x`` for log parameters, ``scale`` otherwise."""
        return np.where(self.log_mask, np.asarray(x, dtype=float), self.scale)

    def to_dict(self) -> dict:
        """JSON-friendly description (lists of floats/bools)."""
        return {k: [bool(v) if k == "log_mask" else float(v) for v in getattr(self, k)]
                for k in ("log_mask", "offset", "scale", "lower", "upper")}


def _as_vector(name: str, value: Sequence[float], n: int | None = None) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim != 1 or (n is not None and arr.shape[0] != n):
        want = f"({n},)" if n is not None else "1-D"
        raise ConfigError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def make_scaling(x0: Sequence[float], lower: Sequence[float], upper: Sequence[float], *,
                 log_mask: Sequence[bool] | None = None, log_floor_rel: float = LOG_FLOOR_REL) -> Scaling:
    """Build the scaled parameterisation for a start ``x0`` inside ``[lower, upper]``.

    ``log_mask`` default: parameters with a finite ``lower >= 0`` and ``x0 > 0``. A log parameter needs
    ``x0 > 0``; if its lower bound is ≤ 0 the floor ``x0 · log_floor_rel`` replaces it.
    Raises :class:`ConfigError` for mismatched shapes, non-finite ``x0``, inverted bounds, ``x0`` outside
    the bounds or a log parameter with ``x0 <= 0``.
    """
    x0 = _as_vector("x0", x0)
    n = x0.shape[0]
    lo, hi = _as_vector("lower", lower, n).copy(), _as_vector("upper", upper, n).copy()
    if not np.all(np.isfinite(x0)):
        raise ConfigError(f"x0 must be finite, got non-finite entries at {np.flatnonzero(~np.isfinite(x0)).tolist()}")
    if np.any(np.isnan(lo) | np.isnan(hi)) or np.any(lo >= hi):
        bad = np.flatnonzero(np.isnan(lo) | np.isnan(hi) | (lo >= hi)).tolist()
        raise ConfigError(f"bounds must satisfy lower < upper, violated at indices {bad}")
    if np.any((x0 < lo) | (x0 > hi)):
        bad = np.flatnonzero((x0 < lo) | (x0 > hi)).tolist()
        raise ConfigError(f"x0 lies outside [lower, upper] at indices {bad}")
    if not 0.0 < log_floor_rel < 1.0:
        raise ConfigError(f"log_floor_rel must lie in (0, 1), got {log_floor_rel}")
    if log_mask is None:
        mask = np.isfinite(lo) & (lo >= 0.0) & (x0 > 0.0)
    else:
        mask = np.asarray(log_mask, dtype=bool)
        if mask.shape != (n,):
            raise ConfigError(f"log_mask must have shape ({n},), got {mask.shape}")
        if np.any(mask & (x0 <= 0.0)):
            bad = np.flatnonzero(mask & (x0 <= 0)).tolist()
            raise ConfigError(f"log parameters need x0 > 0, violated at indices {bad}")
    lo = np.where(mask & (lo <= 0.0), x0 * log_floor_rel, lo)
    finite = np.isfinite(lo) & np.isfinite(hi)
    offset = np.where(mask, 0.0, np.where(finite, lo, 0.0))
    scale = np.where(mask, 1.0, np.where(finite, hi - lo, np.where(x0 != 0.0, np.abs(x0), 1.0)))
    with np.errstate(divide="ignore"):
        lower_u = np.where(mask, np.log(np.where(mask, lo, 1.0)), (lo - offset) / scale)
        upper_u = np.where(mask, np.log(np.where(mask, hi, 1.0)), (hi - offset) / scale)
    return Scaling(log_mask=mask, offset=offset, scale=scale, lower=lo, upper=hi,
                   lower_u=lower_u, upper_u=upper_u)


# ---------------------------------------------------------------------------------------------- result
@dataclass
class PolishResult:
    """Outcome of :func:`polish`.

    x: accepted parameters (physical units) — the start itself when ``improved`` is False.
    x0: the start. cost = 0.5·Σr² (scipy's convention) and sse = Σr² at ``x``; sse0 = Σr² at ``x0``.
    nfev: calls of ``residual_fn`` (finite-difference calls included); njev: Jacobian evaluations by the
    optimiser; n_failed: trial evaluations replaced by the penalty residual.
    success/status/message: scipy's verdict (``status`` as in ``least_squares``; -2 when the start itself
    was not finite, nothing was run).
    improved: True iff the optimiser's point lowered the sum of squares by more than ``min_rel_improvement``.
    residual: residual at ``x`` (m,). jac: Jacobian dr/du at ``x`` in the scaled coordinates (m, n), None
    when the residual at the start is not finite. scaling: the :class:`Scaling` used.
    start_index: row of the start in :func:`polish_many` (0 for :func:`polish`).
    """

    x: np.ndarray
    x0: np.ndarray
    cost: float
    sse: float
    sse0: float
    nfev: int
    njev: int
    n_failed: int
    success: bool
    status: int
    message: str
    improved: bool
    residual: np.ndarray
    jac: np.ndarray | None
    scaling: Scaling
    start_index: int = 0

    def jac_phys(self) -> np.ndarray:
        """Jacobian dr/dx at ``x`` in physical units (m, n)."""
        if self.jac is None:
            raise ConfigError("no Jacobian: the residual at the start was not finite")
        return self.jac / self.scaling.dx_du(self.x)[None, :]

    def jac_log(self) -> np.ndarray:
        """Jacobian dr/dlog(x) at ``x`` (m, n), the input of :func:`toggle_id.identifiability.analyze`.

        Needs ``x > 0`` in every column (else use :func:`toggle_id.identifiability.log_jacobian` with a mask).
        """
        if np.any(self.x <= 0.0):
            raise ConfigError("jac_log needs x > 0 for every parameter; use identifiability.log_jacobian with log_mask")
        return self.jac_phys() * self.x[None, :]


# ---------------------------------------------------------------------------------------------- polish
class _Objective:
    """Residual and Jacobian in the scaled coordinates, with failed evaluations turned into data."""

    def __init__(self, residual_fn: ResidualFn, jac_fn: JacobianFn | None, scaling: Scaling,
                 m: int, penalty: float) -> None:
        self.residual_fn, self.jac_fn, self.scaling = residual_fn, jac_fn, scaling
        self.m, self.penalty = m, penalty
        self.nfev = 0
        self.n_failed = 0

    def residual(self, u: np.ndarray) -> np.ndarray:
        x = self.scaling.to_x(u)
        self.nfev += 1
        try:
            r = np.asarray(self.residual_fn(x), dtype=float)
        except TRIAL_ERRORS:
            r = None
        if r is not None and r.shape != (self.m,):
            raise ConfigError(f"residual_fn returned shape {r.shape} at a trial point, expected ({self.m},)")
        if r is None or not np.all(np.isfinite(r)):
            self.n_failed += 1
            return np.full(self.m, self.penalty)
        return r

    def jacobian(self, u: np.ndarray) -> np.ndarray:
        x = self.scaling.to_x(u)
        n = x.shape[0]
        try:
            j = np.asarray(self.jac_fn(x), dtype=float)  # type: ignore[misc]
        except TRIAL_ERRORS:
            return np.zeros((self.m, n))
        if j.shape != (self.m, n):
            raise ConfigError(f"jac_fn returned shape {j.shape}, expected ({self.m}, {n})")
        return np.where(np.isfinite(j), j, 0.0) * self.scaling.dx_du(x)[None, :]


def _fd_jacobian_u(obj: _Objective, u: np.ndarray, r: np.ndarray, diff_step: float | None) -> np.ndarray:
    """Forward-difference dr/du at ``u`` (scipy's step rule), stepping backwards at an upper bound."""
    rel = np.sqrt(np.finfo(float).eps) if diff_step is None else float(diff_step)
    jac = np.empty((r.shape[0], u.shape[0]))
    for k in range(u.shape[0]):
        h = rel * max(1.0, abs(u[k]))
        if u[k] + h > obj.scaling.upper_u[k]:
            h = -h
        up = u.copy()
        up[k] += h
        jac[:, k] = (obj.residual(up) - r) / (up[k] - u[k])
    return jac


_CONTROLLER: ThreadpoolController | None = None


def blas_limit(threads: int | None):
    """A context that runs BLAS with ``threads`` threads (a no-op for None); the controller, which scans the
    loaded libraries, is made once."""
    global _CONTROLLER
    if threads is None:
        return contextlib.nullcontext()
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=int(threads), user_api="blas")


def one_blas_thread(fn: Callable) -> Callable:
    """Run ``fn`` with one BLAS thread (for whole loops of small, tall least-squares problems: the fits, the
    structure tests' projections; see the module docstring)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with blas_limit(1):
            return fn(*args, **kwargs)
    return wrapper


def polish(residual_fn: ResidualFn, x0: Sequence[float], lower: Sequence[float], upper: Sequence[float], *,
           log_mask: Sequence[bool] | None = None, jac_fn: JacobianFn | None = None, max_nfev: int = 200,
           ftol: float = 1e-12, xtol: float = 1e-12, gtol: float = 1e-12, diff_step: float | None = None,
           fd_method: str = "2-point", log_floor_rel: float = LOG_FLOOR_REL,
           min_rel_improvement: float = MIN_REL_IMPROVEMENT, penalty: float | None = None,
           blas_threads: int | None = 1) -> PolishResult:
    """Refine ``x0`` by bounded least squares on ``residual_fn`` in the scaled parameterisation.

    residual_fn: x (n,) physical → residual (m,); may return NaN/inf (or raise one of :data:`TRIAL_ERRORS`)
        at trial points — such points get the penalty residual.
    x0, lower, upper: start and bounds (n,), physical units; ``x0`` must lie within the bounds.
    log_mask: which parameters are optimised in log space (see :func:`make_scaling`).
    jac_fn: optional analytic Jacobian dr/dx (m, n) in physical units; chain-ruled into the scaled space.
        Without it, ``fd_method`` ('2-point' or '3-point') finite differences with relative step
        ``diff_step`` (in the scaled coordinates, scipy's rule ``h = diff_step · max(1, |u|)``).
    max_nfev: scipy's budget (for 'trf' it does not count finite-difference calls: each Jacobian costs
        another n (2n) residual calls). ftol/xtol/gtol: scipy's termination tolerances.
    min_rel_improvement: the polished point is accepted only if ``sse < sse0 · (1 - min_rel_improvement)``.
    penalty: value of each entry of the residual at a failed trial point; default
        ``1e3 · max(1, max|r(x0)|)``, so that a failed point has a sum of squares ≥ 1e6 × the start's.
    blas_threads: BLAS threads while scipy iterates (see the module docstring); None leaves the pool as it is.
    Returns a :class:`PolishResult`; never raises for a failing trial point.
    """
    scaling = make_scaling(x0, lower, upper, log_mask=log_mask, log_floor_rel=log_floor_rel)
    x0 = np.asarray(x0, dtype=float).copy()
    if fd_method not in ("2-point", "3-point"):
        raise ConfigError(f"fd_method must be '2-point' or '3-point', got {fd_method!r}")
    if max_nfev < 1:
        raise ConfigError(f"max_nfev must be >= 1, got {max_nfev}")
    if not 0.0 <= min_rel_improvement < 1.0:
        raise ConfigError(f"min_rel_improvement must lie in [0, 1), got {min_rel_improvement}")
    r0 = np.asarray(residual_fn(x0), dtype=float)
    if r0.ndim != 1 or r0.shape[0] == 0:
        raise ConfigError(f"residual_fn must return a non-empty 1-D array, got shape {r0.shape}")
    m = r0.shape[0]
    if not np.all(np.isfinite(r0)):
        return PolishResult(x=x0, x0=x0.copy(), cost=np.inf, sse=np.inf, sse0=np.inf, nfev=1, njev=0,
                            n_failed=1, success=False, status=-2, message="residual at the start is not finite",
                            improved=False, residual=r0, jac=None, scaling=scaling)
    sse0 = float(r0 @ r0)
    if penalty is None:
        penalty = 1e3 * max(1.0, float(np.max(np.abs(r0))))
    obj = _Objective(residual_fn, jac_fn, scaling, m, float(penalty))
    obj.nfev = 1
    u0 = np.clip(scaling.to_u(x0), scaling.lower_u, scaling.upper_u)
    with blas_limit(blas_threads):
        res = least_squares(obj.residual, u0, jac=obj.jacobian if jac_fn is not None else fd_method,
                            bounds=(scaling.lower_u, scaling.upper_u), method="trf", x_scale=1.0,
                            ftol=ftol, xtol=xtol, gtol=gtol, max_nfev=max_nfev, diff_step=diff_step)
    r_new = np.asarray(res.fun, dtype=float)
    sse_new = float(r_new @ r_new)
    improved = bool(np.all(np.isfinite(r_new)) and sse_new < sse0 * (1.0 - min_rel_improvement))
    if improved:
        x, r, sse, jac = scaling.to_x(res.x), r_new, sse_new, np.asarray(res.jac, dtype=float)
    else:
        x, r, sse = x0.copy(), r0, sse0  # Jacobian at the kept start (forward differences without jac_fn)
        jac = obj.jacobian(u0) if jac_fn is not None else _fd_jacobian_u(obj, u0, r0, diff_step)
    return PolishResult(x=x, x0=x0, cost=0.5 * sse, sse=sse, sse0=sse0, nfev=obj.nfev, njev=int(res.njev or 0),
                        n_failed=obj.n_failed, success=bool(res.success), status=int(res.status),
                        message=str(res.message), improved=improved, residual=r, jac=jac, scaling=scaling)


def polish_many(residual_fn: ResidualFn, starts: np.ndarray, lower: Sequence[float], upper: Sequence[float],
                **kwargs) -> PolishResult:
    """Polish from each row of ``starts`` (k, n) — e.g. the GA's best individuals — and return the best.

    "Best" is the lowest sum of squares after polishing; a start that was not improved competes with its own
    sum of squares, so when nothing improves the best start is returned (``improved`` False).
    Identical rows are polished once. ``kwargs`` go to :func:`polish`; ``start_index`` of the result is the
    row it came from.
    """
    starts = np.asarray(starts, dtype=float)
    if starts.ndim == 1:
        starts = starts[None, :]
    if starts.ndim != 2 or starts.shape[0] == 0:
        raise ConfigError(f"starts must have shape (k, n) with k >= 1, got {starts.shape}")
    _, first = np.unique(starts, axis=0, return_index=True)
    best: PolishResult | None = None
    for k in np.sort(first):
        result = polish(residual_fn, starts[k], lower, upper, **kwargs)
        result.start_index = int(k)
        if best is None or result.sse < best.sse:
            best = result
    assert best is not None
    return best
