"""Whether a refitted effect is supported: in sample (prewhitened F-test, its heteroscedasticity-robust twin and
BIC, at ``alpha`` over the number of candidates a forward step chooses among), out of sample (time-block
cross-validation — by more than the noise would make it at ``cv_alpha`` < 0.5 — and a second record when the user
gives one), and after the others (backward elimination).

The loop fits by ordinary least squares, or the prediction-error way under the AR model of its current residual
(``discover.prediction_error``). A comparison (:meth:`Judge.judge_pair`) takes its noise model from
the residual of the *larger* model: when the effect is real that residual is the noise; when it is not, the two
residuals are alike. (The smaller model's residual, which holds the effect's structure, would pass for coloured
noise and hide it.) When that noise model is white the two least-squares fits are compared as they are; when it
is coloured both are refitted the prediction-error way under it (least squares on the prewhitened residual,
``Model.noise``), so that the F-test on the two whitened SSEs has its textbook distribution — two least-squares
fits judged by whitened SSEs would not: either may sit anywhere in the directions the colour hides. The larger
model's whitened refit starts from its least-squares fit *and* from the smaller model's whitened fit with the new
parameters added (nested), and keeps the lower: from its own least-squares optimum alone it can end above the
smaller model (measured on a backlash record: F = −2.6 for a refit that had lowered the least-squares SSE by 16 %).
Likewise the smaller model's whitened refit starts from its own fit and from the larger one's whitened fit with the
new parameters off: a larger model whose shared parameters went to another valley wins nothing by the valley alone
(rec33 of the adversarial set: a viscous friction refitted to c_B ≈ 1 N·s/m, nothing, with a least-squares error
above the smaller model's, passed at F 126). And the loop's own fits must show the gain (check ``reported_fits``,
of every nested comparison that is coloured or whose fits are prediction-error ones: their F-test on their SSEs as
minimised, which for least-squares fits under coloured noise counts every sample and so is only a necessary
condition): the parameters reported are theirs, and a refit whose effect sits at "off" there (c_B ≈ 10⁻⁶ N·s/m on
rec33, accepted at F 84.5 by the whitened refits) is no finding of the model reported.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..record import Record
from ..effects import ALL_INDEX
from .derivatives import sensitivities
from .model import Fit, Model, _with, fit_free, minimising_under
from .noise import WHITE, NoiseModel, fit_noise, prediction_error_drift
from .residual import leave_out_glitches, level_of
from .settings import DiscoverSettings
from .stats import compare, f_test, out_of_sample, robust_f, serial_ratio


@dataclass
class Evidence:
    """The case for a larger model against a smaller one (see the module docstring)."""

    noise: NoiseModel
    F: float
    p_value: float
    delta_bic: float
    cv0: float
    cv1: float
    sse0_w: float
    sse1_w: float
    validation0: float | None = None
    validation1: float | None = None
    #: the F statistic corrected for a noise level that varies along the record and its p-value; ``hc_ratio``
    #: is the factor it was divided by (:func:`.stats.robust_f`; 1: the noise's level does not matter here)
    F_robust: float = float("nan")
    p_robust: float = float("nan")
    hc_ratio: float = 1.0
    #: where that factor's variance came from: "per sample" (HC3) or "level" (``discover.level_min_count``)
    hc_variance: str = "per sample"
    #: the out-of-sample gain against the noise's spread of it and its one-sided p-value (:func:`.stats.out_of_sample`)
    cv_z: float = float("nan")
    cv_p: float = float("nan")
    #: the level the F-tests were read at (alpha, over the candidates a forward step chose among: :attr:`Judge.level`)
    level: float = float("nan")
    #: how the comparison was made: "prewhitened" (under ``noise``), or "least squares (HAC)" when ``noise`` is an
    #: error the model lacks (:meth:`Judge.serial_evidence`; ``drift`` says why)
    inference: str = "prewhitened"
    drift: str | None = None
    checks: dict = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return all(self.checks.values())

    @property
    def reason(self) -> str:
        if self.passed:
            return ("significant in sample (prewhitened F-test, robust to the noise level, and BIC) and better out "
                    "of sample")
        at = f" at {self.level:.2g}" if np.isfinite(self.level) else ""
        names = {"f_test": f"F-test not significant{at}",
                 "robust_f_test": "not significant once the noise's level is let vary along the record "
                                  f"(heteroscedasticity-robust F-test{at})",
                 "bic": "BIC does not improve",
                 "cross_validation": "no better out of sample (time-block cross-validation)",
                 "validation_record": "does not predict the validation record better",
                 "identifiable": "a new parameter is not identifiable (|correlation| > max_corr)",
                 "reported_fits": "the loop's own fit, whose parameters are reported, does not lower its error "
                                  "significantly" + (": the gain is the judge's prewhitened refits' alone, and the "
                                                     "model reported would not have it"
                                                     if self.checks.get("f_test") else "")}
        return "; ".join(v for k, v in names.items() if k in self.checks and not self.checks[k])

    def to_dict(self) -> dict:
        return {"noise_model": self.noise.to_dict(), "F": self.F, "p_value": self.p_value,
                "delta_bic": self.delta_bic, "F_robust": self.F_robust, "p_value_robust": self.p_robust,
                "hc_ratio": self.hc_ratio, "hc_variance": self.hc_variance, "sse_w_before": self.sse0_w,
                "sse_w_after": self.sse1_w,
                "cv_sse_w_before": self.cv0, "cv_sse_w_after": self.cv1, "cv_z": self.cv_z, "cv_p_value": self.cv_p,
                "level": self.level, "inference": self.inference, "drift": self.drift,
                "validation_sse_before_m2": self.validation0, "validation_sse_after_m2": self.validation1,
                "checks": dict(self.checks), "passed": self.passed, "reason": self.reason}


class Judge:
    """Judges larger models against smaller ones on one record (and an optional validation record), caching
    each fit's residual and sensitivities."""

    def __init__(self, model: Model, settings: DiscoverSettings, validation: Record | None = None) -> None:
        self.model = model
        self.s = settings
        self.validation = Model(validation, model.settings, model.parallel) if validation is not None else None
        self._cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
        self._val: dict[bytes, float] = {}
        self._levels: dict[bytes, np.ndarray | None] = {}
        #: how many candidates the comparison being judged was chosen among (:attr:`level`; set by the forward step)
        self.family = 1
        #: the glitches of the measurement left out of both records (:func:`.residual.leave_out_glitches`; None:
        #: not looked for yet)
        self.glitches: list[dict] | None = None

    @property
    def level(self) -> float:
        """The F-tests' level: ``alpha`` over the :attr:`family` of candidates a forward step chooses among
        (Bonferroni: the best of m chance gains passes a test at ``alpha`` about m times as often)."""
        return self.s.alpha / max(int(self.family), 1)

    def leave_out_glitches(self, theta: np.ndarray) -> bool:
        """Look once for glitches of the measurement in the residuals of ``theta`` on the record and the validation
        record and leave them out of every later residual (:attr:`glitches`); the cached residuals are dropped.
        True when any was found."""
        models = [m for m in (self.model, self.validation) if m is not None]
        self.glitches = [g for m in models for g in [leave_out_glitches(m, theta, self.s.glitch_k)] if g is not None]
        self._cache.clear()
        self._val.clear()
        self._levels.clear()
        return any(g["count"] for g in self.glitches)

    def _key(self, fit: Fit) -> bytes:
        return fit.theta.tobytes() + ",".join(fit.free).encode()

    def residual_and_jacobian(self, fit: Fit) -> tuple[np.ndarray, np.ndarray]:
        key = self._key(fit)
        if key not in self._cache:
            r = self.model.residuals(fit.theta[None, :])[0]
            J = sensitivities(self.model, fit.theta, fit.free, self.s.jac_rel_step)
            self._cache[key] = (r, J)
        return self._cache[key]

    def level_basis(self, fit: Fit) -> np.ndarray | None:
        """What the noise's level may follow along ``fit``'s trajectory (:func:`.residual.level_of`), once per fit:
        its whitened refits and the loop's fit of one model are judged more than once."""
        key = self._key(fit)
        if key not in self._levels:
            self._levels[key] = level_of(self.model, fit.theta, self.s)
        return self._levels[key]

    def residual(self, fit: Fit) -> np.ndarray:
        """The residual of ``fit`` on the record: the cached one of a fit already judged, else one simulation."""
        hit = self._cache.get(self._key(fit))
        return hit[0] if hit is not None else self.model.residuals(fit.theta[None, :])[0]

    def validation_sse(self, fit: Fit) -> float | None:
        if self.validation is None:
            return None
        key = self._key(fit)
        if key not in self._val:
            r = self.validation.residuals(fit.theta[None, :])[0]
            self._val[key] = float(r @ r) if np.all(np.isfinite(r)) else float("inf")
        return self._val[key]

    def judge_pair(self, small: Fit, large: Fit) -> Evidence:
        """The case for ``large`` against ``small`` (the loop's fits) under the noise model of ``large``'s
        residual; both refitted under it first when it is coloured (see the module docstring)."""
        r1, _ = self.residual_and_jacobian(large)
        noise = fit_noise(r1, self.s.noise_max_order) if np.all(np.isfinite(r1)) else NoiseModel()
        nested = set(small.free) < set(large.free)
        if noise.white:
            ev = self.evidence(small, large, noise)
            if nested and not all(f.noise is None or f.noise.white for f in (small, large)):
                # prediction-error fits judged as they are: their own gain, as they were minimised, must show too
                ev.checks["reported_fits"] = self._reported_gain(small, large)
            return ev
        with minimising_under(self.model, noise):
            small_w = fit_free(self.model, small.theta, small.free, self.s.null_nfev, self.s.fd_rel_step)
            large_w = fit_free(self.model, large.theta, large.free, self.s.null_nfev, self.s.fd_rel_step)
            if nested:
                # nested: each model from both fits (see the module docstring); the smaller from the larger's
                # whitened fit with the new parameters as the smaller has them (off)
                extra = {nm: small.theta[ALL_INDEX[nm]] for nm in large.free if nm not in small.free}
                back = fit_free(self.model, _with(large_w.theta, extra), small.free, self.s.null_nfev,
                                self.s.fd_rel_step)
                small_w = min((small_w, back), key=lambda f: f.sse)
                # the larger model also from the smaller one's whitened fit with everything else as in
                # ``large`` (its extra parameters, and the fixed ones that shape them: a nuisance parameter, the
                # knots of a generic term) — the least-squares optimum of ``large`` can lie where the whitened one
                # of the smaller model is not, and a whitened refit from there alone can end above it (F < 0)
                shared = {nm: small_w.theta[ALL_INDEX[nm]] for nm in small.free}
                from_small = fit_free(self.model, _with(large.theta, shared), large.free, self.s.null_nfev,
                                      self.s.fd_rel_step)
                large_w = min((large_w, from_small), key=lambda f: f.sse)
        if nested and self.s.pe_guard_alpha > 0:
            drift = prediction_error_drift(large, large_w, noise, self.s.pe_guard_alpha)
            if drift is not None:
                return self.serial_evidence(small, large, noise, drift)
        ev = self.evidence(small_w, large_w, noise)
        if nested:  # the loop's own fits, whose parameters are reported, must show the gain too
            ev.checks["reported_fits"] = self._reported_gain(small, large)
        return ev

    def serial_evidence(self, small: Fit, large: Fit, noise: NoiseModel, drift: str) -> Evidence:
        """The case for ``large`` against ``small`` (the loop's least-squares fits) when the noise model of
        ``large``'s residual is an error the model lacks: ``large``'s prediction-error refit under it drifted from
        least squares by more than noise allows (``drift``, :func:`.noise.prediction_error_drift`, at
        ``pe_guard_alpha``). Whitening by it would let the fits drift along the missing effect and hide what lies in
        the record's slow part (rec15_d1 of the held-out draw: a true 15-µm offset whose whitened out-of-sample gain
        is lost at the sweep's first impact, rejected at z −15). So the fits are judged as least
        squares, with inference that allows for the residual's serial correlation instead of removing it: the F-test
        on F/c and BIC on n/c samples, c the Newey–West ratio of the new parameters (:func:`.stats.serial_ratio` —
        heteroscedasticity- and autocorrelation-consistent, so it is the robust F-test too); cross-validation and the
        validation record unwhitened (OLS with HAC inference: what stays valid when a Hausman test rejects the
        whitened estimator). Opt-in: on rec15_d1 it accepted the true offset and then two stand-ins — the plug-in
        bandwidth under-corrects a residual that is mostly a missing effect (docs/discovery.md, *Open problems*)."""
        ev = self.evidence(small, large, WHITE)
        ev.noise, ev.inference, ev.drift = noise, "least squares (HAC)", drift
        r1, J1 = self.residual_and_jacobian(large)
        if not (np.all(np.isfinite(r1)) and ev.sse1_w > 0 and np.isfinite(ev.sse0_w)):
            return ev
        new = [j for j, nm in enumerate(large.free) if nm not in set(small.free)]
        c = serial_ratio(r1, J1, new)["ratio"]
        k, n = max(len(new), 1), self.model.n
        F = ev.F / c
        p = float(stats.f.sf(F, k, max(n - len(large.free), 1))) if F > 0 else 1.0
        n_eff = n / c
        ev.F = ev.F_robust = F
        ev.p_value = ev.p_robust = p
        ev.hc_ratio, ev.hc_variance = c, "serial (HAC)"
        ev.delta_bic = float(n_eff * np.log(ev.sse1_w / ev.sse0_w) + k * np.log(n_eff))
        ev.checks.update(f_test=p < self.level, robust_f_test=p < self.level, bic=ev.delta_bic < 0)
        return ev

    def _reported_gain(self, small: Fit, large: Fit) -> bool:
        """The F-test of the loop's own two fits, on their SSEs as they were minimised (:func:`loop_sse`)."""
        return bool(f_test(*loop_sse(small, large), len(large.free) - len(small.free), self.model.n,
                           len(large.free))[1] < self.level)

    def evidence(self, small: Fit, large: Fit, noise: NoiseModel | None = None) -> Evidence:
        """The case for ``large`` (more free parameters) against ``small``, both fitted under ``noise``
        (default: the model's current noise model)."""
        r0, J0 = self.residual_and_jacobian(small)
        r1, J1 = self.residual_and_jacobian(large)
        k = max(len(large.free) - len(small.free), 1)
        if not (np.all(np.isfinite(r1)) and np.all(np.isfinite(r0))):
            nm = NoiseModel(note="a residual is not finite")
            return Evidence(nm, 0.0, 1.0, float("inf"), np.inf, np.inf, np.inf, np.inf,
                            checks={"f_test": False})
        noise = self.model.noise if noise is None else noise
        c = compare(noise, r0, r1, k, len(large.free))
        oos = out_of_sample(noise, r0, J0, r1, J1, self.s.cv_block, self.s.cv_folds, self.s.cv_rcond)
        new = [j for j, nm in enumerate(large.free) if nm not in set(small.free)]
        rob = robust_f(c["F"], noise, r1, J1, new, change=r0 - r1, level=self.level_basis(large))
        ev = Evidence(noise, c["F"], c["p_value"], c["delta_bic"], oos["cv0"], oos["cv1"], c["sse0_w"], c["sse1_w"],
                      F_robust=rob["F"], p_robust=rob["p_value"], hc_ratio=rob["ratio"], hc_variance=rob["variance"],
                      cv_z=oos["z"], cv_p=oos["p_value"], level=self.level)
        ev.checks = {"f_test": c["p_value"] < self.level, "robust_f_test": rob["p_value"] < self.level,
                     "bic": c["delta_bic"] < 0, "cross_validation": oos["p_value"] < self.s.cv_alpha}
        if self.validation is not None:
            ev.validation0, ev.validation1 = self.validation_sse(small), self.validation_sse(large)
            ev.checks["validation_record"] = bool(ev.validation1 < ev.validation0)
        return ev


def loop_sse(small: Fit, large: Fit) -> tuple[float, float]:
    """The two fits' SSEs as the loop minimised them: prewhitened when both were fitted under one noise model
    (``discover.prediction_error``), else raw (least squares)."""
    if small.minimised_under == large.minimised_under:
        return small.sse, large.sse
    return tuple(f.raw_sse if f.raw_sse is not None else f.sse for f in (small, large))


def in_sample_summary(ev: Evidence, n: int) -> dict:
    """In- and out-of-sample error of the two models of a comparison, per sample (whitened units, m)."""
    return {"in_sample_rms_w_before": float(np.sqrt(ev.sse0_w / n)), "in_sample_rms_w_after": float(np.sqrt(ev.sse1_w / n)),
            "out_of_sample_rms_w_before": float(np.sqrt(ev.cv0 / n)), "out_of_sample_rms_w_after": float(np.sqrt(ev.cv1 / n))}


def names_without(free: Sequence[str], drop: Sequence[str]) -> tuple[str, ...]:
    d = set(drop)
    return tuple(nm for nm in free if nm not in d)
