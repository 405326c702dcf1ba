"""Is structure left in the residual, and where does it concentrate?

:func:`locate` tests the prewhitened residual against prewhitened functions of each signal of the trajectory —
piecewise-constant bins of slider position and velocity, model current, input, and time, position and current
also signed by the direction of motion — plus the lagged input (the classical input-correlation test,
prewhitened). A family that predicts the whitened residual beyond its χ² level is structure the noise model cannot
explain; the conditional means per bin say *where*: "a bump near x_B ≈ 40 mm", "grows with i_q above 150 A". That
points the engineer to the physics outside the library.

The verdict uses the physical families (position, velocities, current, input, lagged input), with a Bonferroni
correction over them; time is shown, not tested: structure in time alone is what coloured noise looks like.

The public functions run BLAS with one thread: their least squares on tall, thin bases (5001 × ~12) are several
times slower on a multi-threaded pool (the polish's finding, :mod:`toggle_id.polish`).
"""
from __future__ import annotations

import textwrap
from collections.abc import Mapping

import numpy as np
from scipy import stats

from ..polish import one_blas_thread
from .noise import NoiseModel
from .stats import lagged_basis, piecewise_basis, structure_test

#: Signals of the localisation: key → (label, unit, display scale, display unit).
SIGNALS = {
    "x_B": ("slider B position", "m", 1e3, "mm"),
    "xdot_B": ("slider B velocity", "m/s", 1e3, "mm/s"),
    "i_q": ("model current i_q", "A", 1.0, "A"),
    "x_B_dir": ("slider B position, signed by the direction of motion", "m", 1e3, "mm"),
    "i_q_dir": ("model current i_q, signed by the direction of motion", "A", 1.0, "A"),
    "v_in": ("input voltage", "V", 1.0, "V"),
    "t": ("time", "s", 1.0, "s"),
    # EMPS (toggle_id.emps): load position and velocity, drive force gtau·ν, controller output
    "q": ("load position", "m", 1e3, "mm"),
    "q_dir": ("load position × direction of motion (negative: moving back)", "m", 1e3, "mm"),
    "qdot": ("load velocity", "m/s", 1e3, "mm/s"),
    "force": ("drive force", "N", 1.0, "N"),
    "vir": ("controller output", "V", 1.0, "V"),
}
#: Families of a signal's bins signed by the direction of slider B's motion (``<signal>_dir``).
SIGNED = ("x_B_dir", "i_q_dir")
#: Families that enter the verdict (time is shown only).
TESTED = ("x_B", "x_B_dir", "xdot_B", "i_q", "i_q_dir", "v_in", "v_in_lags", "q", "q_dir", "qdot")


def signals_of(t: np.ndarray, v_in: np.ndarray, states: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The signals of :data:`SIGNALS` available from a trajectory's states (see ``residuals.plant_states``)."""
    out = {k: np.asarray(states[k], float) for k in ("x_B", "xdot_B", "i_q") if k in states}
    out["v_in"] = np.asarray(v_in, float)
    out["t"] = np.asarray(t, float)
    return out


def _describe(name: str, edges: np.ndarray, levels: np.ndarray) -> dict:
    """Where the conditional means of one family concentrate, in words and numbers (bins by their edges)."""
    label, _, scale, unit = SIGNALS.get(name, (name, "", 1.0, ""))
    centres = 0.5 * (edges[:-1] + edges[1:])
    dev = levels - np.median(levels)
    j = int(np.argmax(np.abs(dev)))
    big = np.flatnonzero(np.abs(dev) >= 0.5 * abs(dev[j]))
    lo, hi = float(edges[big.min()]), float(edges[big.max() + 1])
    sign = "+" if dev[j] > 0 else "−"
    at_low, at_high = big.min() == 0, big.max() == centres.size - 1
    if at_high and not at_low and big.size >= 2:
        where = f"grows with {label} above {lo * scale:.3g} {unit}"
    elif at_low and not at_high and big.size >= 2:
        where = f"grows towards low {label}, below {hi * scale:.3g} {unit}"
    elif at_low and at_high and big.size >= 2:  # no bump: large deviations at both ends of the signal's range
        where = (f"spread over the whole range of {label} ({lo * scale:.3g}–{hi * scale:.3g} {unit}), largest near "
                 f"{centres[j] * scale:.3g} {unit}")
    else:
        where = f"a bump near {label} ≈ {centres[j] * scale:.3g} {unit} (bins {lo * scale:.3g}–{hi * scale:.3g} {unit})"
    return {"where": where, "peak_at": float(centres[j]), "range": [lo, hi], "peak_level_m": float(dev[j]),
            "text": f"{where}, residual level {sign}{abs(dev[j]) * 1e6:.3g} µm"}


def family_bases(signals: Mapping[str, np.ndarray], bins: int = 12, lags: int = 50, lag_step: int = 5
                 ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The bases of the structure test, one family per signal: equal-width bins of each signal (and of the
    slider position and of the model current, each signed by the direction of motion: a friction localised on the
    stroke, and one that grows with the load — a hysteresis of the clamping force), plus the lagged input.
    Returns (bases, bin centres, bin edges), keyed by family."""
    bases, centres, edges_of = {}, {}, {}
    for name, v in signals.items():
        B, edges = piecewise_basis(v, bins)
        if B.shape[1] >= 2:
            bases[name] = B
            edges_of[name] = edges
            centres[name] = 0.5 * (edges[:-1] + edges[1:])
    for name in SIGNED:  # friction-like: localised on the stroke, or growing with the load; against the motion
        base = name[:-4]
        if base in bases and "xdot_B" in signals:
            bases[name] = bases[base] * np.sign(signals["xdot_B"])[:, None]
            centres[name], edges_of[name] = centres[base], edges_of[base]
    if "v_in" in signals:
        bases["v_in_lags"] = lagged_basis(signals["v_in"], lags, lag_step)
    return bases, centres, edges_of


@one_blas_thread
def structure_energy(r: np.ndarray, signals: Mapping[str, np.ndarray], *, bins: int = 12, lags: int = 50,
                     lag_step: int = 5) -> float:
    """Σ over the tested families of ‖P_B r‖²: the energy of the raw residual ``r`` (m²) that functions of
    position, velocity, current and input express (least-squares projection on each family's basis).

    A descriptive measure, not a test: it compares residuals of one record (how much of the structure an effect
    removed) in the residual's own unit. The test statistics are whitened by an AR noise model, which acts as
    a high-pass filter — the smooth error a missing friction leaves is largely removed by it — so a whitened
    statistic can even grow when an effect removes most of the error."""
    r = np.asarray(r, float)
    total = 0.0
    for B in _tested_bases(signals, bins, lags, lag_step):
        fitted = B @ np.linalg.lstsq(B, r, rcond=1e-10)[0]
        total += float(fitted @ fitted)
    return total


def _tested_bases(signals: Mapping[str, np.ndarray], bins: int, lags: int, lag_step: int) -> list[np.ndarray]:
    """The bases of the families that enter the verdict (:data:`TESTED`), those whose signals are finite."""
    bases, _, _ = family_bases(signals, bins, lags, lag_step)
    return [B for name, B in bases.items() if name in TESTED and np.all(np.isfinite(B))]


@one_blas_thread
def structure_removed(r: np.ndarray, signals: Mapping[str, np.ndarray], *, bins: int = 12, lags: int = 50,
                      lag_step: int = 5) -> np.ndarray:
    """``r`` less its least-squares projection on the tested families' bases all at once: what no function of
    position, velocity, current and input (nor the lagged input) expresses — the noise's part of a residual that
    still holds a missing effect's structure. A noise model fitted to the whole residual takes a smooth error for
    slow noise (a far nominal fit's 27-µm error on a 1-s record read as AR(7) noise of ≈5 independent samples)."""
    r = np.asarray(r, float)
    cols = _tested_bases(signals, bins, lags, lag_step)
    if not cols:
        return r.copy()
    X = np.hstack(cols)
    return r - X @ np.linalg.lstsq(X, r, rcond=1e-10)[0]


@one_blas_thread
def locate(noise: NoiseModel | None, r: np.ndarray, signals: Mapping[str, np.ndarray], *, bins: int = 12,
           alpha: float = 0.01, lags: int = 50, lag_step: int = 5, J: np.ndarray | None = None,
           robust: bool = False, fitted: np.ndarray | None = None, fitted_noise: NoiseModel | None = None,
           unconverged_share: float = 0.1) -> dict:
    """Structure test and localisation of the residual ``r`` (see the module docstring; ``J``: the fit's
    sensitivities, for the robust statistic of :func:`.stats.structure_test`; ``robust``: the verdict from the
    smaller of the two statistics; ``fitted``: the sensitivities of the parameters fitted to ``r`` that are inside
    their bounds, ``fitted_noise`` the noise model the fit minimised under, and ``unconverged_share``, for
    :func:`convergence`).

    Returns {structure_left, alpha, families: {name: {p_value, statistic, dof, share, centres, levels,
    where, text}}, strongest, convergence, text}. ``structure_left`` when a tested family's p-value is below
    alpha / (number of tested families), or when the fit has not converged.
    """
    bases, centres, edges_of = family_bases(signals, bins, lags, lag_step)
    res = structure_test(noise, r, bases, J=J, robust=robust)
    tested = [k for k in TESTED if k in res]
    level = alpha / max(len(tested), 1)
    conv = convergence(r, fitted, level, fitted_noise, unconverged_share) if fitted is not None else None
    families = {}
    for name, d in res.items():
        fam = {k: d[k] for k in ("statistic", "statistic_classical", "statistic_robust", "dof", "p_value", "share")}
        fam["tested"] = name in tested
        fam["significant"] = bool(name in tested and d["p_value"] < level)
        if name in centres:
            levels = np.asarray(d["coef"], float)
            fam.update({"centres": centres[name].tolist(), "edges": edges_of[name].tolist(),
                        "levels_m": levels.tolist()})
            fam.update(_describe(name, edges_of[name], levels))
        families[name] = fam
    sig = sorted((k for k in tested if families[k]["significant"]), key=lambda k: families[k]["p_value"])
    strongest = sig[0] if sig else None
    unconverged = conv is not None and not conv["converged"]
    if strongest is None and not unconverged:
        text = "no structure left: the whitened residual is not predicted by position, velocity, current or input"
    else:
        parts = (_parts(families, sig) or ["correlated with the past input"]) if sig else []
        text = "structure left: " + "; ".join(([conv["text"]] if unconverged else []) + parts[:3])
    return {"structure_left": strongest is not None or unconverged, "alpha": alpha, "level_per_family": level,
            "bins": bins, "families": families, "strongest": strongest, "significant": sig, "convergence": conv,
            "text": text}


def convergence(r: np.ndarray, fitted: np.ndarray, level: float, noise: NoiseModel | None = None,
                min_share: float = 0.1) -> dict:
    """Has the fit whose residual is ``r`` reached a minimum of its own criterion — the residual prewhitened by the
    ``noise`` model it was fitted under (None: white, least squares)? The whitened residual is regressed on the
    whitened sensitivities ``fitted`` (N, q) of its free parameters inside their bounds: at a minimum it has no
    component along them (the explained share is 0, up to the polish's tolerance and its Jacobian's tier), while a
    fit stopped short leaves a residual its own parameters still explain. The statistic is read against χ²(q), which
    it stays far below at a smooth minimum (measured 1–9 for q = 11–16 at converged fits of 1-s and 5-s records), so
    this test adds next to nothing to the verdict's false-alarm rate. At a kink of the model the linearisation does
    not hold: the backlash fit of rec12 (adversarial set) reads 29 on 14 (p 0.01), 0.6 % of its residual. So a fit
    is called unconverged only when, beyond the level, its parameters explain more than ``min_share`` of its
    whitened residual — a further step would then lower its RMS by about half that share or more; a fit stopped far
    from its minimum leaves most of it (98 % in the routes test). The families are tested *after* the
    sensitivities (:func:`.stats.structure_test`), so without this check such a fit (10–11 µm on a 1-µm-noise
    record) reads as noise.

    Returns {statistic, dof, p_value, share, converged, text}: not ``converged`` when the p-value is below ``level``
    and the share above ``min_share``."""
    fitted = np.asarray(fitted, float)
    d = (structure_test(noise if noise is not None else NoiseModel(), r, {"parameters": fitted})
         .get("parameters") if fitted.ndim == 2 and np.any(fitted) else None)
    if d is None:
        return {"statistic": 0.0, "dof": 0, "p_value": 1.0, "share": 0.0, "converged": True,
                "text": "no free parameter inside its bounds"}
    converged = bool(d["p_value"] >= level or d["share"] <= min_share)
    text = ("the fit has converged" if converged else
            f"the fit has not converged: its own parameters still explain {100 * d['share']:.3g} % of its residual "
            f"(p = {d['p_value']:.2g})")
    return {"statistic": d["statistic"], "dof": d["dof"], "p_value": d["p_value"], "share": d["share"],
            "converged": converged, "text": text}


def _same_place(a: Mapping, b: Mapping) -> bool:
    """Two families of one signal (its bins, and its bins signed by the direction of motion) that point at the same
    bins with the same size of level: on this record they say one thing."""
    la, lb = abs(a.get("peak_level_m", 0.0)), abs(b.get("peak_level_m", 0.0))
    return (a.get("peak_at") == b.get("peak_at") and a.get("range") == b.get("range")
            and max(la, lb) > 0 and abs(la - lb) <= 0.1 * max(la, lb))


def _parts(families: Mapping[str, dict], significant: list[str]) -> list[str]:
    """The significant families' descriptions, strongest first (the lagged input apart), a signal's signed family
    folded into its own where both point at the same place: which of the two, the record does not tell."""
    parts = []
    for k in significant:
        if k == "v_in_lags":
            continue
        fam = families[k]
        base, twin = (k[:-4], None) if k.endswith("_dir") else (None, f"{k}_dir")
        if base in significant and _same_place(fam, families[base]):
            continue  # said by the signal's own family, below or above
        text = fam.get("text", f"{k} (p = {fam['p_value']:.2g})")
        if twin in significant and _same_place(fam, families[twin]):
            text += " (the same with the direction of motion's sign)"
        parts.append(text)
    return parts


#: Families of :func:`noise_level`: key → (signal, taken as a magnitude, label, display scale, display unit).
#: Those whose signal a trajectory has are tested (the toggle plant's first four, the EMPS axis's next three).
LEVEL_FAMILIES = {"speed": ("xdot_B", True, "slider B speed", 1e3, "mm/s"),
                  "x_B": ("x_B", False, "slider B position", 1e3, "mm"),
                  "current": ("i_q", True, "|model current|", 1.0, "A"),
                  "load_speed": ("qdot", True, "load speed", 1e3, "mm/s"),
                  "q": ("q", False, "load position", 1e3, "mm"),
                  "force": ("force", True, "|drive force|", 1.0, "N"),
                  "t": ("t", False, "time", 1.0, "s")}


def level_basis(signals: Mapping[str, np.ndarray], bins: int = 12, min_count: int = 100) -> np.ndarray | None:
    """What the noise's level may follow, as bases (N, m) for :func:`.stats.robust_f`: the bins of each family of
    :data:`LEVEL_FAMILIES` the ``signals`` hold (speed, position, current or force magnitude, time), side by side;
    a bin holds at least ``min_count`` samples, so that the level in it is an average (±14 % in σ² at 100)."""
    cols = []
    for key, magnitude, *_ in LEVEL_FAMILIES.values():
        if key in signals:
            v = np.asarray(signals[key], float)
            cols.append(piecewise_basis(np.abs(v) if magnitude else v, bins, min_count)[0])
    return np.hstack(cols) if cols else None


@one_blas_thread
def noise_level(noise: NoiseModel, r: np.ndarray, signals: Mapping[str, np.ndarray], *, bins: int = 12,
                alpha: float = 0.01) -> dict:
    """Does the noise's level vary along the record, and with what? Report-only.

    The squared prewhitened residual is regressed on the bins of each family of :data:`LEVEL_FAMILIES` the
    ``signals`` hold (speed, position, force or current magnitude, time), one at a time; n·R² is χ²(bins − 1) when
    the level is the same everywhere (Koenker's studentised Breusch–Pagan test, which does not assume Gaussian
    noise: quantised or heavy-tailed noise keeps its level). A family whose p-value is below ``alpha`` / the number
    of families says where the noise is loud and where quiet, σ per bin in the residual's units. The discovery
    tests allow for such noise (:func:`.stats.robust_f`, the robust structure statistic); this only tells the
    user — an encoder or a mounting that is noisier at speed. Returns {varies, families: {name: {statistic, dof,
    p_value, edges, sigma_m}}, strongest, text}."""
    e = noise.whiten(np.asarray(r, float))[noise.order:]
    e2 = e * e
    to_residual = np.sqrt(noise.variance_ratio) if not noise.white else 1.0
    families = {}
    for name, (key, magnitude, *_) in LEVEL_FAMILIES.items():
        if key not in signals:
            continue
        v = np.asarray(signals[key], float)
        B, edges = piecewise_basis((np.abs(v) if magnitude else v)[noise.order:], bins)
        if B.shape[1] < 2 or not np.all(np.isfinite(e2)):
            continue
        coef = np.linalg.lstsq(B, e2, rcond=1e-10)[0]
        dev = e2 - e2.mean()
        tss = float(dev @ dev)
        ess = float(np.sum((B @ coef - e2.mean()) ** 2))
        stat = e2.size * ess / tss if tss > 0 else 0.0
        dof = B.shape[1] - 1
        families[name] = {"statistic": stat, "dof": dof, "p_value": float(stats.chi2.sf(stat, dof)),
                          "edges": edges.tolist(), "sigma_m": (np.sqrt(np.maximum(coef, 0.0)) * to_residual).tolist()}
    level = alpha / max(len(families), 1)
    sig = sorted((k for k, f in families.items() if f["p_value"] < level), key=lambda k: families[k]["p_value"])
    out = {"varies": bool(sig), "alpha": alpha, "families": families, "strongest": sig[0] if sig else None,
           "text": "the noise's level is the same along the record"}
    if sig:
        f = families[sig[0]]
        _, _, label, scale, unit = LEVEL_FAMILIES[sig[0]]
        sd, edges = np.asarray(f["sigma_m"]), np.asarray(f["edges"]) * scale
        lo, hi = int(np.argmin(sd)), int(np.argmax(sd))
        tiny = 1e-3 * float(edges[-1] - edges[0])

        def span(j: int) -> str:
            a, b = (0.0 if abs(x) < tiny else float(x) for x in edges[j:j + 2])
            return f"{a:.3g}–{b:.3g} {unit}"

        out["text"] = (f"the noise's level varies with {label}: σ ≈ {sd[hi] * 1e6:.3g} µm at {span(hi)}, "
                       f"{sd[lo] * 1e6:.3g} µm at {span(lo)}")
    return out


def figure(locate_result: dict, r: np.ndarray, signals: Mapping[str, np.ndarray], title: str = ""):
    """Residual against each signal (thin dots) with its per-bin level from the whitened regression."""
    from matplotlib.figure import Figure

    names = [k for k in SIGNALS if "levels_m" in locate_result["families"].get(k, {})]
    fig = Figure(figsize=(11, 2.4 * max(len(names), 1)), layout="constrained")
    axes = fig.subplots(max(len(names), 1), 1, squeeze=False)[:, 0]
    for ax, name in zip(axes, names):
        label, _, scale, unit = SIGNALS[name]
        fam = locate_result["families"][name]
        signed = name in SIGNED
        v = np.asarray(signals[name[:-4] if signed else name], float) * scale
        rr = np.asarray(r) * (np.sign(signals["xdot_B"]) if signed else 1.0)
        ax.plot(v, rr * 1e6, ".", ms=1, alpha=0.25, color="0.4")
        ax.stairs(np.asarray(fam["levels_m"]) * 1e6, np.asarray(fam["edges"]) * scale, lw=2,
                  color="C3" if fam["significant"] else "C0", label="level per bin (prewhitened fit)")
        tag = "" if not fam["tested"] else (f"p = {fam['p_value']:.2g}" + (" — structure" if fam["significant"]
                                                                           else ""))
        ax.set_title(f"{label}: {tag}", fontsize=9, loc="left")
        ax.set_xlabel(f"{label} [{unit}]")
        ax.set_ylabel("residual [µm]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    fig.suptitle(textwrap.fill(title or locate_result["text"], 140), fontsize=9)
    return fig
