"""The toggle plant as the discovery engine sees it: batched PRECISE simulations of one record, sensitivities in
analysis coordinates, the range of the free parameters' sensitivities, and bounded least-squares fits."""
from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import params as P
from ..effects import ALL_INDEX, EFFECTS, Effect, sensor_error
from ..errors import ConfigError, DataError
from ..identify import stage_bounds
from ..kernels.slots import GS_LO
from ..polish import polish
from ..record import Record
from ..simulate import PRECISE, STATUS_OK, SolverSettings, simulate
from .derivatives import DERIVATIVES, _coords, _typical, broyden, output_derivatives, sensitivities
from .noise import NoiseModel
from .settings import DiscoverSettings
from .timing import PhaseClock

#: Bytes of simulated x_B a :class:`Model` keeps for batches asked for again (:meth:`Model.outputs`).
CACHE_BYTES = 64 * 2**20

#: White noise: ordinary least squares, and the model of the uncertainty when no other is given.
WHITE_ASSUMED = NoiseModel(note="white noise assumed")


#: Effects whose magnitude is on (≠ its off value) in an extended vector: what makes a record stiff or not.
_MAGNITUDES = np.array([ALL_INDEX[e.magnitude.name] for e in EFFECTS], dtype=np.int64)
_MAGNITUDE_OFF = np.array([e.magnitude.off for e in EFFECTS], dtype=float)


def effects_on(theta: np.ndarray) -> bytes:
    """A key naming the effects switched on in ``theta`` (one extended vector)."""
    return np.packbits(theta[_MAGNITUDES] != _MAGNITUDE_OFF).tobytes()


class Model:
    """Simulations of one record in the PRECISE tier: residuals, batched, with failures as NaN rows.

    ``noise``: the noise model the fits minimise under (prediction-error fits: the residual prewhitened by
    it; white noise is ordinary output-error least squares). Set it, the loop does, before fitting.

    A tier with a fallback (PRECISE: DOPRI5, Rodas4 for rows that exhaust DOPRI5's step budget) spends the
    whole budget before the fallback starts. Some effects make every simulation of a record stiff (a motor-side
    Coulomb friction chatters at each reversal): once most rows of a batch with a given set of effects on
    fell back, later batches with that set go to the fallback directly (:attr:`stiff`) — the same
    integrator the rows ended in, at about half the cost.

    A batch asked for again (the same rows on the same integrator settings: mostly scipy evaluating a point it
    has already evaluated, or a refit starting where a scout ended) is taken from a bounded cache of the latest
    batches (:data:`CACHE_BYTES`) instead of simulated again: the same numbers bit for bit, since a row's
    simulation depends on nothing else; :attr:`n_sims` counts the simulations run, :attr:`n_cached` the rows
    served from the cache."""

    def __init__(self, record: Record, settings: SolverSettings = PRECISE, parallel: bool = True,
                 jacobian: tuple[SolverSettings, float] | None = None, jacobian_reuse: int = 0,
                 derivatives: str = "fd") -> None:
        if record.x_B is None:
            raise DataError(f"record {record.name!r} has no measured x_B to fit")
        self.record = record
        self.settings = settings
        #: the integrator of the polishes' finite-difference Jacobians and of the screening grids (default
        #: ``settings``, the residuals' own) and their relative step (None: each fit's ``fd_rel_step``)
        self.jacobian, self.jacobian_step = jacobian if jacobian is not None else (settings, None)
        self.parallel = parallel
        #: Broyden updates allowed between two finite-difference Jacobians in a polish's coarse rounds (0: none;
        #: see :func:`fit_free`)
        self.jacobian_reuse = int(jacobian_reuse)
        if derivatives not in DERIVATIVES:
            raise ConfigError(f"derivatives must be one of {', '.join(DERIVATIVES)}, got {derivatives!r}")
        #: how the polishes' Jacobians and the sensitivities are taken: ``fd`` (finite differences) or
        #: ``analytic`` (forward sensitivities, :mod:`.derivatives`; differences where they do not apply)
        self.derivatives = derivatives
        #: simulations with sensitivities run (each also counts once in :attr:`n_sims`)
        self.n_derivative_runs = 0
        self.n_sims = 0
        self.n_cached = 0
        #: seconds and simulations per phase of the loop (:mod:`.timing`): ``with model.clock("scouts"): …``
        self.clock = PhaseClock(lambda: self.n_sims)
        self._cache: OrderedDict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()
        self._cache_bytes = 0
        self.noise = WHITE_ASSUMED
        #: effect sets (:func:`effects_on`) whose simulations go straight to the fallback
        self.stiff: set[bytes] = set()
        #: samples the model takes as measured (bool (N,); None: none): glitches of the measurement
        #: (:func:`toggle_id.residuals.glitches`), which then weigh in no residual, sensitivity or test
        self.excluded: np.ndarray | None = None
        #: feasible domains this record narrows (name → (low, high)), over the library's own: every fit of the
        #: model keeps to them and the score tests and grids probe within them (:meth:`probes`)
        self.bounds: dict[str, tuple[float, float]] = {}
        #: the library's domains of the effect parameters that scale with the mechanism or the current, as they read
        #: in the gauge the loop's fits work in (:func:`.gauge.domains_in_gauge`; set by the plant whose fits run)
        self.gauge_bounds: dict[str, tuple[float, float]] = {}

    @property
    def n(self) -> int:
        return self.record.n

    def domains(self) -> dict[str, tuple[float, float]]:
        """The feasible domains every fit of the model keeps to, over the library's own: the gauge's
        (:attr:`gauge_bounds`), then the record's (:attr:`bounds`)."""
        return {**self.gauge_bounds, **self.bounds}

    def domain(self, name: str) -> tuple[float, float]:
        """The feasible domain of parameter ``name`` in the model's fits (:meth:`domains`, else the library's)."""
        lo, hi = stage_bounds([name], self.domains())
        return float(lo[0]), float(hi[0])

    def probes(self, effect) -> list[dict]:
        """The probe settings of ``effect`` (:attr:`~toggle_id.effects.Effect.probe`) moved into its domains
        (:meth:`domains`), each once, in order."""
        out: list[dict] = []
        domains = self.domains()
        for pr in effect.probe:
            pr = {k: float(np.clip(v, *domains[k])) if k in domains else v for k, v in pr.items()}
            if pr not in out:
                out.append(pr)
        return out

    def _settings_for(self, theta: np.ndarray, tier: SolverSettings | None = None) -> SolverSettings:
        tier = tier if tier is not None else self.settings
        fb = tier.fallback
        return fb if fb is not None and effects_on(theta) in self.stiff else tier

    def mark_stiff(self, theta: np.ndarray) -> None:
        """Send later simulations with ``theta``'s effect set straight to the fallback (:attr:`stiff`)."""
        self.stiff.add(effects_on(theta))

    def outputs(self, thetas: np.ndarray, tier: SolverSettings | None = None) -> np.ndarray:
        """(P, N) model x_B [m] of extended vectors ``thetas`` (P, N_THETA), the generic sensor error
        (:func:`toggle_id.effects.sensor_error`) added; NaN rows for failures. ``tier``: the integrator settings
        (default :attr:`settings`; the stiff fallback once the effect set is known stiff)."""
        thetas = np.atleast_2d(thetas)
        # rows that differ only in the generic sensor error (an output map) share one simulation; the plant rows in
        # the order they first occur, so plant[0] is thetas[0] (the stiff-fallback decision reads it)
        _, first, inverse = np.unique(thetas[:, :GS_LO], axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first)
        plant = thetas[first[order]]
        inverse = np.argsort(order)[inverse.reshape(-1)]
        tier = tier if tier is not None else self.settings
        settings = self._settings_for(plant[0], tier)
        x_B, status, fell_back = self._simulated(plant, settings)
        if settings is tier and 2 * int(fell_back.sum()) > len(plant):
            self.mark_stiff(plant[0])
        x = x_B[inverse]
        x += sensor_error(thetas, x)
        ok = status[inverse] == STATUS_OK
        x[~ok] = np.nan
        if self.excluded is not None:
            x[np.ix_(ok, self.excluded)] = self.record.x_B[self.excluded]
        return x

    def _simulated(self, plant: np.ndarray, settings: SolverSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x_B, status and the fallback flags of the rows ``plant`` on ``settings``: from the cache when this
        batch was simulated on these settings lately, else simulated (and kept, the oldest batches dropped
        beyond :data:`CACHE_BYTES`). The arrays returned are read-only."""
        key = (settings, plant.shape, plant.tobytes())
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            self.n_cached += plant.shape[0]
            return hit
        self.n_sims += plant.shape[0]
        res = simulate(plant, self.record, settings, parallel=self.parallel and plant.shape[0] > 1)
        fell_back = res.fell_back if res.fell_back is not None else np.zeros(len(plant), dtype=bool)
        out = (res.x_B, res.status, fell_back)
        size = res.x_B.nbytes
        if size <= CACHE_BYTES:
            for a in out:
                a.setflags(write=False)
            self._cache[key] = out
            self._cache_bytes += size
            while self._cache_bytes > CACHE_BYTES:
                _, old = self._cache.popitem(last=False)
                self._cache_bytes -= old[0].nbytes
        return out

    def residuals(self, thetas: np.ndarray, tier: SolverSettings | None = None) -> np.ndarray:
        """(P, N) measured − model [m]."""
        return self.record.x_B[None, :] - self.outputs(thetas, tier)

    def fit_residuals(self, thetas: np.ndarray, tier: SolverSettings | None = None) -> np.ndarray:
        """(P, N) residuals prewhitened by :attr:`noise` (what a fit minimises)."""
        return self.noise.whiten(self.residuals(thetas, tier))

    def response(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """x_B [m], i_q [A] and the status of one vector."""
        res = simulate(np.atleast_2d(theta), self.record, self._settings_for(np.atleast_2d(theta)[0]))
        return res.x_B[0] + sensor_error(theta, res.x_B[0])[0], res.i_q[0], int(res.status[0])


def _sse(r: np.ndarray) -> np.ndarray:
    r = np.atleast_2d(r)
    s = np.einsum("ij,ij->i", r, r)
    s[~np.isfinite(s)] = np.inf
    return s


@dataclass
class Projector:
    """Orthonormal basis U of the range of J (rank by ``rank_rtol``) and its pseudo-inverse pieces."""

    U: np.ndarray
    s: np.ndarray
    Vt: np.ndarray

    @classmethod
    def of(cls, J: np.ndarray, rank_rtol: float = 1e-7) -> Projector:
        if J.size == 0:
            return cls(np.zeros((J.shape[0], 0)), np.zeros(0), np.zeros((0, J.shape[1])))
        U, s, Vt = np.linalg.svd(J, full_matrices=False)
        k = int(np.sum(s > rank_rtol * s[0])) if s.size and s[0] > 0 else 0
        return cls(U[:, :k], s[:k], Vt[:k])

    @property
    def rank(self) -> int:
        return int(self.s.size)

    def perp(self, v: np.ndarray) -> np.ndarray:
        """(I − U Uᵀ) v for v (N,) or (P, N) rows."""
        v = np.asarray(v, float)
        if self.rank == 0:
            return v.copy()
        return v - (v @ self.U) @ self.U.T

    def solve(self, r: np.ndarray) -> np.ndarray:
        """Minimum-norm least-squares step δu with J δu ≈ r."""
        if self.rank == 0:
            return np.zeros(self.Vt.shape[1])
        return self.Vt.T @ ((self.U.T @ r) / self.s)


def _with(theta: np.ndarray, values: Mapping[str, float]) -> np.ndarray:
    out = theta.copy()
    for k, v in values.items():
        out[ALL_INDEX[k]] = float(v)
    return out


def revived(theta: np.ndarray, free: Sequence[str], collapse: float = 1e-3) -> np.ndarray | None:
    """``theta`` with every free physical parameter that collapsed towards its lower bound of 0 (below
    ``collapse`` × its assigned value) put back at its assigned value; None when none collapsed.

    Positive parameters are fitted in log space, where a parameter near 0 has almost no sensitivity: once a
    fit has pushed it there (say the slider's friction coefficient, while another term stood in for it), no
    later polish brings it back, and a model that contains the truth stays above the noise. Such a start
    lets the polish find the interior optimum."""
    out = theta.copy()
    hit = False
    for nm in free:
        j = P.INDEX.get(nm)
        if j is not None and P.LOWER[j] == 0.0 and 0.0 <= out[j] < collapse * P.ASSIGNED[j]:
            out[j] = P.ASSIGNED[j]
            hit = True
    return out if hit else None


def _off_values(effect: Effect) -> dict[str, float]:
    return {p.name: p.off for p in effect.params}


@dataclass
class Fit:
    """A fitted model: extended vector, free names, SSE on the whole record and the polish's record."""

    theta: np.ndarray
    free: tuple[str, ...]
    sse: float
    info: dict = field(default_factory=dict)
    jac_u: np.ndarray | None = None
    scaling: Any = None
    raw_sse: float | None = None
    noise: Any = None

    def rmse(self, n: int) -> float:
        """RMS of the (raw) residual [m]."""
        return float(np.sqrt((self.sse if self.raw_sse is None else self.raw_sse) / n))

    @property
    def minimised_under(self) -> tuple[float, ...]:
        """The AR coefficients of the noise model the fit was minimised under (none: least squares): two fits whose
        whitened SSEs compare have the same."""
        return self.noise.a if self.noise is not None else ()


@contextmanager
def minimising_under(model: Model, noise: NoiseModel) -> Iterator[Model]:
    """Inside the block the fits of ``model`` minimise under ``noise`` (white: least squares); after it, under the
    noise model they had."""
    before, model.noise = model.noise, noise
    try:
        yield model
    finally:
        model.noise = before


def strictly_inside(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, rtol: float = 1e-6) -> np.ndarray:
    """Bool: the values ``x`` farther than ``rtol`` of their range (of |x| or 1 where it is unbounded) from the
    bounds ``lo``, ``hi`` — parameters a fit could still move either way. One at a bound may keep a gradient at the
    fit's minimum."""
    x, lo, hi = (np.asarray(v, float) for v in (x, lo, hi))
    with np.errstate(invalid="ignore"):
        tol = rtol * np.where(np.isfinite(hi - lo), hi - lo, np.maximum(np.abs(x), 1.0))
    return (x - lo > tol) & (hi - x > tol)


def inside_bounds(theta: np.ndarray, free: Sequence[str], rtol: float = 1e-6) -> np.ndarray:
    """Bool (len(free),): the free parameters of ``theta`` strictly inside their bounds (:func:`stage_bounds`)."""
    lo, hi = stage_bounds(list(free))
    return strictly_inside(theta[[ALL_INDEX[n] for n in free]], lo, hi, rtol)


def fit_free(model: Model, theta: np.ndarray, free: Sequence[str], max_nfev: int, fd_rel_step: float = 1e-4,
             bounds: Mapping[str, Sequence[float]] | None = None, rounds: int = 1, round_rtol: float = 1e-4,
             coarse: bool = True, screen: tuple[SolverSettings, float] | None = None) -> Fit:
    """Polish ``free`` parameters of ``theta`` on the whole record (PRECISE, bounded least squares in log
    space for positive parameters). Keeps ``theta`` when nothing improves; never raises for a failed trial.

    ``rounds`` > 1 restarts the polish from its result (a fresh trust region) while a round still lowers the
    SSE by more than ``round_rtol`` (relative): the nominal parameters lie in long curved valleys (scaling
    symmetries), where one trust-region run often stops early.

    With ``coarse`` and a model whose Jacobians come from a looser tier (:attr:`Model.jacobian`) or are partly
    Broyden updates (:attr:`Model.jacobian_reuse`), the rounds use
    them and one more round with the residuals' own Jacobians (PRECISE, ``fd_rel_step``) ends the fit: the fixed
    point of an approximate Jacobian is biased along the sloppy directions (measured: ~3 σ² of SSE on a 5-s
    record), which an exact round removes in a few steps. Without ``coarse`` every round is PRECISE (a scout:
    8 evaluations, too few for the coarse rounds to get as far; measured on a dead-time record, 5.63 against
    5.12 µm, which reordered the candidates). ``screen`` = (integrator, step): one round with residuals and
    Jacobians both in it (one consistent problem), the end point's SSE then in the residuals' own tier.
    """
    if screen is not None:  # a screening fit, comparable with every other fit by its SSE
        fit = _fit_once(model, theta, free, max_nfev, screen[1], bounds, coarse=False, residual_tier=screen[0])
        r = model.residuals(fit.theta[None, :])
        sse, raw = float(_sse(model.noise.whiten(r))[0]), float(_sse(r)[0])
        return Fit(fit.theta, fit.free, sse, {**fit.info, "screen_tier_sse": fit.sse, "sse_after": sse}, fit.jac_u,
                   fit.scaling, raw, fit.noise)
    fit = _fit_once(model, theta, free, max_nfev, fd_rel_step, bounds, coarse=coarse)
    info = dict(fit.info)

    def merge(more: Fit) -> None:
        nonlocal fit
        info["nfev"] += more.info["nfev"]
        info["seconds"] += more.info["seconds"]
        info["sse_after"] = more.sse
        info["message"] = more.info["message"]
        info["rounds"] = info.get("rounds", 1) + 1
        fit = more

    for _ in range(max(int(rounds), 1) - 1):
        more = _fit_once(model, fit.theta, free, max_nfev, fd_rel_step, bounds, coarse=coarse)
        gain = (fit.sse - more.sse) / fit.sse if fit.sse > 0 else 0.0
        if more.sse < fit.sse:
            merge(more)
        if gain <= round_rtol:
            break
    if coarse and (model.jacobian is not model.settings or model.jacobian_reuse > 0):
        more = _fit_once(model, fit.theta, free, max_nfev, fd_rel_step, bounds, coarse=False)
        if more.sse < fit.sse:
            merge(more)
    fit.info = info
    return fit


def _fit_once(model: Model, theta: np.ndarray, free: Sequence[str], max_nfev: int, fd_rel_step: float,
              bounds: Mapping[str, Sequence[float]] | None, coarse: bool = True,
              residual_tier: SolverSettings | None = None) -> Fit:
    """One bounded least-squares run; ``coarse``: finite differences in :attr:`Model.jacobian` (else in the
    residuals' tier at ``fd_rel_step``); ``residual_tier``: the residuals' tier (default the model's own)."""
    free = tuple(free)
    own = residual_tier if residual_tier is not None else model.settings
    tier, step = (model.jacobian, model.jacobian_step or fd_rel_step) if coarse else (own, fd_rel_step)
    idx = np.array([ALL_INDEX[n] for n in free], dtype=np.int64)
    lo, hi = stage_bounds(list(free), {**model.domains(), **(bounds or {})})
    x0 = np.clip(theta[idx].astype(float), lo, hi)
    typ = _typical(free, theta)
    mask = (lo >= 0.0) & (x0 > 0.0)
    # a log parameter must start strictly inside its bounds
    x0 = np.where(mask, np.clip(x0, lo + 1e-12 * typ, hi * (1 - 1e-12)), x0)

    def thetas_of(X: np.ndarray) -> np.ndarray:
        T = np.repeat(theta[None, :], X.shape[0], axis=0)
        T[:, idx] = X
        return T

    last: list[tuple[np.ndarray, np.ndarray]] = []  # the latest residual: scipy asks for the Jacobian there
    reuse = model.jacobian_reuse if coarse else 0
    held: dict = {}  # the latest Jacobian, where it was taken, the residual there, Broyden updates since a fresh one

    def resid(x: np.ndarray) -> np.ndarray:
        r = model.fit_residuals(thetas_of(x[None, :]), own)[0]
        last[:] = [(x.copy(), r)]
        return r

    def jac(x: np.ndarray) -> np.ndarray:
        here = last[0][1] if last and np.array_equal(last[0][0], x) else None
        if reuse and held and held["age"] < reuse and here is not None and np.all(np.isfinite(here)):
            J = broyden(held["J"], held["x"], held["r"], x, here, typ)
            if J is not None:
                held.update(J=J, x=x.copy(), r=here, age=held["age"] + 1)
                return J
        h = step * np.maximum(np.abs(x), typ)
        h = np.where(x + h > hi, -h, h)
        if model.derivatives == "analytic" and own is model.settings:
            D = output_derivatives(model, thetas_of(x[None, :])[0], idx)
            if D is not None:  # residual = measured − model, prewhitened: J = −A(q) ∂x/∂θ
                J = -model.noise.whiten_columns(np.nan_to_num(D))
                todo = np.flatnonzero(~np.all(np.isfinite(D), axis=0))
                if todo.size:  # columns the sensitivities do not give: forward differences
                    r0 = here if here is not None else model.fit_residuals(thetas_of(x[None, :]))[0]
                    R = model.fit_residuals(thetas_of(x[None, :] + np.diag(h)[todo]))
                    J[:, todo] = (R - r0).T / h[todo]
                if reuse and here is not None:
                    held.update(J=J, x=x.copy(), r=here, age=0)
                return J
        X = x[None, :] + np.diag(h)
        if tier is own and here is not None:
            r0, Rr = here, model.fit_residuals(thetas_of(X), own)
        else:  # the point itself in the Jacobian's tier too: both ends of every difference from one integrator
            R = model.fit_residuals(thetas_of(np.vstack([x[None, :], X])), tier)
            r0, Rr = R[0], R[1:]
        J = (Rr - r0).T / h
        if reuse and here is not None:
            held.update(J=J, x=x.copy(), r=here, age=0)
        return J

    t0 = time.perf_counter()
    res = polish(resid, x0, lo, hi, log_mask=mask, jac_fn=jac, max_nfev=max_nfev)
    out = thetas_of(res.x[None, :])[0]
    info = {"sse_before": float(res.sse0), "sse_after": float(res.sse), "improved": bool(res.improved),
            "nfev": int(res.nfev), "message": str(res.message), "seconds": time.perf_counter() - t0}
    raw = float(_sse(model.residuals(out[None, :]))[0]) if not model.noise.white else float(res.sse)
    return Fit(out, free, float(res.sse), info, res.jac, res.scaling, raw, model.noise)


def parameter_uncertainty(model: Model, fit: Fit, settings: DiscoverSettings, held: Sequence[str] = (),
                          noise: NoiseModel | None = None) -> dict:
    """Identifiability report (:func:`toggle_id.identifiability.analyze`) of the free parameters at ``fit``:
    standard errors, 95 % intervals and whether each parameter is determined by the record (a parameter
    with a component along a null direction of the sensitivities is not, whatever its local curvature).

    ``held``: parameters treated as known — one per exact symmetry fixed by :func:`gauge_fix` (the
    symmetry's scale is then the reference's, and e.g. a friction torque is determined relative to it).
    ``noise``: the AR noise model of the residual; sensitivities and residual are prewhitened by it (the
    intervals of the prediction-error estimate), and the report names it. Each variance is the larger of the
    classical one and the HC3 sandwich's (a noise level that varies along the record)."""
    from ..identifiability import analyze

    names = [nm for nm in fit.free if nm not in set(held)]
    try:
        J = sensitivities(model, fit.theta, names, settings.jac_rel_step)
        r = model.residuals(fit.theta[None, :])[0]
        mask, scale = _coords(names, fit.theta)
        x = np.array([fit.theta[ALL_INDEX[nm]] for nm in names])
        nm = noise if noise is not None else WHITE_ASSUMED
        known = settings.noise_std ** 2 if settings.noise_std and nm.white else None
        out = analyze(nm.whiten_columns(J), nm.whiten(r), names, x, log_mask=mask, scale=scale,
                      noise_var=known, robust=True).to_dict()
        out["held_for_symmetries"] = list(held)
        out["noise_model"] = nm.to_dict()
        return out
    except (ConfigError, DataError, np.linalg.LinAlgError, ValueError) as err:
        return {"error": str(err)}


def _std_errors(fit: Fit, names: Sequence[str], n: int) -> dict[str, float | None]:
    """Gauss–Newton standard errors (physical units) of ``names`` from the polish's Jacobian (pseudo-inverse:
    directions the data do not see are left out, so read them as lower bounds there)."""
    if fit.jac_u is None or fit.scaling is None:
        return {k: None for k in names}
    J = np.asarray(fit.jac_u, float)
    sigma2 = fit.sse / max(n - J.shape[1], 1)
    try:
        cov = sigma2 * np.linalg.pinv(J.T @ J, rcond=1e-12)
    except np.linalg.LinAlgError:
        return {k: None for k in names}
    x = np.array([fit.theta[ALL_INDEX[k]] for k in fit.free])
    dxdu = fit.scaling.dx_du(x)
    out = {}
    for k in names:
        j = fit.free.index(k)
        v = cov[j, j]
        out[k] = float(np.sqrt(v) * abs(dxdu[j])) if np.isfinite(v) and v >= 0 else None
    return out
