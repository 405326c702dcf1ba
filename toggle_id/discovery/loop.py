"""The discovery loop (see the package docstring)."""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from .. import params as P
from ..effects import ALL_INDEX, EFFECTS, EFFECTS_BY_NAME, Effect
from ..errors import ConfigError
from ..polish import one_blas_thread
from ..fast import difference_noise
from ..identify import IdentificationResult
from ..plant import GEOMETRY
from ..record import Record
from ..simulate import PRECISE, extend
from ..stages import stage_bounds
from .gauge import GAUGE_HELD, _force_like, current_power, gauge_fix, gauge_symmetries
from .model import Fit, Model, _with, parameter_uncertainty
from .refit import NEAR_NOISE, Refit
from .periodic import cogging_domain
from .toggle_plant import TogglePlant
from .report import DiscoveryResult, _conclusion, conclusion_notes
from .settings import DiscoverSettings
from .engine import run_loop
from .forward import at_bound
from .landscape import Profile, profiles, rough_text
from .routes import Route, choose, more_routes, route_line
from .residual import predicted_left, prediction_report, residual_report
from .noise import fit_noise
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
             on_refit: Callable[[Refit], None] | None = None, progress: Callable[[str], None] | None = None,
             bounds: Mapping[str, Sequence[float]] | None = None,
             label: str = "nominal", alternatives: Sequence[tuple[str, object]] = (),
             restarts: Sequence[tuple[str, object]] = ()) -> DiscoveryResult:
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
    bounds: feasible domains of effect parameters in the library's place ({name: (low, high)}, at the reference
        scale; physical parameters' entries are the identification's and are left out here).
    on_refit: called with every :class:`Refit` (e.g. to log an MLflow child run); progress: one-line messages.
    label: where ``nominal`` came from (e.g. ``two_stage``); alternatives: further nominal fits, as (label, fit)
        pairs — a fit as ``nominal``, or a callable without arguments that makes it (run only when needed) —
        from which the loop runs again when ``settings.routes`` says so (:mod:`.routes`); restarts: further
        nominal fits of ``label``'s method from other seeds, as such pairs: a route only from a baseline lower than
        every route's so far, and only while no route has explained the record (:func:`.routes.more_routes`).
    """
    settings = (settings or DiscoverSettings()).validate()
    domains = {k: v for k, v in (bounds or {}).items() if k not in P.INDEX}
    stage_bounds(list(domains), domains)  # an unknown name or an empty domain: one line, before any work
    say = progress or (lambda msg: log.info(msg))
    t_start = time.perf_counter()
    model = Model(record, PRECISE, settings.parallel, jacobian=settings.jacobian,
                  jacobian_reuse=settings.jacobian_reuse, derivatives=settings.derivatives)
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
    pool = cogging_domain(model, pool, settings.cogging_min_periods, say)
    # one parameter per exact symmetry of x_B held during the polishes (the gauge): same fits, no flat directions
    held = tuple(GAUGE_HELD[s] for s in gauge_symmetries(free)) if settings.hold_gauge else ()
    free = tuple(nm for nm in free if nm not in held)
    split = record.clamp_index(GEOMETRY.x_B_L)
    split = split if 0 < split < record.n else None
    n = record.n

    # the representatives of the fits nearest the reference along the exact symmetries (same output) are reported,
    # and the effects' domains hold at its scale
    ref = _with(_nominal_theta(reference), fixed) if reference is not None else _with(extend(P.ASSIGNED)[0], fixed)

    def plant_from(theta0: np.ndarray, others: Sequence[np.ndarray]) -> TogglePlant:
        return TogglePlant(model, judge, settings, theta0, others, free, held, pool, split, say, on_refit, ref,
                           domains)

    def loop(p: TogglePlant):
        return run_loop(p, max_effects=settings.max_effects, backward=settings.backward,
                        ambiguity_alpha=settings.ambiguity_alpha, explain_fraction=settings.explain_fraction,
                        noise_max_order=settings.noise_max_order, encompassing=settings.encompassing,
                        clock=model.clock)

    out_of_time = OUT_OF_TIME.format(settings.max_seconds) if settings.max_seconds is not None else ""
    first = plant_from(theta, [_with(_nominal_theta(st), fixed) for st in starts])
    routes = [Route(label, first, loop(first), nominal)]
    if settings.routes == "always" or (settings.routes == "unexplained" and routes[0].structure_left):
        with model.clock.scope("other routes: "), model.clock("their nominal fits, the rest"):
            more_routes(routes, alternatives, restarts, lambda th: plant_from(_with(_nominal_theta(th), fixed), []),
                        loop, n, settings.route_rtol, say, max_ratio=settings.route_max_ratio,
                        deadline=None if settings.max_seconds is None else t_start + settings.max_seconds,
                        budget_text=out_of_time)
    pick, compared = choose(routes, judge.residual, n, settings.noise_max_order, settings.ambiguity_alpha)
    route_report = [r.to_dict(n, i == pick) for i, r in enumerate(routes)]
    if len(routes) > 1:
        for d in route_report:
            say(route_line(d))
    plant, out, nominal = routes[pick].plant, routes[pick].outcome, routes[pick].nominal
    model.gauge_bounds = plant.gauge_bounds  # the fits of the report keep to the chosen route's domains
    baseline, current, added, compensating, eliminated = (plant.baseline_fit, out.final, out.added, out.compensating,
                                                          out.eliminated)
    diag_after, r_after, _ = out.structure
    if diag_after.get("verdict", {}).get("structure_left"):
        plant.describe_missing(out.final, out.structure)
    noise0, first_scores, iterations, all_refits = plant.noise0, plant.first_scores, plant.iterations, plant.all_refits
    with_compensating, catch_report = out.with_compensating, plant.catch_report
    compensating += compensating_refits(all_refits, compensating, added)

    edge = at_the_edge(model, added, current)  # in the loop's gauge, before the report's representatives
    record_noise = difference_noise([record])  # the record's own noise, read off its third differences
    with model.clock("profiles of the named effects"):
        rough = rough_profiles(model, added, current, settings,
                               diag_after.get("verdict", {}).get("structure_left", False), record_noise)
    gauge_before = gauge_after = {"applied": False}
    if settings.gauge:
        broken = {sym for a in added for sym in EFFECTS_BY_NAME[a["name"]].breaks}
        baseline.theta, gauge_before = gauge_fix(model, baseline.theta, baseline.free + held, ref)
        if current is not baseline:
            current.theta, gauge_after = gauge_fix(model, current.theta, tuple(set(current.free) | set(held)), ref,
                                                   broken=broken, widened=plant.widened)
        else:
            gauge_after = gauge_before
    beyond = beyond_the_library([a for a in added if EFFECTS_BY_NAME[a["name"]].magnitude.name in plant.widened],
                                current, domains, gauge_after.get("applied", False))
    r_final = model.residuals(current.theta[None, :])[0]
    noise_after = fit_noise(r_final, settings.noise_max_order)
    with model.clock("intervals"):
        uncertainty = parameter_uncertainty(model, current, settings, gauge_after.get("held", ()), noise_after) \
            if added else {}
    _describe_added(added, current, uncertainty, gauge_after)
    # an effect the record cannot tell apart from another supported one is not named as added: the pair is
    # reported as ambiguous (the final model keeps the better-fitting one, for prediction)
    ambiguous = [a for a in added if a.get("indistinguishable_from")]
    added = [a for a in added if not a.get("indistinguishable_from")]
    with model.clock("residual tests of the baseline"):
        diag_before, r_before, _ = residual_report(model, baseline.theta, settings, split,
                                                   judge.residual_and_jacobian(baseline)[1], baseline.free,
                                                   baseline.noise)
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
    # validation record's residual beyond what the parameters' sensitivities can take means the model still lacks
    # something, whatever the fitted record says (an error all in their span is reported, not called unexplained)
    with model.clock("validation record's prediction"):
        predicted = (prediction_report(judge.validation, current.theta, settings,
                                       (model, current.free, r_final, noise_after)) if judge.validation else None)
    if predicted is not None and predicted_left(predicted):
        unexplained = True
    conclusion = _conclusion(added, diag_before, diag_after, unexplained, settings, compensating, predicted,
                             ambiguous, catch_report)
    unrun = [r.label for r in routes if r.skipped and r.skipped == out_of_time]
    conclusion += conclusion_notes(diag_after, unexplained, settings, beyond, edge, judge.glitches or [], unrun,
                                   [r.label for r in routes], pick, routes[0].structure_left,
                                   rough_text(rough, record_noise))
    glitches = judge.glitches or []
    extra = {"ambiguous": ambiguous, "symmetry_gauge": {"before": gauge_before, "after": gauge_after},
             "identifiability_after": uncertainty,
             "compensating": compensating, "rejected": rejected, "backward_elimination": eliminated,
             "noise_model": {"before": noise0.to_dict(), "after": noise_after.to_dict()},
             # what the final model's fit minimised: least squares (white), or the prewhitened residual
             "fits_minimise_under": (current.noise.to_dict() if current.noise is not None else None),
             "localisation": diag_after.get("localisation"),
             "validation_record": validation.name if validation is not None else None, "catch_all": catch_report,
             "validation_prediction": predicted,
             "routes": route_report, "route_comparisons": compared, "glitches": glitches,
             # the domains in the chosen route's gauge widened where an added effect pressed against them
             "domains_widened": {k: list(v) for k, v in plant.widened.items()},
             # the error profiled along the final model's effect parameters (where the fit is off the noise)
             "landscape": [p.to_dict() for p in rough]}
    if with_compensating is not None:
        extra["rmse_with_compensating_m"] = with_compensating.rmse(n)
    seconds = time.perf_counter() - t_start
    # where the loop's time went (exclusive per phase; what no phase marks is "other")
    extra["time_by_phase"] = model.clock.rows(seconds, model.n_sims)
    return DiscoveryResult(record=record.name, n=n, baseline=baseline, final=current, effects_added=added,
                           candidates=cands, iterations=iterations, diagnostics_before=diag_before,
                           diagnostics_after=diag_after, residual_before=r_before, residual_after=r_after,
                           nominal=nominal.to_dict() if isinstance(nominal, IdentificationResult) else None,
                           conclusion=conclusion, unexplained=unexplained, seconds=seconds,
                           n_simulations=model.n_sims, refits=all_refits, extra=extra)


#: why a route was not run: the loop's time budget (``discover.max_seconds``) was spent
OUT_OF_TIME = "the loop's time budget (discover.max_seconds = {:g} s) was spent before it could start"


def compensating_refits(refits: Sequence[Refit], compensating: Sequence[dict], added: Sequence[dict]) -> list[dict]:
    """The refits that lowered the error but were not accepted, one item per effect: its latest refit
    (``refits`` in iteration order) decides, and only when it was judged against a model with every added effect
    (an iteration after the last one that added an effect kept in ``added``) — a stand-in for an effect added later
    lowers the error of a model the loop did not end with (rec32 under prediction-error fits: a dead time and a torque
    saturation, refitted before the cogging torque was added, were listed). Effects already listed as compensating,
    added, or tied with an added one are left out."""
    listed = ({c["name"] for c in compensating} | {a["name"] for a in added}
              | {r["name"] for a in added for r in a.get("indistinguishable_from", ())})
    complete = max((a.get("iteration", 0) for a in added), default=0)
    latest = {rf.name: rf for rf in refits}
    return [{"name": rf.name, "iteration": rf.iteration, "params": rf.params, "reason": rf.reason,
             "evidence": rf.evidence} for rf in latest.values()
            if rf.iteration > complete and rf.lowers_error and not rf.accepted and rf.name not in listed]


def rough_profiles(model: Model, added: Sequence[dict], current: Fit, settings: DiscoverSettings,
                   structure_left: bool, noise_m: float) -> list[Profile]:
    """The error profiled along the parameters of the final model's effects (:func:`.landscape.profiles`, in the
    loop's gauge), where structure is left or the fit ends above 1.5 times the record's own noise ``noise_m``: a rough
    cost there says the error left may be the search's (none when ``discover.rescreen_points`` is 0)."""
    names = [a["name"] for a in added]
    if not (names and settings.rescreen_points and noise_m > 0.0
            and (structure_left or current.rmse(model.n) > NEAR_NOISE * noise_m)):
        return []
    return profiles(model, current.theta, names, settings.rescreen_span, settings.rescreen_points,
                    settings.rescreen_prominence * noise_m)


def at_the_edge(model: Model, added: Sequence[dict], current: Fit) -> list[str]:
    """A sentence for each added effect whose magnitude the final fit left at the edge of its feasible domain in
    the loop's gauge (:func:`.forward.at_bound`)."""
    out = []
    for a in added:
        mag = EFFECTS_BY_NAME[a["name"]].magnitude
        dom = model.domain(mag.name)
        if at_bound(EFFECTS_BY_NAME[a["name"]], float(current.theta[ALL_INDEX[mag.name]]), dom):
            out.append(f"{a['name']}'s {mag.name} ends at the edge of its domain [{dom[0]:.4g}, {dom[1]:.4g}] "
                       f"(in the loop's gauge; +bounds.{mag.name}=[low,high] sets it at the reference scale)")
    return out


def beyond_the_library(added: Sequence[dict], current: Fit, domains: Mapping[str, Sequence[float]],
                       at_reference: bool) -> list[str]:
    """A sentence for each added effect whose magnitude, as ``current`` states it (the report's representative: at
    the reference scale when ``at_reference``, else in the loop's gauge), lies outside its domain at the reference
    scale: the one a user gave (``domains``), else the library's."""
    out = []
    for a in added:
        mag = EFFECTS_BY_NAME[a["name"]].magnitude
        lo, hi = domains.get(mag.name) or (mag.lower, mag.upper)
        value = float(current.theta[ALL_INDEX[mag.name]])
        if not lo <= value <= hi:
            out.append(f"{a['name']}'s {mag.name} reads {value:.4g} {mag.unit} "
                       + ("at the reference scale" if at_reference else "in the loop's gauge (the reference scale "
                          "could not be applied)")
                       + f", outside the library's domain at the reference scale [{lo:.4g}, {hi:.4g}]")
    return out


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
                          "at_reference_scale": bool(gauge_after.get("applied")) and _force_like(eff.magnitude.name),
                          # the HC3 sandwich's variance over the classical one (> 1: the interval was widened for a
                          # noise level that varies along the record)
                          "hc_ratio": (uncertainty.get("hc_ratio") or {}).get(eff.magnitude.name)}
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
