"""Ambiguity: two supported effects whose fits the record cannot tell apart are reported together, neither as
added (:mod:`.engine` runs these rules after the forward steps).

- :func:`indistinguishable`: Vuong's test of the non-nested fits (:func:`.stats.vuong`), each residual whitened by
  the chosen fit's noise model; :func:`tie_band`: how close a scout must come to the best refit to be refitted as
  a possible rival.
- :func:`reconsider_ties`: a tie found while other effects were still missing is judged again on the final model
  (the missing structure, left in both residuals, can hide a difference that the complete model shows).
- :func:`settle_ties_by_encompassing`: a tie Vuong's test leaves is judged by the comprehensive model, the final
  model with both effects (the encompassing approach to non-nested models, Davidson & MacKinnon). Vuong's test
  asks which fit is closer overall, and a difference concentrated in a few hundred samples barely moves it; the
  F-test of an effect added to the model that has its rival asks whether the effect follows what the rival
  cannot, and is several times more sensitive to it. One effect needed beside its rival, and the rival not
  beside it, names the effect.
- :func:`settle_ties_out_of_sample`: with a second record of the machine (never fitted), a tie that the fitted
  record leaves is judged on it: the model that predicts it better, by Vuong's test, names its effect.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import stats

from .noise import fit_noise
from .stats import separation, vuong


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
    Returns, per other fit, the test's dict with ``tied``: True when it is not significant at ``alpha``, and
    ``separation`` (:func:`.stats.separation`: how far apart the two fits are, and what any test could do)."""
    noise = fit_noise(r_chosen, noise_max_order)
    out = []
    for r, k in others:
        v = vuong(noise, r_chosen, r, k_chosen, k)
        out.append({**v, "tied": bool(v["p_value"] >= alpha), "separation": separation(noise, r_chosen, r, alpha)})
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


def settle_ties_by_encompassing(current: Any, added: list[dict], swap: Callable[[Any, dict, dict], Any],
                                union: Callable[[Any, dict], Any], judge: Callable[[Any, Any], Any],
                                summary: Callable[[Any], dict], say: Callable[[str], None],
                                pair_alpha: float = 0.0) -> Any:
    """Judge the ties Vuong's test left by the comprehensive model: the final model with both effects of a tie.

    For each item ``a`` of ``added`` with ties and each rival: ``union(current, rival)`` is the final model with
    the rival switched on too (started at its refit values, refitted) and ``swap(current, a, rival)`` the final
    model with the rival in ``a``'s place (either None where the plant forbids it: the tie stays).
    ``judge(small, large)`` is the plant's case for an effect (the one the forward steps and backward elimination
    use: prewhitened and robust F-tests, BIC, cross-validation): the effect beside its rival is
    ``judge(swapped, union)``, the rival beside the effect ``judge(current, union)``. When the effect is needed
    beside its rival and the rival not beside it, the effect is named (the rival moves to ``ties_resolved``);
    the reverse makes the item the rival's (``replaced`` naming the effect it replaces) and the swapped model
    the final model, which is returned. Where both or neither are needed the tie stays — with neither, the
    record holds what both effects do and nothing only one does; with both, the record may hold both, and the
    forward steps that did not add the second say why. The two cases are kept under ``encompassing``.

    A tie in which neither is needed at the judge's own level (``discover.alpha``, set for screening a whole
    library) is a decision between two effects the record already supports, so it is read again at
    ``pair_alpha`` (> 0; the loop passes Vuong's level, ``ambiguity_alpha``), the level of the other pairwise
    rule: each F-test at that level, every other check (BIC, cross-validation, a second record, the loop's own
    fits) as the judge made it (:func:`passes_at`). When one effect is needed beside the other there and not the
    reverse, it is named. With one of the two the truth, naming the other takes the rival's F-test beside the
    true effect past BIC's ln n (p ≈ 0.0035 for one parameter over 5000 samples) and cross-validation, so the
    rule adds at most that rate of wrong names; it resolves no tie the judge's level left with both needed, and
    undoes none it resolved. Edits ``added`` in place."""
    def decide(cur: Any, a: dict, rv: dict, swapped: Any) -> tuple[str, dict]:
        both = union(cur, rv)
        if both is None:
            return "tied", rv
        beside_rival, beside_effect = judge(swapped, both), judge(cur, both)
        f_a, f_rv = beside_rival.to_dict().get("F", np.nan), beside_effect.to_dict().get("F", np.nan)
        entry = {**rv, "encompassing": {"effect_beside_rival": beside_rival.to_dict(),
                                        "rival_beside_effect": beside_effect.to_dict(), "both": summary(both),
                                        "swapped": summary(swapped)}}
        outcome = ("named" if beside_rival.passed and not beside_effect.passed else
                   "rival" if beside_effect.passed and not beside_rival.passed else "tied")
        if outcome == "tied" and pair_alpha > 0 and not (beside_rival.passed or beside_effect.passed):
            a_pair, rv_pair = (passes_at(ev.to_dict(), pair_alpha) for ev in (beside_rival, beside_effect))
            entry["encompassing"]["pair_alpha"] = float(pair_alpha)
            outcome = "named" if a_pair and not rv_pair else "rival" if rv_pair and not a_pair else "tied"
            if outcome != "tied":
                entry["encompassing"]["at_pair_alpha"] = True
        say(f"tie {a['name']} / {rv['name']} judged by the model with both: {a['name']} beside {rv['name']} F "
            f"{f_a:.3g} ({'needed' if beside_rival.passed else 'not needed'}), {rv['name']} beside {a['name']} F "
            f"{f_rv:.3g} ({'needed' if beside_effect.passed else 'not needed'}) — "
            f"{'still tied' if outcome == 'tied' else 'resolved'}"
            f"{f' at the pairwise level {pair_alpha:g}' if entry['encompassing'].get('at_pair_alpha') else ''}")
        if outcome != "tied":
            better, worse, f = ((a["name"], rv["name"], f_a) if outcome == "named" else (rv["name"], a["name"], f_rv))
            level = (f" at the pairwise level {pair_alpha:g} (BIC and cross-validation as judged)"
                     if entry["encompassing"].get("at_pair_alpha") else "")
            entry["reason"] = (f"the model with both needs {better} beside {worse} (F {f:.3g}) and not {worse} beside "
                               f"{better}{level}: {better} follows what {worse} cannot")
        return outcome, entry

    return _settle(current, added, swap, decide, summary)


def passes_at(evidence: dict, level: float) -> bool:
    """A judge's case (:meth:`.validation.Evidence.to_dict`) read again with its two F-tests at ``level``; every
    other check as the judge made it. False where the case has no checks."""
    checks = dict(evidence.get("checks") or {})
    if "f_test" in checks:
        checks["f_test"] = bool(evidence.get("p_value", 1.0) < level)
    if "robust_f_test" in checks:
        checks["robust_f_test"] = bool(evidence.get("p_value_robust", 1.0) < level)
    return bool(checks) and all(checks.values())


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
    def decide(cur: Any, a: dict, rv: dict, swapped: Any) -> tuple[str, dict]:
        r_cur, r_sw = residual(cur), residual(swapped)
        if not (np.all(np.isfinite(r_cur)) and np.all(np.isfinite(r_sw))):
            return "tied", rv
        rival_better = float(r_sw @ r_sw) < float(r_cur @ r_cur)
        ref, other = (r_sw, n_free(swapped)), (r_cur, n_free(cur))
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
            return "tied", entry
        entry["reason"] = (f"{better} predicts the validation record better than {worse} (Vuong z {v['z']:.2f}, "
                           f"p {v['p_value']:.2g})")
        return ("rival" if rival_better else "named"), entry

    return _settle(current, added, swap, decide, summary)


def _settle(current: Any, added: list[dict], swap: Callable[[Any, dict, dict], Any],
            decide: Callable[[Any, dict, dict, Any], tuple[str, dict]], summary: Callable[[Any], dict]) -> Any:
    """The bookkeeping of a tie-settling rule: for each item of ``added`` with ties and each rival not in the
    model, ``decide(current, a, rival, swap(current, a, rival))`` says ``tied`` (the entry it returns stays a
    rival), ``named`` (it moves to the item's ``ties_resolved``) or ``rival`` (the item becomes the rival's; the
    swapped model is returned as the final one; the item's other rivals stay tied). A rival that is itself in
    the model is resolved; a swap that is impossible (None) leaves the tie."""
    for i, a in enumerate(list(added)):
        rivals = list(a.get("indistinguishable_from") or [])
        if not rivals:
            continue
        keep, resolved, winner = [], [], None
        for rv in rivals:
            if rv["name"] in {b["name"] for b in added}:
                resolved.append({**rv, "reason": f"{rv['name']} is in the final model too"})
                continue
            swapped = swap(current, a, rv) if winner is None else None
            if swapped is None:
                keep.append(rv)
                continue
            outcome, entry = decide(current, a, rv, swapped)
            if outcome == "rival":
                winner = (swapped, entry)
            else:
                (resolved if outcome == "named" else keep).append(entry)
        if winner is not None:
            swapped, entry = winner
            loser = {k: a[k] for k in ("name", "params_at_acceptance", "evidence", "F", "p_value", "delta_bic")
                     if k in a}
            added[i] = {**a, **{k: entry[k] for k in ("F", "p_value", "delta_bic", "evidence") if k in entry},
                        "name": entry["name"], "params_at_acceptance": entry.get("params", {}),
                        "rmse_after_m": (summary(swapped) or {}).get("rmse_m", a.get("rmse_after_m")),
                        "replaced": {**loser, "reason": entry["reason"]},
                        "indistinguishable_from": [r for r in keep if r["name"] != entry["name"]],
                        "ties_resolved": [*a.get("ties_resolved", []), *resolved,
                                          {**{k: v for k, v in entry.items() if k != "name"}, "name": a["name"]}]}
            current = swapped
            continue
        a["indistinguishable_from"] = keep
        if resolved:
            a["ties_resolved"] = [*a.get("ties_resolved", []), *resolved]
    return current
