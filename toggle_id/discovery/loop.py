"""The discovery loop (see the package docstring)."""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from scipy import stats

from .. import params as P
from ..effects import ALL_INDEX, EFFECTS, EFFECTS_BY_NAME, Effect
from ..errors import ConfigError, DataError
from ..polish import one_blas_thread
from ..identify import IdentificationResult
from ..plant import GEOMETRY
from ..record import Record
from ..simulate import PRECISE, extend
from .gauge import GAUGE_HELD, _force_like, current_power, freed_with, gauge_fix, gauge_symmetries
from .model import Fit, Model, _off_values, _with, fit_free, parameter_uncertainty, revived
from .refit import Refit, guard_null, refit_candidate, scout_candidate
from .report import DiscoveryResult, _conclusion
from .scoring import CandidateScore, assess
from .settings import DiscoverSettings
from .catchall import catch_all
from .engine import (backward_eliminate, indistinguishable, reconsider_ties, settle_ties_out_of_sample,
                     split_explaining, tie_band)
from .residual import prediction_report, residual_report, residual_structure_energy, structure_energy_of
from .noise import WHITE, fit_noise
from .stats import f_test
from .validation import Judge

log = logging.getLogger("toggle_id")


def _nominal_theta(nominal: IdentificationResult | np.ndarray | Mapping[str, float] | None) -> np.ndarray:
    theta = extend(P.ASSIGNED)[0]
    if nominal is None:
        return theta
    if isinstance(nominal, IdentificationResult):
        return extend(np.asarray(nominal.theta, float))[0]
    if isinstance(nominal, Mapping):
        return _with(theta, nominal)
    return extend(np.asarray(nominal, float))[0]


@one_blas_thread
def discover(record: Record, *, nominal: IdentificationResult | np.ndarray | Mapping[str, float] | None = None,
             effects: Sequence[Effect] = EFFECTS, settings: DiscoverSettings | None = None,
             free: Sequence[str] | None = None, fixed: Mapping[str, float] | None = None,
             starts: Sequence[np.ndarray | Mapping[str, float]] = (),
             reference: np.ndarray | Mapping[str, float] | None = None, validation: Record | None = None,
             on_refit: Callable[[Refit], None] | None = None, progress: Callable[[str], None] | None = None
             ) -> DiscoveryResult:
    """Run the discovery loop on ``record`` (see the package docstring).

    nominal: the nominal fit (an :class:`IdentificationResult`, an extended/physical vector or a name → value
        mapping; None: the assigned values) — the loop starts by polishing it on the whole record.
    effects: the candidate library (default all of :data:`toggle_id.effects.EFFECTS`), filtered by
        ``settings.candidates``. free: nominal parameters fitted (default the 15 physical ones minus
        ``fixed``); fixed: parameters held at given values. starts: further starting points of the baseline
        polish (e.g. the assigned values beside a GA result); the best polished one is the baseline.
    reference: the values the reported parameters are brought closest to along the exact symmetries of the
        output (:func:`gauge_fix`; default the assigned values) — it fixes the otherwise arbitrary scale of the
        mechanism, and with it the magnitude of force-type effects.
    validation: a second record of the same machine, never fitted: an effect must predict it better too.
    on_refit: called with every :class:`Refit` (e.g. to log an MLflow child run); progress: one-line messages.
    """
    settings = (settings or DiscoverSettings()).validate()
    say = progress or (lambda msg: log.info(msg))
    t_start = time.perf_counter()
    model = Model(record, PRECISE, settings.parallel, jacobian=settings.jacobian)
    judge = Judge(model, settings, validation)
    fixed = dict(fixed or {})
    for k in fixed:
        if k not in ALL_INDEX:
            raise ConfigError(f"fixed: unknown parameter {k!r}")
    theta = _with(_nominal_theta(nominal), fixed)
    free = tuple(free) if free is not None else tuple(n for n in P.PARAM_NAMES if n not in fixed)
    for k in free:
        if k not in ALL_INDEX:
            raise ConfigError(f"unknown free parameter {k!r}")
    pool = [e for e in effects if settings.candidates is None or e.name in settings.candidates]
    pool = [e for e in pool if not any(p in free or p in fixed for p in e.names)]
    # one parameter per exact symmetry of x_B held during the polishes (the gauge): same fits, no flat directions
    held = tuple(GAUGE_HELD[s] for s in gauge_symmetries(free)) if settings.hold_gauge else ()
    free = tuple(nm for nm in free if nm not in held)
    split = record.clamp_index(GEOMETRY.x_B_L)
    split = split if 0 < split < record.n else None
    n = record.n

    model.noise = WHITE
    baseline, anchor = _baseline(model, theta, [_with(_nominal_theta(st), fixed) for st in starts], free,
                                 settings, say)
    noise0 = fit_noise(model.residuals(baseline.theta[None, :])[0], settings.noise_max_order)
    say(f"noise model of the nominal residual: {noise0.describe()}")
    current = baseline
    iterations: list[dict] = []
    added: list[dict] = []
    first_scores: list[CandidateScore] | None = None
    all_refits: list[Refit] = []
    for it in range(1, settings.max_effects + 1):
        remaining = [e for e in pool if e.name not in {a["name"] for a in added}]
        if not remaining:
            break
        step = _iteration(model, judge, current, anchor, free, remaining, settings, it, held, say, on_refit)
        all_refits.extend(step["refits"])
        if first_scores is None:
            first_scores = step["scores"]
        current = step["base"]  # the current model, or a better optimum of it found by a guard re-polish
        if step["better_null"] is not None and not added:  # a better nominal optimum: the error "before" is its
            baseline = current
        chosen = step["chosen"]
        iterations.append(step["record"])
        if chosen is None:
            break
        current = _polish_with_effect(model, chosen, anchor, free, settings, say)
        added.append({"name": chosen.name, "iteration": it, "F": chosen.F, "p_value": chosen.p_value,
                      "delta_bic": chosen.delta_bic, "rmse_after_m": current.rmse(n),
                      "params_at_acceptance": chosen.params, "evidence": chosen.evidence,
                      "indistinguishable_from": step["rivals"]})
        say(f"added {chosen.name} {chosen.params}; rms {current.rmse(n) * 1e6:.4g} µm")

    eliminated: list[dict] = []
    if settings.backward and added:
        current, added, eliminated = _backward(model, judge, current, added, held, settings, say)
    if settings.ambiguity_alpha > 0:
        def swap(cur: Fit, a: dict, rv: dict) -> Fit:
            return _without(model, cur, a["name"], added, held, settings, rv)

        reconsider_ties(current, added, swap, judge.residual, lambda fit: len(fit.free), lambda fit: {"rmse_m": fit.rmse(n)},
                        settings.noise_max_order, settings.ambiguity_alpha, say)
        if judge.validation is not None:
            current = settle_ties_out_of_sample(
                current, added, swap, lambda fit: judge.validation.residuals(fit.theta[None, :])[0], lambda fit: len(fit.free),
                lambda fit: {"rmse_m": fit.rmse(n)}, settings.noise_max_order, settings.ambiguity_alpha, say)

    # the noise-aware structure test decides whether the effects explain the residual or only compensate
    diag_after, r_after, states_after = residual_report(model, current.theta, settings, split)
    structure = bool(diag_after.get("verdict", {}).get("structure_left", False))
    compensating: list[dict] = []
    with_compensating = catch_report = None
    if structure and added:
        # structure is left: an effect explains only if it removed most of the structure energy it was added for,
        # and if it does something a force of unknown shape on slider B would not (the catch-all check)
        e_with = structure_energy_of(model, r_after, states_after, settings)
        all_added = list(added)

        def without(fit: Fit, a: dict) -> Fit:
            return _without(model, fit, a["name"], all_added, held, settings)

        for a in added:  # the final model without each effect (backward elimination has most): both rules use it
            if a.get("_reduced") is None:
                a["_reduced"] = without(current, a)
        added, compensating = split_explaining(
            added, e_with, lambda a: residual_structure_energy(model, a["_reduced"].theta, settings),
            settings.explain_fraction)
        if added and settings.catch_all and states_after:
            added, more, catch_report = catch_all(model, judge, current, added, states_after, without, settings, say)
            compensating += more
        if compensating:
            demoted = [c["name"] for c in compensating]
            say("structure remains; " + ", ".join(demoted) + " lower the error but do not explain it (listed as "
                "compensating, not added)")
            with_compensating = current
            current = baseline if not added else fit_free(
                model, _with(current.theta, {p.name: p.off for nm in demoted for p in EFFECTS_BY_NAME[nm].params}),
                tuple(nm for nm in current.free if not any(nm in EFFECTS_BY_NAME[d].names for d in demoted)),
                settings.baseline_nfev, settings.fd_rel_step, rounds=settings.rounds)
            diag_after, r_after, _ = residual_report(model, current.theta, settings, split)
    for a in added + compensating:
        a.pop("_reduced", None)
    compensating += compensating_refits(all_refits, compensating, added)

    # the representatives of the fits nearest the reference along the exact symmetries (same output)
    ref = _with(_nominal_theta(reference), fixed) if reference is not None else _with(extend(P.ASSIGNED)[0], fixed)
    gauge_before = gauge_after = {"applied": False}
    if settings.gauge:
        broken = {sym for a in added for sym in EFFECTS_BY_NAME[a["name"]].breaks}
        baseline.theta, gauge_before = gauge_fix(model, baseline.theta, baseline.free + held, ref)
        if current is not baseline:
            current.theta, gauge_after = gauge_fix(model, current.theta, tuple(set(current.free) | set(held)), ref,
                                                   broken=broken)
        else:
            gauge_after = gauge_before
    noise_after = fit_noise(model.residuals(current.theta[None, :])[0], settings.noise_max_order)
    uncertainty = parameter_uncertainty(model, current, settings, gauge_after.get("held", ()), noise_after) \
        if added else {}
    _describe_added(added, current, uncertainty, gauge_after)
    # an effect the record cannot tell apart from another supported one is not named as added: the pair is
    # reported as ambiguous (the final model keeps the better-fitting one, for prediction)
    ambiguous = [a for a in added if a.get("indistinguishable_from")]
    added = [a for a in added if not a.get("indistinguishable_from")]
    diag_before, r_before, _ = residual_report(model, baseline.theta, settings, split)
    accepted_names = {a["name"] for a in added}
    ambiguous_names = {nm for a in ambiguous for nm in [a["name"]] + [r["name"] for r in a["indistinguishable_from"]]}
    cands = []
    for c in first_scores or []:
        tried = [rf for rf in all_refits if rf.name == c.name]
        cands.append({**c.to_dict(), "accepted": c.name in accepted_names, "refitted": bool(tried),
                      "refit_p_value": min((rf.p_value for rf in tried), default=None),
                      "verdict": ("accepted" if c.name in accepted_names else
                                  "ambiguous" if c.name in ambiguous_names else
                                  "compensating" if c.name in {x["name"] for x in compensating} else "rejected"),
                      "evidence": tried[-1].evidence if tried else {}})
    why_out = {e["name"]: "eliminated (backward): " + e["reason"] for e in eliminated}
    for rf in all_refits:
        why_out.setdefault(rf.name, rf.reason)
    rejected = [{"name": c["name"], "refitted": c["refitted"],
                 "reason": why_out.get(c["name"], "its scout explains less than the candidates refitted")}
                for c in cands if c["verdict"] == "rejected"]
    unexplained = bool(diag_after.get("verdict", {}).get("structure_left", False))
    # an effect that is real predicts a record it was not fitted on to that record's noise: structure left in the
    # validation record's residual means the model still lacks something, whatever the fitted record says
    predicted = prediction_report(judge.validation, current.theta, settings) if judge.validation else None
    if predicted is not None and predicted.get("structure_left"):
        unexplained = True
    conclusion = _conclusion(added, diag_before, diag_after, unexplained, settings, compensating, predicted,
                             ambiguous, catch_report)
    extra = {"ambiguous": ambiguous, "symmetry_gauge": {"before": gauge_before, "after": gauge_after},
             "identifiability_after": uncertainty,
             "compensating": compensating, "rejected": rejected, "backward_elimination": eliminated,
             "noise_model": {"before": noise0.to_dict(), "after": noise_after.to_dict()},
             "localisation": diag_after.get("localisation"),
             "validation_record": validation.name if validation is not None else None, "catch_all": catch_report,
             "validation_prediction": predicted}
    if with_compensating is not None:
        extra["rmse_with_compensating_m"] = with_compensating.rmse(n)
    return DiscoveryResult(record=record.name, n=n, baseline=baseline, final=current, effects_added=added,
                           candidates=cands, iterations=iterations, diagnostics_before=diag_before,
                           diagnostics_after=diag_after, residual_before=r_before, residual_after=r_after,
                           nominal=nominal.to_dict() if isinstance(nominal, IdentificationResult) else None,
                           conclusion=conclusion, unexplained=unexplained, seconds=time.perf_counter() - t_start,
                           n_simulations=model.n_sims, refits=all_refits, extra=extra)


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


def _iteration(model: Model, judge: Judge, current: Fit, anchor: np.ndarray, free: Sequence[str],
               remaining: Sequence[Effect], settings: DiscoverSettings, it: int, held: Sequence[str],
               say: Callable[[str], None], on_refit: Callable[[Refit], None] | None) -> dict:
    """Scores, scouts and refits of one iteration; the candidate to add (or None)."""
    n = model.n
    noise = fit_noise(model.residuals(current.theta[None, :])[0], settings.noise_max_order)
    points = [assess(model, "current fit", current.theta, current.free, remaining, settings, noise)]
    # second linearisation point: the nominal fit as given, with the effects added so far — the polished fit may
    # have bent the nominal parameters far towards the missing effect, where the local picture is distorted
    alt = _with(anchor, {nm: current.theta[ALL_INDEX[nm]] for nm in current.free if nm not in free})
    if settings.second_point and not np.allclose(alt, current.theta, rtol=1e-3, atol=0.0):
        second = assess(model, "nominal start", alt, current.free, remaining, settings, noise)
        if second is not None:  # (None: the nominal start cannot be simulated with these effects)
            points.append(second)
    scores = list(points[0].scores.values())  # the score tests proper: at the fitted point
    for c in scores:
        for pt in points[1:]:
            c.profile_score_alt = pt.scores[c.name].profile_score
    say("scores (profile | LM, prewhitened): " + ", ".join(
        f"{c.name} {c.profile_score:.3g} | {c.score:.3g}" for c in sorted(scores, key=lambda c: -c.profile_score)))
    screen = float(stats.chi2.isf(settings.screen_alpha, 1))
    here = points[0].scores
    if settings.scout_all:  # global screening: every candidate with a grid is scouted
        screened = [c for c in scores if any(c.name in pt.profiles for pt in points)]
    else:
        screened = [c for c in scores if any(c.name in pt.profiles for pt in points)
                    and (max(here[c.name].profile_score, here[c.name].score) > screen
                         or (c.name not in points[0].profiles
                             and any(pt.scores[c.name].profile_score > screen for pt in points[1:])))]
    scouts = {c.name: scout_candidate(model, current, points, EFFECTS_BY_NAME[c.name], settings, held)
              for c in screened}
    for c in scores:
        c.scout_rmse_m = float(np.sqrt(scouts[c.name].sse / n)) if c.name in scouts else None
    order = sorted(scouts.values(), key=lambda sc: sc.sse)
    scores.sort(key=lambda c: (scouts[c.name].sse if c.name in scouts else np.inf, -c.profile_score))
    say("scouts: " + (", ".join(f"{sc.name} {np.sqrt(sc.sse / n) * 1e6:.4g} µm" for sc in order) or "none"))
    base = current
    refits: list[Refit] = []
    better_null: Fit | None = None
    # the candidate the score test ranks first is refitted whatever its scout: a short polish of a threshold or
    # delay effect may show little of what its converged refit explains, and the two rankings disagreeing is
    # itself a reason to look
    top_score = max((c for c in scores if c.name in scouts and np.isfinite(scouts[c.name].sse)),
                    key=lambda c: max(c.profile_score, c.score), default=None)
    for i, sc in enumerate(order):
        best = min((rf.fit.rmse(n) ** 2 * n for rf in refits if rf.accepted), default=None)
        # at least top_k refits; beyond them, refit while a scout explains more than the best accepted refit
        # (no effect is accepted while a candidate that explains more has not been refitted), and while a scout
        # comes within reach of it (a rival the record may not tell apart from it); with none accepted yet, while
        # a scout's short polish is significant as least squares (no effect is dismissed on its scout alone: a
        # short polish may show little of what a converged refit explains)
        if not np.isfinite(sc.sse):
            break
        if i >= settings.top_k and (top_score is None or sc.name != top_score.name):
            if best is not None and sc.sse >= best + tie_band(best, n, settings.ambiguity_alpha):
                continue
            k_sc = len(freed_with(base.free, EFFECTS_BY_NAME[sc.name], held)) - len(base.free)
            if best is None and not f_test(base.sse, sc.sse, k_sc, n, len(base.free) + k_sc)[1] < settings.alpha:
                continue
        eff = EFFECTS_BY_NAME[sc.name]
        start = _with(anchor, {nm: base.theta[ALL_INDEX[nm]] for nm in base.free if nm not in free})
        rf = refit_candidate(model, base, eff, sc, settings, it, judge, held, anchor=start)
        if rf.accepted:
            null = guard_null(model, base, rf, eff, settings, judge)
            if null is not None and null.sse < base.sse:
                say(f"  nominal re-polish from the {eff.name} refit lowered the baseline to "
                    f"{null.rmse(n) * 1e6:.4g} µm")
                base = better_null = null
                for other in refits:  # earlier refits are judged against the better baseline too
                    if other.accepted:
                        other.judge(judge.judge_pair(base, other.fit), base.sse)
                        if not other.accepted:
                            other.reason = "against the re-polished nominal model: " + other.reason
        ev = rf.evidence
        say(f"  refit {eff.name}: rms {(rf.fit.rmse(n) if rf.fit else np.inf) * 1e6:.4g} µm, F {rf.F:.3g}, p {rf.p_value:.3g}, "
            f"ΔBIC {rf.delta_bic:.4g}, out of sample {ev.get('cv_sse_w_before', np.nan):.4g} → "
            f"{ev.get('cv_sse_w_after', np.nan):.4g} → {'accepted' if rf.accepted else 'rejected: ' + rf.reason} "
            f"({rf.seconds:.1f} s)")
        refits.append(rf)
        if on_refit is not None:
            on_refit(rf)
    winners = [rf for rf in refits if rf.accepted]
    chosen = min(winners, key=lambda rf: rf.sse1) if winners else None
    rivals = _rivals(judge, chosen, winners, settings) if chosen is not None else []
    for rf in winners:
        if rf is not chosen and rf.name not in {r["name"] for r in rivals}:
            rf.reason = f"supported, but {chosen.name} explains more (lower SSE); judged again next iteration"
    if rivals:
        say(f"  {chosen.name} and " + ", ".join(r["name"] for r in rivals) + " fit this record equally well "
            "(Vuong " + ", ".join(f"z {r['vuong']['z']:.2f}" for r in rivals) + "): ambiguous")
    record = {"iteration": it, "rmse_m": base.rmse(n), "rank_J": points[0].proj.rank,
              "noise_model_of_current_residual": noise.to_dict(), "points": [pt.label for pt in points],
              "scores": [c.to_dict() for c in scores], "refits": [rf.to_dict(n) for rf in refits],
              "accepted": chosen.name if chosen else None, "indistinguishable_from": rivals}
    return {"scores": scores, "refits": refits, "chosen": chosen, "better_null": better_null, "record": record,
            "base": base, "rivals": rivals}


def _rivals(judge: Judge, chosen: Refit, winners: Sequence[Refit], settings: DiscoverSettings) -> list[dict]:
    """The other supported refits of the round the record cannot tell apart from ``chosen``
    (:func:`.engine.indistinguishable`, on the residuals the judge already simulated); each such refit's reason
    says so."""
    if not settings.ambiguity_alpha > 0:
        return []
    others = [rf for rf in winners if rf is not chosen]
    found = indistinguishable(judge.residual(chosen.fit), chosen.k, [(judge.residual(rf.fit), rf.k) for rf in others],
                              settings.noise_max_order, settings.ambiguity_alpha)
    out = []
    for rf, v in zip(others, found):
        rf.evidence["vuong_against_" + chosen.name] = v
        if v["tied"]:
            rf.reason = (f"fits as well as {chosen.name} (Vuong z {v['z']:.2f}, p {v['p_value']:.2g}): the record "
                         "cannot tell them apart")
            out.append({"name": rf.name, "params": rf.params, "rmse_m": rf.fit.rmse(judge.model.n), "vuong": v,
                        "F": rf.F, "p_value": rf.p_value, "delta_bic": rf.delta_bic, "evidence": rf.evidence})
    return out


def _polish_with_effect(model: Model, chosen: Refit, anchor: np.ndarray, free: Sequence[str],
                        settings: DiscoverSettings, say: Callable[[str], None]) -> Fit:
    """The accepted refit polished in full, also from the nominal fit as given with the effects' values (the
    polished baseline may sit in another valley); the better of the two."""
    n = model.n
    current = fit_free(model, chosen.fit.theta, chosen.fit.free, settings.baseline_nfev, settings.fd_rel_step,
                       rounds=settings.rounds)
    effect_names = [nm for nm in chosen.fit.free if nm not in free]
    alt = fit_free(model, _with(anchor, {nm: current.theta[ALL_INDEX[nm]] for nm in effect_names}),
                   chosen.fit.free, settings.baseline_nfev, settings.fd_rel_step, rounds=settings.rounds)
    if alt.sse < current.sse:
        say(f"  second start (nominal fit + effects) reached {alt.rmse(n) * 1e6:.4g} µm "
            f"instead of {current.rmse(n) * 1e6:.4g} µm")
        current = alt
    return current


def _backward(model: Model, judge: Judge, current: Fit, added: list[dict], held: Sequence[str],
              settings: DiscoverSettings, say: Callable[[str], None]) -> tuple[Fit, list[dict], list[dict]]:
    """Backward elimination (:func:`.engine.backward_eliminate`) with the toggle plant's refits and judge."""
    return backward_eliminate(
        current, added, lambda cur, a, now: _without(model, cur, a["name"], now, held, settings), judge.judge_pair,
        say, lambda fit: f"rms {fit.rmse(model.n) * 1e6:.4g} µm")


def _without(model: Model, current: Fit, name: str, added: Sequence[dict], held: Sequence[str],
             settings: DiscoverSettings, rival: dict | None = None) -> Fit:
    """The current model refitted with effect ``name`` switched off (and the gauge parameter it alone freed held
    again); with ``rival`` ({name, params}), that effect switched on in its place, started at its ``params``."""
    eff = EFFECTS_BY_NAME[name]
    others = {s for b in added if b["name"] != name for s in EFFECTS_BY_NAME[b["name"]].breaks}
    rehold = {GAUGE_HELD[s] for s in eff.breaks if s not in others and GAUGE_HELD[s] in held}
    free = tuple(nm for nm in current.free if nm not in eff.names and nm not in rehold)
    start = _with(current.theta, _off_values(eff))
    if rival is not None:
        free = freed_with(free, EFFECTS_BY_NAME[rival["name"]], held)
        start = _with(start, rival["params"])
    return fit_free(model, start, free, settings.baseline_nfev, settings.fd_rel_step, rounds=settings.rounds)


def compensating_refits(refits: Sequence[Refit], compensating: Sequence[dict], added: Sequence[dict]) -> list[dict]:
    """The refits that lowered the error but were not accepted, one item per effect — its latest refit, judged
    against the most complete model (``refits`` in iteration order) — leaving out the effects already listed as
    compensating, added, or tied with an added one."""
    listed = ({c["name"] for c in compensating} | {a["name"] for a in added}
              | {r["name"] for a in added for r in a.get("indistinguishable_from", ())})
    latest = {rf.name: rf for rf in refits if rf.lowers_error and not rf.accepted and rf.name not in listed}
    return [{"name": rf.name, "iteration": rf.iteration, "params": rf.params, "reason": rf.reason,
             "evidence": rf.evidence} for rf in latest.values()]


def _describe_added(added: list[dict], current: Fit, uncertainty: dict, gauge_after: dict) -> None:
    """The values of the final model for each added effect (later refits move earlier effects' parameters)."""
    for a in added:
        eff = EFFECTS_BY_NAME[a["name"]]
        a["params"] = {nm: float(current.theta[ALL_INDEX[nm]]) for nm in eff.names}
        a["std_errors"] = {nm: (uncertainty.get("std_errors") or {}).get(nm) for nm in eff.names}
        a["ci95"] = {nm: (uncertainty.get("ci95") or {}).get(nm) for nm in eff.names}
        a["identifiable"] = {nm: (uncertainty.get("identifiable") or {}).get(nm) for nm in eff.names}
        a["magnitude"] = {"name": eff.magnitude.name, "value": a["params"][eff.magnitude.name],
                          "unit": eff.magnitude.unit, "std_error": a["std_errors"][eff.magnitude.name],
                          "identifiable": a["identifiable"][eff.magnitude.name],
                          "scales_with_mechanism": _force_like(eff.magnitude.name),
                          "at_reference_scale": bool(gauge_after.get("applied")) and _force_like(eff.magnitude.name)}
        k_l = float(current.theta[ALL_INDEX["K_l"]])
        if _force_like(eff.magnitude.name) and k_l > 0:
            # x_B fixes a force only relative to the mechanism (every force scales with it, exactly): the ratio
            # to the contact stiffness is what the record determines, whatever representative is reported
            a["magnitude"]["per_K_l"] = a["params"][eff.magnitude.name] / k_l
        if current_power(eff.magnitude.name) == 2:
            # a torque saturation is fixed only relative to the current scale (K_i → K_i/c, i_q → i_q/c leaves
            # c_kt·K_i² unchanged); i_sat = 1/√c_kt is the current at which K_t has fallen by 1/√2
            k_i = float(current.theta[ALL_INDEX["K_i"]])
            a["magnitude"]["times_K_i2"] = a["params"][eff.magnitude.name] * k_i * k_i
            if a["params"][eff.magnitude.name] > 0:
                a["magnitude"]["i_sat_A"] = float(a["params"][eff.magnitude.name] ** -0.5)
                # the stall current is K_i·v_in/R_s: the command at which the stall torque constant is down by
                # 1/√2, R_s/(K_i·√c_kt), is what the clamped phases show
                a["magnitude"]["stall_command_V"] = float(
                    current.theta[ALL_INDEX["R_s"]] / (k_i * np.sqrt(a["params"][eff.magnitude.name])))
