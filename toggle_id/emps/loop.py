"""The EMPS plant of the discovery engine (:class:`EmpsPlant`) and its job's loop, :func:`run_emps_loop`: the
engine's loop (:func:`toggle_id.discovery.engine.run_loop`, the toggle plant's too) over this plant.

It fits the nominal model (M, Fv) by output error (:mod:`.fit`), then adds effects from
:data:`~toggle_id.emps.model.EFFECTS` greedily, each judged by :func:`~.fit.judge_effect` into the discovery
engine's verdict object, :class:`toggle_id.discovery.validation.Evidence`, with its statistics
(:mod:`toggle_id.discovery.noise`, :mod:`toggle_id.discovery.stats`) and its acceptance rule plus an
identifiability gate. The residuals of a 1 kHz closed loop are strongly autocorrelated, so counting N ≈ 25 000
independent samples would make any test far too lenient; instead every comparison describes the noise by an
AR(p) model fitted (Yule–Walker, order by BIC) to the *larger* model's residual and computes its statistics on
prewhitened signals. A candidate is accepted only if the prewhitened F-test gives p < alpha, the prewhitened
ΔBIC < 0, the time-block cross-validated whitened SSE drops (both fits linearised at their optimum with their own
Jacobians) and its new parameters stay identifiable (|correlation| ≤ max_corr); among those that pass, the one
with the lowest prewhitened SSE is taken, all of a round's residuals whitened by one noise model (that of the
refit that explains the most, as the toggle plant ranks its refits).

Then the engine's verdict rules (:func:`toggle_id.discovery.engine.verdict_rules`): backward elimination, and — when
the noise-aware structure test (:func:`toggle_id.discovery.localise.locate`) finds structure left in the final
position residual — an accepted effect that removed less than ``explain_fraction`` of the structure energy is
listed as compensating, not added; and an accepted effect that the record cannot tell apart from another that
passed the same round (:mod:`toggle_id.discovery.ties`: Vuong's test, judged again on the final model when it was
found in an earlier round, and by the model with both) is reported with it as *ambiguous*, neither named as added.
The report: the three lists (``effects_added``, ``compensating``, ``rejected``), and where structure concentrates.
"""
from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from ..discovery.engine import Step, run_loop
from ..discovery.localise import locate, noise_level, structure_energy
from ..discovery.model import strictly_inside
from ..discovery.noise import fit_noise, whitened_sse
from ..discovery.ties import indistinguishable
from ..discovery.validation import Evidence
from ..errors import ConfigError, DataError
from ..polish import one_blas_thread
from ..residuals import glitch_report, glitches
from .data import EmpsRecord
from .fit import (
    OEFitResult,
    _check_solver,
    _compare_published,
    effect_last,
    evidence_entry,
    fit_output_error,
    judge_effect,
    new_params_corr,
    predict_validation,
    significant_in_sample,
)
from .idim import idim_ls
from .model import (EFFECTS, INDEX, LOWER, NOMINAL_NAMES, OFF, PUBLISHED, PUBLISHED_THETA, UPPER, Effect,
                    position_rel_error_pct, simulate_emps)


def _rank_passing(refits: Sequence[tuple[dict, OEFitResult, Effect]],
                  noise_max_order: int) -> tuple[tuple[dict, OEFitResult, Effect] | None, dict]:
    """The refit to accept among those whose checks all passed: the lowest prewhitened SSE, every residual of the
    round whitened by one noise model, as the toggle plant ranks its refits (:mod:`toggle_id.discovery.loop`):
    the AR model of the residual of the refit that explains the most (lowest raw SSE). Each candidate's own noise
    model (the one its tests use) would not do for the ranking: a residual that keeps more structure gets a noise
    model that predicts it and a smaller whitened SSE. Sets ``sse_w_round`` on every entry; returns the chosen
    (entry, fit, effect) or None, and {lead, noise_model} of the round."""
    finite = [rf for rf in refits if rf[1].residual is not None and np.all(np.isfinite(rf[1].residual))]
    if not finite:
        return None, {"lead": None, "noise_model": None}
    lead = min(finite, key=lambda rf: rf[1].sse)
    noise = fit_noise(lead[1].residual, noise_max_order)
    for entry, fit, _ in refits:
        ok = fit.residual is not None and np.all(np.isfinite(fit.residual))
        entry["sse_w_round"] = float(whitened_sse(noise, fit.residual)[0]) if ok else float("inf")
    passing = [rf for rf in refits if rf[0]["passed"]]
    chosen = min(passing, key=lambda rf: rf[0]["sse_w_round"]) if passing else None
    return chosen, {"lead": lead[2].name, "noise_model": noise.to_dict()}


def _ties(chosen: tuple[dict, OEFitResult, Effect], refits: Sequence[tuple[dict, OEFitResult, Effect]],
          noise_max_order: int, alpha: float) -> list[dict]:
    """The other refits of the round that passed every check and that the record cannot tell apart from the
    chosen one (:func:`toggle_id.discovery.ties.indistinguishable`): [{name, params, vuong}]."""
    if not alpha > 0:
        return []
    others = [rf for rf in refits if rf[0]["passed"] and rf is not chosen]
    found = indistinguishable(chosen[1].residual, len(chosen[2].params),
                              [(rf[1].residual, len(rf[2].params)) for rf in others], noise_max_order, alpha)
    return [{"name": rf[2].name, "params": dict(rf[0]["params"]), "vuong": v} for rf, v in zip(others, found)
            if v["tied"]]


def localisation_signals(record: EmpsRecord, theta: np.ndarray,
                         sim_options: Mapping | None = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The position residual qm − q_sim of the model ``theta`` (m) and the signals the structure test bins it by
    (keys of :data:`toggle_id.discovery.localise.SIGNALS`): the simulated load position ``q`` (m), the position
    signed by the direction of motion ``q_dir`` = q·sign(q̇) (m: forward strokes on the positive side, backward ones
    on the negative side, so that a friction force localised on the stroke — which changes sign with the motion
    and averages out in bins of q alone — shows as a level per bin), the velocity ``qdot`` (m/s, central
    differences of q), the simulated drive force ``force`` = gtau·ν (N), the record's controller output ``vir`` (V)
    and the time ``t`` (s). NaN where the simulation fails."""
    sim = simulate_emps(theta, record, **dict(sim_options or {}))
    q, nu = sim.q[0], sim.nu[0]
    qdot = np.gradient(q, record.dt) if np.all(np.isfinite(q)) else np.full(record.n, np.nan)
    return record.residual(q), {"q": q, "q_dir": q * np.sign(qdot), "qdot": qdot, "force": record.gtau * nu,
                                "vir": np.asarray(record.vir, float), "t": np.asarray(record.t, float)}


def localise(record: EmpsRecord, theta: np.ndarray, sim_options: Mapping | None = None, *, bins: int = 12,
             alpha: float = 0.01, fit: OEFitResult | None = None) -> dict:
    """Is structure left in the position residual of ``theta``, and where? :func:`toggle_id.discovery.localise.locate`
    with no fixed noise model (each family judged under the AR noise model of its own alternative; the verdict robust
    to a noise level that varies, as the toggle loop's) on the signals of :func:`localisation_signals`; position,
    position signed by the direction of motion and velocity enter the verdict (Bonferroni over the three), drive
    force, controller output and time are shown (in a closed loop the controller output carries the position error
    itself). Returns locate's dict (``structure_left``, ``families``, ``significant``, ``strongest``, ``text``) with
    ``noise_level`` (report-only, :func:`toggle_id.discovery.localise.noise_level`); ``{"error": ...}`` when the
    model cannot be simulated on the record. With the output-error ``fit`` of ``theta``, the verdict also asks whether
    it reached its minimum (:func:`toggle_id.discovery.localise.convergence`, least squares, on its Jacobian's columns
    of the parameters inside their bounds), as the toggle plant's does."""
    r, signals = localisation_signals(record, theta, sim_options)
    if not (np.all(np.isfinite(r)) and all(np.all(np.isfinite(v)) for v in signals.values())):
        return {"error": "the final model cannot be simulated on the record", "structure_left": None,
                "text": "no localisation: the final model cannot be simulated on the record"}
    fitted = None
    if fit is not None and fit.jacobian is not None:
        idx = np.array([INDEX[n] for n in fit.free], dtype=np.int64)
        fitted = fit.jacobian[:, strictly_inside(np.asarray(fit.theta, float)[idx], LOWER[idx], UPPER[idx])]
    out = locate(None, r, signals, bins=int(bins), alpha=float(alpha), robust=True, fitted=fitted)
    out["noise_level"] = noise_level(fit_noise(r), r, signals, bins=int(bins), alpha=float(alpha))
    return out


def three_lists(names: Sequence[str], tried: Sequence[dict], evidence: Mapping[int, Evidence],
                max_effects: int | None) -> tuple[list[dict], list[dict], list[dict]]:
    """The verdict per effect, as the toggle plant's ``discovery.json`` gives it: ``effects_added`` (accepted),
    ``compensating`` (its last refit is significant in sample — prewhitened F-test and BIC pass — but no better out
    of sample or not identifiable; never called added) and ``rejected`` (not significant in sample, passed but left
    out by ``max_effects``, or never refitted because an effect it refines is not in the model). Unlike the toggle
    loop, structure left in the final residual does not move the accepted effects to ``compensating``: each passed
    all four checks against the model before it, and the structure test reports separately what is left. Each item:
    ``name``, ``round``, ``params``, ``reason``, ``evidence`` (``Evidence.to_dict()`` of its last judgement, None if
    never judged); an added effect also has ``F``, ``p_value``, ``delta_bic``. ``evidence`` maps ``id(entry)`` of
    the ``tried`` entries to their :class:`Evidence`."""
    added, compensating, rejected = [], [], []
    for name in names:
        mine = [c for c in tried if c["name"] == name]
        if not mine:
            req = [r for r in EFFECTS[name].requires]
            rejected.append({"name": name, "round": None, "params": {}, "evidence": None,
                             "reason": "never refitted: it refines " + ", ".join(req) + ", which is not in the model"
                             if req else "never refitted"})
            continue
        last = next((c for c in mine if c["accepted"]), mine[-1])
        ev = evidence[id(last)]
        item = {"name": name, "round": last["round"], "params": dict(last["params"]), "reason": ev.reason,
                "evidence": ev.to_dict()}
        if last["accepted"]:
            added.append(added_item(last, ev))
        elif ev.passed:
            item["reason"] = (f"passed every check in round {last['round']} but was not added: the limit "
                              f"emps.max_effects = {max_effects} was reached")
            rejected.append(item)
        elif significant_in_sample(ev):
            item["reason"] = "significant in sample (prewhitened F-test, its robust twin and BIC), but " + ev.reason
            compensating.append(item)
        else:
            rejected.append(item)
    added.sort(key=lambda a: a["round"])
    return added, compensating, rejected


def added_item(entry: dict, ev: Evidence) -> dict:
    """The item of an accepted effect (``entry`` of the round that accepted it, judged by ``ev``), as
    ``effects_added`` lists it."""
    return {"name": entry["name"], "round": entry["round"], "params": dict(entry["params"]), "reason": ev.reason,
            "evidence": ev.to_dict(), "F": ev.F, "p_value": ev.p_value, "delta_bic": ev.delta_bic,
            "indistinguishable_from": list(entry.get("indistinguishable_from") or [])}


class EmpsPlant:
    """The EMPS axis as a plant of the discovery engine (:class:`toggle_id.discovery.engine.Plant`): a round refits
    every remaining candidate whose ``requires`` are in the model (well under a second each) and judges each against
    the current model (:func:`~.fit.judge_effect`); an effect another refines may not be removed; the structure test
    is :func:`localise`; every fitted value in the library's domain is some machine's. The validation record is
    predicted at the end, never used to choose. Keeps every refit's entry (``tried``, its Evidence in ``evidence``)
    and the rounds' ranking noise models (``rounds``)."""

    stage = "round"
    has_validation = False

    def __init__(self, record: EmpsRecord, names: Sequence[str], nominal: OEFitResult, fit_kw: Mapping,
                 judge_kw: Mapping, sim_kw: Mapping, bins: int, alpha: float, ambiguity_alpha: float,
                 bonferroni: bool = True) -> None:
        self.record, self.names, self.nominal, self.bonferroni = record, list(names), nominal, bonferroni
        self.fit_kw, self.judge_kw, self.sim_kw, self.bins, self.alpha = fit_kw, judge_kw, sim_kw, bins, alpha
        self.ambiguity_alpha, self.free, self.tried = ambiguity_alpha, list(nominal.free), []
        self.evidence: dict[int, Evidence] = {}  # id(entry of ``tried``) → its Evidence
        self.rounds: list[dict] = []

    def say(self, msg: str) -> None:
        pass

    def baseline(self) -> OEFitResult:
        return self.nominal

    def remaining(self, added: Sequence[dict]) -> list[str]:
        return [nm for nm in self.names if nm not in {a["name"] for a in added}]

    def forward_step(self, current: OEFitResult, added: Sequence[dict], rnd: int) -> Step:
        """One round: every candidate refitted and judged; the best that passes (:func:`_rank_passing`) with its
        ties (:func:`_ties`)."""
        in_model = [a["name"] for a in added]
        n, noise_max_order = self.record.n, int(self.judge_kw["noise_max_order"])
        refits: list[tuple[dict, OEFitResult, Effect]] = []
        eligible = [nm for nm in self.remaining(added) if all(req in in_model for req in EFFECTS[nm].requires)]
        # the round picks the best of its candidates: their F-tests at alpha over their number (Bonferroni)
        kw = {**self.judge_kw, "alpha": self.judge_kw["alpha"] / (max(len(eligible), 1) if self.bonferroni else 1)}
        for name in eligible:
            eff = EFFECTS[name]
            th = current.theta.copy()
            for p, d in zip(eff.params, eff.default):
                th[INDEX[p]] = d
            fit = fit_output_error(self.record, self.free + list(eff.params), th, **self.fit_kw)
            ev = judge_effect(current, fit, **kw)
            entry = {"round": rnd, "name": name,
                     **evidence_entry(ev, n, new_params_corr(current, fit), self.judge_kw["cv_block"],
                                      self.judge_kw["cv_folds"]),
                     "sse_ratio": float(fit.sse / current.sse), "rel_error_pct": fit.rel_error_pct,
                     "params": {p: float(fit.theta[INDEX[p]]) for p in eff.params}, "accepted": False,
                     "verdict": "passed" if ev.passed else "rejected", "seconds": fit.seconds}
            self.tried.append(entry)
            self.evidence[id(entry)] = ev
            refits.append((entry, fit, eff))
        if not refits:
            return Step(current)
        chosen, ranking = _rank_passing(refits, noise_max_order)
        self.rounds.append({"round": rnd, **ranking, "accepted": chosen[2].name if chosen else None})
        if chosen is None:
            return Step(current)
        entry, fit, eff = chosen
        entry["accepted"] = True
        entry["verdict"] = "accepted"
        entry["indistinguishable_from"] = _ties(chosen, refits, noise_max_order, self.ambiguity_alpha)
        tied = {t["name"] for t in entry["indistinguishable_from"]}
        for other, _, _ in refits:
            if other["name"] in tied:
                other["verdict"] = "ambiguous"
                other["reason"] = (f"passed every check and fits as well as {eff.name}: the record cannot tell "
                                   "them apart (Vuong's test)")
            elif other["passed"] and other is not entry:
                other["verdict"] = "passed, not the best"
                other["reason"] = (f"passed every check, but {eff.name} has the lower prewhitened SSE under the "
                                   f"round's noise model ({entry['sse_w_round']:.4g} against "
                                   f"{other['sse_w_round']:.4g} m²); judged again next round")
        self.free += list(eff.params)
        return Step(current, added_item(entry, self.evidence[id(entry)]), fit)

    def without(self, current: OEFitResult, a: dict | None, added: Sequence[dict], rival: dict | None = None
                ) -> OEFitResult:
        return _without(self.record, current, a and a["name"], self.fit_kw, rival)

    def judge(self, small: OEFitResult, large: OEFitResult) -> Evidence:
        return judge_effect(small, effect_last(large, [p for p in large.free if p not in small.free]),
                            **self.judge_kw)

    def residual(self, fit: OEFitResult) -> np.ndarray:
        return fit.residual

    def n_free(self, fit: OEFitResult) -> int:
        return len(fit.free)

    def summary(self, fit: OEFitResult) -> dict:
        return {"rel_error_pct": float(fit.rel_error_pct)}

    def error_text(self, fit: OEFitResult) -> str:
        return f"{fit.rel_error_pct:.3g} %"

    def keep(self, a: dict, added: Sequence[dict]) -> bool:
        return any(a["name"] in EFFECTS[b["name"]].requires for b in added if b is not a)

    def structure(self, fit: OEFitResult) -> tuple[bool | None, dict]:
        loc = localise(self.record, fit.theta, self.sim_kw, bins=self.bins, alpha=self.alpha, fit=fit)
        return loc.get("structure_left"), loc

    def structure_energy(self, fit: OEFitResult, details: dict | None = None) -> float:
        r, signals = localisation_signals(self.record, fit.theta, self.sim_kw)
        ok = np.all(np.isfinite(r)) and all(np.all(np.isfinite(v)) for v in signals.values())
        return structure_energy(r, signals, bins=self.bins) if ok else float("inf")

    def implausible(self, current: OEFitResult, added: Sequence[dict]) -> list[dict]:
        return []

    def own_signature(self, current: OEFitResult, a: dict) -> None:  # none the structure bins cannot see
        return None

    def explains(self, current: OEFitResult, added: list[dict], details: dict, everyone: Sequence[dict]):
        return added, []

    def demote(self, current: OEFitResult, demoted: Sequence[dict], added: Sequence[dict]) -> OEFitResult:
        for d in demoted:
            current = _without(self.record, current, d["name"], self.fit_kw)
        return current

    def validation_residual(self, fit: OEFitResult) -> np.ndarray:
        raise NotImplementedError("the EMPS validation record is predicted, never used to choose")

    validation_structure = validation_structure_energy = validation_residual


@one_blas_thread
def run_emps_loop(record: EmpsRecord, validation: EmpsRecord | None = None, *,
                  candidates: Sequence[str] | None = None, alpha: float = 0.01, max_nfev: int = 50,
                  max_effects: int | None = None, max_corr: float = 0.99, solver: str = "polish",
                  reference_fit: bool = True, noise_max_order: int = 8, cv_block: int = 100, cv_folds: int = 5,
                  cv_alpha: float = 0.5, bonferroni: bool = True, structure_bins: int = 12,
                  structure_alpha: float = 0.01, backward: bool = True,
                  explain_fraction: float = 0.5, ambiguity_alpha: float = 0.05, glitch_k: float = 8.0,
                  sim_options: Mapping | None = None) -> dict:
    """Nominal output-error fit, then greedy effect discovery; returns a plain (JSON-serialisable) dict report.

    Each round refits all parameters of the current model plus one candidate (from its registry default) for every
    remaining candidate whose ``requires`` are in the model, and judges each refit against the current model with
    :func:`judge_effect` (the discovery engine's :class:`~toggle_id.discovery.validation.Evidence`: AR(p ≤
    ``noise_max_order``) noise model of the refit's residual; prewhitened F-test p < ``alpha`` — over the round's
    number of candidates with ``bonferroni`` —, prewhitened ΔBIC < 0, a lower time-block cross-validated whitened
    SSE with blocks of ``cv_block`` samples dealt to ``cv_folds`` folds (by more than the noise would make it at
    ``cv_alpha`` < 0.5), and every new parameter identifiable: |correlation| with each other free parameter ≤
    ``max_corr``, e.g. the offset and the Coulomb asymmetry differ only at standstill). Of the candidates that
    pass, the one with the lowest prewhitened SSE is accepted, the round's residuals all whitened by one noise
    model (:func:`_rank_passing`); the loop stops when none passes. Before the loop, the nominal fit's residual is
    looked at for glitches of the measurement (:func:`toggle_id.residuals.glitches` at ``glitch_k`` robust σ; 0:
    no look): samples found are left out of every later fit and test (:attr:`EmpsRecord.excluded`) and the nominal
    model is fitted again without them. Then the noise-aware structure test localises what the final model leaves
    in its position residual (:func:`localise`, ``structure_bins`` bins per signal, level ``structure_alpha``).
    Keys of the report:

    - ``position_rel_error_pct_before`` (nominal M, Fv fit), ``position_rel_error_pct_after`` (final model), %;
    - ``effects_added``, ``compensating``, ``rejected``: the three lists of :func:`three_lists` (each item with
      name, reason, evidence); ``effects_added`` items also keep {params, round, F, p_value, delta_bic};
      ``free`` (final free parameters);
    - ``candidates`` [{round, name, noise_model, F, p_value, delta_bic, in_sample_rms_w_before/after,
      out_of_sample_rms_w_before/after, checks, max_corr, verdict (accepted | passed, not the best | rejected),
      reason, sse_w_round, sse_ratio, rel_error_pct, params, accepted, seconds, …}] (:func:`evidence_entry`);
    - ``rounds`` [{round, lead, noise_model, accepted}]: the noise model each round's ranking whitened by;
    - ``nominal``: the nominal fit {free, identified (M, Fv), rel_error_pct, noise_model};
    - ``noise_model``: the AR noise model of the final model's residual (its effective sample size included);
    - ``structure_left`` (bool, None if the final model cannot be simulated) and ``localisation`` (locate's dict:
      families with p-values and per-bin levels, ``significant``, ``strongest``, ``text``);
    - ``identified`` (all 8 parameters), ``std`` (approximate σ of the free ones, white-residual assumption);
    - ``published``, ``pct_diff_vs_published`` (M, Fv, Fc, offset; None where not in the final model) and, if the
      asymmetry was added, ``pct_diff_vs_published_asym`` and ``asymmetric_values`` (Fv±, Fc±);
    - ``published_model_rel_error_pct``: the PDF's symmetric values simulated by this simulator;
    - ``reference`` (if ``reference_fit``): output-error fit of the PDF's own structure (M, Fv, Fc, offset) with its
      rel. error and % differences vs the PDF;
    - ``validation`` (if given): the held-out record predicted by the final, published and reference models
      (:func:`predict_validation`; nothing is fitted on it);
    - ``glitches``: {record, count, indices, times_s, residual_m, ...} of the look (None when ``glitch_k`` is 0);
    - ``seconds``, ``n_samples``, ``alpha``, ``max_corr``, ``noise_max_order``, ``cv_block``, ``cv_folds``, ``cv_alpha``,
      ``structure_bins``, ``structure_alpha``, ``solver``.
    """
    t0 = time.perf_counter()
    names = list(EFFECTS) if candidates is None else list(candidates)
    unknown = [c for c in names if c not in EFFECTS]
    if unknown:
        raise ConfigError(f"unknown EMPS effect(s) {unknown}; known: {list(EFFECTS)}")
    for label, value, ok, where in (("alpha", alpha, 0 < alpha < 1, "(0, 1)"),
                                    ("structure_alpha", structure_alpha, 0 < structure_alpha < 1, "(0, 1)"),
                                    ("explain_fraction", explain_fraction, 0 < explain_fraction < 1, "(0, 1)"),
                                    ("ambiguity_alpha", ambiguity_alpha, 0 <= ambiguity_alpha < 1, "[0, 1)"),
                                    ("cv_alpha", cv_alpha, 0 < cv_alpha <= 0.5, "(0, 0.5]"),
                                    ("max_corr", max_corr, 0 < max_corr <= 1, "(0, 1]")):
        if isinstance(value, bool) or not ok:
            raise ConfigError(f"{label} must lie in {where}, got {value!r}")
    if isinstance(glitch_k, bool) or not (np.isfinite(glitch_k) and glitch_k >= 0):
        raise ConfigError(f"glitch_k must be a finite number >= 0, got {glitch_k!r}")
    if not isinstance(bonferroni, bool):
        raise ConfigError(f"bonferroni must be true or false, got {bonferroni!r}")
    for label, value, least in (("noise_max_order", noise_max_order, 0), ("cv_block", cv_block, 1),
                                ("cv_folds", cv_folds, 2), ("structure_bins", structure_bins, 2)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ConfigError(f"{label} must be a whole number >= {least}, got {value!r}")
    _check_solver(solver)
    n = record.n
    fit_kw = dict(max_nfev=max_nfev, solver=solver, sim_options=sim_options)
    judge_kw = {"alpha": alpha, "max_corr": max_corr, "noise_max_order": int(noise_max_order),
                "cv_block": int(cv_block), "cv_folds": int(cv_folds), "cv_alpha": float(cv_alpha)}

    # nominal model: IDIM-LS (M, Fv only) start, then output error
    theta = OFF.copy()
    try:
        start = idim_ls(record, terms=NOMINAL_NAMES)["params"]
        for nm in NOMINAL_NAMES:
            theta[INDEX[nm]] = np.clip(start[nm], LOWER[INDEX[nm]], UPPER[INDEX[nm]])
    except DataError:  # record too short for the recipe: start from the registry's round values
        pass
    free: list[str] = list(NOMINAL_NAMES)
    current = fit_output_error(record, free, theta, **fit_kw)
    glitch = None
    if glitch_k > 0:
        mask = glitches(current.residual, glitch_k)
        glitch = {"record": record.name, **glitch_report(record.t, current.residual, mask, glitch_k)}
        if mask.any():  # the model takes them as measured; the nominal model fitted again without them
            record = replace(record, excluded=mask)
            current = fit_output_error(record, free, current.theta, **fit_kw)
    nominal = current
    before = current.rel_error_pct

    sim_kw = dict(sim_options or {})
    plant = EmpsPlant(record, names, current, fit_kw, judge_kw, sim_kw, structure_bins, structure_alpha,
                      ambiguity_alpha, bonferroni)
    out = run_loop(plant, max_effects=max_effects, backward=backward, ambiguity_alpha=ambiguity_alpha,
                   explain_fraction=explain_fraction, noise_max_order=int(noise_max_order))
    _, compensating, rejected = three_lists(names, plant.tried, plant.evidence, max_effects)
    current, added, loc, rounds, tried = out.final, out.added, out.structure, plant.rounds, plant.tried
    compensating += out.compensating
    rejected += [{"name": e["name"], "round": None, "params": {}, "evidence": e["evidence"],
                  "reason": "eliminated (backward): " + e["reason"]} for e in out.eliminated]
    # an effect the record cannot tell apart from another that passed the same round is not named as added
    ambiguous = [a for a in added if a.get("indistinguishable_from")]
    added = [a for a in added if not a.get("indistinguishable_from")]
    free = list(current.free)
    noise_final = fit_noise(current.residual, noise_max_order)
    noise_nominal = fit_noise(nominal.residual, noise_max_order)

    pub_sim = simulate_emps(PUBLISHED_THETA, record, **sim_kw)
    cmp = _compare_published(current.theta, free)
    report = {
        "record": record.name,
        "n_samples": int(n),
        "position_rel_error_pct_before": float(before),
        "position_rel_error_pct_after": float(current.rel_error_pct),
        "effects_added": added,
        "ambiguous": ambiguous,
        "compensating": compensating,
        "rejected": rejected,
        "candidates": tried,
        "rounds": rounds,
        "free": list(free),
        "nominal": {"free": list(NOMINAL_NAMES), "identified": {k: nominal.params[k] for k in NOMINAL_NAMES},
                    "rel_error_pct": float(before), "noise_model": noise_nominal.to_dict()},
        "noise_model": {**noise_final.to_dict(), "description": noise_final.describe()},
        "structure_left": loc["structure_left"],
        "localisation": loc,
        "backward_elimination": out.eliminated,
        "explain_fraction": float(explain_fraction),
        "identified": current.params,
        "std": dict(current.std),
        "published": dict(PUBLISHED),
        "pct_diff_vs_published": cmp["symmetric"],
        "published_model_rel_error_pct": float(position_rel_error_pct(record.qm, pub_sim.q[0])),
        "alpha": float(alpha),
        "max_corr": float(max_corr),
        "noise_max_order": int(noise_max_order),
        "cv_block": int(cv_block),
        "cv_folds": int(cv_folds),
        "cv_alpha": float(cv_alpha), "bonferroni": bonferroni,
        "structure_bins": int(structure_bins),
        "structure_alpha": float(structure_alpha),
        "solver": solver,
        "glitches": glitch,
    }
    if "asymmetric" in cmp:
        report["asymmetric_values"] = cmp["asymmetric_values"]
        report["pct_diff_vs_published_asym"] = cmp["asymmetric"]
    if reference_fit:
        ref = fit_output_error(record, ["M", "Fv", "Fc", "offset"], PUBLISHED_THETA, **fit_kw)
        report["reference"] = {
            "free": list(ref.free),
            "identified": {k: ref.params[k] for k in ref.free},
            "rel_error_pct": ref.rel_error_pct,
            "pct_diff_vs_published": _compare_published(ref.theta, ref.free)["symmetric"],
        }
    if validation is not None:
        models = {"final": current.theta, "published": PUBLISHED_THETA}
        if "reference" in report:
            models["reference"] = ref.theta
        report["validation"] = predict_validation(validation, models, sim_kw)
    report["seconds"] = float(time.perf_counter() - t0)
    return report


def _without(record: EmpsRecord, current: OEFitResult, name: str | None, fit_kw: Mapping,
             rival: Mapping | None = None) -> OEFitResult:
    """The current model refitted with effect ``name`` off — and, when ``rival`` ({name, params}) is given, with
    that effect in its place (``name`` None: beside the model's), started at its refit values."""
    gone = EFFECTS[name].params if name is not None else ()
    theta = current.theta.copy()
    for p in gone:
        theta[INDEX[p]] = OFF[INDEX[p]]
    free = [p for p in current.free if p not in gone]
    if rival is not None:
        for p, v in rival["params"].items():
            theta[INDEX[p]] = v
        free += [p for p in EFFECTS[rival["name"]].params if p not in current.free]
    return fit_output_error(record, free, theta, **fit_kw)

