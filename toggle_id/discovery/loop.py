"""The discovery loop (see the package docstring)."""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from scipy import stats

from .. import params as P
from .. import residuals as R
from ..effects import ALL_INDEX, EFFECTS, EFFECTS_BY_NAME, Effect
from ..errors import ConfigError, DataError
from ..identify import IdentificationResult
from ..plant import GEOMETRY
from ..record import Record
from ..simulate import PRECISE, STATUS_OK, extend
from .gauge import GAUGE_HELD, _force_like, gauge_fix, gauge_symmetries
from .model import Model, _with, fit_free, parameter_uncertainty
from .refit import Refit, guard_null, refit_candidate, scout_candidate
from .report import DiscoveryResult, _conclusion
from .scoring import CandidateScore, assess
from .settings import DiscoverSettings
from .stats import f_test

log = logging.getLogger("toggle_id")


def residual_report(model: Model, theta: np.ndarray, settings: DiscoverSettings, split_index: int | None
                    ) -> tuple[dict, np.ndarray, dict]:
    """Diagnostics of the residual of ``theta`` (dict), the residual (N,) and the state signals."""
    x, i_q, status = model.response(theta)
    rec = model.record
    r = rec.x_B - x
    if status != STATUS_OK or not np.all(np.isfinite(r)):
        return {"error": f"the model cannot be simulated on this record (status {status})"}, r, {}
    states = R.plant_states(rec.t, x, i_q, x_off=float(theta[ALL_INDEX["x_off"]]))
    d = R.diagnose(rec.t, r, rec.v_in, states, alpha=settings.alpha_diag, acf_lags=settings.acf_lags,
                   ccf_lags=settings.ccf_lags, ccf_step=settings.ccf_step, split_index=split_index,
                   noise_std=settings.noise_std)
    return d, r, states


def _nominal_theta(nominal: IdentificationResult | np.ndarray | Mapping[str, float] | None) -> np.ndarray:
    theta = extend(P.ASSIGNED)[0]
    if nominal is None:
        return theta
    if isinstance(nominal, IdentificationResult):
        return extend(np.asarray(nominal.theta, float))[0]
    if isinstance(nominal, Mapping):
        return _with(theta, nominal)
    return extend(np.asarray(nominal, float))[0]


def discover(record: Record, *, nominal: IdentificationResult | np.ndarray | Mapping[str, float] | None = None,
             effects: Sequence[Effect] = EFFECTS, settings: DiscoverSettings | None = None,
             free: Sequence[str] | None = None, fixed: Mapping[str, float] | None = None,
             starts: Sequence[np.ndarray | Mapping[str, float]] = (),
             reference: np.ndarray | Mapping[str, float] | None = None, on_refit: Callable[[Refit], None] | None = None, progress: Callable[[str], None] | None = None
             ) -> DiscoveryResult:
    """Run the discovery loop on ``record`` (see the module docstring).

    nominal: the nominal fit (an :class:`IdentificationResult`, an extended/physical vector or a name → value
        mapping; None: the assigned values) — the loop starts by polishing it on the whole record.
    effects: the candidate library (default all of :data:`toggle_id.effects.EFFECTS`), filtered by
        ``settings.candidates``. free: nominal parameters fitted (default the 15 physical ones minus
        ``fixed``); fixed: parameters held at given values. starts: further starting points of the baseline
        polish (e.g. the assigned values beside a GA result); the best polished one is the baseline.
    reference: the values the reported parameters are brought closest to along the exact symmetries of the
        output (:func:`gauge_fix`; default the assigned values) — it fixes the otherwise arbitrary scale of the
        mechanism, and with it the magnitude of force-type effects.
    on_refit: called with every :class:`Refit` (e.g. to log an MLflow child run); progress: one-line messages.
    """
    settings = (settings or DiscoverSettings()).validate()
    say = progress or (lambda msg: log.info(msg))
    t_start = time.perf_counter()
    model = Model(record, PRECISE, settings.parallel)
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

    # 1. baseline: the nominal model polished on the whole record (from every start; the best is kept)
    anchors = [theta] + [_with(_nominal_theta(st), fixed) for st in starts]
    current, anchor, start_report = None, theta, []
    for k, th0 in enumerate(anchors):
        if not np.all(np.isfinite(model.residuals(th0[None, :])[0])):
            start_report.append({"start": k, "error": "cannot be simulated on this record"})
            continue
        say(f"baseline polish of {len(free)} parameters on {n} samples (start {k + 1} of {len(anchors)})")
        fit = fit_free(model, th0, free, settings.baseline_nfev, settings.fd_rel_step, rounds=settings.rounds)
        start_report.append({"start": k, "rmse_m": fit.rmse(n), "nfev": fit.info["nfev"]})
        say(f"  rms {fit.rmse(n) * 1e6:.4g} µm ({fit.info['nfev']} evaluations, {fit.info['seconds']:.1f} s)")
        if current is None or fit.sse < current.sse:
            current, anchor = fit, th0
    if current is None:
        raise DataError("the nominal model cannot be simulated on this record from any start; fit it first")
    current.info["starts"] = start_report
    baseline = current

    iterations: list[dict] = []
    added: list[dict] = []
    first_scores: list[CandidateScore] | None = None
    accepted_names: set[str] = set()
    all_refits: list[Refit] = []
    for it in range(1, settings.max_effects + 1):
        remaining = [e for e in pool if e.name not in accepted_names]
        if not remaining:
            break
        points = [assess(model, "current fit", current.theta, current.free, remaining, settings)]
        # second linearisation point: the nominal fit as given, with the effects added so far — the polished
        # fit may have bent the nominal parameters far towards the missing effect (masses → 0, friction × 50),
        # where the local picture of the remaining candidates is distorted
        alt = _with(anchor, {nm: current.theta[ALL_INDEX[nm]] for nm in current.free if nm not in free})
        if settings.second_point and not np.allclose(alt, current.theta, rtol=1e-3, atol=0.0):
            second = assess(model, "nominal start", alt, current.free, remaining, settings)
            if second is not None:  # (None: the nominal start cannot be simulated with these effects)
                points.append(second)
        scores = list(points[0].scores.values())  # the score tests proper: at the fitted point
        for c in scores:
            for pt in points[1:]:
                c.profile_score_alt = pt.scores[c.name].profile_score
        say("scores (profile | LM): " + ", ".join(f"{c.name} {c.profile_score:.3g} | {c.score:.3g}"
                                                  for c in sorted(scores, key=lambda c: -c.profile_score)))
        # screened at the fitted point (where the statistics mean what they say); every screened candidate is
        # scouted (short polish with the effect freed, from each point) and the refits follow the scouts
        screen = float(stats.chi2.isf(settings.screen_alpha, 1))
        here = points[0].scores
        # (a candidate the fitted point cannot see at all — silent there, e.g. a voltage limit above the fit's
        # drive voltage — is judged by the scout from the other point instead)
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
        if first_scores is None:
            first_scores = scores
        say("scouts: " + (", ".join(f"{sc.name} {np.sqrt(sc.sse / n) * 1e6:.4g} µm" for sc in order) or "none"))
        refits: list[Refit] = []
        for sc in order[:settings.top_k]:
            eff = EFFECTS_BY_NAME[sc.name]
            rf = refit_candidate(model, current, eff, sc, settings, it, held)
            if rf.accepted:
                better_null = guard_null(model, current, rf, eff, settings)
                if better_null is not None and better_null.sse < current.sse:
                    say(f"  nominal re-polish from the {eff.name} refit lowered the baseline to "
                        f"{better_null.rmse(n) * 1e6:.4g} µm")
                    current = better_null
                    if not added:  # still the nominal model: the error "before" is this better fit's
                        baseline = current
                    for other in refits:  # earlier refits are compared with the better baseline too
                        if other.accepted:
                            F, p, dbic = f_test(current.sse, other.sse1, other.k, n, other.p1)
                            other.sse0, other.F, other.p_value, other.delta_bic = current.sse, F, p, dbic
                            other.accepted = p < settings.alpha and dbic < 0
                            if not other.accepted:
                                other.reason = "not significant against the re-polished nominal model"
            say(f"  refit {eff.name}: rms {np.sqrt(rf.sse1 / n) * 1e6:.4g} µm, F {rf.F:.3g}, p {rf.p_value:.3g}, "
                f"ΔBIC {rf.delta_bic:.4g} → {'accepted' if rf.accepted else 'rejected'} ({rf.seconds:.1f} s)")
            refits.append(rf)
            all_refits.append(rf)
            if on_refit is not None:
                on_refit(rf)
        winners = [rf for rf in refits if rf.accepted]
        chosen = min(winners, key=lambda rf: rf.sse1) if winners else None
        iterations.append({"iteration": it, "rmse_m": current.rmse(n), "rank_J": points[0].proj.rank,
                           "points": [pt.label for pt in points],
                           "scores": [c.to_dict() for c in scores],
                           "refits": [rf.to_dict(n) for rf in refits],
                           "accepted": chosen.name if chosen else None})
        if chosen is None:
            break
        accepted_names.add(chosen.name)
        current = fit_free(model, chosen.fit.theta, chosen.fit.free, settings.baseline_nfev, settings.fd_rel_step,
                           rounds=settings.rounds)
        # second start: the nominal fit as given (before the baseline polish bent it towards the missing
        # effect) with the effects' current values — the polished baseline may sit in another valley
        effect_names = [nm for nm in chosen.fit.free if nm not in free]
        alt = fit_free(model, _with(anchor, {nm: current.theta[ALL_INDEX[nm]] for nm in effect_names}),
                       chosen.fit.free, settings.baseline_nfev, settings.fd_rel_step, rounds=settings.rounds)
        if alt.sse < current.sse:
            say(f"  second start (nominal fit + effects) reached {alt.rmse(n) * 1e6:.4g} µm "
                f"instead of {current.rmse(n) * 1e6:.4g} µm")
            current = alt
        added.append({"name": chosen.name, "iteration": it, "F": chosen.F, "p_value": chosen.p_value,
                      "delta_bic": chosen.delta_bic, "rmse_after_m": current.rmse(n),
                      "params_at_acceptance": chosen.params})
        say(f"added {chosen.name} {chosen.params}; rms {current.rmse(n) * 1e6:.4g} µm")

    # the representatives of the fits nearest the reference along the exact symmetries (same output)
    ref = _with(_nominal_theta(reference), fixed) if reference is not None else _with(extend(P.ASSIGNED)[0], fixed)
    gauge_before = gauge_after = {"applied": False}
    if settings.gauge:
        broken = {sym for a in added for sym in EFFECTS_BY_NAME[a["name"]].breaks}
        baseline.theta, gauge_before = gauge_fix(model, baseline.theta, baseline.free + held, ref)
        current.theta, gauge_after = gauge_fix(model, current.theta, tuple(set(current.free) | set(held)), ref,
                                               broken=broken)
    uncertainty = parameter_uncertainty(model, current, settings, gauge_after.get("held", ())) if added else {}
    for a in added:  # the values of the final model (later refits move earlier effects' parameters too)
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
    diag_before, r_before, _ = residual_report(model, baseline.theta, settings, split)
    diag_after, r_after, _ = residual_report(model, current.theta, settings, split)
    cands = []
    for c in first_scores or []:
        tried = [rf for rf in all_refits if rf.name == c.name]
        cands.append({**c.to_dict(), "accepted": c.name in accepted_names, "refitted": bool(tried),
                      "refit_p_value": min((rf.p_value for rf in tried), default=None)})
    structure = diag_after.get("verdict", {}).get("structure_left", False)
    unexplained = bool(structure)
    conclusion = _conclusion(added, diag_before, diag_after, unexplained, settings)
    return DiscoveryResult(record=record.name, n=n, baseline=baseline, final=current, effects_added=added,
                           candidates=cands, iterations=iterations, diagnostics_before=diag_before,
                           diagnostics_after=diag_after, residual_before=r_before, residual_after=r_after,
                           nominal=nominal.to_dict() if isinstance(nominal, IdentificationResult) else None,
                           conclusion=conclusion, unexplained=unexplained, seconds=time.perf_counter() - t_start,
                           n_simulations=model.n_sims, refits=all_refits,
                           extra={"symmetry_gauge": {"before": gauge_before, "after": gauge_after},
                                  "identifiability_after": uncertainty})
