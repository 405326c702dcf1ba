"""The catch-all check: does an accepted effect do anything that a force or a reading error of unknown shape would not?

When structure is left in the residual of the final model, the record holds something the library lacks, and
an accepted effect may only stand in for it — a constant load force for a drag that, on a stroke run mostly
one way, acts nearly as one. Its F-test, BIC and cross-validation cannot tell: each compares the effect
with the model *without* it, and against that model a stand-in does lower the error, in and out of sample.

The check asks the question against a model that could hold the missing physics instead. It fits the final
model with a generic force on slider B, any piecewise-linear function of the slider's speed plus one of its
position (:data:`toggle_id.effects.GENERIC_FORCE`; the knots span the range the record covers, so the
force is a non-parametric stand-in for every friction, drag, load or spring acting there), and with a generic
error of the position reading, any piecewise-linear function of the position on 40 knots
(:data:`toggle_id.effects.GENERIC_SENSOR`: a stand-in for a scale's interpolation error, a bent or misaligned
scale, and for a sensor offset, which it contains; an output map, so it costs no simulation). The reading error is
fitted after the force, from its fit, and kept only where the judge finds it needed beyond the force: its constant
would otherwise make every true sensor offset look unneeded. If the judge finds the generic terms significant
(prewhitened F-test and BIC, and the validation record when given; see :data:`SUPPORT`), every accepted effect is
taken out of the model with them in turn: one whose removal the same checks do
not find significant — or that keeps less than ``catch_all_keep`` (10 %) of the error reduction it brings to the
final model (a least-squares polish converges only so far, and an F-test on thousands of samples finds a 0.1 %
gap) — does nothing the generic force does not do, and is listed as *compensating*, never as added. That share is
read against what the effect would keep were it true (:func:`share_if_true`): the generic terms can span an effect's
own signature (on the paper's sweep the motor angle is a function of x_B, so the position error of a cogging ripple
the servo holds is one too, which the reading error's 40 knots follow), and a true effect then keeps little beside
them by construction; an effect significant beside them that keeps less than ``catch_all_keep`` is still needed when
it keeps at least ``catch_all_keep`` of that calibrated share — where the share is at least ``catch_all_share_min``
(under it the generic terms span a true one too, and the plain floor rules).
An effect of another kind (a cogging torque, a dead time, a backlash) keeps its place, as does any effect when
the generic terms explain nothing more — the missing physics is then neither a force on slider B nor an error of
the reading, and the check decides nothing. The generic terms are never part of the reported model. An effect
kept while still tied with a rival (:mod:`.ties`) has the rival judged there in its place the same way: one the
generic terms make unnecessary stood in for part of what the library lacks, and the tie is resolved for the effect
(:func:`_ties_beside`).

With nothing accepted and structure left, the same fits run for the report alone: whether what is missing acts
like a force on the slider or an error of the reading, or — not supported — like neither: then it is no function
of the slider's position and speed (a command or drive effect, a memory of the motion, something in time).

With ``discover.beside_generic`` (on by default) a forward step that supports nothing while the generic terms are
supported refits the effects of no kind they contain beside them (:func:`beside_generic`), and backward elimination
judges such an effect as it was accepted (:func:`removal_verdict`).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..effects import ALL_INDEX, EFFECTS_BY_NAME, GENERIC_FORCE, GENERIC_SENSOR, sensor_error
from ..kernels.slots import N_GEN, N_GS
from .gauge import freed_with
from .model import Fit, Model, _off_values, _std_errors, _with, fit_free
from .periodic import whole_counts
from .refit import Refit, Scout, from_current, in_sample
from .settings import DiscoverSettings
from .validation import Judge

#: The fitted weights of the generic force (their knots are set from the record). g is held at 0 at its first knot:
#: f and g each hold the constant, and a direction of the fit that changes nothing would slow it down.
FORCE_WEIGHTS: tuple[str, ...] = tuple(nm for nm in GENERIC_FORCE.names if "_w" in nm and nm != "gx_w0")
#: The fitted weights of the generic error of the reading (its knots are set from the record).
SENSOR_WEIGHTS: tuple[str, ...] = tuple(nm for nm in GENERIC_SENSOR.names if "_w" in nm)
WEIGHTS: tuple[str, ...] = FORCE_WEIGHTS + SENSOR_WEIGHTS


#: The judge's checks that decide whether the generic force is supported, and whether an effect is still needed
#: beside it. Not the time-block cross-validation:
#: the force's weights are determined by the few hundred samples in motion (on the experiment sweep ~110 of 5001),
#: a 10-sample block takes out much of what fixes a knot, and the one-step refit of a fold then measures the
#: basis's leverage, not the force (measured on the drag record of tests/test_catchall.py: in sample 1.369 →
#: 0.9989 µm, out of sample 1.29e-8 → 3.65e-8 m², and 5.0e-9 m² with the refit truncated at the directions above
#: 1e-4 of the largest). The force is never accepted: it only casts doubt on effects that were.
SUPPORT: tuple[str, ...] = ("f_test", "bic", "validation_record")


#: The generic terms, for the reasons the check gives.
GENERIC_FORCE_TEXT = "a generic force on slider B (any function of its speed and position)"
GENERIC_READING_TEXT = "error of the position reading (any function of it)"


def _supports(ev) -> bool:
    """Whether the judge's evidence ``ev`` passes the checks of :data:`SUPPORT` it ran."""
    return all(ok for check, ok in ev.checks.items() if check in SUPPORT)


def _needed(ev, kept_fraction: float, settings: DiscoverSettings, share: float = 1.0) -> bool:
    """Whether an effect is still needed beside the generic terms: the judge's evidence ``ev`` passes the checks of
    :data:`SUPPORT`, and it keeps at least ``catch_all_keep`` of what it explains without them — of what a true
    effect of its size would keep there, ``share`` (:func:`share_if_true`; 1: the generic terms cannot do its work)."""
    return _supports(ev) and kept_fraction >= settings.catch_all_keep * min(1.0, max(share, 0.0))


def _judged(ev, kept_fraction: float, settings: DiscoverSettings,
            share: Callable[[], float | None]) -> tuple[bool, float | None]:
    """(needed, the calibrated share or None) of an effect or a tied rival beside the generic terms: needed by the
    plain floor, or — significant there but under it, with ``catch_all_calibrated`` — by the share a true one of its
    size keeps there (``share()``, asked only then: it fits a noise-free twin) — unless that share is under
    ``catch_all_share_min``: the generic terms then span a true one too, and keeping it would rest on significance
    alone (rec25_d1: a scale error's constant part named as a sensor offset, 0.2 % kept against 0.3 %)."""
    plain = _needed(ev, kept_fraction, settings)
    if plain or not (_supports(ev) and settings.catch_all_calibrated):
        return plain, None
    calibrated = share()
    seen = calibrated is not None and calibrated >= settings.catch_all_share_min  # else the generic terms span it
    return seen and _needed(ev, kept_fraction, settings, calibrated), calibrated


def _share_text(share: float | None, settings: DiscoverSettings) -> str:
    """The calibrated share's clause of a catch-all log line (empty when none was asked)."""
    if share is None:
        return ""
    return (f", and a true one of its size {share:.1%} there, noise-free"
            + (": they span it, too little to tell" if share < settings.catch_all_share_min else ""))


def _in_place(current: Fit, a: dict, rival: dict) -> Fit:
    """The final model ``current`` with effect ``a`` switched off and its tied ``rival`` on at the rival's values
    (the model a true rival of that size would be; its other parameters as fitted with ``a``), free as ``current``
    less ``a``'s parameters."""
    theta = _with(_with(current.theta, _off_values(EFFECTS_BY_NAME[a["name"]])), rival["params"])
    names = EFFECTS_BY_NAME[a["name"]].names
    return replace(current, theta=theta, free=tuple(nm for nm in current.free if nm not in names))


def _generic_fit(model: Model, start: np.ndarray, free: Sequence[str], shaping: tuple[str, ...],
                 weights: tuple[str, ...], settings: DiscoverSettings) -> Fit:
    """The generic terms ``weights`` fitted on ``model`` from ``start``: ``shaping`` alone first (their shape, the
    model held), then ``free`` and ``weights`` together."""
    shaped = fit_free(model, start, shaping, settings.baseline_nfev, settings.fd_rel_step)
    return fit_free(model, shaped.theta, tuple(free) + weights, settings.baseline_nfev, settings.fd_rel_step,
                    rounds=settings.rounds)


def share_if_true(model: Model, current: Fit, a: dict, knots: dict, weights: tuple[str, ...],
                  settings: DiscoverSettings) -> float | None:
    """The share of its gain that effect ``a``, were it true at its fitted size, keeps beside the generic terms
    ``weights``: the final model ``current`` simulated without noise (a twin of ``model``: the same integrators,
    domains, noise model and samples left out), refitted there without ``a`` and then with the generic terms as the
    check fits them (the force first, then the reading error) — SSE with them over SSE without ``a``. None when the
    twin cannot be simulated or ``a`` explains nothing there."""
    x = model.outputs(current.theta[None, :])[0]
    if not np.all(np.isfinite(x)):
        return None
    twin = Model(replace(model.record, x_B=x), model.settings, model.parallel,
                 jacobian=(model.jacobian, model.jacobian_step), jacobian_reuse=model.jacobian_reuse,
                 derivatives=model.derivatives)
    twin.noise, twin.stiff, twin.excluded = model.noise, set(model.stiff), model.excluded
    twin.bounds, twin.gauge_bounds = dict(model.bounds), dict(model.gauge_bounds)
    effect = EFFECTS_BY_NAME[a["name"]]
    off = fit_free(twin, _with(current.theta, _off_values(effect)),
                   tuple(nm for nm in current.free if nm not in effect.names), settings.baseline_nfev,
                   settings.fd_rel_step, rounds=settings.rounds)
    share = None
    if off.sse > 0:
        generic = _generic_fit(twin, _with(off.theta, knots), off.free, FORCE_WEIGHTS, FORCE_WEIGHTS, settings)
        if weights != FORCE_WEIGHTS:
            generic = _generic_fit(twin, generic.theta, off.free, SENSOR_WEIGHTS, weights, settings)
        share = float(np.clip(generic.sse / off.sse, 0.0, 1.0))
    model.n_sims += twin.n_sims  # the job's count of simulations holds the twin's
    return share


def model_state(model: Model) -> tuple:
    """What a fit of ``model`` depends on besides its start and free names: the noise model it minimises under, the
    domains, the integrators, the effect sets sent straight to the stiff fallback and the samples left out. Two fits
    from the same start in the same state are the same fit, bit for bit."""
    excluded = None if model.excluded is None else model.excluded.tobytes()
    return (model.noise.a, tuple(sorted(model.domains().items())), model.settings, model.jacobian,
            model.jacobian_step, model.jacobian_reuse, model.derivatives, frozenset(model.stiff), excluded)


def reusable(seen: Fit, fit: Fit, state: tuple, model: Model) -> bool:
    """Whether fits made on ``seen`` with the model in ``state`` (:func:`model_state`) are what the same fits on
    ``fit`` would give now: the same values, free names and noise model, and the model in that state still."""
    return (seen.theta.tobytes() == fit.theta.tobytes() and tuple(seen.free) == tuple(fit.free)
            and seen.minimised_under == fit.minimised_under and model_state(model) == state)


def knots_of(states: dict, x_measured: np.ndarray) -> dict[str, float]:
    """The knot ranges of the generic terms, each from the smallest to the largest value on the record: the force's
    from a model's plant states (slider B's speed and position), the sensor error's from the measured position
    (the range the reading covers; the error is evaluated at the model's position, constant beyond its knots)."""
    v = np.asarray(states["xdot_B"], float)
    x = np.asarray(states["x_B"], float)
    xm = np.asarray(x_measured, float)
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(x)) and np.all(np.isfinite(xm))):
        raise ValueError("the plant states or the measured position are not finite")
    return {"gv_lo": float(v.min()), "gv_hi": float(v.max()), "gx_lo": float(x.min()), "gx_hi": float(x.max()),
            "gs_lo": float(xm.min()), "gs_hi": float(max(xm.max(), xm.min() + 1e-6))}  # a record at rest: 1 µm


def shape_of(theta: np.ndarray) -> dict[str, list[float]]:
    """The generic terms of ``theta`` at their knots: speeds ``v_m_s`` and f (N), positions ``x_m`` and g (N);
    measured positions ``xs_m`` and the sensor error h (m). f is fixed only up to a constant that g (held at 0 at
    its first knot) and any constant slider force of the model share with it; h's constant is shared with a
    sensor offset of the model."""
    th = np.asarray(theta, float)
    v = np.linspace(th[ALL_INDEX["gv_lo"]], th[ALL_INDEX["gv_hi"]], N_GEN)
    x = np.linspace(th[ALL_INDEX["gx_lo"]], th[ALL_INDEX["gx_hi"]], N_GEN)
    xs = np.linspace(th[ALL_INDEX["gs_lo"]], th[ALL_INDEX["gs_hi"]], N_GS)
    f = [float(th[ALL_INDEX[f"gv_w{k}"]]) for k in range(N_GEN)]
    g = [float(th[ALL_INDEX[f"gx_w{k}"]]) for k in range(N_GEN)]
    h = [float(th[ALL_INDEX[f"gs_w{k}"]]) for k in range(N_GS)]
    return {"v_m_s": v.tolist(), "f_N": f, "x_m": x.tolist(), "g_N": g, "xs_m": xs.tolist(), "h_m": h}


#: The share of the sensor error's variance a straight line must hold for the report to call it a scale error
#: (a description of the fitted shape; no verdict reads it).
TREND_R2 = 0.5


def trend_of(shape: dict[str, list[float]]) -> dict[str, float]:
    """The straight-line part of the sensor error h of ``shape`` (:func:`shape_of`) over its knots, uniform along the
    measured range: ``scale_error`` (its slope, m/m: a scale's thermal expansion or a wrong resolution reads as one),
    ``rise_m`` over the range, and ``r2``, the share of h's variance over the knots that the line holds (0 when h is
    flat)."""
    xs, h = np.asarray(shape["xs_m"], float), np.asarray(shape["h_m"], float)
    slope, icpt = np.polyfit(xs, h, 1)
    var = float(np.var(h))
    r2 = 1.0 - float(np.var(h - (slope * xs + icpt))) / var if var > 0 else 0.0
    return {"scale_error": float(slope), "rise_m": float(slope * (xs[-1] - xs[0])), "r2": r2}


def reading_needed(report: dict) -> bool:
    """Whether the catch-all ``report`` kept the generic error of the reading beside the force (reports written before
    the two were judged apart always had it)."""
    return bool((report.get("reading_error") or {}).get("needed", True))


def figure(report: dict, title: str | None = None):
    """The fitted generic terms: f against slider B's speed, g against its position and the sensor error h against
    the measured position, at the knots (a matplotlib Figure)."""
    from ..figures import _finish, _new_figure

    sh = report["shape"]
    fig, (a1, a2, a3) = _new_figure(1, 3, height=3.4, width=13.0)
    a1.plot(np.asarray(sh["v_m_s"]) * 1e3, sh["f_N"], "o-")
    a1.set_xlabel("slider B speed ẋ_B (mm/s)")
    a1.set_ylabel("f(ẋ_B) (N, opposes closing)")
    a2.plot(np.asarray(sh["x_m"]) * 1e3, sh["g_N"], "o-", color="tab:orange")
    a2.set_xlabel("slider B position x_B (mm)")
    a2.set_ylabel("g(x_B) (N)")
    a3.plot(np.asarray(sh["xs_m"]) * 1e3, np.asarray(sh["h_m"]) * 1e6, ".-", color="tab:green")
    a3.set_xlabel("measured position x_B (mm)")
    a3.set_ylabel("h(x_B), error of the reading (µm)")
    reading = reading_needed(report)
    if not reading:
        a3.set_title("not needed beside the force: left out", fontsize=9)
    for ax in (a1, a2, a3):
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.grid(alpha=0.3)
    terms = "A generic force on slider B" + (" and a generic error of the position reading" if reading else "")
    return _finish(fig, title or f"{terms} on top of the final model: rms {report['rmse_before_m'] * 1e6:.4g} → "
                              f"{report['rmse_m'] * 1e6:.4g} µm\n(fitted beside the model's effects: f up to a "
                              "constant shared with g and any load; h's constant shared with a sensor offset)")


def catch_all(model: Model, judge: Judge, current: Fit, added: Sequence[dict], states: dict,
              without: Callable[[Fit, dict], Fit], settings: DiscoverSettings, say: Callable[[str], None],
              store: dict | None = None, with_rival: Callable[[Fit, dict], Fit] | None = None,
              looked: tuple[Fit, Fit] | None = None) -> tuple[list[dict], list[dict], dict]:
    """(kept, compensating, report) of the accepted effects ``added`` of the final model ``current`` (structure
    left in its residual; ``states``: its plant states). ``without(fit, a)``: ``fit`` refitted with effect ``a``
    switched off; ``with_rival(fit, rival)``: ``fit`` refitted with a tied rival ({name, params}) switched on,
    started at its params — given, the ties of a kept effect are judged beside the generic terms too
    (:func:`_ties_beside`); ``store``: given, receives the fit with the generic terms (``generic``) and the two fits
    they start from (``force``, the generic force alone; ``both``, the reading error beside it); ``looked``: those two
    fits made before on ``current`` with the model in the same state (the caller checks the state), used instead of
    fitting them again when their knots are this record's. See the module docstring."""
    n = model.n
    knots = knots_of(states, model.record.x_B)

    # the force first, then the reading error beside it (nested: from the force's fit). The reading error is kept
    # only if the judge finds it needed beyond the force: it contains a constant, so a true sensor offset would
    # otherwise always be "done" by it, whatever else it finds to do
    if looked is not None and all(looked[0].theta[ALL_INDEX[k]] == v for k, v in knots.items()):
        force, both = looked
        say("catch-all: the generic terms fitted on this model before (its second look), the model as it was then")
    else:
        force = _generic_fit(model, _with(current.theta, knots), current.free, FORCE_WEIGHTS, FORCE_WEIGHTS, settings)
        both = _generic_fit(model, force.theta, current.free, SENSOR_WEIGHTS, WEIGHTS, settings)
    ev_reading = judge.judge_pair(force, both)
    reading = _supports(ev_reading)
    weights, generic = (WEIGHTS, both) if reading else (FORCE_WEIGHTS, force)
    free = tuple(current.free) + weights

    def taken_out(a: dict) -> Fit:  # the generic terms take over first (the model held), then the whole refit
        off = fit_free(model, _with(generic.theta, _off_values(EFFECTS_BY_NAME[a["name"]])), weights,
                       settings.baseline_nfev, settings.fd_rel_step)
        return without(replace(off, free=generic.free), a)

    reduced: dict[str, Fit] = {}
    for attempt in range(len(added) + 1 if added else 0):  # none added: the report alone (what is missing acts like)
        reduced = {a["name"]: taken_out(a) for a in added}
        # nested models: the fit with every effect can do what one without an effect did; a polish stuck above it
        # is continued from there, and the effects are taken out of that better fit again
        best = min(reduced.values(), key=lambda f: f.sse)
        if best.sse >= generic.sse or attempt == len(added):
            break
        generic = fit_free(model, best.theta, free, settings.baseline_nfev, settings.fd_rel_step,
                           rounds=settings.rounds)
    if store is not None:
        store.update(generic=generic, force=force, both=both)
    ev = judge.judge_pair(current, generic)
    # supported in sample, and by the validation record when there is one; not by the time-block cross-validation
    # (see SUPPORT)
    supported = _supports(ev)
    shape = shape_of(generic.theta)
    report = {"knots": knots, "n_knots": N_GEN, "n_knots_sensor": N_GS,
              "rmse_before_m": current.rmse(n), "rmse_m": generic.rmse(n),
              "reading_error": {"needed": reading, "rmse_force_only_m": force.rmse(n),
                                "rmse_with_it_m": both.rmse(n), "evidence": ev_reading.to_dict()},
              "evidence": ev.to_dict(), "supported": supported, "support_checks": list(SUPPORT),
              "shape": shape, "effects": {}, "sensor_trend": trend_of(shape),
              # at the measured positions (the model's are a simulation away; they differ by the residual), about
              # its mean: h's constant is shared with the model's sensor offset
              "sensor_rms_m": float(np.std(sensor_error(generic.theta, model.record.x_B)))}
    say(f"catch-all: a generic slider force f(ẋ_B) + g(x_B) on top of the final model: rms "
        f"{current.rmse(n) * 1e6:.4g} → {force.rmse(n) * 1e6:.4g} µm; a generic sensor error h(x_B) beside it: "
        f"{both.rmse(n) * 1e6:.4g} µm, "
        + ("needed" if reading else f"not needed ({ev_reading.reason})") + "; the generic terms: "
        + ("supported" if supported else "not supported (" + ev.reason + "); they decide nothing"))
    if not supported:
        return list(added), [], report
    kept, compensating = [], []
    terms = GENERIC_FORCE_TEXT + (f" and {GENERIC_READING_TEXT}" if reading else "")
    for a in added:
        small = reduced[a["name"]]
        ev_a = judge.judge_pair(small, generic)
        # what the effect still explains beside the generic force, as a fraction of what it explains without it
        alone = a.get("_reduced") or without(current, a)
        gain = alone.sse - current.sse
        kept_fraction = float((small.sse - generic.sse) / gain) if gain > 0 else 0.0
        needed, share = _judged(ev_a, kept_fraction, settings, lambda: share_if_true(model, current, a, knots,
                                                                                      weights, settings))
        # its values beside the generic terms: where the final model leaves structure, its own values may stand in
        # for part of what is missing (rec38: a_cog 0.0106 N·m in its final model, 0.0058 when first fitted beside
        # the generic terms; truth 0.0052)
        values = {nm: float(generic.theta[ALL_INDEX[nm]]) for nm in EFFECTS_BY_NAME[a["name"]].names}
        report["effects"][a["name"]] = {"rmse_without_m": small.rmse(n), "rmse_final_without_m": alone.rmse(n),
                                        "kept_fraction": kept_fraction, "share_if_true": share,
                                        "evidence": ev_a.to_dict(),
                                        "needed": needed, "values_with_generic": values}
        say(f"  without {a['name']}: rms {small.rmse(n) * 1e6:.4g} µm (it keeps {kept_fraction:.1%} of what it "
            f"explains without the generic force" + _share_text(share, settings) + f"; {ev_a.reason}) → "
            + ("still needed" if needed else "not needed"))
        if needed:
            kept.append(a)
            if with_rival is not None and a.get("indistinguishable_from"):
                _ties_beside(a, small, gain, judge, with_rival, settings, n, terms, say,
                             report["effects"][a["name"]],
                             lambda rv, a=a: share_if_true(model, _in_place(current, a, rv), rv, knots, weights,
                                                           settings))
        else:
            compensating.append(dict(a, reason=(
                f"lowers the error, but {GENERIC_FORCE_TEXT}" + (f" or {GENERIC_READING_TEXT}" if reading else "")
                + " does its work: with them "
                f"{generic.rmse(n) * 1e6:.4g} µm, and {small.rmse(n) * 1e6:.4g} µm "
                f"without {a['name']} (it keeps {kept_fraction:.1%} of what it explains in the final model, "
                f"{alone.rmse(n) * 1e6:.4g} → {current.rmse(n) * 1e6:.4g} µm). It stands in for something outside "
                "the library")))
    return kept, compensating, report


def _ties_beside(a: dict, small: Fit, gain_a: float, judge: Judge,
                 with_rival: Callable[[Fit, dict], Fit], settings: DiscoverSettings, n: int, terms: str,
                 say: Callable[[str], None], entry: dict, share_of: Callable[[dict], float | None]) -> None:
    """The ties of an effect ``a`` the catch-all check keeps, judged beside the generic terms as ``a`` was.

    ``small``: the fit with the generic terms (``terms``, for the reason) and without ``a``; ``gain_a``: what ``a``
    explains without them (the SSE of the final model without ``a`` less the final model's, both minimised under
    the same noise model). Each rival is switched on in ``a``'s place there (``with_rival``) and needed as ``a`` is:
    supported by the judge's checks of :data:`SUPPORT`, and keeping ``catch_all_keep`` of what it explains without
    the generic terms — ``gain_a``, since the two are tied: the whitened fits the tie compared gain alike (their raw
    errors may differ: on rec38 3.159 µm with the rival in the cogging's place, 2.922 µm with the cogging). A rival
    the generic terms make unnecessary while ``a`` stays needed does what a force on slider B or an error of the
    reading of unknown shape does: it stood in for part of what the library lacks, which also hid the difference
    between the two (rec38 of the adversarial set: a Stribeck friction tied with the cogging torque beside a
    quadratic drag). It moves to ``a``'s ``ties_resolved``; a rival still needed stays tied. Edits ``a`` in place;
    ``entry`` (``a``'s entry in the report) receives each rival's case under ``rivals``. A rival significant there
    but under the floor is held to the rule ``a`` was (:func:`_judged`): ``share_of(rival)``, the share a true rival
    of its size keeps beside the generic terms (:func:`share_if_true` on the final model with the rival in ``a``'s
    place, :func:`_in_place`), so the floor that kept ``a`` by its calibrated share cannot resolve the tie against
    a rival the generic terms span as much."""
    keep, resolved = [], []
    for rv in a["indistinguishable_from"]:
        big = with_rival(small, rv)
        ev = judge.judge_pair(small, big)
        frac = float((small.sse - big.sse) / gain_a) if gain_a > 0 else 0.0
        needed, share = _judged(ev, frac, settings, lambda: share_of(rv))  # asked, if at all, in this iteration
        case = {"rmse_with_it_m": big.rmse(n), "kept_fraction": frac, "share_if_true": share,
                "evidence": ev.to_dict(), "needed": needed}
        entry.setdefault("rivals", {})[rv["name"]] = case
        say(f"  its rival {rv['name']} in its place beside the generic terms: rms {small.rmse(n) * 1e6:.4g} → "
            f"{big.rmse(n) * 1e6:.4g} µm (it keeps {frac:.1%} of what it explains without them"
            + _share_text(share, settings) + f"; {ev.reason}) → "
            + ("still needed: the tie stays" if needed else f"not needed: the tie is resolved for {a['name']}"))
        if needed:
            keep.append(rv)
        else:
            resolved.append({**rv, "beside_generic": case, "reason": (
                f"beside {terms} {rv['name']} in its place is not needed ({small.rmse(n) * 1e6:.4g} → "
                f"{big.rmse(n) * 1e6:.4g} µm, {frac:.1%} of what it explains without them) and {a['name']} is: "
                f"{rv['name']} stood in for part of what the library lacks")})
    a["indistinguishable_from"] = keep
    if resolved:
        a["ties_resolved"] = [*a.get("ties_resolved", []), *resolved]


def beside_generic(model: Model, judge: Judge, base: Fit, generic: Fit, scouts: Sequence[Scout],
                   settings: DiscoverSettings, held: Sequence[str], iteration: int, say: Callable[[str], None]
                   ) -> list[Refit]:
    """The effects of ``scouts`` refitted beside the generic terms (``generic``: the model ``base`` with them, fitted
    by :func:`catch_all`) — a forward step against a model that no longer bends to the missing physics. Each effect's
    parameters are fitted on ``generic`` from its scout (:func:`.refit.from_current`), then everything; one the judge
    supports there (every check, out of sample too) is refitted on ``base`` from the values reached (a cogging
    torque's count held at its whole value, when it has one) and accepted where it also lowers the error there in
    sample (:attr:`.refit.Refit.lowers_error`): beside physics the library
    lacks, its out-of-sample gain may show only once that physics is taken (rec38 of the adversarial set: a cogging
    torque beside a quadratic drag). Give it effects of no kind the generic terms contain (a force on the slider, an
    error of the reading): those are judged by :func:`catch_all`. The generic terms are never part of a model the
    loop reports."""
    n = model.n
    out = []
    for sc in scouts:
        eff = EFFECTS_BY_NAME[sc.name]
        start = from_current(model, generic, sc, settings)
        if start.theta is None:
            continue
        big = fit_free(model, start.theta, freed_with(generic.free, eff, held), settings.baseline_nfev,
                       settings.fd_rel_step, rounds=settings.rounds)
        ev = judge.judge_pair(generic, big)
        values = {nm: float(big.theta[ALL_INDEX[nm]]) for nm in eff.names}
        say(f"  beside the generic terms, {eff.name}: rms {generic.rmse(n) * 1e6:.4g} → {big.rmse(n) * 1e6:.4g} µm "
            f"at {', '.join(f'{k} {v:.4g}' for k, v in values.items())} ({ev.reason})")
        if not ev.passed:
            continue
        free = freed_with(base.free, eff, held)
        # a motor's count, determined beside the generic terms, is held at its whole value from here on: without
        # them it drifts to where the ripple stands in for the missing physics (rec38: to the floor of
        # discover.cogging_min_periods, 4.53, at the same error as at 6.03)
        whole = whole_counts(eff.name, big.theta, free, settings.cogging_whole_tol)
        values.update({nm: float(k) for nm, k in whole.items()})
        free = tuple(nm for nm in free if nm not in whole)
        fit = fit_free(model, _with(base.theta, values), free, settings.baseline_nfev, settings.fd_rel_step,
                       rounds=settings.rounds)
        rf = Refit(eff.name, iteration, fit, {nm: float(fit.theta[ALL_INDEX[nm]]) for nm in eff.names}, base.sse,
                   fit.sse, len(free) - len(base.free), len(free), 0.0, 1.0, float("inf"), False, "",
                   {"beside_generic": {"rmse_generic_m": generic.rmse(n), "rmse_with_it_m": big.rmse(n),
                                       "values": values}},
                   std_errors=_std_errors(fit, [nm for nm in eff.names if nm in free], n))
        rf.judge(judge.judge_pair(base, fit), base.sse)
        rf.evidence["beside_generic"] = ev.to_dict()
        if rf.lowers_error and not rf.accepted:
            rf.accepted = True
            rf.reason = ("supported beside a generic slider force and reading error (" + ev.reason + "), and without "
                         "them significant in sample; " + rf.reason + " without them")
        say(f"  refit {eff.name} from there, without the generic terms: rms {fit.rmse(n) * 1e6:.4g} µm, F {rf.F:.3g}, "
            f"→ {'accepted' if rf.accepted else 'rejected: ' + rf.reason}")
        out.append(rf)
    return out


@dataclass
class KeptBeside:
    """Backward elimination's verdict on an effect accepted beside the generic terms (:func:`beside_generic`) whose
    removal costs in sample but not out of sample: kept, as it was accepted — its out-of-sample gain shows only
    once the physics the library lacks is taken by the generic terms (``evidence``: the judge's verdict)."""

    evidence: object
    passed: bool = True

    @property
    def reason(self) -> str:
        return ("significant in sample; accepted beside the generic terms, where it was better out of sample ("
                + self.evidence.reason + " without them)")

    def to_dict(self) -> dict:
        return {**self.evidence.to_dict(), "passed": True, "reason": self.reason}


def accepted_beside(item: dict) -> dict | None:
    """The judge's evidence beside the generic terms of an item :func:`beside_generic` accepted (None: the item was
    accepted the ordinary way)."""
    return (item.get("evidence") or {}).get("beside_generic")


def removal_verdict(ev, item: dict):
    """The verdict on removing ``item`` given the judge's ``ev``: ``ev`` itself, or :class:`KeptBeside` for an effect
    accepted beside the generic terms whose removal ``ev`` finds significant in sample only."""
    if ev.passed or accepted_beside(item) is None or not in_sample(ev.checks):
        return ev
    return KeptBeside(ev)
