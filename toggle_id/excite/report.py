"""The excite job's figure and summary: the proposed input, the rivals' predicted responses and what is left
between them after refitting, and the singular values of the sensitivities before and after."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .. import figures
from ..record import Record


def write_figure(path: Path, proposed: Record, curves: Sequence[Mapping], sigma: float,
                 sv_before: Sequence[float] | None, sv_after: Sequence[float] | None,
                 ranks: tuple[int, int] | None) -> str:
    """``excite.png``: v_in of the proposed input; per rival A's response and B's refitted one (mm) and their
    difference (µm, ±σ band); the singular values on the record's input and on the proposed one."""
    n_rows = 1 + 2 * len(curves) + (1 if sv_before is not None and sv_after is not None else 0)
    fig, axes = figures._new_figure(n_rows, 1, height=2.2 * n_rows + 0.6)
    t = proposed.t
    axes[0].plot(t, proposed.v_in, lw=0.8, color="k")
    axes[0].set_ylabel("v_in (V)")
    axes[0].set_title("proposed input")
    k = 1
    for c in curves:
        ax = axes[k]
        ax.plot(t, 1e3 * c["y_a"], lw=0.9, label=f"A: {c['name'].split(' vs ')[0]} on")
        ax.plot(t, 1e3 * c["y_b"], lw=0.9, ls="--", label="B: nominal, refitted to A")
        ax.set_ylabel("x_B (mm)")
        figures._legend(ax)
        ax = axes[k + 1]
        d = 1e6 * (c["y_a"] - c["y_b"])
        ax.fill_between(t, -1e6 * sigma, 1e6 * sigma, color="0.85", label="±σ")
        ax.plot(t, d, lw=0.7, color="C3", label=f"A − B: RMS {np.sqrt(np.nanmean(d * d)):.3g} µm "
                                                 f"= {np.sqrt(np.nanmean(d * d)) / (1e6 * sigma):.3g} σ")
        ax.set_ylabel("A − B (µm)")
        figures._legend(ax)
        k += 2
    axes[k - 1].set_xlabel("t (s)")
    if sv_before is not None and sv_after is not None:
        ax = axes[k]
        idx = np.arange(1, len(sv_before) + 1)
        rb, ra = ranks or (len(sv_before), len(sv_after))
        ax.semilogy(idx, sv_before, "o-", ms=4, label=f"record's input (numerical rank {rb})")
        ax.semilogy(idx, sv_after, "s-", ms=4, label=f"proposed input (numerical rank {ra})")
        ax.set_xlabel("index")
        ax.set_ylabel("singular value of ∂x_B/∂log θ (m)")
        figures._legend(ax)
    figures._finish(fig, "excite: the experiment that tells the explanations apart")
    out = figures.save(fig, path)
    figures.close(fig)
    return out


def summary_text(report: Mapping) -> str:
    """A few lines: the proposed input, per rival its separation, the parameters, the search."""
    lines = []
    best = report.get("proposed")
    sigma_um = report["sigma_um"]
    if not best:
        lines.append(f"no candidate input passed the checks ({report['n_candidates']} tried); nothing proposed")
        lines += [f"warning: {w}" for w in report.get("warnings", [])]
        return "\n".join(lines)
    lines.append(f"proposed input: {best['family']} {_fmt_params(best['params'])} (levels as fractions of v_max; "
                 f"candidate {best['index'] + 1} "
                 f"of {report['n_candidates']}; |v_in| ≤ {report['limits']['v_max']:g} V, "
                 f"{report['limits']['duration']:g} s)")
    for r in report.get("rivals", []):
        lines.append(f"  {r['name']}: separation after refitting {r['predicted_separation_um']:.3g} µm = "
                     f"{r['predicted_separation_sigma']:.3g} σ (σ = {sigma_um:.3g} µm; on the record's input "
                     f"{r['record_separation_um']:.3g} µm first-order) — "
                     + ("separated" if r["separated"] else "not separated") +
                     f" at {report['targets']['separation_sigma']:g} σ" +
                     (f"; a record under it would let Vuong's test (white noise σ) name the true one with probability "
                      f"{r['vuong_power']:.3g} (expected z {r['expected_vuong_z']:.3g})"
                      if np.isfinite(r.get("vuong_power", np.nan)) else ""))
    par = report.get("parameters")
    if par:
        k = par["sv_index"]
        lines.append(f"  parameters: numerical rank {par['rank_before']} → {par['rank_after']}, s{k} "
                     f"{_e(par['sv_before'])} → {_e(par['sv_after'])} m (resolved: {_e(par['sv_after_resolved'])}; "
                     f"gain ×{_e(par['sv_gain'])}); identifiable before: {', '.join(par['identifiable_before']) or 'none'}; "
                     f"after: {', '.join(par['identifiable_after']) or 'none'}; become identifiable: "
                     f"{', '.join(par['become_identifiable']) or 'none'}")
    lines.append(f"search: {report['n_candidates']} candidates ({report['n_rejected']} rejected), "
                 f"{report['n_verified']} verified by refits, {report['wall_seconds']:.0f} s")
    lines += [f"warning: {w}" for w in report.get("warnings", [])]
    return "\n".join(lines)


def _e(v) -> str:
    return "n/a" if v is None else f"{v:.3g}"


def _fmt_params(p: Mapping) -> str:
    return "(" + ", ".join(f"{k} {v:.3g}" for k, v in p.items()) + ")"
