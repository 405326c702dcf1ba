"""Does the residual repeat with a position? Report-only.

A linear scale's interpolation error repeats with its pitch along the stroke, a ball screw's lead error and an
encoder's eccentricity once per motor revolution, a motor's cogging n times per revolution. Such an error is a
periodic function of a position, not of time (the record's speed changes, so it is no line in the spectrum), and
twelve bins over the stroke (:mod:`.localise`) cannot draw a period shorter than a few bins.

:func:`periodic` scans each position the trajectory has (slider B's position and the motor angle of the toggle
plant) for a sinusoid sin/cos(2π·x/P): a least-squares periodogram of the prewhitened
residual over periods from ``min_cycles`` per stroke down to a few samples' travel, on a grid oversampled
``oversample`` times. The best period is then tested as one basis by :func:`.stats.structure_test` (under the noise
model of the residual with the sinusoid removed, robust to a varying noise level, after the fit's sensitivities),
and its p-value multiplied by the number of positions and by N/2, the most 2-dof directions an N-sample record can
hold (Bonferroni over the scan: the grid's own count, range × frequency band, was measured too small — 2 of 12
draws of white noise flagged at 1 % on a stroke that rests at its ends, where the sinusoids are far from
orthogonal). It names the period and amplitude of the position that explains most. A mechanism's positions are
functions of one another, so an error periodic in one shows, weaker, in the others — and where the map between
them is nearly linear over part of the stroke, the wrong one can explain more (rec23 of the adversarial set: a
linear scale's error of pitch 5 mm, found every 4.81 mm of slider B position at p = 9e-120 and 3.4 times per motor
revolution at p = 9e-291). So another significant position is named too when its period explains the residual
beyond the best one's (the same test and scan correction, after that sinusoid), with the caveat that the record
may not tell which one the error follows. A count per motor revolution farther than ``whole_tol`` from a whole
number is said to be none of the motor-side causes (each repeats a whole number of times per revolution), with the
period along the slider's position when that one is significant too: on rec23 that points at the scale. The loop's
verdict does not use it. The loop does use :func:`cogging_domain`: the cogging counts of which the record's
motor-angle range holds enough periods to be told from a slow error.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..effects import ALL_INDEX, EFFECTS_BY_NAME, Effect
from ..residuals import plant_states
from .noise import NoiseModel, fit_noise
from .stats import structure_test

if TYPE_CHECKING:
    from .model import Model

#: Positions scanned: state key → (label, display scale, display unit, the period also said per motor revolution).
POSITIONS = {"x_B": ("slider B position", 1e3, "mm", False),
             "motor_angle": ("motor angle", 1.0, "rad", True)}
#: What a period of each position may be (the user's next look).
CAUSES = {"x_B": "a linear scale's interpolation error, or a force that repeats along the stroke?",
          "motor_angle": "cogging, an encoder's eccentricity or a ball screw's lead error?"}


def whole_count(count: float, tol: float) -> int | None:
    """The whole number of times per revolution that ``count`` is, within ``tol`` (None: no whole number) — a
    motor-side cause (a cogging, an encoder's eccentricity, a screw's lead error) repeats a whole number of times."""
    k = round(float(count))
    return int(k) if abs(float(count) - k) <= tol else None


#: The parameters that count repetitions per motor revolution: a machine has them whole (a motor's slots and
#: poles), so a fitted fraction is the missing physics' or the search's, not the motor's.
COUNTS = ("n_cog",)


def whole_counts(name: str, theta: np.ndarray, free: Sequence[str], tol: float) -> dict[str, int]:
    """The counts of effect ``name`` (:data:`COUNTS`) free in a fit at ``theta`` that lie within ``tol`` of a whole
    number, each with that number. The forward step holds an accepted refit's there from then on
    (:func:`.forward._polish_with_effect`'s ``hold``), as the catch-all does an effect's beside its generic terms
    (:func:`.catchall.beside_generic`), so no later fit (the polish, the next effects' refits, backward elimination,
    the final polish) can move it. Left free beside physics the library lacks, the count drifts to wherever its
    ripple stands in for that physics: rec38 of the adversarial set (a cogging at n_cog = 6 beside a quadratic drag)
    accepted its cogging at n_cog 6.035, the polish and the later fits moved it to 4.56 (near the floor of
    ``cogging_min_periods``) and the final check called it compensating, no whole count. A count farther from a
    whole number stays free and is judged by :func:`implausible` at the end."""
    out = {}
    for nm in EFFECTS_BY_NAME[name].names:
        if nm in COUNTS and nm in free:
            k = whole_count(float(theta[ALL_INDEX[nm]]), tol)
            if k is not None:
                out[nm] = k
    return out


def implausible(name: str, theta: np.ndarray, cogging_whole_tol: float) -> str | None:
    """Why the fitted values of effect ``name`` in ``theta`` are no machine's (None: nothing against them). A motor's
    cogging torque repeats a whole number of times per revolution (the least common multiple of its slots and
    poles): an n_cog farther than ``cogging_whole_tol`` from a whole number stands in for something else that repeats
    with a position — a scale's pitch along the stroke, a screw's lead error."""
    if name == "cogging_torque":
        n = float(theta[ALL_INDEX["n_cog"]])
        if whole_count(n, cogging_whole_tol) is None:
            return (f"lowers the error, but repeats {n:.3g} times per motor revolution, and a motor's cogging repeats "
                    "a whole number of times (its slots and poles): it stands in for something outside the library "
                    "that repeats with a position")
    return None


def turns(angle: np.ndarray) -> float:
    """The revolutions an angle (rad) spans over a record: its range over 2π."""
    return float(np.ptp(angle)) / (2.0 * np.pi)


def _basis(x: np.ndarray, f: np.ndarray) -> np.ndarray:
    """sin and cos of 2π·f·x for each frequency f (cycles per unit of x): (N, 2·len(f)), sines first."""
    ph = 2.0 * np.pi * np.outer(x, f)
    return np.hstack([np.sin(ph), np.cos(ph)])


def scan(noise: NoiseModel, r: np.ndarray, x: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """Explained sum of squares over the whitened residual's variance of a sinusoid in ``x`` at each of ``freqs``
    (the classical statistic, χ²(2) under white innovations)."""
    k0 = noise.order
    e = noise.whiten(r)[k0:]
    s2 = float(e @ e) / max(e.size, 1)
    W = noise.whiten_columns(_basis(x, freqs))[k0:]
    nf = freqs.size
    S, C = W[:, :nf], W[:, nf:]
    ss, cc, sc = np.sum(S * S, 0), np.sum(C * C, 0), np.sum(S * C, 0)
    se, ce = S.T @ e, C.T @ e
    det = ss * cc - sc * sc
    ok = det > 1e-12 * np.maximum(ss * cc, np.finfo(float).tiny)
    ess = np.where(ok, (cc * se * se - 2.0 * sc * se * ce + ss * ce * ce) / np.where(ok, det, 1.0), 0.0)
    return ess / s2 if s2 > 0 else np.zeros(nf)


def frequency_grid(x: np.ndarray, min_cycles: float = 3.0, oversample: int = 2, samples_per_period: float = 4.0,
                   max_periods: int = 400) -> tuple[np.ndarray, float]:
    """Frequencies to scan (cycles per unit of ``x``) and how many periods the band holds (range × band): from
    ``min_cycles`` over the range of ``x`` up to a period of ``samples_per_period`` times the typical travel
    between samples in motion (the 75th percentile of |Δx| over the samples that move at least a twentieth of the
    fastest; a clamped slider barely moves), at most ``max_periods`` in the band; step
    1/(``oversample``·range)."""
    span = float(np.ptp(x))
    step = np.abs(np.diff(x))
    step = step[step >= 0.05 * float(np.max(step))] if span > 0 and step.size else step[:0]
    if span <= 0 or step.size == 0 or not step[0] > 0:
        return np.zeros(0), 0.0
    f_lo = min_cycles / span
    f_hi = min(1.0 / (samples_per_period * float(np.percentile(step, 75))), f_lo + max_periods / span)
    if f_hi <= f_lo:
        return np.zeros(0), 0.0
    freqs = np.arange(f_lo, f_hi, 1.0 / (oversample * span))
    return freqs, max((f_hi - f_lo) * span, 1.0)


def periodic(r: np.ndarray, states: Mapping[str, np.ndarray], *, alpha: float = 0.01, max_order: int = 8,
             J: np.ndarray | None = None, robust: bool = True, min_cycles: float = 3.0, oversample: int = 2,
             noise: NoiseModel | None = None, whole_tol: float = 0.1) -> dict:
    """Scan the residual ``r`` for a period in each position of :data:`POSITIONS` that ``states`` holds (see the
    module docstring; ``noise``: the residual's AR noise model when the caller has it, else fitted here;
    ``whole_tol``: how far from a whole number a count per motor revolution may lie for a motor-side cause). Returns
    {periodic, alpha, families: {key: {period, period_display, cycles_per_revolution, amplitude_m, statistic, dof,
    p_value, p_scan, periods_in_band, significant, repeats, text, beyond_strongest (the others)}}, strongest, text}."""
    r = np.asarray(r, float)
    keys = [k for k in POSITIONS if k in states and np.all(np.isfinite(states[k]))]
    out: dict = {"periodic": False, "alpha": alpha, "families": {}, "strongest": None,
                 "text": "the residual repeats with no position"}
    if not keys or not np.all(np.isfinite(r)):
        return out
    noise = noise if noise is not None else fit_noise(r, max_order)
    bases: dict[str, np.ndarray] = {}
    for key in keys:
        x = np.asarray(states[key], float)
        freqs, m = frequency_grid(x, min_cycles, oversample)
        if freqs.size == 0:
            continue
        stat = scan(noise, r, x, freqs)
        j = int(np.argmax(stat))
        df = freqs[1] - freqs[0] if freqs.size > 1 else freqs[0] * 0.01
        fine = np.linspace(freqs[j] - df, freqs[j] + df, 41)
        fine = fine[fine > 0]
        f = float(fine[int(np.argmax(scan(noise, r, x, fine)))])
        B = _basis(x, np.array([f]))
        test = structure_test(None, r, {"periodic": B}, max_order=max_order, J=J, robust=robust)["periodic"]
        coef = np.linalg.lstsq(np.column_stack([B, np.ones_like(x)]), r, rcond=None)[0]
        p_scan = min(1.0, test["p_value"] * 0.5 * r.size * len(keys))
        label, scale, unit, per_rev = POSITIONS[key]
        fam = {"period": 1.0 / f, "period_display": f"{scale / f:.3g} {unit}",
               "cycles_per_revolution": 2.0 * np.pi * f if per_rev else None,
               "amplitude_m": float(np.hypot(coef[0], coef[1])), "statistic": float(test["statistic"]),
               "dof": int(test["dof"]), "p_value": float(test["p_value"]), "p_scan": p_scan,
               "periods_in_band": float(m), "significant": bool(p_scan < alpha)}
        every = (f"{fam['cycles_per_revolution']:.3g} times per motor revolution (every {fam['period_display']})"
                 if per_rev else f"every {fam['period_display']} of {label}")
        fam["repeats"] = f"{every}, amplitude {fam['amplitude_m'] * 1e6:.3g} µm (p = {p_scan:.2g} after the scan)"
        fam["text"] = f"the residual repeats {fam['repeats']}: {CAUSES[key]}"
        out["families"][key] = fam
        bases[key] = B
    fams = out["families"]
    sig = sorted((k for k, v in fams.items() if v["significant"]), key=lambda k: fams[k]["p_scan"])
    if not sig:
        return out
    # a period in one position shows in the others: another is said only where it explains more than the best does
    best = bases[sig[0]]
    also = [k for k in sig[1:] if _beyond(r, bases[k], best, J, max_order, robust) * 0.5 * r.size * len(keys) < alpha]
    for k in sig[1:]:
        fams[k]["beyond_strongest"] = k in also
    said = [sig[0], *also]
    first = fams[sig[0]]
    fraction = first["cycles_per_revolution"] is not None and whole_count(first["cycles_per_revolution"],
                                                                          whole_tol) is None
    if fraction:
        # no motor-side cause repeats a fraction of times per revolution: the error follows another position
        first["text"] = (f"the residual repeats {first['repeats']}, not a whole number of times per revolution as "
                         "a cogging, an encoder's eccentricity or a ball screw's lead error would: an error that "
                         "repeats with another position, seen through the mechanism" + "".join(
                             f"; along {POSITIONS[k][0]} it repeats every {fams[k]['period_display']} "
                             f"(p = {fams[k]['p_scan']:.2g} after the scan): {CAUSES[k]}"
                             for k in sig[1:] if POSITIONS[k][3] is False))
    text = first["text"] if not also else (
        "the residual repeats " + ", and ".join(fams[k]["repeats"] for k in said)
        + ", the later beyond the first: the mechanism ties these positions to each other, so which one the error "
        "follows the record may not tell" + (" (the count per revolution is no whole number)" if fraction else "")
        + " — " + "; or ".join(CAUSES[k].rstrip("?") for k in said) + "?")
    out.update(periodic=True, strongest=sig[0], text=text)
    return out


def _beyond(r: np.ndarray, B: np.ndarray, best: np.ndarray, J: np.ndarray | None, max_order: int,
            robust: bool) -> float:
    """p-value of the sinusoid ``B`` tested after the sinusoid ``best`` (both taken out of the residual and of ``B``
    by least squares; the robust statistic also after the sensitivities ``J``)."""
    def out_of(M: np.ndarray) -> np.ndarray:
        return M - best @ np.linalg.lstsq(best, M, rcond=None)[0]
    JJ = best if J is None or not np.size(J) else np.hstack([np.asarray(J, float), best])
    return structure_test(None, out_of(r), {"periodic": out_of(B)}, max_order=max_order, J=JJ,
                          robust=robust)["periodic"]["p_value"]


def cogging_floor(record, periods: float) -> float:
    """The lowest cogging count n_cog of which the motor-angle range of ``record`` (from its measured x_B through the
    mechanism, :func:`~toggle_id.residuals.plant_states`) holds ``periods`` periods: 2π·periods / range (inf for a
    record at rest). On the adversarial set's commands the range is 13.9–14.8 rad: 4.2–4.5 at 10 periods."""
    revs = turns(plant_states(record.t, record.x_B)["motor_angle"])
    return float(periods) / revs if revs > 0 else float("inf")


def cogging_domain(model: Model, pool: Sequence[Effect], periods: float, say: Callable[[str], None]
                   ) -> list[Effect]:
    """The candidates of ``pool`` with the cogging torque's count narrowed on ``model`` (:attr:`Model.bounds`) to those
    of which the record's motor-angle range holds ``periods`` periods (:func:`cogging_floor`; 0: as the library has
    it), or left out when no count up to the library's bound does."""
    if not periods > 0 or not any(e.name == "cogging_torque" for e in pool):
        return list(pool)
    n_min = cogging_floor(model.record, periods)
    n_hi = next(p.upper for p in EFFECTS_BY_NAME["cogging_torque"].params if p.name == "n_cog")
    if n_min >= n_hi:
        say(f"cogging_torque left out: the record's motor angle spans fewer than {periods:g} periods of any count up "
            f"to {n_hi:g} per revolution")
        return [e for e in pool if e.name != "cogging_torque"]
    if n_min > 1.0:
        model.bounds["n_cog"] = (n_min, n_hi)
        say(f"cogging_torque: counts from {n_min:.3g} per revolution, {periods:g} periods of the record's motor-angle "
            "range (discover.cogging_min_periods)")
    return list(pool)
