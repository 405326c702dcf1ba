"""The discovery engine: one loop (:func:`run_loop`) over any plant behind a small interface (:class:`Plant`), run by
the toggle plant (:class:`toggle_id.discovery.toggle_plant.TogglePlant`, :func:`toggle_id.discovery.discover`) and
the EMPS plant (:class:`toggle_id.emps.loop.EmpsPlant`, :func:`toggle_id.emps.loop.run_emps_loop`).

The loop is forward steps from the plant's baseline (how a plant searches its library is its own: it knows what a
refit costs), then the plant-independent verdict rules below (:func:`verdict_rules`).

Each plant brings its own fits (a model with an effect switched off, refitted) and its own judge (an
:class:`~.validation.Evidence` for a larger model against a smaller one: noise model of the larger model's
residual, prewhitened F-test and BIC, time-block cross-validation, validation record). The rules are:

- **backward elimination** (:func:`backward_eliminate`): after the forward steps, drop any accepted effect that
  the model without it — refitted — matches as well (the judge no longer passes the effect against it);
  repeat until every effect is needed;
- **explaining or compensating** (:func:`split_explaining`): when the final residual still holds structure, an
  accepted effect *explains* only if it removed at least ``explain_fraction`` of the structure energy
  (:func:`.localise.structure_energy`: the raw residual's energy that functions of position, velocity,
  current and input express); otherwise it lowers the error without explaining it and is listed as
  *compensating*, never as added;
- **ambiguity** (:func:`indistinguishable`, :func:`tie_band`): two supported effects whose fits the record
  cannot tell apart (Vuong's test of the non-nested models, :func:`.stats.vuong`) are reported together, neither
  as added. A tie found while other effects were still missing is judged again on the final model
  (:func:`reconsider_ties`): the missing structure, left in both residuals, can hide a difference that the
  complete model shows. With a second record of the machine (never fitted), a tie that the fitted record leaves
  is judged on it (:func:`settle_ties_out_of_sample`): the model that predicts it better, by Vuong's test, names
  its effect.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from scipy import stats

from .noise import fit_noise
from .stats import vuong


class Verdict(Protocol):
    """What a judge returns (:class:`~.validation.Evidence`)."""

    passed: bool
    reason: str

    def to_dict(self) -> dict: ...


def backward_eliminate(current: Any, added: Sequence[dict], without: Callable[[Any, dict, Sequence[dict]], Any],
                       judge: Callable[[Any, Any], Verdict], say: Callable[[str], None],
                       error_of: Callable[[Any], str], keep: Callable[[dict, Sequence[dict]], bool] = lambda a, s: False
                       ) -> tuple[Any, list[dict], list[dict]]:
    """Backward elimination over the accepted effects ``added`` (dicts with ``name``; the latest last).

    ``without(current, a, added)``: the current model refitted with effect ``a`` off; ``judge(reduced, current)``:
    the verdict for the current model against it; ``error_of(fit)``: its error for the log line; ``keep(a,
    added)``: True where ``a`` may not be removed (another effect refines it). Each kept item gets
    ``backward`` (the verdict's dict) and ``_reduced`` (the model without it). Returns (model, kept, eliminated
    [{name, reason, evidence}])."""
    added = list(added)
    eliminated: list[dict] = []
    changed = True
    while changed and added:
        changed = False
        for a in reversed(added):
            if keep(a, added):
                continue
            reduced = without(current, a, added)
            ev = judge(reduced, current)
            a["backward"] = ev.to_dict()
            a["_reduced"] = reduced
            say(f"backward: without {a['name']} {error_of(reduced)} — {'kept' if ev.passed else 'dropped: ' + ev.reason}")
            if not ev.passed:
                eliminated.append({"name": a["name"], "reason": ev.reason, "evidence": ev.to_dict()})
                added.remove(a)
                current = reduced
                changed = True
                break
    return current, added, eliminated


def explained_fraction(energy_without: float, energy_with: float) -> float:
    """The share of the structure energy of the model without an effect that the model with it removed (1 when
    the model without it cannot even be simulated)."""
    if not np.isfinite(energy_without):
        return 1.0
    return float((energy_without - energy_with) / energy_without) if energy_without > 0 else 0.0


def split_explaining(added: Sequence[dict], energy_with: float, energy_without: Callable[[dict], float],
                     explain_fraction: float) -> tuple[list[dict], list[dict]]:
    """(explaining, compensating) of the accepted effects ``added`` when structure is left in the residual of the
    model with all of them (structure energy ``energy_with``); ``energy_without(a)``: that of the model without
    ``a``. Each item gets ``structure_explained`` {fraction, energy_without_m2, energy_with_m2}; a compensating
    one also a ``reason``."""
    keep, demoted = [], []
    for a in added:
        e0 = float(energy_without(a))
        frac = explained_fraction(e0, energy_with)
        a["structure_explained"] = {"fraction": frac, "energy_without_m2": e0, "energy_with_m2": float(energy_with),
                                    "measure": "raw residual energy in the structure test's bases"}
        (keep if frac >= explain_fraction else demoted).append(a)
    compensating = [dict(a, reason=f"lowers the error, but removes only {a['structure_explained']['fraction']:.0%} "
                                   f"of the structure energy (position, velocity, current and input bins), and "
                                   f"structure remains") for a in demoted]
    return keep, compensating


def tie_band(best_sse: float, n: int, alpha: float) -> float:
    """How far above the best accepted refit's SSE a scout may lie and still be refitted as a possible rival:
    twice the SSE difference at which Vuong's test separates two fits at level ``alpha`` (z ≈ √(ΔSSE/σ²)/2 for a
    deterministic difference; a scout is polished less than a refit). 0 when ``alpha`` is 0 (no ambiguity)."""
    if not alpha > 0:
        return 0.0
    z = float(stats.norm.isf(alpha / 2.0))
    return 8.0 * z * z * best_sse / n


def indistinguishable(r_chosen: np.ndarray, k_chosen: int, others: Sequence[tuple[np.ndarray, int]],
                      noise_max_order: int, alpha: float) -> list[dict]:
    """Vuong's test of the chosen fit (residual ``r_chosen``, ``k_chosen`` parameters added) against each other
    supported fit (residual, parameters added), every residual whitened by the noise model of the chosen one's.
    Returns, per other fit, the test's dict with ``tied``: True when it is not significant at ``alpha``."""
    noise = fit_noise(r_chosen, noise_max_order)
    out = []
    for r, k in others:
        v = vuong(noise, r_chosen, r, k_chosen, k)
        out.append({**v, "tied": bool(v["p_value"] >= alpha)})
    return out


def reconsider_ties(current: Any, added: Sequence[dict], swap: Callable[[Any, dict, dict], Any],
                    residual: Callable[[Any], np.ndarray], n_free: Callable[[Any], int],
                    summary: Callable[[Any], dict], noise_max_order: int, alpha: float,
                    say: Callable[[str], None], stage: str = "iteration") -> None:
    """Judge again, on the final model ``current``, the ties of every effect added before the last one.

    An effect and its rival were found indistinguishable (``indistinguishable_from``) on residuals that still held
    the effects added later; there, the unexplained structure dominates both residuals and its noise model, and
    hides the difference between the two. ``swap(current, a, rival)``: the final model with ``a`` replaced by the
    rival (started at the rival's refit values, refitted), or None where the swap is impossible (another effect
    of the model refines ``a``; the tie then stays as it was); ``stage``: the key of an item's forward step
    (``iteration``, ``round``); ``residual(fit)``, ``n_free(fit)``, ``summary(fit)``: its residual, number of free
    parameters and a JSON-able summary (kept under ``swapped``). Vuong's test of the final model against the
    swapped one (on the final model's noise model) decides: a rival the final model beats at ``alpha`` moves to the
    item's ``ties_resolved``; one that is still tied, or now preferred, stays (with the new test under
    ``vuong_final``). A rival that is itself among ``added`` is resolved (both are in the model). Edits ``added``
    in place."""
    if not added:
        return
    last = max(a[stage] for a in added)
    names = {a["name"] for a in added}
    r_cur = None
    for a in added:
        rivals = list(a.get("indistinguishable_from") or [])
        if not rivals or a[stage] == last:
            continue
        keep, resolved = [], []
        for rv in rivals:
            if rv["name"] in names:
                resolved.append({**rv, "reason": f"{rv['name']} is in the final model too"})
                continue
            r_cur = residual(current) if r_cur is None else r_cur
            swapped = swap(current, a, rv)
            if swapped is None:
                keep.append(rv)
                continue
            v = indistinguishable(r_cur, n_free(current), [(residual(swapped), n_free(swapped))], noise_max_order,
                                  alpha)[0]
            entry = {**rv, "vuong_final": v, "swapped": summary(swapped)}
            if not v["tied"] and v["z"] > 0:
                entry["reason"] = (f"the final model with {a['name']} beats it with {rv['name']} in its place "
                                   f"(Vuong z {v['z']:.2f}, p {v['p_value']:.2g})")
                resolved.append(entry)
            else:
                keep.append(entry)
            say(f"tie {a['name']} / {rv['name']} judged again on the final model: Vuong z {v['z']:.2f}, "
                f"p {v['p_value']:.2g} — {'resolved' if entry in resolved else 'still tied'}")
        a["indistinguishable_from"] = keep
        if resolved:
            a["ties_resolved"] = resolved


def settle_ties_out_of_sample(current: Any, added: list[dict], swap: Callable[[Any, dict, dict], Any],
                              residual: Callable[[Any], np.ndarray], n_free: Callable[[Any], int],
                              summary: Callable[[Any], dict], noise_max_order: int, alpha: float,
                              say: Callable[[str], None]) -> Any:
    """Judge the ties the fitted record left on a second record of the same machine that was never fitted.

    Two effects tied on the fitted record may act differently under another command (a torque saturation and a
    cubic contact stiffness agree wherever the motor draws a large current only in the clamp; an open/close
    cycling command draws it in free motion too). For each item of ``added`` with ties: ``swap(current, a,
    rival)`` is the final model with the rival in ``a``'s place (refitted to the fitted record, or None where
    that is impossible) and ``residual(fit)`` its residual on the second record. Vuong's test of the two
    predictions — both whitened by the noise model of the better prediction's residual — decides at ``alpha``:
    the effect of the better prediction is named (the rival moves to ``ties_resolved``); when it is the rival,
    the item becomes the rival's (its own forward evidence, ``replaced`` naming the effect it replaces) and the
    swapped model becomes the final model, which is returned. A tie the second record does not settle either
    stays, with the test under ``vuong_validation``; a rival that is itself in the model is resolved. Edits
    ``added`` in place."""
    for i, a in enumerate(list(added)):
        rivals = list(a.get("indistinguishable_from") or [])
        if not rivals:
            continue
        keep, resolved, winner = [], [], None
        r_cur = residual(current)
        for rv in rivals:
            if rv["name"] in {b["name"] for b in added}:
                resolved.append({**rv, "reason": f"{rv['name']} is in the final model too"})
                continue
            swapped = swap(current, a, rv)
            if swapped is None or winner is not None:
                keep.append(rv)
                continue
            r_sw = residual(swapped)
            if not (np.all(np.isfinite(r_cur)) and np.all(np.isfinite(r_sw))):
                keep.append(rv)
                continue
            rival_better = float(r_sw @ r_sw) < float(r_cur @ r_cur)
            ref, other = (r_sw, n_free(swapped)), (r_cur, n_free(current))
            if not rival_better:
                ref, other = other, ref
            v = indistinguishable(ref[0], ref[1], [other], noise_max_order, alpha)[0]
            entry = {**rv, "vuong_validation": v, "swapped_validation": summary(swapped),
                     "validation_rms_m": {a["name"]: float(np.sqrt(np.mean(r_cur ** 2))),
                                          rv["name"]: float(np.sqrt(np.mean(r_sw ** 2)))}}
            better, worse = (rv["name"], a["name"]) if rival_better else (a["name"], rv["name"])
            say(f"tie {a['name']} / {rv['name']} judged on the validation record: {better} predicts it better "
                f"(Vuong z {v['z']:.2f}, p {v['p_value']:.2g}) — {'still tied' if v['tied'] else 'resolved'}")
            if v["tied"]:
                keep.append(entry)
                continue
            entry["reason"] = (f"{better} predicts the validation record better than {worse} (Vuong z {v['z']:.2f}, "
                               f"p {v['p_value']:.2g})")
            if rival_better:
                winner = (swapped, entry)
            else:
                resolved.append(entry)
        if winner is not None:
            swapped, entry = winner
            loser = {k: a[k] for k in ("name", "params_at_acceptance", "evidence", "F", "p_value", "delta_bic")
                     if k in a}
            new = {**a, **{k: entry[k] for k in ("F", "p_value", "delta_bic", "evidence") if k in entry},
                   "name": entry["name"], "params_at_acceptance": entry.get("params", {}),
                   "rmse_after_m": (summary(swapped) or {}).get("rmse_m", a.get("rmse_after_m")),
                   "replaced": {**loser, "reason": entry["reason"]},
                   "indistinguishable_from": [r for r in keep if r["name"] != entry["name"]],
                   "ties_resolved": [*a.get("ties_resolved", []), *resolved,
                                     {**{k: v for k, v in entry.items() if k != "name"}, "name": a["name"]}]}
            added[i] = new
            current = swapped
            continue
        a["indistinguishable_from"] = keep
        if resolved:
            a["ties_resolved"] = [*a.get("ties_resolved", []), *resolved]
    return current


# ------------------------------------------------------------------------------------------ the loop itself
@dataclass
class Step:
    """One forward step of a plant: ``base`` is the current model (or a better optimum of it the step found),
    ``chosen`` the item of the effect it adds (a dict with ``name`` and the plant's stage key; None: nothing is
    supported, the forward search ends) and ``after`` the model with it."""

    base: Any
    chosen: dict | None = None
    after: Any = None


@dataclass
class Outcome:
    """What the loop leaves: the final model, the three lists' first two (``added``, ``compensating``), the effects
    backward elimination dropped, the plant's structure verdict of the final model and, when effects were demoted
    to compensating, the model that still had them."""

    final: Any
    added: list[dict]
    compensating: list[dict]
    eliminated: list[dict]
    structure: Any
    with_compensating: Any = None


class Plant(Protocol):
    """What the discovery engine needs of a plant (the toggle mechanism: :class:`toggle_id.discovery.toggle_plant.TogglePlant`;
    the EMPS axis: :class:`toggle_id.emps.loop.EmpsPlant`). A *fit* is the plant's own object (a model with some
    effects on, fitted); an *item* a dict describing an accepted effect (``name``, the forward step under
    :attr:`stage`, ``indistinguishable_from``, its evidence).

    Forward search: :meth:`baseline` (the nominal model fitted), :meth:`remaining` (the candidates not in the model)
    and :meth:`forward_step` — how a plant searches its library is its own (the toggle plant scores, scouts and
    refits a few candidates, each refit costing seconds; the EMPS plant refits them all). The verdict rules are
    the engine's (:func:`run_loop`) over :meth:`without` (the model refitted with an effect off, or a rival in its
    place; None where the plant forbids it), :meth:`judge` (the case for a larger model against a smaller:
    :class:`~.validation.Evidence`), :meth:`residual`, :meth:`n_free`, :meth:`summary` (JSON-able) and
    :meth:`error_text` of a fit, :meth:`keep` (an item that may not be removed: another refines it),
    :meth:`structure` ((structure left?, the plant's details) of a fit's residual), :meth:`structure_energy`,
    :meth:`explains` (a last check of the explaining effects, given all that were accepted, e.g. the catch-all
    force; may demote more),
    :meth:`demote` (the model without the compensating effects), :meth:`validation_residual` (the residual on a
    second record, never fitted, where :attr:`has_validation`) and :meth:`say`. :attr:`stage`: the key of an item's
    forward step (``iteration``, ``round``)."""

    stage: str
    has_validation: bool

    def baseline(self) -> Any: ...
    def remaining(self, added: Sequence[dict]) -> list: ...
    def forward_step(self, current: Any, added: Sequence[dict], iteration: int) -> Step: ...
    def without(self, current: Any, a: dict, added: Sequence[dict], rival: dict | None = None) -> Any: ...
    def judge(self, small: Any, large: Any) -> Verdict: ...
    def residual(self, fit: Any) -> np.ndarray: ...
    def n_free(self, fit: Any) -> int: ...
    def summary(self, fit: Any) -> dict: ...
    def error_text(self, fit: Any) -> str: ...
    def keep(self, a: dict, added: Sequence[dict]) -> bool: ...
    def structure(self, fit: Any) -> tuple[bool | None, Any]: ...
    def structure_energy(self, fit: Any, details: Any = None) -> float: ...
    def explains(self, current: Any, added: list[dict], details: Any, everyone: Sequence[dict]
                 ) -> tuple[list[dict], list[dict]]: ...
    def demote(self, current: Any, demoted: Sequence[dict], added: Sequence[dict]) -> Any: ...
    def validation_residual(self, fit: Any) -> np.ndarray | None: ...
    def say(self, msg: str) -> None: ...


def run_loop(plant: Plant, *, max_effects: int | None, backward: bool, ambiguity_alpha: float,
             explain_fraction: float, noise_max_order: int) -> Outcome:
    """The discovery loop over any plant: :func:`forward` steps, then the :func:`verdict_rules`."""
    current, added = forward(plant, max_effects)
    return verdict_rules(plant, current, added, backward=backward, ambiguity_alpha=ambiguity_alpha,
                         explain_fraction=explain_fraction, noise_max_order=noise_max_order)


def forward(plant: Plant, max_effects: int | None) -> tuple[Any, list[dict]]:
    """From the plant's baseline, forward steps until none adds an effect or ``max_effects`` are in; the model
    and the items added."""
    current = plant.baseline()
    added: list[dict] = []
    it = 0
    while (max_effects is None or len(added) < max_effects) and plant.remaining(added):
        it += 1
        step = plant.forward_step(current, added, it)
        current = step.base
        if step.chosen is None:
            break
        current = step.after
        added.append(step.chosen)
    return current, added


def verdict_rules(plant: Plant, current: Any, added: list[dict], *, backward: bool, ambiguity_alpha: float,
                  explain_fraction: float, noise_max_order: int) -> Outcome:
    """The verdict rules on the model ``current`` with the accepted items ``added``: backward elimination (when
    ``backward``), ties judged again on the final model (and on a second record when the plant has one; when
    ``ambiguity_alpha`` > 0), and, when structure is left, the split of the accepted effects into explaining and
    compensating (at ``explain_fraction``; the compensating ones taken out of the final model)."""
    eliminated: list[dict] = []
    if backward and added:
        current, added, eliminated = backward_eliminate(
            current, added, lambda cur, a, now: plant.without(cur, a, now), plant.judge, plant.say,
            plant.error_text, keep=plant.keep)
    if ambiguity_alpha > 0 and added:
        def swap(cur: Any, a: dict, rv: dict) -> Any:
            return None if plant.keep(a, added) else plant.without(cur, a, added, rv)

        reconsider_ties(current, added, swap, plant.residual, plant.n_free, plant.summary, noise_max_order,
                        ambiguity_alpha, plant.say, stage=plant.stage)
        if plant.has_validation:
            current = settle_ties_out_of_sample(current, added, swap, plant.validation_residual, plant.n_free,
                                                plant.summary, noise_max_order, ambiguity_alpha, plant.say)

    left, details = plant.structure(current)
    compensating: list[dict] = []
    with_compensating = None
    if left and added:
        # structure is left: an effect explains only if it removed most of the structure energy it was added for
        e_with = plant.structure_energy(current, details)
        everyone = list(added)
        for a in added:  # the final model without each effect (backward elimination has most)
            if a.get("_reduced") is None:
                a["_reduced"] = plant.without(current, a, everyone)
        added, compensating = split_explaining(added, e_with, lambda a: plant.structure_energy(a["_reduced"]),
                                               explain_fraction)
        for d in [d for d in compensating if plant.keep(d, added)]:
            compensating.remove(d)  # an effect that an explaining one refines stays with it
            added.append({k: v for k, v in d.items() if k != "reason"})
        if added:
            added, more = plant.explains(current, added, details, everyone)
            compensating += more
        if compensating:
            plant.say("structure remains; " + ", ".join(c["name"] for c in compensating) + " lower the error but "
                      "do not explain it (listed as compensating, not added)")
            with_compensating = current
            current = plant.demote(current, compensating, added)
            left, details = plant.structure(current)
    for a in added + compensating:
        a.pop("_reduced", None)
    return Outcome(current, added, compensating, eliminated, details, with_compensating)
