"""The EMPS job's report: figures, console text and MLflow child runs and metrics."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

from .data import (
    EmpsRecord,
)

if TYPE_CHECKING:
    from ..tracking import Tracker

def param_units() -> dict[str, str]:
    """Unit of every EMPS parameter, by name."""
    from .model import PARAMS

    return {p.name: p.unit for p in PARAMS}


def response_figure(record: EmpsRecord, models: Mapping[str, np.ndarray], title: str,
                    pulse_gain: float = 1.0) -> Any:
    """Measured and simulated position (mm), their difference (µm) and the measured controller output ν (V), with
    the record's pulse train (as added to ν: ``pulse_gain``·pulses_N) where it has one."""
    from .. import figures

    fig = figures.response_comparison(record.t, record.qm, models, v_in=record.vir, title=title)
    ax = fig.axes
    ax[0].set_ylabel("q [mm]")
    ax[0].set_title("(a) load position", loc="left", fontsize="medium")
    ax[1].set_ylabel(r"$q^{model} - q^{meas}$ [µm]")
    ax[2].set_ylabel(r"$\nu$ [V]")
    ax[2].set_title("(c) measured controller output", loc="left", fontsize="medium")
    if np.any(record.pulses != 0) and pulse_gain != 0:
        ax[2].plot(record.t, pulse_gain * record.pulses, lw=0.8, color="0.3", ls="--",
                   label=f"pulses added to the controller output ({pulse_gain:g}·pulses_N)")
        ax[2].legend(fontsize="small", loc="upper right")
    return fig


def friction_figure(record: EmpsRecord, models: Mapping[str, np.ndarray], mass: float, eps: float) -> Any:
    """Friction force (N) against velocity (mm/s): each model's curve, and the measured estimate
    gtau·ν − M̂·q̈ (q̇, q̈ from the benchmark's 100 Hz zero-phase filter) as points, M̂ the final model's mass."""
    from matplotlib.figure import Figure

    from .. import figures
    from .idim import filtered_derivatives
    from .model import friction_force

    _, qd, qdd = filtered_derivatives(record.qm, record.dt)
    est = record.tau - mass * qdd
    step = max(1, record.n // 4000)
    vmax = float(np.max(np.abs(qd))) * 1.05 if record.n else 0.1
    v = np.concatenate([np.linspace(-vmax, vmax, 801), np.linspace(-20 * eps, 20 * eps, 201)])
    v.sort()
    fig = Figure(figsize=(8.0, 4.6), dpi=figures.DPI, layout="constrained")
    ax = fig.subplots()
    ax.plot(qd[::step] * 1e3, est[::step], ".", ms=1.5, color="0.6", alpha=0.5,
            label=r"measured: $g_\tau\nu - \hat M\ddot q$")
    curves = {label: friction_force(theta, v, eps) for label, theta in models.items()}
    for (label, f), ls in zip(curves.items(), ("-", "-", "--", ":", "-.")):
        ax.plot(v * 1e3, f, lw=1.6, ls=ls, label=label)
    lo = min(float(np.min(f)) for f in curves.values())
    hi = max(float(np.max(f)) for f in curves.values())
    pad = 0.15 * (hi - lo) if hi > lo else 1.0
    ax.set_ylim(lo - pad, hi + pad)  # measured outliers (at reversals, where q̈ is noisy) would hide the curves
    ax.axhline(0.0, color="k", lw=0.5)
    ax.axvline(0.0, color="k", lw=0.5)
    ax.set_xlabel(r"velocity $\dot q$ [mm/s]")
    ax.set_ylabel("friction force [N]")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small", loc="upper left")
    fig.suptitle("EMPS friction law")
    return fig


# ------------------------------------------------------------------------------------------ console
def validation_lines(report: Mapping) -> list[str]:
    """Console lines of the validation record's prediction (or why there is none)."""
    v = report.get("validation")
    if not v:
        return []
    if "skipped" in v:
        return [f"validation: skipped ({v['skipped']})"]
    names = {"final": "final", "published": "published", "reference": "OE ref"}
    parts = [f"{names.get(k, k)} {m['position_rel_error_pct']:.4g} %" for k, m in v["models"].items()]
    lines = [f"validation {v['record']} ({v['n_samples']} samples, predicted, nothing fitted on it): "
             + ", ".join(parts)]
    if v.get("has_pulses"):
        lines.append(f"  pulses at the controller output x{v['pulse_gain']:g} V per unit of pulses_N (logged vir "
                     f"shows x{v['logged_pulse_gain']:.4f}); without the pulses: "
                     + ", ".join(f"{names.get(k, k)} {m['without_pulses_rel_error_pct']:.4g} %"
                                 for k, m in v["models"].items()))
    bad = {k: m["status"] for k, m in v["models"].items() if m["status"] != 0}
    if bad:
        lines.append(f"  simulation status not ok: {bad}")
    return lines


def candidate_lines(report: Mapping) -> list[str]:
    """Console lines of the discovery: every candidate refit with its noise model, prewhitened F-test, ΔBIC,
    whitened RMS in and out of sample and its verdict; then the final residual's noise model."""
    lines = []
    for c in report.get("candidates") or []:
        lines.append(f"  round {c['round']} {c['name']}: {c['noise_model']['kind']} noise "
                     f"(≈{c['noise_model']['effective_samples']} independent samples), F {c['F']:.4g}, "
                     f"p {c['p_value']:.3g}, ΔBIC {c['delta_bic']:.4g}, whitened rms {c['in_sample_rms_w_before'] * 1e6:.4g}"
                     f" → {c['in_sample_rms_w_after'] * 1e6:.4g} µm in sample, {c['out_of_sample_rms_w_before'] * 1e6:.4g}"
                     f" → {c['out_of_sample_rms_w_after'] * 1e6:.4g} µm cross-validated: {c['verdict']}"
                     + ("" if c["verdict"] == "accepted" else f" ({c['reason']})"))
    nm = report.get("noise_model")
    if nm:
        lines.insert(0, "discovery (prewhitened F-test p < alpha, ΔBIC < 0, lower cross-validated whitened SSE, "
                        "identifiable):")
        lines.append(f"noise model of the final residual: {nm.get('description', nm.get('kind'))}")
    return lines


#: Short names of the localisation's signals in the console.
_SIGNAL_WORDS = {"q": "position", "q_dir": "position × direction", "qdot": "velocity", "force": "drive force",
                 "vir": "controller output", "t": "time"}


def verdict_lines(report: Mapping) -> list[str]:
    """Console lines of the three lists (accepted, compensating, rejected, each with its reason) and of the
    structure test of the final position residual: whether structure is left, where, and each family's p-value."""
    lines = []
    added = report.get("effects_added") or []
    def explained(a: Mapping) -> str:
        se = a.get("structure_explained")
        return f", removed {se['fraction']:.0%} of the structure energy" if se else ""

    lines.append("effects accepted: " + (", ".join(f"{a['name']} (round {a['round']}{explained(a)})" for a in added)
                                         or "none"))
    lines.extend(f"  eliminated (backward): {e['name']}: {e['reason']}" for e in report.get("backward_elimination") or [])
    for a in report.get("ambiguous") or []:
        lines.append(f"ambiguous: {a['name']} or " + " or ".join(
            f"{t['name']} (Vuong z {t['vuong']['z']:.2f})" for t in a["indistinguishable_from"]) +
            " — the record cannot tell them apart; neither is named as added")
    for label, key in (("compensating (lower the error without explaining it; never added)", "compensating"),
                       ("rejected", "rejected")):
        items = report.get(key) or []
        lines.append(f"{label}:" + (" none" if not items else ""))
        lines.extend(f"  {c['name']}: {c['reason']}" for c in items)
    from ..discovery.localise import SIGNALS

    loc = report.get("localisation") or {}
    if "families" not in loc:
        if loc:
            lines.append(f"structure test: {loc.get('text', loc.get('error'))}")
        return lines
    fams = loc["families"]
    ps = ", ".join(f"{_SIGNAL_WORDS.get(k, k)} {f['p_value']:.2g}" + ("" if f["tested"] else " (shown)")
                   for k, f in fams.items())
    level = f"p < {loc['level_per_family']:.2g} per tested family"
    if loc["structure_left"]:
        where = loc["text"].removeprefix("structure left: ")
        lines.append(f"structure left in the final position residual ({level}): {where}. The noise model cannot "
                     "explain it: something outside the EMPS library (friction law, drive, controller) remains; "
                     "see localisation.png. Residual level per bin (µm, r = qm − q_sim):")
        for k in loc["significant"]:
            f = fams[k]
            if "levels_m" not in f:
                continue
            _, _, scale, unit = SIGNALS.get(k, (k, "", 1.0, ""))
            e = np.asarray(f["edges"]) * scale
            lines.append(f"  {_SIGNAL_WORDS.get(k, k)} [{unit}] (p {f['p_value']:.2g}): "
                         + ", ".join(f"{e[i]:.4g}…{e[i + 1]:.4g} {lv * 1e6:+.2g}"
                                     for i, lv in enumerate(f["levels_m"])))
    else:
        lines.append(f"no structure left in the final position residual ({level}): the whitened residual is not "
                     "predicted by position (also signed by the direction of motion) or velocity")
    lines.append(f"  p-values: {ps}")
    level_test = loc.get("noise_level") or {}
    if level_test.get("varies"):
        lines.append(f"noise level of the final position residual (report-only): {level_test['text']}")
    return lines


def console_text(report: Mapping) -> str:
    """A short table: published vs identified M, Fv, Fc, offset, the other fitted parameters, errors, timing."""
    from .. import console

    cmp = report["comparison"]
    units = param_units()

    def pct(v: float | None) -> str:
        return "—" if v is None else f"{v:+.2f}%"

    def val(v: float | None) -> str:
        return "—" if v is None else f"{v:.5g}"

    rows = [[n, c["unit"], val(c["published"]), val(c["idim_ls"]), pct(c["idim_ls_pct_diff"]),
             val(c["final_model"]), pct(c["final_model_pct_diff"]), val(c["reference_fit"]),
             pct(c["reference_fit_pct_diff"])] for n, c in cmp.items()]
    for n in report["free"]:
        if n not in cmp:
            rows.append([n, units[n], "—", "—", "—", val(report["identified"][n]), "—", "—", "—"])
    header = ["param", "unit", "published", "IDIM-LS", "%", "final", "%", "OE ref", "%"]
    effects = ", ".join(e["name"] for e in report["effects_added"]) or "none"
    lines = [f"EMPS: {report['record']} ({report['n_samples']} samples); effects added: {effects}",
             console.text_table(header, rows),
             f"position rel. error: nominal (M, Fv) {report['position_rel_error_pct_before']:.4g} %, "
             f"final {report['position_rel_error_pct_after']:.4g} %, published values "
             f"{report['published_model_rel_error_pct']:.4g} %"
             + (f", OE ref {report['reference']['rel_error_pct']:.4g} %" if report.get("reference") else "")]
    glitch = report.get("glitches") or {}
    if glitch.get("count"):
        from ..residuals import glitch_text

        lines.append(f"glitches of the measurement (each alone off its neighbours' path), left out of every fit and "
                     f"test: {glitch_text(glitch)}")
    if "error" in (report.get("idim_ls") or {}):
        lines.append(f"IDIM-LS: {report['idim_ls']['error']}")
    lines.extend(candidate_lines(report))
    lines.extend(verdict_lines(report))
    lines.extend(validation_lines(report))
    ident = report.get("identifiability") or {}
    if "rank" in ident:
        lines.append(f"identifiability: rank {ident['rank']}/{len(ident['param_order'])}, practical rank "
                     f"{ident['practical_rank']}" + "".join(f"; not identifiable: {c}"
                                                           for c in ident["null_combinations"]))
    elif "error" in ident:
        lines.append(f"identifiability: {ident['error']}")
    lines.append(f"time {report['wall_seconds']:.1f} s")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ MLflow
def log_children(tracker: Tracker, report: Mapping) -> None:
    """One nested run per output-error fit: the nominal model, every candidate refit, the reference fit."""
    nom = report["nominal"]
    with tracker.run("nominal", tags={"fit": "nominal"}, nested=True):
        tracker.log_params({"free": ",".join(nom["free"])})
        tracker.log_metrics({"rel_error_pct": nom["rel_error_pct"],
                             **{f"param.{k}": v for k, v in nom["identified"].items()}})
    for c in report["candidates"]:
        with tracker.run(f"round{c['round']}_{c['name']}", nested=True,
                         tags={"fit": "candidate", "effect": c["name"], "round": c["round"],
                               "accepted": c["accepted"]}):
            tracker.log_params({"effect": c["name"], "round": c["round"], "verdict": c["verdict"],
                                "noise_model": c["noise_model"]["kind"], "reason": c["reason"][:500]})
            metrics = {"F": c["F"], "p_value": c["p_value"], "delta_bic": c["delta_bic"], "max_corr": c["max_corr"],
                       "in_sample_rms_w_before": c["in_sample_rms_w_before"],
                       "in_sample_rms_w_after": c["in_sample_rms_w_after"],
                       "out_of_sample_rms_w_before": c["out_of_sample_rms_w_before"],
                       "out_of_sample_rms_w_after": c["out_of_sample_rms_w_after"],
                       "noise.effective_samples": c["noise_model"]["effective_samples"],
                       "sse_ratio": c["sse_ratio"], "rel_error_pct": c["rel_error_pct"],
                       "seconds": c["seconds"], "accepted": float(c["accepted"]),
                       **{f"param.{k}": v for k, v in c["params"].items()}}
            tracker.log_metrics({k: v for k, v in metrics.items() if v is not None and math.isfinite(v)})
    ref = report.get("reference")
    if ref:
        with tracker.run("reference", tags={"fit": "reference"}, nested=True):
            tracker.log_params({"free": ",".join(ref["free"])})
            tracker.log_metrics({"rel_error_pct": ref["rel_error_pct"],
                                 **{f"param.{k}": v for k, v in ref["identified"].items()},
                                 **{f"pct_diff.{k}": v for k, v in ref["pct_diff_vs_published"].items()
                                    if v is not None}})


def parent_metrics(report: Mapping) -> dict:
    """The EMPS job's metrics for its parent MLflow run: errors before and after, parameters, noise model,
    localisation and validation figures."""
    m = {"position_rel_error_pct_before": report["position_rel_error_pct_before"],
         "position_rel_error_pct_after": report["position_rel_error_pct_after"],
         "published_model_rel_error_pct": report["published_model_rel_error_pct"],
         "n_effects": len(report["effects_added"]), "n_compensating": len(report.get("compensating") or []),
         "n_rejected": len(report.get("rejected") or []), "wall_seconds": report["wall_seconds"],
         "noise.order": report["noise_model"]["order"],
         "noise.effective_samples": report["noise_model"]["effective_samples"],
         **{f"param.{k}": report["identified"][k] for k in report["free"]},
         **{f"pct_diff.{k}": v for k, v in report["pct_diff_vs_published"].items() if v is not None}}
    if report.get("structure_left") is not None:
        m["structure_left"] = float(report["structure_left"])
        for k, fam in report["localisation"]["families"].items():
            if fam["p_value"] > 0:
                m[f"localisation.{k}.log10_p"] = float(np.log10(fam["p_value"]))
    v = report.get("validation") or {}
    if "models" in v:
        m["validation.position_rel_error_pct"] = v["position_rel_error_pct"]
        m["validation.published_model_rel_error_pct"] = v["published_model_rel_error_pct"]
        for label, entry in v["models"].items():
            m[f"validation.{label}.position_rel_error_pct"] = entry["position_rel_error_pct"]
            m[f"validation.{label}.max_abs_error_um"] = entry["max_abs_error_um"]
            if "without_pulses_rel_error_pct" in entry:
                m[f"validation.{label}.without_pulses_rel_error_pct"] = entry["without_pulses_rel_error_pct"]
        if v.get("logged_pulse_gain") is not None:
            m["validation.logged_pulse_gain"] = v["logged_pulse_gain"]
    return m


# ------------------------------------------------------------------------------------------ the job
