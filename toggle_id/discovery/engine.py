"""The plant-independent verdict rules of the discovery loop, shared by the toggle plant (:mod:`.loop`) and the
EMPS plant (:mod:`toggle_id.emps.loop`).

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
