"""The toggle mechanism as a plant of the discovery engine (:class:`.engine.Plant`): the baseline polish, the
forward step (scores, scouts, refits and their guards), the refits without an effect, the structure test and the
catch-all check. :func:`.loop.discover` runs the engine's loop over it."""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from ..effects import ALL_INDEX, EFFECTS_BY_NAME, Effect
from ..errors import DataError
from ..fast import difference_noise
from ..residuals import glitch_text
from .catchall import (accepted_beside, beside_generic, catch_all, model_state, reading_needed, removal_verdict,
                       reusable)
from .engine import Step
from .gauge import domains_in_gauge, gauge_scales, in_gauge_of
from .model import Fit, Model, _with, fit_free, revived
from .noise import WHITE, fit_noise, prediction_error_drift
from .periodic import implausible, turns, whole_count, whole_counts
from .forward import _iteration, _polish_with_effect, rescreened, widened_at_edge
from .refit import Refit, without_effect
from .residual import (fitting_noise, prediction_report, residual_report, residual_structure_energy,
                       structure_energy_of)
from .scoring import CandidateScore
from .settings import DiscoverSettings
from .validation import Evidence, Judge


class TogglePlant:
    """The toggle plant (see the module; the forward step: :func:`.forward._iteration`). Keeps what the report needs:
    the baseline (updated when a guard finds a better nominal optimum before any effect is added), the first
    iteration's scores, every iteration's record and every refit."""

    stage = "iteration"

    def __init__(self, model: Model, judge: Judge, settings: DiscoverSettings, theta: np.ndarray,
                 starts: Sequence[np.ndarray], free: Sequence[str], held: Sequence[str], pool: Sequence[Effect],
                 split: int | None, say: Callable[[str], None], on_refit: Callable[[Refit], None] | None,
                 reference: np.ndarray | None = None, domains: Mapping[str, Sequence[float]] | None = None) -> None:
        self.model, self.referee, self.s = model, judge, settings
        #: the values whose scale the report states force-type magnitudes at (:func:`.gauge.gauge_fix`), the effect
        #: domains a user gave (at that scale), and the effects' domains in this route's gauge (:meth:`_in_gauge`)
        self.reference, self.domains, self.gauge_bounds = reference, dict(domains or {}), dict(domains or {})
        self.theta, self.starts, self.free, self.held, self.pool, self.split = theta, starts, free, held, pool, split
        self._say, self.on_refit = say, on_refit
        self.baseline_fit: Fit | None = None
        self.anchor = theta
        self.noise0 = None
        self.first_scores: list[CandidateScore] | None = None
        self.iterations: list[dict] = []
        self.all_refits: list[Refit] = []
        self.catch_report: dict | None = None
        #: the catch-all's report-only fits of a model (second look): the model, its report, its fits (the ``store`` of
        #: :func:`.catchall.catch_all`) and the model's state (:func:`.catchall.model_state`) they were made in — None
        #: when it changed while they ran, and the final check cannot take them over
        self._looked: tuple[Fit, dict, dict, tuple | None] | None = None
        self._structure: tuple[Fit, tuple] | None = None  # the structure test of the latest model asked about
        #: the magnitudes whose domain in the loop's gauge was widened at its edge (:func:`.forward.widened_at_edge`)
        self.widened: dict[str, tuple[float, float]] = {}
        #: the noise model the loop's fits minimise under (white: least squares; ``prediction_error``: the AR model
        #: of the current model's residual less its structure, :func:`.residual.fitting_noise`)
        self.fit_noise = WHITE
        #: the loop's fits by the set of effects they have: a model refitted without an effect starts from there too
        self.had: dict[frozenset, Fit] = {}

    @property
    def has_validation(self) -> bool:
        return self.referee.validation is not None

    def say(self, msg: str) -> None:
        self._say(msg)

    def baseline(self) -> Fit:
        """The nominal model polished from every start (once: a route's baseline is looked at before its loop); with
        ``prediction_error``, polished again under the noise model of its residual (:meth:`_under`)."""
        if self.baseline_fit is not None:
            self._fitting()
            return self.baseline_fit
        self.model.noise = self.fit_noise = WHITE
        self.model.gauge_bounds = self.gauge_bounds = dict(self.domains)
        with self.model.clock("baseline polish"):
            self.baseline_fit, self.anchor = _baseline(self.model, self.theta, self.starts, self.free, self.s,
                                                       self.say)
        if self.s.glitch_k > 0 and self.referee.glitches is None and self.referee.leave_out_glitches(
                self.baseline_fit.theta):
            # looked for in the residual of a fitted model (a far nominal start leaves residuals of millimetres
            # whose few sharp samples can look alone), once for every route; the baseline fitted again without them
            for g in self.referee.glitches:
                if g["count"]:
                    self.say(f"glitches of the measurement in {g['record']} (each alone, up to "
                             f"{max(abs(v) for v in g['residual_m']) * 1e6:.3g} µm off its neighbours' path), left "
                             f"out of every fit and test: {glitch_text(g)}")
            starts = self.baseline_fit.info.get("starts")
            self.baseline_fit = fit_free(self.model, self.baseline_fit.theta, self.baseline_fit.free,
                                         self.s.baseline_nfev, self.s.fd_rel_step, rounds=self.s.rounds)
            self.baseline_fit.info["starts"] = starts
            self.say(f"  baseline without them: rms {self.baseline_fit.rmse(self.model.n) * 1e6:.4g} µm")
        self._in_gauge(self.baseline_fit)
        self.noise0 = fit_noise(self.model.residuals(self.baseline_fit.theta[None, :])[0], self.s.noise_max_order)
        self.say(f"noise model of the nominal residual: {self.noise0.describe()}")
        if self.s.prediction_error:
            self.baseline_fit = self._under(self.baseline_fit)
        return self.baseline_fit

    def _fitting(self) -> None:
        """The model's fits minimise under this route's noise model and keep to its gauge's domains (routes share
        the model)."""
        self.model.noise = self.fit_noise
        self.model.gauge_bounds = self.gauge_bounds

    def _in_gauge(self, fit: Fit) -> None:
        """The effects' feasible domains in the gauge of ``fit`` (the baseline, whose gauge parameters the loop
        holds): the library's at the reference scale (:func:`.gauge.domains_in_gauge`); the library's as they are
        without a reference or where the scales cannot be read (a gauge parameter not positive). The domains a
        user gave (``domains``) take the library's place."""
        scales = gauge_scales(fit.theta, tuple(fit.free) + tuple(self.held), self.reference) \
            if self.reference is not None and self.s.gauge else None
        self.model.gauge_bounds = self.gauge_bounds = domains_in_gauge(*scales, self.domains) \
            if scales is not None else dict(self.domains)
        if scales is not None and any(abs(np.log(c)) > 1e-9 for c in scales):
            self.say(f"  gauge of the baseline: mechanism ×{1 / scales[0]:.4g}, current ×{1 / scales[1]:.4g} the "
                     f"reference scale; the effects' domains read there")

    def _under(self, fit: Fit) -> Fit:
        """``fit`` polished again the prediction-error way under the noise model of its residual
        (:func:`.residual.fitting_noise`), which the loop's fits use from now on; ``fit`` itself when that model
        is the one it was fitted under, or white and ``fit`` a least-squares fit."""
        with self.model.clock("prediction-error refits"):
            noise = fitting_noise(self.model, fit.theta, self.s)
            self.model.noise = self.fit_noise = noise
            if noise.a == fit.minimised_under:
                return fit
            out = fit_free(self.model, fit.theta, fit.free, self.s.baseline_nfev, self.s.fd_rel_step,
                           rounds=self.s.rounds)
        out.info["starts"] = fit.info.get("starts")
        drift = prediction_error_drift(fit, out, noise, self.s.pe_guard_alpha)
        if drift is not None:  # the noise model holds what the model lacks: least squares (asked again next model)
            self.model.noise = self.fit_noise = WHITE
            self.say(f"  prediction-error fit under {noise.describe()} refused: {drift}; this model stays fitted "
                     "by least squares")
            return fit
        self.say(f"  prediction-error fit under the noise model of its residual less what the states express, "
                 f"{noise.describe()}: rms {out.rmse(self.model.n) * 1e6:.4g} µm (before "
                 f"{fit.rmse(self.model.n) * 1e6:.4g} µm)")
        return out

    def _other_starts(self) -> tuple[list[np.ndarray], float]:
        """The baseline's starts moved into its gauge — the one it came from last: with an effect on, its polish may
        reach another basin (rec15_d1, docs/discovery.md) — and the record's own noise (m, its third differences),
        for the searches from the other starts (``other_starts_above``); none when that is off."""
        if not self.s.other_starts_above > 0:
            return [], 0.0
        moved = [th for th in (in_gauge_of(th, self.anchor) for th in (self.theta, *self.starts)) if th is not None]
        own = [th for th in moved if np.allclose(th, self.anchor, rtol=1e-9, atol=0.0)]
        others = [th for th in moved if not np.allclose(th, self.anchor, rtol=1e-9, atol=0.0)] + own[:1]
        return (others, difference_noise([self.model.record])) if others else ([], 0.0)

    def remaining(self, added: Sequence[dict]) -> list[Effect]:
        return [e for e in self.pool if e.name not in {a["name"] for a in added}]

    def forward_step(self, current: Fit, added: Sequence[dict], iteration: int) -> Step:
        n = self.model.n
        self._fitting()
        remaining = self.remaining(added)
        # the step picks the best of the candidates left: its F-tests at alpha over their number (Bonferroni)
        self.referee.family = len(remaining) if self.s.bonferroni else 1
        try:
            step = _iteration(self.model, self.referee, current, self.anchor, self.free, remaining, self.s,
                              iteration, self.held, self.say, self.on_refit, self.missing_kinds,
                              self._beside if self.s.beside_generic else None, *self._other_starts())
        finally:
            self.referee.family = 1
        self.gauge_bounds = self.model.gauge_bounds  # (widened where a find from another start needs the room)
        self.all_refits.extend(step["refits"])
        if self.first_scores is None:
            self.first_scores = step["scores"]
        base = step["base"]  # the current model, or a better optimum of it found by a guard re-polish
        if step["better_null"] is not None and not added:  # a better nominal optimum: the error "before" is its
            self.baseline_fit = base
        self.iterations.append(step["record"])
        self.had[frozenset(a["name"] for a in added)] = base
        chosen = step["chosen"]
        if chosen is None:
            return Step(base)
        if self.s.prediction_error and chosen.fit.noise is not None and chosen.fit.noise.a != self.fit_noise.a:
            # fitted under the noise model of its own residual (the dismissed candidates' search from the other
            # starts, :func:`.refit.from_other_starts`): the loop's fits minimise under that one from here, as they
            # would once the effect is added — under the old one, fitted to a residual the effect dominated, the
            # polish can whiten the effect away again
            self.model.noise = self.fit_noise = chosen.fit.noise
        names = [chosen.name] + ([chosen.partner] if chosen.partner else [])  # a pair adds both (:mod:`.pairs`)
        whole = {k: v for nm in names for k, v in whole_counts(nm, chosen.fit.theta, chosen.fit.free,
                                                                self.s.cogging_whole_tol).items()}
        screened = []
        with self.model.clock("polish with the added effect"):
            after = _polish_with_effect(self.model, chosen, self.anchor, self.free, self.s, self.say, hold=whole)
            for nm in names:
                after, wide = widened_at_edge(self.model, nm, after, self.s, self.say, self.domains)
                self.gauge_bounds = self.model.gauge_bounds
                self.widened.update(wide)
                after, more = rescreened(self.model, nm, after, self.s, self.say)
                screened += more
        if self.s.prediction_error:  # the noise model again, from the residual of the model with the effect
            after = self._under(after)
        item = {"name": chosen.name, "iteration": iteration, "F": chosen.F, "p_value": chosen.p_value,
                "delta_bic": chosen.delta_bic, "rmse_after_m": after.rmse(n), "params_at_acceptance": chosen.params,
                "evidence": chosen.evidence, "indistinguishable_from": step["rivals"]}
        if screened:
            item["rescreened"] = screened
        if whole:  # counts held at their whole numbers from here on
            item["held_whole"] = {nm: {"fitted": chosen.params[nm], "held_at": k, "rmse_free_m": chosen.fit.rmse(n),
                                       "rmse_held_m": after.rmse(n)} for nm, k in whole.items()}
        self.had[frozenset(a["name"] for a in added) | set(names)] = after
        self.say(f"added {' and '.join(names)} "
                 + ", ".join(f"{p} {after.theta[ALL_INDEX[p]]:.4g}" for nm in names for p in EFFECTS_BY_NAME[nm].names)
                 + f"; rms {after.rmse(n) * 1e6:.4g} µm")
        if chosen.partner is None:
            return Step(base, item, after)
        item["added_with"] = chosen.partner
        second = {**item, "name": chosen.partner, "added_with": chosen.name,
                  "params_at_acceptance": {p: chosen.params[p] for p in EFFECTS_BY_NAME[chosen.partner].names}}
        item["params_at_acceptance"] = {p: chosen.params[p] for p in EFFECTS_BY_NAME[chosen.name].names}
        return Step(base, item, after, more=[second])

    def without(self, current: Fit, a: dict | None, added: Sequence[dict], rival: dict | None = None) -> Fit:
        self._fitting()
        had = self.had.get(frozenset(b["name"] for b in added) - {a["name"]}) if a and rival is None else None
        return without_effect(self.model, current, a and a["name"], added, self.held, self.s, rival, had)

    def judge(self, small: Fit, large: Fit) -> Evidence:
        return self.referee.judge_pair(small, large)

    def judge_removal(self, small: Fit, large: Fit, a: dict):
        """Backward elimination's verdict on removing ``a`` (:func:`.catchall.removal_verdict`: an effect accepted
        beside the generic terms is judged as it was accepted)."""
        return removal_verdict(self.judge(small, large), a)

    def residual(self, fit: Fit) -> np.ndarray:
        return self.referee.residual(fit)

    def n_free(self, fit: Fit) -> int:
        return len(fit.free)

    def summary(self, fit: Fit) -> dict:
        return {"rmse_m": fit.rmse(self.model.n)}

    def error_text(self, fit: Fit) -> str:
        return f"rms {fit.rmse(self.model.n) * 1e6:.4g} µm"

    def keep(self, a: dict, added: Sequence[dict]) -> bool:
        return False  # no effect of the toggle library refines another

    def own_signature(self, current: Fit, a: dict) -> str | None:
        """Why an accepted effect ``a`` that removed little of the structure energy explains all the same (None: it
        does not). A cogging torque: its ripple, periodic in the motor angle, is what the structure test's position,
        velocity, current and input bins cannot see, so beside an effect the library lacks its share of that energy
        says nothing (rec37 of the adversarial set: −4 % beside a friction bump). It explains when the residual of the
        final model without it (refitted) repeats at its whole count per revolution n_cog (within
        ``cogging_whole_tol``), significantly after the periodic look's scan (:func:`.periodic.periodic`), over at
        least ``signature_min_periods`` periods of the motor angle's range (rec37: 14.7 rad, 14 periods at n_cog = 6) —
        a localised error fits a low count over a few periods only (rec01: 1.11 per revolution, 2.6 periods) — and the
        residual with it repeats at no such count. Where the residual without it repeats at no such count, it may
        still hold the ripple under the missing physics' misfit (rec38: a quadratic drag's 3 µm beside a cogging at
        6 per revolution): the cogging goes on, marked ``hidden_ripple`` on ``a``, to the catch-all check, which keeps
        it where it is still needed beside the generic terms (:meth:`explains`), as it does one accepted beside them.
        Measured on rec38: the periodic look does not find the ripple in the residual of the generic terms' fit
        without the cogging either (1.609 against 1.126 µm with it, under that residual's AR noise model), so no
        periodic look is asked of it there; the catch-all's prewhitened, robust and out-of-sample tests decide.

        An effect accepted beside the generic terms (``discover.beside_generic``: its evidence holds
        ``beside_generic``) explains in the same way: the structure energy of the models without those terms is the
        missing physics' misfit, which the effect was never asked to remove; it goes on to the catch-all check
        (:meth:`explains`), which judges it beside them again (rec38 of the adversarial set: a cogging torque beside a
        quadratic drag, demoted at −0 % of that energy)."""
        beside = accepted_beside(a)
        if beside is not None:
            return ("removed little of the structure energy, which the physics the library lacks fills, but was "
                    "accepted beside a generic slider force and reading error that take that physics ("
                    + beside["reason"] + "): judged beside them, by the catch-all check")
        reduced = a.get("_reduced")
        if a["name"] != "cogging_torque" or reduced is None or not np.all(np.isfinite(reduced.theta)):
            return None
        n = float(current.theta[ALL_INDEX["n_cog"]])
        if whole_count(n, self.s.cogging_whole_tol) is None:
            return None
        # the final model first: the engine has just looked at it, so its report is still at hand
        if self._ripple(current, n)[0]:
            return None
        without, periods = self._ripple(reduced, n)
        if periods < self.s.signature_min_periods:
            return None
        if not without:
            # the residual without it holds the missing physics' misfit too, which can hide the ripple from the
            # periodic look (rec38: a quadratic drag's 3 µm beside a 6-per-revolution cogging, under an AR(8) noise
            # model fitted to that residual); the catch-all check takes that physics with its generic terms and
            # judges the cogging beside them, as it judges one accepted there
            a["hidden_ripple"] = n
            return (f"removed little of the structure energy, whose position bins cannot see a ripple; without it the "
                    f"residual repeats at no count near n_cog = {n:.3g}, but it holds what the library lacks too: "
                    "judged beside a generic slider force and reading error that take that, by the catch-all check")
        return (f"removed little of the structure energy, whose position bins cannot see a ripple, but without it the "
                f"residual repeats {without['repeats']} over {periods:.0f} periods of its range, and with it at no "
                f"count near n_cog = {n:.3g}: it explains the ripple, beside something the library lacks")

    def _ripple(self, fit: Fit, n: float) -> tuple[dict, float]:
        """The periodic look's motor-angle family of ``fit``'s residual where it repeats significantly (after the
        scan) within ``cogging_whole_tol`` of ``n`` times per revolution (else {}), and the periods of that count the
        record's motor-angle range holds."""
        diag, _, states = self.structure(fit)[1]
        fam = ((diag.get("periodic") or {}).get("families") or {}).get("motor_angle") or {}
        revs = turns(states["motor_angle"]) if states and "motor_angle" in states else 0.0
        at_n = bool(fam.get("significant")) and \
            abs(float(fam.get("cycles_per_revolution") or 0.0) - n) <= self.s.cogging_whole_tol
        return (fam if at_n else {}), revs * n

    def structure(self, fit: Fit) -> tuple[bool, tuple]:
        if self._structure is None or self._structure[0] is not fit:
            diag, r, states = residual_report(self.model, fit.theta, self.s, self.split,
                                              self.referee.residual_and_jacobian(fit)[1], fit.free,
                                              fit.noise)
            self._structure = fit, (bool(diag.get("verdict", {}).get("structure_left", False)), (diag, r, states))
        return self._structure[1]

    def structure_energy(self, fit: Fit, details: tuple | None = None) -> float:
        if details is not None:
            return structure_energy_of(self.model, details[1], details[2], self.s)
        return residual_structure_energy(self.model, fit.theta, self.s)

    def implausible(self, current: Fit, added: Sequence[dict]) -> list[dict]:
        """The accepted effects whose fitted values no machine has (:func:`implausible`), each with its reason."""
        odd = [dict(a, reason=why) for a in added
               if (why := implausible(a["name"], current.theta, self.s.cogging_whole_tol))]
        for a in odd:
            self.say(f"{a['name']}: {a['reason']}")
        return odd

    def explains(self, current: Fit, added: list[dict], details: tuple, everyone: Sequence[dict]
                 ) -> tuple[list[dict], list[dict]]:
        """The catch-all check (:func:`.catchall.catch_all`): an effect that a force of unknown shape on slider B
        makes unnecessary is compensating (the engine took out those no machine has first: :meth:`implausible`).
        Before it: when the residual's noise model is too slow to be told from a slow error of the model
        (:func:`.residual.slow_noise`), every effect is compensating — the statistics that accepted it were
        prewhitened by a noise model that may hold the error it stands in for (rec28 of the adversarial set) —
        except an effect kept for its own fast signature (:meth:`own_signature`: a ripple over ten periods and more
        of its range, tested under that same noise model), which no slow error stands in for: it goes on to the
        catch-all check (rec37: its cogging, beside a friction bump that leaves 35 of 5001 samples independent).
        The ties of an effect it keeps are judged there too, each rival in the effect's place (``with_rival``)."""
        slow = (details[0] or {}).get("slow_noise") or {}
        doubted: list[dict] = []
        if slow.get("slow") and added:
            why = (f"lowers the error, but was accepted under a noise model that leaves "
                   f"{slow['effective_samples']} samples independent: an error the model lacks and slow noise "
                   "cannot be told apart on this record")
            doubted = [dict(a, reason=why) for a in added if not a.get("own_signature")]
            added = [a for a in added if a.get("own_signature")]
            if doubted:
                self.say(f"{', '.join(a['name'] for a in doubted)}: {why}")
        if not added:
            return [], doubted
        self._fitting()
        states = details[2]
        if not (self.s.catch_all and states):
            # a cogging sent here to be judged beside the generic terms (own_signature: its ripple hidden) cannot be
            # judged without them: not kept
            hidden = [dict(a, reason="lowers the error, but its ripple is hidden under what the library lacks, and "
                                     "without the catch-all check (discover.catch_all) nothing can take that apart")
                      for a in added if a.get("hidden_ripple")]
            return [a for a in added if not a.get("hidden_ripple")], doubted + hidden

        added, more, self.catch_report = catch_all(
            self.model, self.referee, current, added, states, lambda fit, a: self.without(fit, a, everyone), self.s,
            self.say, with_rival=lambda fit, rival: self.without(fit, None, everyone, rival),
            looked=self._looked_pair(current))
        return added, doubted + more

    def _looked_pair(self, fit: Fit) -> tuple[Fit, Fit] | None:
        """The generic force and reading-error fits of the second look (:meth:`_catch_all_alone`) when they were made
        on ``fit`` itself with the model in the state it is in now (:func:`.catchall.reusable`)."""
        if self._looked is None or self._looked[3] is None:
            return None
        seen, _, fits, state = self._looked
        return (fits["force"], fits["both"]) if reusable(seen, fit, state, self.model) else None

    def missing_kinds(self, fit: Fit) -> set[str]:
        """The kinds of effect (:attr:`~toggle_id.effects.Effect.acts_on`) that a generic term of the catch-all check
        finds missing from ``fit``: ``slider`` when the generic force is supported on top of it, with ``reading``
        when the generic error of the reading is needed beside the force; none when its residual holds no
        structure (the forward step's second look: :func:`.forward._iteration`)."""
        left, details = self.structure(fit)
        if not (self.s.catch_all and left and details[2]):
            return set()
        report = self._catch_all_alone(fit, details[2])
        return ({"slider", "reading"} if reading_needed(report) else {"slider"}) if report["supported"] else set()

    def describe_missing(self, current: Fit, details: tuple) -> None:
        """With structure left in the final model and no catch-all report yet (nothing was accepted for it to check),
        the catch-all's fits alone: whether what is missing acts like a force on the slider or an error of the
        reading, or like neither (report-only; :attr:`catch_report`; fitted once per model)."""
        states = details[2] if details else None
        if self.s.catch_all and states and self.catch_report is None:
            self.catch_report = self._catch_all_alone(current, states)

    def _catch_all_alone(self, fit: Fit, states: dict) -> dict:
        """The catch-all's report on ``fit`` with no effect to check (fitted once per model; the fit with the
        generic terms kept beside it)."""
        self._fitting()
        if self._looked is None or self._looked[0] is not fit:
            store: dict = {}
            before = model_state(self.model)
            with self.model.clock("catch-all fits"):
                report = catch_all(self.model, self.referee, fit, [], states, lambda f, a: f, self.s, self.say,
                                   store)[2]
            # a set marked stiff during the fits would send the same fits to another integrator next time
            self._looked = fit, report, store, before if model_state(self.model) == before else None
        return self._looked[1]

    def _beside(self, base: Fit, scouts: list) -> list[Refit]:
        """The forward step's third look (``discover.beside_generic``): with nothing supported and the catch-all's
        generic terms supported on ``base``, the effects of ``scouts`` refitted beside them
        (:func:`.catchall.beside_generic`)."""
        if not (scouts and self.missing_kinds(base)) or self._looked is None or "generic" not in self._looked[2]:
            return []
        self.say("  nothing supported, and the generic terms explain what is left: refitting "
                 + ", ".join(sc.name for sc in scouts) + " beside them")
        return beside_generic(self.model, self.referee, base, self._looked[2]["generic"], scouts, self.s, self.held,
                              len(self.iterations) + 1, self.say)

    def demote(self, current: Fit, demoted: Sequence[dict], added: Sequence[dict]) -> Fit:
        """The final model without the compensating effects: the baseline when none explains, else refitted."""
        self._fitting()
        if not added:
            return self.baseline_fit
        names = [c["name"] for c in demoted]
        return fit_free(self.model, _with(current.theta, {p.name: p.off for nm in names
                                                          for p in EFFECTS_BY_NAME[nm].params}),
                        tuple(nm for nm in current.free if not any(nm in EFFECTS_BY_NAME[d].names for d in names)),
                        self.s.baseline_nfev, self.s.fd_rel_step, rounds=self.s.rounds)

    def validation_residual(self, fit: Fit) -> np.ndarray:
        return self.referee.validation.residuals(fit.theta[None, :])[0]

    def validation_structure(self, fit: Fit) -> bool:
        """Structure left in the prediction of the validation record, not all of it within the uncertainty of the
        parameters fitted on the record (:func:`.residual.prediction_report`), and an error more than
        ``validation_material`` times the fitted record's. An error in the span of the parameters' sensitivities
        but beyond their uncertainty counts: on rec28 a stand-in left 7.70 µm there, 7.64 µm of it in that span
        (Mahalanobis 750 on 15 dof) — parameters that do not carry over, or an effect they mimic on one command and
        not on the other."""
        r = self.referee.residual(fit)
        pred = prediction_report(self.referee.validation, fit.theta, self.s,
                                 (self.model, fit.free, r, fit_noise(r, self.s.noise_max_order)))
        return bool(pred["structure_left"]
                    and pred.get("rmse_m", np.inf) > self.s.validation_material * fit.rmse(self.model.n))

    def validation_structure_energy(self, fit: Fit) -> float:
        return residual_structure_energy(self.referee.validation, fit.theta, self.s)


def _baseline(model: Model, theta: np.ndarray, others: Sequence[np.ndarray], free: Sequence[str],
              settings: DiscoverSettings, say: Callable[[str], None]) -> tuple[Fit, np.ndarray]:
    """The nominal model polished on the whole record from every start; the best and its start."""
    n = model.n
    current, anchor, report = None, theta, []
    anchors = [theta, *others]
    anchors += [th for th in (revived(a, free) for a in list(anchors)) if th is not None]  # collapsed parameters
    for k, th0 in enumerate(anchors):
        if not np.all(np.isfinite(model.residuals(th0[None, :])[0])):
            report.append({"start": k, "error": "cannot be simulated on this record"})
            continue
        say(f"baseline polish of {len(free)} parameters on {n} samples (start {k + 1} of {len(anchors)})")
        fit = fit_free(model, th0, free, settings.baseline_nfev, settings.fd_rel_step, rounds=settings.rounds)
        report.append({"start": k, "rmse_m": fit.rmse(n), "nfev": fit.info["nfev"]})
        say(f"  rms {fit.rmse(n) * 1e6:.4g} µm ({fit.info['nfev']} evaluations, {fit.info['seconds']:.1f} s)")
        if current is None or fit.sse < current.sse:
            current, anchor = fit, th0
    if current is None:
        raise DataError("the nominal model cannot be simulated on this record from any start; fit it first")
    current.info["starts"] = report
    return current, anchor
