"""Scouts and refits of a candidate effect, and the guard against a better nominal optimum."""
from __future__ import annotations

import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..effects import ALL_INDEX, Effect
from .gauge import freed_with
from .model import Fit, Model, _off_values, _std_errors, _with, fit_free
from .scoring import Point, refit_start
from .settings import DiscoverSettings
from .stats import f_test


@dataclass
class Refit:
    """One candidate refitted: its fit, the F-test and BIC against the nominal baseline, and the verdict."""

    name: str
    iteration: int
    fit: Fit | None
    params: dict
    sse0: float
    sse1: float
    k: int
    p1: int
    F: float
    p_value: float
    delta_bic: float
    accepted: bool
    reason: str
    search: dict
    null_sse: float | None = None
    std_errors: dict = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self, n: int) -> dict:
        return {"name": self.name, "iteration": self.iteration, "params": self.params, "std_errors": self.std_errors,
                "sse_before_m2": self.sse0, "sse_after_m2": self.sse1, "rmse_before_m": float(np.sqrt(self.sse0 / n)),
                "rmse_after_m": float(np.sqrt(self.sse1 / n)) if np.isfinite(self.sse1) else None,
                "added_params": self.k, "total_params": self.p1, "F": self.F, "p_value": self.p_value,
                "delta_bic": self.delta_bic, "significant": self.accepted, "reason": self.reason,
                "null_refit_sse_m2": self.null_sse, "search": self.search,
                "polish": self.fit.info if self.fit else None, "seconds": self.seconds}




@dataclass
class Scout:
    """A short polish of one candidate from each linearisation point's best grid start: how much of the
    residual the effect can explain with the free parameters re-adjusted (the ranking of the refits)."""

    name: str
    sse: float
    theta: np.ndarray | None
    search: dict
    seconds: float = 0.0


def scout_candidate(model: Model, base: Fit, points: Sequence[Point], effect: Effect, settings: DiscoverSettings,
                    held: Collection[str] = ()) -> Scout:
    """From each point's profile: the best grid start (:func:`refit_start`), polished for ``scout_nfev``
    evaluations with the effect's parameters freed (and the gauge parameters of ``held`` it makes determined);
    the lowest SSE is the candidate's scout result."""
    t0 = time.perf_counter()
    results, infos = [], []
    for pt in points:
        prof = pt.profiles.get(effect.name)
        if prof is None or not prof.rows:
            continue
        st, info = refit_start(model, pt.theta, base.free, pt.proj, prof)
        info["point"] = pt.label
        infos.append(info)
        if st is None:
            continue
        fit = fit_free(model, st, freed_with(base.free, effect, held), settings.scout_nfev, settings.fd_rel_step)
        info["scout_sse_m2"] = fit.sse
        results.append((fit.sse, fit.theta, info))
    if not results:
        return Scout(effect.name, float("inf"), None, {"starts": infos, "note": "no simulable start"},
                     time.perf_counter() - t0)
    sse, theta, info = min(results, key=lambda r_: r_[0])
    search = dict(info)
    search["scouts"] = {i["point"]: i.get("scout_sse_m2") for i in infos}
    return Scout(effect.name, float(sse), theta, search, time.perf_counter() - t0)


def refit_candidate(model: Model, base: Fit, effect: Effect, scout: Scout, settings: DiscoverSettings,
                    iteration: int, held: Collection[str] = ()) -> Refit:
    """Polish with the effect's parameters freed, continuing from the scout, then the F-test/BIC against
    ``base``."""
    t0 = time.perf_counter()
    n = model.n
    names = effect.names
    free = freed_with(base.free, effect, held)
    k = len(free) - len(base.free)  # the effect's parameters and any gauge parameter it frees
    p1 = len(free)
    if scout.theta is None:
        return Refit(effect.name, iteration, None, {}, base.sse, float("inf"), k, p1, 0.0, 1.0, float("inf"),
                     False, "no simulable start for the effect", scout.search, seconds=time.perf_counter() - t0)
    fit = fit_free(model, scout.theta, free, settings.refit_nfev, settings.fd_rel_step,
                   rounds=settings.refit_rounds)
    params = {nm: float(fit.theta[ALL_INDEX[nm]]) for nm in names}
    F, p, dbic = f_test(base.sse, fit.sse, k, n, p1)
    passed = p < settings.alpha and dbic < 0
    reason = "significant (F-test and BIC)" if passed else \
        ("F-test not significant" if p >= settings.alpha else "BIC does not improve")
    out = Refit(effect.name, iteration, fit, params, base.sse, fit.sse, k, p1, F, p, dbic, passed, reason,
                scout.search, std_errors=_std_errors(fit, names, n))
    out.seconds = time.perf_counter() - t0 + scout.seconds
    return out


def guard_null(model: Model, base: Fit, refit: Refit, effect: Effect, settings: DiscoverSettings) -> Fit | None:
    """Re-polish the model without the effect from the refit's parameters; if it beats the baseline the
    refit is re-tested against it. Returns the better null fit (or None when it did not improve)."""
    start = _with(refit.fit.theta, _off_values(effect))
    null = fit_free(model, start, base.free, settings.null_nfev, settings.fd_rel_step, rounds=settings.rounds)
    refit.null_sse = null.sse
    if null.sse < base.sse:
        F, p, dbic = f_test(null.sse, refit.sse1, refit.k, model.n, refit.p1)
        refit.sse0, refit.F, refit.p_value, refit.delta_bic = null.sse, F, p, dbic
        refit.accepted = p < settings.alpha and dbic < 0
        if not refit.accepted:
            refit.reason = ("a better nominal optimum explains the gain: " +
                            ("F-test not significant" if p >= settings.alpha else "BIC does not improve"))
        return null
    return None
