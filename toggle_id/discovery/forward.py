"""One forward iteration of the toggle plant's discovery loop (:meth:`.toggle_plant.TogglePlant.forward_step`): the
score tests at the current fit (and at the nominal start), the scouts of the screened candidates, the refits in the
scouts' order with their guards, the second look of the catch-all when nothing is supported, and the choice of the
effect to add with the rivals the record cannot tell apart from it; then the chosen refit polished in full."""
from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence

import numpy as np
from scipy import stats

from ..effects import ALL_INDEX, EFFECTS, EFFECTS_BY_NAME, Effect
from ..fast import difference_noise
from .gauge import carried, freed_with, scale_type
from .landscape import profile, profiled_names
from .model import Fit, Model, _with, fit_free
from .noise import fit_noise
from .pairs import pair_look
from .refit import (NEAR_NOISE, Refit, from_current, from_other_starts, guard_null, refit_candidate,
                    scout_candidate, share_of_room)
from .residual import structure_left_at
from .scoring import assess, score_leaders, worth_refitting
from .settings import DiscoverSettings
from .ties import indistinguishable
from .validation import Judge


def _iteration(model: Model, judge: Judge, current: Fit, anchor: np.ndarray, free: Sequence[str],
               remaining: Sequence[Effect], settings: DiscoverSettings, it: int, held: Sequence[str],
               say: Callable[[str], None], on_refit: Callable[[Refit], None] | None,
               second_look: Callable[[Fit], set[str]] | None = None,
               beside: Callable[[Fit, list], list[Refit]] | None = None, others: Sequence[np.ndarray] = (),
               noise_m: float = 0.0) -> dict:
    """Scores, scouts and refits of one iteration; the candidate to add (or None). ``second_look(fit)``: the kinds
    of effect (:attr:`~toggle_id.effects.Effect.acts_on`) a generic term of the catch-all check finds missing
    from ``fit``, asked when no refit is supported. ``beside(fit, scouts)``: when still none is, the effects of
    ``scouts`` (those of no kind) refitted beside the catch-all's generic terms
    (:func:`.catchall.beside_generic`). ``others``: the baseline's other starts, in its gauge, from which an
    accepted refit far above ``noise_m`` (the record's noise, m) is polished again (:func:`.refit.refit_candidate`),
    and, while no supported refit ends within ``other_starts_above`` times that noise, every dismissed candidate the
    score test ranks significant, strongest first, until one ends near it (:func:`.refit.from_other_starts`)."""
    n = model.n
    clock = model.clock
    with clock("score tests"):
        noise = fit_noise(model.residuals(current.theta[None, :])[0], settings.noise_max_order)
        points = [assess(model, "current fit", current.theta, current.free, remaining, settings, noise)]
        # second linearisation point: the nominal fit as given, with the effects added so far — the polished fit
        # may have bent the nominal parameters far towards the missing effect, where the local picture is distorted
        alt = _with(anchor, {nm: current.theta[ALL_INDEX[nm]] for nm in effects_on(current.free, free)})
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
                    and (here[c.name].statistic > screen
                         or (c.name not in points[0].profiles
                             and any(pt.scores[c.name].profile_score > screen for pt in points[1:])))]
    with clock("scouts"):
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
    # the candidates the score test ranks first are refitted whatever their scouts: a short polish of a threshold
    # or delay effect may show little of what its converged refit explains, and the two rankings disagreeing is
    # itself a reason to look
    leaders = score_leaders([c for c in scores if c.name in scouts and np.isfinite(scouts[c.name].sse)],
                            settings.ambiguity_alpha, screen)
    stat = {c.name: c.statistic for c in scores}

    def so_far() -> dict:
        """The values of the effects added so far (in the current ``base``)."""
        return {nm: base.theta[ALL_INDEX[nm]] for nm in effects_on(base.free, free)}

    def refit(sc) -> None:
        added = so_far()
        # once a supported refit of the round is near the noise, the others' refits are not searched again from
        # the other starts: such a search can at most tie it (the discover job's end-to-end test, a 50-µm offset
        # named at 0.975 µm: the load force's refit, accepted at 10.58 µm, was then polished from four other
        # starts to 10.59–10.6 µm — 63 s of the loop's 127 s with the guard's null refit — and never chosen)
        near = any(rf.accepted and rf.fit.rmse(n) <= NEAR_NOISE * noise_m for rf in refits)
        with clock("refits"):
            rf = refit_candidate(model, base, EFFECTS_BY_NAME[sc.name], sc, settings, it, judge, held,
                                 anchor=_with(anchor, added),
                                 others=[] if near else [_with(st, carried(added, st, base.theta)) for st in others],
                                 noise_m=noise_m)
        take(rf)

    def take(rf: Refit, replaces: Refit | None = None) -> None:
        """``rf`` guarded, logged and kept (in the place of ``replaces``)."""
        nonlocal base, better_null
        eff = EFFECTS_BY_NAME[rf.name]
        if rf.accepted:
            with clock("null re-polishes (guard)"):
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
        hc = ev.get("hc_ratio", 1.0) or 1.0
        robust = f" (robust p {ev.get('p_value_robust', np.nan):.3g}, ×{hc:.3g})" if hc > 1.2 else ""
        if ev.get("inference", "prewhitened") != "prewhitened":  # Judge.serial_evidence
            robust = f" (least squares, serial correlation ×{hc:.3g}: its noise model is an error the model lacks)"
        say(f"  refit {eff.name}: rms {(rf.fit.rmse(n) if rf.fit else np.inf) * 1e6:.4g} µm, F {rf.F:.3g}, "
            f"p {rf.p_value:.3g}{robust}, ΔBIC {rf.delta_bic:.4g}, "
            f"out of sample {ev.get('cv_sse_w_before', np.nan):.4g} → "
            f"{ev.get('cv_sse_w_after', np.nan):.4g} (z {ev.get('cv_z', np.nan):.3g}) → "
            f"{'accepted' if rf.accepted else 'rejected: ' + rf.reason} ({rf.seconds:.1f} s)"
            + (f"; from another start of the baseline (it had stopped at "
               f"{rf.search['before_other_starts']['rmse_m'] * 1e6:.4g} µm)" if "before_other_starts" in rf.search
               else "")
            + (" (the other starts' polishes: " + ", ".join(f"{p['rmse_m'] * 1e6:.4g}" for p in rf.search["other_starts"])
               + " µm)" if rf.search.get("other_starts") else ""))
        if replaces is None:
            refits.append(rf)
        else:
            refits[refits.index(replaces)] = rf
        if on_refit is not None:
            on_refit(rf)

    for i, sc in enumerate(order):
        leading = min((rf for rf in refits if rf.accepted), key=lambda rf: rf.fit.rmse(n), default=None)
        best = leading.fit.rmse(n) ** 2 * n if leading is not None else None
        realised = leading.F * leading.k if leading is not None else None
        if not np.isfinite(sc.sse):
            break
        if i >= settings.top_k and sc.name not in leaders:  # at least top_k refits, the leaders whatever their scouts
            k_sc = len(freed_with(base.free, EFFECTS_BY_NAME[sc.name], held)) - len(base.free)
            if not worth_refitting(sc.sse, stat.get(sc.name, 0.0), base.sse, len(base.free), k_sc, n, settings,
                                   best, realised):
                continue
        refit(sc)
    if settings.next_leaders:
        for sc in next_leaders(refits, scores, [sc for sc in order if np.isfinite(sc.sse)], leaders, screen,
                               settings.ambiguity_alpha):
            refit(sc)
    tried = {rf.name for rf in refits}
    untried = [sc for sc in order if np.isfinite(sc.sse) and EFFECTS_BY_NAME[sc.name].acts_on and sc.name not in tried]
    if second_look is not None and untried and not any(rf.accepted for rf in refits):
        # nothing supported, and the scouts left effects untried: when a force on the slider (or an error of the
        # reading) of any shape explains what is left, every library effect of that kind is refitted before the
        # record is called unexplained — a scout's short polish from a model that absorbed a smooth effect shows
        # little of it (adversarial record rec33: a slider viscous friction scouted 8th, never refitted)
        with clock("catch-all's second look"):
            kinds = second_look(base)
        untried = [sc for sc in untried if EFFECTS_BY_NAME[sc.name].acts_on in kinds]
        if untried:
            say("  nothing supported, and " + " or ".join(KIND_TEXT[k] for k in sorted(kinds)) + " of any shape "
                "explains what is left (catch-all): refitting " + ", ".join(sc.name for sc in untried))
        for sc in untried:
            refit(from_current(model, base, sc, settings))
    if beside is not None and not any(rf.accepted for rf in refits):
        with clock("refits beside the generic terms"):
            besides = beside(base, [sc for sc in order if np.isfinite(sc.sse) and not EFFECTS_BY_NAME[sc.name].acts_on])
        for rf in besides:
            refits.append(rf)
            if on_refit is not None:
                on_refit(rf)
    far = settings.other_starts_above * noise_m
    lowest_now = min((rf.fit for rf in refits if rf.accepted), key=lambda f: f.rmse(n), default=base)
    if others and far > 0.0 and lowest_now.rmse(n) > far and structure_left_at(model, lowest_now.theta, settings)[0]:
        # nothing supported reaches near the noise, and what is left is structure: the dismissed candidates the
        # score test ranks significant, strongest first, polished again from the baseline's other starts (a bent
        # baseline can hide a large effect)
        added = so_far()
        for rf in sorted((rf for rf in refits if not rf.accepted and stat.get(rf.name, 0.0) > screen),
                         key=lambda rf: -stat[rf.name]):
            with clock("refits from other starts"):
                again = from_other_starts(model, base, rf, settings, judge, [_with(st, added) for st in others],
                                          noise_m)
            if again is not None:
                take(again, replaces=rf)
                if again.accepted and again.fit.rmse(n) <= NEAR_NOISE * noise_m:
                    break
    winners = [rf for rf in refits if rf.accepted]
    chosen = lowest_of(winners, n)
    pairs: list[dict] = []
    if settings.pair_look > 1:  # no single effect takes the record into the noise band: pairs refitted together
        # and only where what the step leaves is structure by the noise-aware structure test: the record's noise
        # read off its third differences is a quarter of σ under AR(1) ρ 0.9 noise (0.25–0.29 µm on the set's
        # records of σ = 1 µm) and 0.015 σ under the resonant AR(2) noise, so the RMS gate alone opens there on
        # every step, a noise-only record's last one included
        near = settings.pair_above * (noise_m if noise_m > 0 else difference_noise([model.record]))
        with clock("pairs"):
            left, text = (structure_left_at(model, (chosen.fit if chosen else base).theta, settings)
                          if base.rmse(n) > near and (chosen is None or chosen.fit.rmse(n) > near) else (False, ""))
            if text and not left:
                say(f"  no pair looked at: {chosen.name if chosen else 'the current model'} leaves {text}")
            pair, pairs = (pair_look(model, judge, base, refits, chosen, settings, it, held, say, near) if left
                           else (None, pairs))
        if pair is not None:
            say(f"  {pair.name} and {pair.partner} together explain more than any one effect "
                f"({pair.fit.rmse(n) * 1e6:.4g} µm)")
            chosen = pair
    with clock("ties"):
        rivals = _rivals(judge, chosen, winners, settings) if chosen is not None and chosen.partner is None else []
    for rf in winners:
        if rf is not chosen and rf.name not in {r["name"] for r in rivals}:
            rf.reason = (f"supported, but {chosen.name}{' with ' + chosen.partner if chosen.partner else ''} explains "
                         "more (lower SSE); judged again next iteration")
    if rivals:
        say(f"  {chosen.name} and " + ", ".join(r["name"] for r in rivals) + " fit this record equally well "
            "(Vuong " + ", ".join(f"z {r['vuong']['z']:.2f}" for r in rivals) + "): ambiguous")
    record = {"iteration": it, "rmse_m": base.rmse(n), "rank_J": points[0].proj.rank,
              "noise_model_of_current_residual": noise.to_dict(), "points": [pt.label for pt in points],
              "scores": [c.to_dict() for c in scores], "refits": [rf.to_dict(n) for rf in refits],
              "accepted": chosen.name if chosen else None, "indistinguishable_from": rivals,
              **({"pairs": pairs, "accepted_with": chosen.partner if chosen else None} if pairs else {})}
    return {"scores": scores, "refits": refits, "chosen": chosen, "better_null": better_null, "record": record,
            "base": base, "rivals": rivals}


def next_leaders(refits: list[Refit], scores: Sequence, order: Sequence, leaders: set[str], screen: float,
                 alpha: float):
    """While nothing of the round is supported, the candidates the score test ranks first once the leaders whose
    refits realised nothing are set aside, in the scouts' order (a generator: each is refitted, into ``refits``,
    before the next is chosen). A leader is refitted whatever its scout because its score says it explains the
    most to first order; where its converged refit explains nothing (F·k at most the screen's χ²(1) critical
    value ``screen``), that score told nothing, and the next significant ones (statistic above ``screen``, within
    the test's resolution of the largest: :func:`.scoring.score_leaders`) are owed the same look before the round
    is left to the catch-all. Held-out record rec46_d1 (a backlash on the paper's sweep, 2026-12-07): the dead
    time led (χ² 165) and its refit found nothing (F ≈ 0); the backlash (132), second, had scouted fifth and was
    never refitted alone on that route (the second route named it: F 779, out of sample z 19.9)."""
    scouted = {sc.name for sc in order}
    set_aside: set[str] = set()
    while not any(rf.accepted for rf in refits):
        done = {rf.name: rf for rf in refits}
        empty = {nm for nm in leaders if nm in done and not done[nm].F * done[nm].k > screen} - set_aside
        if not empty:
            return
        set_aside |= empty
        rest = [c for c in scores if c.name not in set_aside and c.statistic > screen and c.name in scouted]
        leaders = score_leaders(rest, alpha, screen)
        new = [sc for sc in order if sc.name in leaders and sc.name not in done]
        if not new:
            return
        yield from new


#: What a kind of effect (:attr:`~toggle_id.effects.Effect.acts_on`) is, for the log.
KIND_TEXT = {"slider": "a force on the slider", "reading": "an error of the reading"}


def _rivals(judge: Judge, chosen: Refit, winners: Sequence[Refit], settings: DiscoverSettings) -> list[dict]:
    """The other supported refits of the round the record cannot tell apart from ``chosen``
    (:func:`.ties.indistinguishable`, on the residuals the judge already simulated); each such refit's reason
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


#: Share of the room between "off" and its feasible bound beyond which an effect's fitted magnitude is at the edge
#: (the stronger starts stop at 0.98 of it: :func:`.refit.stronger_magnitudes`).
AT_BOUND = 0.95


def lowest_of(winners: Sequence[Refit], n: int) -> Refit | None:
    """The supported refit of lowest SSE as the fits minimised it; by their raw errors where they minimised under
    different noise models (a find of the search from the other starts is fitted under the noise model of its own
    residual, :func:`.refit.from_other_starts`), whose whitened SSEs do not compare."""
    if not winners:
        return None
    same = len({rf.fit.minimised_under for rf in winners}) == 1
    return min(winners, key=(lambda rf: rf.sse1) if same else (lambda rf: rf.fit.rmse(n)))


def at_bound(effect: Effect, value: float, domain: tuple[float, float] | None = None) -> bool:
    """Whether the magnitude ``value`` of ``effect`` lies beyond :data:`AT_BOUND` of the way from "off" to the
    feasible bound on its side (of ``domain``, default the library's)."""
    return bool(share_of_room(effect, value, domain) >= AT_BOUND)


def effects_on(fit_free: Sequence[str], free: Sequence[str]) -> list[str]:
    """The parameters a fit with ``fit_free`` free carries beyond the nominal model's ``free``: those free (the
    effects' and the gauge parameters they make determined), and every parameter of an effect one of whose
    parameters is free — a count held at its whole value (:func:`.periodic.whole_counts`) is the effect's all the same, and
    a start built from the nominal fit with the effects so far must carry it."""
    extra = [nm for nm in fit_free if nm not in free]
    held = [nm for e in EFFECTS if any(p in extra for p in e.names) for nm in e.names if nm not in extra]
    return extra + held


def moved_effects(start: np.ndarray, end: np.ndarray, names: Sequence[str], rtol: float) -> list[str]:
    """The effect parameters ``names`` whose value changed from ``start`` to ``end`` by more than ``rtol`` of the
    larger of the two (none when ``rtol`` ≤ 0)."""
    if not rtol > 0:
        return []
    out = []
    for nm in names:
        a, b = float(start[ALL_INDEX[nm]]), float(end[ALL_INDEX[nm]])
        if abs(b - a) > rtol * max(abs(a), abs(b)):
            out.append(nm)
    return out


def _polish_with_effect(model: Model, chosen: Refit, anchor: np.ndarray, free: Sequence[str],
                        settings: DiscoverSettings, say: Callable[[str], None],
                        hold: Mapping[str, float] | None = None) -> Fit:
    """The accepted refit polished in full, also from the nominal fit as given with the effects' values (the
    polished baseline may sit in another valley); the better of the two. ``hold``: parameters of the refit held at
    these values from here on (a count at its whole number, :func:`.periodic.whole_counts`).

    Where the effect's magnitude then sits at the edge of its feasible domain (:func:`at_bound`), the polish also
    starts from the nominal fit as given with the magnitude at ``settings.weaker_starts`` of its distance from
    "off": a lash or a threshold run out to its bound sits where the error no longer moves with it, so no polish
    from there comes back. Measured on the default suite's backlash case cut to 0.5 s (b_l = 0.5 mm): the lash
    refitted from a stronger start stayed at 1.96 mm, 28.4 µm; from the nominal fit as given at a third and a tenth
    of that, 1.002 µm at b_l = 0.5002 mm (from the polished baseline, whose parameters had absorbed the lash,
    neither came back: 94 and 152 µm).

    Where the polish from the nominal fit as given wins but moves the effects' values by more than
    ``settings.reanchor_rtol`` (:func:`moved_effects`), the nominal fit as given is polished once more at the values
    reached: the nominal parameters bend towards the effect on the way and may stall there. Measured on the default
    suite's backlash case (1 s, b_l = 0.5 mm, the tests' small budgets, on an AMD EPYC machine): from the refit's
    b_l = 0.326 mm the polish stalled (`xtol`) at 9.3 µm with b_l = 0.51 mm and the record was called unexplained;
    from the nominal fit as given at 0.51 mm it reaches 0.967 µm at b_l = 0.5002 mm."""
    n = model.n
    hold = dict(hold or {})
    effect_names = effects_on(chosen.fit.free, free)
    names = tuple(nm for nm in chosen.fit.free if nm not in hold)

    def polish(theta: np.ndarray) -> Fit:
        return fit_free(model, theta, names, settings.baseline_nfev, settings.fd_rel_step, rounds=settings.rounds)

    def as_given_with(theta: np.ndarray) -> np.ndarray:
        """The nominal fit as given with the effects' values of ``theta``."""
        return _with(anchor, {nm: theta[ALL_INDEX[nm]] for nm in effect_names})

    current = polish(_with(chosen.fit.theta, hold))
    if hold:
        say(f"  {', '.join(f'{nm} {chosen.fit.theta[ALL_INDEX[nm]]:.4g}' for nm in hold)} held at "
            f"{', '.join(f'{v:g}' for v in hold.values())} (a whole count per revolution): polished "
            f"{current.rmse(n) * 1e6:.4g} µm (the refit, free: {chosen.fit.rmse(n) * 1e6:.4g} µm)")
    as_given = as_given_with(current.theta)
    alt = polish(as_given)
    if alt.sse < current.sse:
        say(f"  second start (nominal fit + effects) reached {alt.rmse(n) * 1e6:.4g} µm "
            f"instead of {current.rmse(n) * 1e6:.4g} µm")
        current = alt
        moved = moved_effects(as_given, current.theta, effect_names, settings.reanchor_rtol)
        if moved:
            again = polish(as_given_with(current.theta))
            say(f"  {', '.join(moved)} moved on the way: from the nominal fit as given at the values reached, "
                f"{again.rmse(n) * 1e6:.4g} µm")
            if again.sse < current.sse:
                current = again
    effect = EFFECTS_BY_NAME[chosen.name]
    mag = effect.magnitude
    value = float(current.theta[ALL_INDEX[mag.name]])
    if settings.weaker_starts and at_bound(effect, value, model.domain(mag.name)):
        for f in settings.weaker_starts:
            weaker = polish(_with(as_given, {mag.name: mag.off + f * (value - mag.off)}))
            say(f"  {mag.name} at the edge of its domain ({value:.4g}): from {f:.3g} of it, "
                f"{weaker.rmse(n) * 1e6:.4g} µm at {weaker.theta[ALL_INDEX[mag.name]]:.4g}")
            if weaker.sse < current.sse:
                current = weaker
    return current


def widened_at_edge(model: Model, name: str, fit: Fit, settings: DiscoverSettings, say: Callable[[str], None],
                    given: Collection[str] = ()) -> tuple[Fit, dict[str, tuple[float, float]]]:
    """``fit`` polished again with the domain of effect ``name``'s magnitude widened on the side it presses against,
    while the polish ends at that edge (:func:`at_bound`) and lowers the error: the room from "off" to the bound
    grows ``settings.edge_widen`` times, at most ``settings.edge_widenings`` times; a wider domain that gains nothing
    is taken back. Only for a magnitude whose domain the gauge moved (:func:`.gauge.scale_type`: a force, torque or
    current-type magnitude, which x_B fixes only relative to the mechanism's or the current's scale), not one a user
    gave (``given``) or the record narrows: the library's domain holds at the reference scale, and the fits move
    the scale as they go, so a box in the loop's gauge can pin such a magnitude short of a value inside the
    library's domain there (docs/discovery.md, probe q4). The widened domain stays in ``model.gauge_bounds`` for the
    later fits. Returns the fit and the domains widened ({name: (low, high)}, in the loop's gauge)."""
    effect = EFFECTS_BY_NAME[name]
    mag = effect.magnitude
    k = mag.name
    widened: dict[str, tuple[float, float]] = {}
    if (settings.edge_widenings <= 0 or not scale_type(k) or k in given or k in model.bounds
            or k not in model.gauge_bounds):
        return fit, widened
    n = model.n
    for _ in range(settings.edge_widenings):
        lo, hi = model.domain(k)
        value = float(fit.theta[ALL_INDEX[k]])
        if not at_bound(effect, value, (lo, hi)):
            break
        wide = (lo, mag.off + settings.edge_widen * (hi - mag.off)) if value >= mag.off else \
            (mag.off + settings.edge_widen * (lo - mag.off), hi)
        model.gauge_bounds = {**model.gauge_bounds, k: wide}
        again = fit_free(model, fit.theta, fit.free, settings.baseline_nfev, settings.fd_rel_step,
                         rounds=settings.rounds)
        say(f"  {k} at the edge of its domain [{lo:.4g}, {hi:.4g}] in the loop's gauge: widened to "
            f"[{wide[0]:.4g}, {wide[1]:.4g}], {again.rmse(n) * 1e6:.4g} µm at {again.theta[ALL_INDEX[k]]:.4g} "
            f"(from {fit.rmse(n) * 1e6:.4g} µm)")
        if not again.sse < fit.sse:  # not pressing after all: the domain as it was
            model.gauge_bounds = {**model.gauge_bounds, k: (lo, hi)}
            break
        widened[k] = wide
        fit = again
    return fit, widened


def rescreened(model: Model, name: str, fit: Fit, settings: DiscoverSettings, say: Callable[[str], None],
               noise_m: float | None = None) -> tuple[Fit, list[dict]]:
    """``fit`` polished again from the lowest point of a fine profile of the added effect ``name``'s parameters
    (:func:`.landscape.profile`, the others held), where the fit ends above ``NEAR_NOISE`` times ``noise_m`` (the
    record's own noise) and a profile point lies below it by more than the profile's prominence; kept where the
    polish ends lower. A converged fit on a smooth cost is the lowest point of its own profiles, so this does
    nothing there; on a rough one (a lash, a large Stribeck friction: the cost a needle at the truth, with local
    minima beside it) the polish of the forward step stops in whichever minimum its start fell into
    (docs/discovery.md, item 11). ``noise_m`` None: read off the model's record
    (:func:`toggle_id.fast.difference_noise`). Returns the fit and the profiles' reports (each with the polish's
    outcome)."""
    n = model.n
    if settings.rescreen_points <= 0:
        return fit, []
    if noise_m is None:
        noise_m = difference_noise([model.record])
    if not noise_m > 0.0 or fit.rmse(n) <= NEAR_NOISE * noise_m:
        return fit, []
    reports = []
    for nm in profiled_names([name]):
        prof = profile(model, fit.theta, nm, settings.rescreen_span, settings.rescreen_points,
                       settings.rescreen_prominence * noise_m)
        rep = prof.to_dict()
        reports.append(rep)
        if not prof.below_fit():
            continue
        value, low = prof.lowest
        again = fit_free(model, _with(fit.theta, {nm: value}), fit.free, settings.baseline_nfev, settings.fd_rel_step,
                         rounds=settings.rounds)
        rep["polished_rmse_m"] = again.rmse(n)
        say(f"  {nm}'s profile around {prof.value:.4g} ({prof.minima} local minima) reads {low * 1e6:.4g} µm at "
            f"{value:.4g}, below the fit's {fit.rmse(n) * 1e6:.4g} µm: polished from there, "
            f"{again.rmse(n) * 1e6:.4g} µm")
        if again.sse < fit.sse:
            fit = again
    return fit, reports
