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
  current and input express) — or, where the plant finds in the residual without it the signature it was added for
  and none with it, or another reason that energy says nothing of it (:meth:`Plant.own_signature`: the toggle
  plant's cogging torque, whose ripple the position bins cannot see, beside an effect the library lacks; an effect
  accepted beside the catch-all's generic terms); otherwise it lowers the error without explaining it and is listed
  as *compensating*, never as added. The same holds on a second record of the machine (never fitted) when the plant
  finds its prediction left with a material error that holds structure, not all of it within what the parameters'
  uncertainty allows;
- **ambiguity** (:mod:`.ties`): two supported effects whose fits the record cannot tell apart (Vuong's test of
  the non-nested models) are reported together, neither as added. A tie found while other effects were still
  missing is judged again on the final model; one Vuong's test leaves is judged by the model with both effects
  (an effect needed beside its rival, and the rival not beside it, is named); with a second record of the
  machine (never fitted), one that is still left is judged on it.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from .ties import reconsider_ties, settle_ties_by_encompassing, settle_ties_out_of_sample


class Verdict(Protocol):
    """What a judge returns (:class:`~.validation.Evidence`)."""

    passed: bool
    reason: str

    def to_dict(self) -> dict: ...


def backward_eliminate(current: Any, added: Sequence[dict], without: Callable[[Any, dict, Sequence[dict]], Any],
                       judge: Callable[[Any, Any], Verdict], say: Callable[[str], None],
                       error_of: Callable[[Any], str],
                       keep: Callable[[dict, Sequence[dict]], bool] = lambda a, s: False,
                       judge_item: Callable[[Any, Any, dict], Verdict] | None = None
                       ) -> tuple[Any, list[dict], list[dict]]:
    """Backward elimination over the accepted effects ``added`` (dicts with ``name``; the latest last).

    ``without(current, a, added)``: the current model refitted with effect ``a`` off; ``judge(reduced, current)``:
    the verdict for the current model against it; ``error_of(fit)``: its error for the log line; ``keep(a,
    added)``: True where ``a`` may not be removed (another effect refines it); ``judge_item(reduced, current, a)``:
    given, the verdict in ``judge``'s place, knowing the item (how it was accepted). Each kept item gets
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
            ev = judge_item(reduced, current, a) if judge_item is not None else judge(reduced, current)
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
                     explain_fraction: float, on_validation: bool = False) -> tuple[list[dict], list[dict]]:
    """(explaining, compensating) of the accepted effects ``added`` when structure is left in the residual of the
    model with all of them (structure energy ``energy_with``); ``energy_without(a)``: that of the model without
    ``a``. Each item gets ``structure_explained`` {fraction, energy_without_m2, energy_with_m2} (with
    ``on_validation``: ``validation_structure_explained``, the energies on the validation record); a compensating
    one also a ``reason``."""
    key = "validation_structure_explained" if on_validation else "structure_explained"
    keep, demoted = [], []
    for a in added:
        e0 = float(energy_without(a))
        frac = explained_fraction(e0, energy_with)
        a[key] = {"fraction": frac, "energy_without_m2": e0, "energy_with_m2": float(energy_with),
                  "measure": "raw residual energy in the structure test's bases"}
        (keep if frac >= explain_fraction else demoted).append(a)
    where = "the validation record's structure energy" if on_validation else "the structure energy"
    compensating = [dict(a, reason=f"lowers the error, but removes only {a[key]['fraction']:.0%} of {where} "
                                   f"(position, velocity, current and input bins), and structure remains"
                                   + (" there" if on_validation else "")) for a in demoted]
    return keep, compensating


def _split(plant: Plant, current: Any, added: list[dict], everyone: Sequence[dict], e_with: float,
           energy: Callable[[Any], float], explain_fraction: float, on_validation: bool = False
           ) -> tuple[list[dict], list[dict]]:
    """:func:`split_explaining` of ``added`` by the structure ``energy`` of the model ``current`` (``e_with``) and of
    the model refitted without each effect; an effect that an explaining one refines stays with it."""
    for a in added:  # the final model without each effect (backward elimination has most)
        if a.get("_reduced") is None:
            a["_reduced"] = plant.without(current, a, everyone)
    added, more = split_explaining(added, e_with, lambda a: energy(a["_reduced"]), explain_fraction, on_validation)
    for d in [d for d in more if plant.keep(d, added)]:
        more.remove(d)
        added.append({k: v for k, v in d.items() if k != "reason"})
    for d in list(more):  # it removed little of the structure energy, but the structure it was added for
        why = plant.own_signature(current, d)
        if why:
            more.remove(d)
            added.append({**{k: v for k, v in d.items() if k != "reason"}, "own_signature": why})
            plant.say(f"{d['name']}: {why}")
    return added, more


# ------------------------------------------------------------------------------------------ the loop itself
@dataclass
class Step:
    """One forward step of a plant: ``base`` is the current model (or a better optimum of it the step found),
    ``chosen`` the item of the effect it adds (a dict with ``name`` and the plant's stage key; None: nothing is
    supported, the forward search ends) and ``after`` the model with it."""

    base: Any
    chosen: dict | None = None
    after: Any = None
    #: further items the step adds with ``chosen`` (effects supported only together with it), already in ``after``
    more: list[dict] = field(default_factory=list)


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
    place, or — the item None — the rival beside the effects it has; None where the plant forbids it),
    :meth:`judge` (the case for a larger model against a smaller: :class:`~.validation.Evidence`; a plant may also
    have ``judge_removal(small, large, item)``, backward elimination's verdict knowing how the item was accepted),
    :meth:`residual`, :meth:`n_free`, :meth:`summary` (JSON-able) and :meth:`error_text` of a fit, :meth:`keep`
    (an item that may not be removed: another refines it), :meth:`structure` ((structure left?, the plant's
    details) of a fit's residual), :meth:`structure_energy`,
    :meth:`implausible` (the accepted items whose fitted values no machine has, each with its ``reason``),
    :meth:`explains` (a last check of the explaining effects, given all that were accepted, the implausible ones
    already taken out: e.g. the catch-all force; may demote more),
    :meth:`demote` (the model without the compensating effects), :meth:`validation_residual` (the residual on a
    second record, never fitted, where :attr:`has_validation`), :meth:`validation_structure` (is a material error
    with structure left in it, not all within the parameters' uncertainty?) and :meth:`validation_structure_energy`,
    and :meth:`say`.
    :attr:`stage`: the key of an item's forward step (``iteration``, ``round``)."""

    stage: str
    has_validation: bool

    def baseline(self) -> Any: ...
    def remaining(self, added: Sequence[dict]) -> list: ...
    def forward_step(self, current: Any, added: Sequence[dict], iteration: int) -> Step: ...
    def without(self, current: Any, a: dict | None, added: Sequence[dict], rival: dict | None = None) -> Any: ...
    def judge(self, small: Any, large: Any) -> Verdict: ...
    def residual(self, fit: Any) -> np.ndarray: ...
    def n_free(self, fit: Any) -> int: ...
    def summary(self, fit: Any) -> dict: ...
    def error_text(self, fit: Any) -> str: ...
    def keep(self, a: dict, added: Sequence[dict]) -> bool: ...
    def own_signature(self, current: Any, a: dict) -> str | None: ...
    def structure(self, fit: Any) -> tuple[bool | None, Any]: ...
    def structure_energy(self, fit: Any, details: Any = None) -> float: ...
    def implausible(self, current: Any, added: Sequence[dict]) -> list[dict]: ...
    def explains(self, current: Any, added: list[dict], details: Any, everyone: Sequence[dict]
                 ) -> tuple[list[dict], list[dict]]: ...
    def demote(self, current: Any, demoted: Sequence[dict], added: Sequence[dict]) -> Any: ...
    def validation_residual(self, fit: Any) -> np.ndarray | None: ...
    def validation_structure(self, fit: Any) -> bool: ...
    def validation_structure_energy(self, fit: Any) -> float: ...
    def say(self, msg: str) -> None: ...


def run_loop(plant: Plant, *, max_effects: int | None, backward: bool, ambiguity_alpha: float,
             explain_fraction: float, noise_max_order: int, encompassing: bool = True,
             clock: Callable[[str], AbstractContextManager] = lambda phase: nullcontext()) -> Outcome:
    """The discovery loop over any plant: :func:`forward` steps, then the :func:`verdict_rules`; ``clock(phase)``
    times each (:class:`.timing.PhaseClock`), the phases the plant marks inside them apart."""
    with clock("forward steps, the rest"):
        current, added = forward(plant, max_effects)
    with clock("verdict rules"):
        return verdict_rules(plant, current, added, backward=backward, ambiguity_alpha=ambiguity_alpha,
                             explain_fraction=explain_fraction, noise_max_order=noise_max_order,
                             encompassing=encompassing)


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
        added.extend(step.more)
    return current, added


def verdict_rules(plant: Plant, current: Any, added: list[dict], *, backward: bool, ambiguity_alpha: float,
                  explain_fraction: float, noise_max_order: int, encompassing: bool = True) -> Outcome:
    """The verdict rules on the model ``current`` with the accepted items ``added``: backward elimination (when
    ``backward``), ties judged again on the final model, by the model with both effects (when ``encompassing``) and
    on a second record when the plant has one (all when ``ambiguity_alpha`` > 0), and, when structure is left, the
    split of the accepted effects into explaining and compensating (at ``explain_fraction``; the compensating ones
    taken out of the final model) — on the fitted record, then on the second record when its prediction is left
    with structure."""
    eliminated: list[dict] = []
    if backward and added:
        current, added, eliminated = backward_eliminate(
            current, added, lambda cur, a, now: plant.without(cur, a, now), plant.judge, plant.say,
            plant.error_text, keep=plant.keep, judge_item=getattr(plant, "judge_removal", None))
    if ambiguity_alpha > 0 and added:
        def swap(cur: Any, a: dict, rv: dict) -> Any:
            return None if plant.keep(a, added) else plant.without(cur, a, added, rv)

        reconsider_ties(current, added, swap, plant.residual, plant.n_free, plant.summary, noise_max_order,
                        ambiguity_alpha, plant.say, stage=plant.stage)
        if encompassing:
            current = settle_ties_by_encompassing(current, added, swap,
                                                  lambda cur, rv: plant.without(cur, None, added, rv), plant.judge,
                                                  plant.summary, plant.say, pair_alpha=ambiguity_alpha)
        if plant.has_validation:
            current = settle_ties_out_of_sample(current, added, swap, plant.validation_residual, plant.n_free,
                                                plant.summary, noise_max_order, ambiguity_alpha, plant.say)

    left, details = plant.structure(current)
    with_compensating = None
    everyone = list(added)
    # an effect whose fitted values no machine has explains nothing, whether structure is left or not: it stands in
    # for something outside the library (with none left, the noise model took the rest: rec28 of the adversarial set)
    compensating = plant.implausible(current, added) if added else []
    added = [a for a in added if a["name"] not in {c["name"] for c in compensating}]
    if left and added:
        # structure is left: an effect explains only if it removed most of the structure energy it was added for
        added, more = _split(plant, current, added, everyone, plant.structure_energy(current, details),
                             plant.structure_energy, explain_fraction)
        compensating += more
        if added:
            added, more = plant.explains(current, added, details, everyone)
            compensating += more
    if plant.has_validation and added and plant.validation_structure(current):
        # a real effect predicts a record it was not fitted on: where the second record is left with structure, an
        # effect explains only if it removed most of that structure too (on the fitted record the noise model may
        # have taken the rest, and a stand-in can predict the second record a little better: rec28)
        e_with = plant.validation_structure_energy(current)
        if np.isfinite(e_with):
            added, more = _split(plant, current, added, everyone, e_with, plant.validation_structure_energy,
                                 explain_fraction, on_validation=True)
            compensating += more
    if compensating:
        plant.say(("structure remains; " if left else "") + ", ".join(c["name"] for c in compensating)
                  + (" lowers the error but does not" if len(compensating) == 1 else " lower the error but do not")
                  + " explain it (listed as compensating, not added)")
        with_compensating = current
        current = plant.demote(current, compensating, added)
        left, details = plant.structure(current)
    for a in added + compensating:
        a.pop("_reduced", None)
    return Outcome(current, added, compensating, eliminated, details, with_compensating)
