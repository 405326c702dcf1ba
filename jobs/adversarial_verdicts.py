"""How a discover run on a record of the adversarial set is judged: the verdict, the result row, the summary and
the table (:mod:`jobs.bench_adversarial`)."""
from __future__ import annotations

import numpy as np

from jobs.adversarial_specs import SIGMA
from toggle_id.discovery.residual import periodic_text


def _names(items) -> list[str]:
    """Effect names from a list of names or of dicts with a ``name`` (or ``effect``) key; [] for anything else."""
    out = []
    for it in items or []:
        if isinstance(it, str):
            out.append(it)
        elif isinstance(it, dict) and (it.get("name") or it.get("effect")):
            out.append(str(it.get("name") or it.get("effect")))
    return out


def accepted_effects(report: dict) -> list[str]:
    """The effects the loop added (``effects_added``, or the list of names ``accepted``)."""
    return _names(report.get("effects_added", report.get("accepted")))


def noise_model_brief(noise_model) -> str | None:
    """'white' / 'AR(2)' / 'AR(1) ρ 0.49' of the residual's noise model after the loop, if the report has one."""
    if not isinstance(noise_model, dict):
        return None if noise_model is None else str(noise_model)
    nm = noise_model.get("after", noise_model)
    if not isinstance(nm, dict):
        return str(nm)
    order = nm.get("order")
    if not order:
        return str(nm.get("kind", "white"))
    rho = nm.get("ar1_rho")
    return f"AR({order})" + (f" ρ {rho:.2f}" if isinstance(rho, (int, float)) else "")


def verdict(entry: dict, report: dict) -> str:
    """exact / spurious / missed / unexplained-correct (and combinations) for one record's discovery.json. A mixed
    record (a library effect and one outside the library) is judged as an in-library one on its library effects,
    and must also be called unexplained: ``+outside-missed`` when it is not."""
    truth = set(entry["effects"])
    accepted = set(accepted_effects(report))
    unexplained = bool(report.get("unexplained"))
    groups = [{a.get("name")} | {r.get("name") for r in a.get("indistinguishable_from") or []}
              for a in report.get("ambiguous") or [] if isinstance(a, dict)]
    if entry["category"] == "outside":
        if accepted:
            return "spurious"
        if groups:
            return "ambiguous-wrong"  # nothing named, but only library effects offered as the alternatives
        return "unexplained-correct" if unexplained else "missed"
    extra = accepted - truth
    missed = {m for m in truth - accepted if not any(m in g for g in groups)}
    wrong_groups = [g for g in groups if not g & truth]
    flags = [v for v, c in (("spurious", extra), ("ambiguous-wrong", wrong_groups), ("missed", missed)) if c]
    # nothing wrong named or offered, and each true effect named or among its group's alternatives
    found = "exact" if accepted == truth and not groups else "+".join(flags) or "ambiguous-correct"
    return found + ("+outside-missed" if entry["category"] == "mixed" and not unexplained else "")


def _validation(report: dict, key: str, scale: float | None = None):
    """A figure of the final model's prediction of the validation record (None without one)."""
    pred = report.get("validation_prediction")
    if not isinstance(pred, dict) or key not in pred:
        return None
    return pred[key] * scale if scale is not None and pred[key] is not None else pred[key]


#: The noise column of a record whose reading carries a disturbance (:data:`jobs.adversarial_set.DISTURBANCES`).
DISTURBANCE_LABELS = {"tone": "σ 1 µm white + a 50-Hz tone of 1 µm", "ar2": "σ 1 µm AR(2), resonant at 20 Hz",
                      "walk": "σ 1 µm white + a random walk (3 µm at the end)"}


def result_row(entry: dict, report: dict, wall: float, report_path: str) -> dict:
    sig = entry["noise"].get("effective_sigma_m") or SIGMA
    before, after = report.get("rmse_before_m"), report.get("rmse_after_m")
    n = entry["noise"]
    noise = ("none" if n["sigma_m"] == 0 else f"σ {n['sigma_m'] * 1e6:g} µm" +
             (f" AR(1) ρ {n['ar']:g}" if n["ar"] else " white"))
    if n["quantum_m"]:
        noise += f", {n['quantum_m'] * 1e6:g}-µm quantum"
    if n.get("outlier_fraction"):
        noise += f", gross errors {n['outlier_m'] * 1e6:g} µm on {n['outlier_fraction']:.0%}"
    if n.get("disturbance"):
        noise = DISTURBANCE_LABELS.get(n["disturbance"], n["disturbance"])
    return {
        "record": entry["name"], "category": entry["category"], "command": entry["command"].get("sweep")
        or entry["command"]["kind"], "truth": list(entry["effects"]) + [k for k in entry["outside"]
                                                                        if k not in entry["effects"]],
        "noise": noise, "accepted": accepted_effects(report),
        "ambiguous": [" or ".join([a.get("name")] + [r.get("name") for r in a.get("indistinguishable_from") or []])
                      for a in report.get("ambiguous") or [] if isinstance(a, dict)],
        "compensating": _names(report.get("compensating")), "rejected": _names(report.get("rejected")),
        "unexplained": bool(report.get("unexplained")),
        "noise_model": noise_model_brief(report.get("noise_model")),
        "structure_left": (report.get("localisation") or {}).get("structure_left")
        if isinstance(report.get("localisation"), dict) else None,
        "rmse_before_um": None if before is None else before * 1e6,
        "rmse_after_um": None if after is None else after * 1e6,
        "before_sigma": None if before is None else before / sig, "after_sigma": None if after is None else after / sig,
        "verdict": verdict(entry, report), "wall_s": wall, "report": report_path, "csv_sha256": entry.get("sha256"),
        "validation_rmse_um": _validation(report, "rmse_m", 1e6),
        "validation_structure_left": _validation(report, "structure_left"),
        "validation_localisation": _validation(report, "text") if _validation(report, "structure_left") else None,
        "localisation": (report.get("localisation") or {}).get("text")
        if isinstance(report.get("localisation"), dict) and report["localisation"].get("structure_left") else None,
        "periodic": periodic_text(report.get("residual_tests_after") or {}),
        "commit": code_label(report.get("code")),
    }


def code_label(code) -> str | None:
    """The short commit of a report's ``code`` (``+dirty`` when the checkout had uncommitted changes), else its
    package version; None for a report made before reports said which code made them."""
    if not isinstance(code, dict):
        return None
    if code.get("git_commit"):
        return str(code["git_commit"])[:7] + ("+dirty" if code.get("git_dirty") else "")
    return f"version {code['version']}" if code.get("version") else None


def _fmt(v, spec=".4g") -> str:
    return "–" if v is None else format(v, spec)


def summarise(rows: list[dict]) -> dict:
    lib = [r for r in rows if r["category"] in ("library", "pair") and r["verdict"] != "error"]
    quiet = [r for r in rows if r["category"] in ("noise", "outside") and r["verdict"] != "error"]
    outside = [r for r in quiet if r["category"] == "outside"]
    mixed = [r for r in rows if r["category"] == "mixed" and r["verdict"] != "error"]
    return {"exact_in_library": sum(r["verdict"] == "exact" for r in lib), "in_library": len(lib),
            "ambiguous_correct": sum(r["verdict"] == "ambiguous-correct" for r in lib),
            "exact_at_noise": sum(r["verdict"] == "exact" and (r["after_sigma"] or np.inf) <= 1.5 for r in lib),
            "nothing_accepted_quiet": sum(not r["accepted"] for r in quiet), "quiet": len(quiet),
            "unexplained_outside": sum(r["verdict"] == "unexplained-correct" for r in outside), "outside": len(outside),
            "exact_mixed": sum(r["verdict"] == "exact" for r in mixed), "mixed": len(mixed),
            "errors": sum(r["verdict"] == "error" for r in rows), "records": len(rows)}


def results_markdown(rows: list[dict], summary: dict) -> str:
    val = any(r.get("validation_rmse_um") is not None for r in rows)
    head = ("| record | kind | command | truth | noise | accepted | compensating | noise model found | "
            "RMS before → after (µm) | before → after (σ) | " + ("validation record predicted (µm) | " if val else "")
            + "verdict | wall (s) |\n|" + "---|" * (13 if val else 12))
    body = []
    for r in rows:
        if r["verdict"] == "error":
            body.append(f"| {r['record']} | {r['category']} | | | | | | | | |{' |' if val else ''} "
                        f"error: {r.get('error', '')[:120]} | {r['wall_s']:.0f} |")
            continue
        pred = ""
        if val:
            pred = (f"{_fmt(r.get('validation_rmse_um'))}"
                    f"{' (structure left)' if r.get('validation_structure_left') else ''} | ")
        body.append(f"| {r['record']} | {r['category']} | {r['command']} | {', '.join(r['truth']) or 'none'} | "
                    f"{r['noise']} | {', '.join(r['accepted']) or 'none'}{' (unexplained)' if r['unexplained'] else ''}"
                    + "".join(f"; ambiguous: {g}" for g in r.get("ambiguous") or []) +
                    f" | {', '.join(r['compensating']) or '–'} | {r.get('noise_model') or '–'} | "
                    f"{_fmt(r['rmse_before_um'])} → "
                    f"{_fmt(r['rmse_after_um'])} | {_fmt(r['before_sigma'])} → {_fmt(r['after_sigma'])} | {pred}"
                    f"{r['verdict']} | {r['wall_s']:.0f} |")
    s = summary
    text = [head, *body, "",
            f"Exact effect set on {s['exact_in_library']} of {s['in_library']} in-library records "
            f"({s['exact_at_noise']} of them with the RMS after ≤ 1.5 σ)"
            + (f", the true effect among an ambiguous pair, nothing wrong named, on {s['ambiguous_correct']}"
               if s.get("ambiguous_correct") else "") + "; nothing accepted on "
            f"{s['nothing_accepted_quiet']} of {s['quiet']} noise-only and outside records; outside records called "
            f"unexplained with nothing accepted: {s['unexplained_outside']} of {s['outside']}"
            + (f"; mixed records with their library effects named and the rest called unexplained: "
               f"{s['exact_mixed']} of {s['mixed']}" if s.get("mixed") else "")
            + (f"; {s['errors']} run(s) failed" if s["errors"] else "") + "."]
    where = [f"- {r['record']} ({', '.join(r['truth']) or 'no effect'}): {r['localisation']}"
             + (f"; periodic: {r['periodic']}" if r.get("periodic") else "") for r in rows if r.get("localisation")]
    where += [f"- {r['record']} ({', '.join(r['truth']) or 'no effect'}), its validation record: "
              f"{r['validation_localisation']}" for r in rows if r.get("validation_localisation")]
    commits: dict[str, list[str]] = {}
    for r in rows:
        if r["verdict"] != "error":
            commits.setdefault(r.get("commit") or "not recorded", []).append(r["record"])
    if commits:
        text += ["", "Code: " + ("; ".join(f"{c} ({', '.join(recs)})" for c, recs in commits.items())
                                 if len(commits) > 1 else f"{next(iter(commits))} (every record)") + "."]
    if where:
        text += ["", "Where the residual concentrates (records with structure left):", *where]
    return "\n".join(text)
