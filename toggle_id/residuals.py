"""Residual diagnostics: is what the model leaves over white noise, or structure the model lacks?

Everything here works on plain arrays and returns plain numbers/dicts (JSON-ready); the figure helpers
return :class:`matplotlib.figure.Figure` objects (save them with :func:`toggle_id.figures.save`).

Tests, each with its significance level ``alpha`` (default 0.01):

- *whiteness*: sample autocorrelation ρ_k of the residual for lags 1…K with the band ±z_{1−α/2}/√N, and the
  Ljung–Box portmanteau statistic Q = N(N+2) Σ_k ρ_k²/(N−k) ~ χ²(K) under white noise;
- *input correlation*: the cross-correlation ρ_{εu}(τ) = corr(ε(t), u(t−τ)) for τ = −K…K with the same band
  (valid per lag when ε is white, however coloured u is), and a joint test of independence from the past
  input (Ljung, *System Identification*, §16.6): regress ε on lagged inputs φ(t) = [u(t−τ_1) … u(t−τ_M)];
  N·R² ~ χ²(rank Φ) when ε is white and independent of u (the regression form accounts for the input's
  own autocorrelation, which makes the lags of a swept sine nearly collinear);
- *states*: Pearson correlation of the residual with each state signal (slider position and velocity,
  slider-C velocity, motor angle, current, contact indicator) with its two-sided t-test p-value;
- *spectrum*: Welch power spectral density and its dominant frequencies (no test, a pointer).

The p-values assume white residuals under the null; when whiteness fails, the input/state p-values are
optimistic and should be read as rankings, not as exact levels.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure
from scipy import signal, stats

from .errors import DataError
from .plant import GEOMETRY, Geometry, kinematics

#: Default significance level of the residual tests.
ALPHA = 0.01
#: Default number of autocorrelation lags of the Ljung–Box test (samples).
ACF_LAGS = 20

STATE_LABELS = {
    "x_B": ("slider B position", "m", 1e3, "mm"),
    "xdot_B": ("slider B velocity", "m/s", 1e3, "mm/s"),
    "xdot_C": ("slider C velocity", "m/s", 1e3, "mm/s"),
    "motor_angle": ("motor angle θ_r = Z·x_C", "rad", 1.0, "rad"),
    "i_q": ("current i_q (model)", "A", 1.0, "A"),
    "contact": ("contact (1 = clamped)", "-", 1.0, "-"),
}


# ---------------------------------------------------------------------------------------------- helpers
def _vector(x, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 1 or a.size < 3:
        raise DataError(f"{what} must be a 1-D array of at least 3 samples, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise DataError(f"{what} has {int(np.sum(~np.isfinite(a)))} non-finite values")
    return a


def significance_band(n: int, alpha: float = ALPHA) -> float:
    """Half width z_{1−α/2}/√n of the (1 − α) band of a sample correlation of n white samples."""
    return float(stats.norm.ppf(1.0 - alpha / 2.0) / np.sqrt(max(int(n), 1)))


def _fmt_p(p: float) -> float:
    return float(max(p, 0.0))


# ---------------------------------------------------------------------------------------------- whiteness
def autocorrelation(r: Sequence[float], max_lag: int = ACF_LAGS) -> np.ndarray:
    """Sample autocorrelation ρ_0…ρ_K of ``r`` (mean removed, biased estimator, ρ_0 = 1)."""
    r = _vector(r, "residual")
    n = r.size
    K = int(min(max(max_lag, 0), n - 1))
    e = r - r.mean()
    c0 = float(e @ e)
    if c0 <= 0.0:
        return np.r_[1.0, np.zeros(K)]
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(e, nfft)
    acov = np.fft.irfft(f * np.conj(f), nfft)[:K + 1]
    return acov / c0


def ljung_box(r: Sequence[float], lags: int = ACF_LAGS, alpha: float = ALPHA, n_fitted: int = 0) -> dict:
    """Ljung–Box whiteness test over lags 1…``lags``.

    Returns {statistic, dof, p_value, alpha, white (p ≥ alpha), lags, acf_lag1, n_outside_band, band}.
    ``n_fitted`` (ARMA-type parameters fitted to the residual itself) reduces the degrees of freedom; for
    the residual of a physical model it is 0.
    """
    r = _vector(r, "residual")
    n = r.size
    K = int(min(max(lags, 1), n - 2))
    rho = autocorrelation(r, K)
    k = np.arange(1, K + 1)
    Q = float(n * (n + 2) * np.sum(rho[1:] ** 2 / (n - k)))
    dof = max(K - int(n_fitted), 1)
    p = _fmt_p(stats.chi2.sf(Q, dof))
    band = significance_band(n, alpha)
    return {"test": "Ljung-Box", "statistic": Q, "dof": dof, "p_value": p, "alpha": alpha, "white": p >= alpha,
            "lags": K, "acf_lag1": float(rho[1]) if K >= 1 else 0.0,
            "n_outside_band": int(np.sum(np.abs(rho[1:]) > band)), "band": band}


# ---------------------------------------------------------------------------------------------- spectrum
def spectrum(r: Sequence[float], fs: float, nperseg: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Welch power spectral density of ``r`` (units of r² per Hz) at frequencies [Hz] (``fs`` in Hz).

    ``nperseg`` default: the largest power of two ≤ N/4 (at least 16), Hann windows, 50 % overlap.
    """
    r = _vector(r, "residual")
    if not (np.isfinite(fs) and fs > 0):
        raise DataError(f"sampling rate must be positive, got {fs}")
    if nperseg is None:
        nperseg = max(16, 1 << int(np.floor(np.log2(max(r.size // 4, 16)))))
    nperseg = int(min(nperseg, r.size))
    f, p = signal.welch(r - r.mean(), fs=fs, nperseg=nperseg)
    return f, p


def dominant_frequencies(f: np.ndarray, p: np.ndarray, k: int = 3, white_level: float | None = None) -> list[dict]:
    """The ``k`` largest local maxima of a spectrum: [{frequency_hz, psd, ratio_to_median}]."""
    f, p = np.asarray(f, float), np.asarray(p, float)
    if p.size < 3:
        return []
    peaks, _ = signal.find_peaks(p)
    if peaks.size == 0:
        peaks = np.array([int(np.argmax(p))])
    order = peaks[np.argsort(-p[peaks])][:k]
    level = white_level if white_level is not None else float(np.median(p[1:])) if p.size > 1 else float(p[0])
    return [{"frequency_hz": float(f[i]), "psd": float(p[i]),
             "ratio_to_median": float(p[i] / level) if level > 0 else float("inf")} for i in order]


def white_noise_psd(variance: float, fs: float) -> float:
    """One-sided PSD level of white noise of ``variance`` sampled at ``fs`` Hz (variance per Hz)."""
    return 2.0 * float(variance) / float(fs)


# ---------------------------------------------------------------------------------------------- input
def cross_correlation(r: Sequence[float], u: Sequence[float], max_lag: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """ρ_{εu}(τ) = corr(ε(t), u(t−τ)) for τ = −K…K samples (positive τ: the residual follows the input)."""
    r = _vector(r, "residual")
    u = _vector(u, "input")
    if u.size != r.size:
        raise DataError(f"input has {u.size} samples but the residual has {r.size}")
    n = r.size
    K = int(min(max(max_lag, 0), n - 1))
    e, v = r - r.mean(), u - u.mean()
    den = float(np.sqrt((e @ e) * (v @ v)))
    lags = np.arange(-K, K + 1)
    if den <= 0.0:
        return lags, np.zeros(lags.size)
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    c = np.fft.irfft(np.fft.rfft(e, nfft) * np.conj(np.fft.rfft(v, nfft)), nfft)
    # c[τ] = Σ_t e(t) v(t − τ) for τ ≥ 0; negative lags wrap to the end
    vals = np.r_[c[nfft - K:], c[:K + 1]] if K > 0 else c[:1]
    return lags, vals / den


def input_correlation_test(r: Sequence[float], u: Sequence[float], max_lag: int = 50, lag_step: int = 5,
                           alpha: float = ALPHA) -> dict:
    """Joint test that the residual is uncorrelated with the past input (lags 0, step, …, ``max_lag``).

    Regression of the residual on the lagged, centred input; N·R² ~ χ²(rank) under white residuals
    independent of the input. Also returns the largest |ρ_{εu}(τ)| over τ = −K…K and how many lags leave
    the (1 − α) band. Returns {statistic, dof, p_value, alpha, independent (p ≥ alpha), max_abs_ccf,
    max_abs_ccf_lag, n_outside_band, band}.
    """
    r = _vector(r, "residual")
    u = _vector(u, "input")
    if u.size != r.size:
        raise DataError(f"input has {u.size} samples but the residual has {r.size}")
    n = r.size
    step = max(int(lag_step), 1)
    K = int(min(max(max_lag, 0), n // 4))
    taus = np.arange(0, K + 1, step)
    e = r - r.mean()
    v = u - u.mean()
    rows = np.arange(K, n)
    Phi = np.column_stack([v[rows - tau] for tau in taus])
    y = e[rows]
    coef, _, rank, _ = np.linalg.lstsq(Phi, y, rcond=1e-10)
    fitted = Phi @ coef
    yy = float(y @ y)
    R2 = float(fitted @ fitted) / yy if yy > 0 else 0.0
    stat = rows.size * R2
    dof = max(int(rank), 1)
    p = _fmt_p(stats.chi2.sf(stat, dof))
    lags, ccf = cross_correlation(r, u, max_lag)
    band = significance_band(n, alpha)
    j = int(np.argmax(np.abs(ccf)))
    return {"test": "input regression N·R²", "statistic": float(stat), "dof": dof, "p_value": p, "alpha": alpha,
            "independent": p >= alpha, "lags": [int(t) for t in taus], "max_abs_ccf": float(abs(ccf[j])),
            "max_abs_ccf_lag": int(lags[j]), "n_outside_band": int(np.sum(np.abs(ccf) > band)), "band": band}


# ---------------------------------------------------------------------------------------------- states
def plant_states(t: Sequence[float], x_B: Sequence[float], i_q: Sequence[float] | None = None, *,
                 x_off: float = 0.0, geometry: Geometry = GEOMETRY) -> dict[str, np.ndarray]:
    """State signals of a (model) trajectory for residual analysis.

    ``x_B`` is the model's output [m] (minus ``x_off``, the sensor offset, to get the mechanism's position);
    returns x_B [m], xdot_B [m/s], xdot_C [m/s], motor_angle θ_r = Z·x_C [rad], i_q [A] (if given) and
    contact (1.0 while x_B ≥ x_B^L, else 0.0). Velocities by central differences on ``t`` [s].
    """
    t = _vector(t, "t")
    x = _vector(x_B, "x_B") - float(x_off)
    if x.size != t.size:
        raise DataError(f"x_B has {x.size} samples but t has {t.size}")
    q = np.arccos(np.clip(x / (geometry.r1 + geometry.r3), -1.0, 1.0))
    kin = kinematics(q, geometry)
    x_C = np.asarray(kin["x_C"], float)
    out = {"x_B": x, "xdot_B": np.gradient(x, t), "xdot_C": np.gradient(x_C, t), "motor_angle": geometry.Z * x_C}
    if i_q is not None:
        i = np.asarray(i_q, float)
        if i.shape == t.shape and np.all(np.isfinite(i)):
            out["i_q"] = i
    out["contact"] = (x >= geometry.x_B_L).astype(float)
    return out


def state_correlations(r: Sequence[float], states: Mapping[str, Sequence[float]], alpha: float = ALPHA) -> dict:
    """Pearson correlation of the residual with each state: {name: {corr, p_value, significant}}.

    A constant state (e.g. no contact at all) gets corr 0 and p-value 1.
    """
    r = _vector(r, "residual")
    out = {}
    for name, s in states.items():
        s = np.asarray(s, float)
        if s.shape != r.shape:
            raise DataError(f"state {name!r} has {s.size} samples but the residual has {r.size}")
        ok = np.isfinite(s)
        if ok.sum() < 3 or np.std(s[ok]) == 0.0 or np.std(r[ok]) == 0.0:
            out[name] = {"corr": 0.0, "p_value": 1.0, "significant": False}
            continue
        c = float(np.corrcoef(r[ok], s[ok])[0, 1])
        dof = int(ok.sum()) - 2
        tt = c * np.sqrt(dof / max(1e-300, 1.0 - c * c))
        p = _fmt_p(2.0 * stats.t.sf(abs(tt), dof))
        out[name] = {"corr": c, "p_value": p, "significant": p < alpha}
    return out


# ---------------------------------------------------------------------------------------------- summary
def diagnose(t: Sequence[float], r: Sequence[float], u: Sequence[float] | None = None,
             states: Mapping[str, Sequence[float]] | None = None, *, alpha: float = ALPHA, acf_lags: int = ACF_LAGS,
             ccf_lags: int = 50, ccf_step: int = 5, split_index: int | None = None,
             noise_std: float | None = None) -> dict:
    """All residual tests of ``r`` (m) sampled at ``t`` (s), as one JSON-ready dict.

    ``u``: the input (V) for the cross-correlation test; ``states``: signals for :func:`state_correlations`;
    ``split_index``: first sample of the clamped phase, for per-phase RMS; ``noise_std`` (m): a known noise
    level, reported as the ratio rms/noise. Keys: n, rms_m, mean_m, max_abs_m, phases, whiteness,
    input_correlation, state_correlations, spectrum (dominant peaks), verdict {white, input_independent,
    structure_left}.
    """
    t = _vector(t, "t")
    r = _vector(r, "residual")
    if t.size != r.size:
        raise DataError(f"residual has {r.size} samples but t has {t.size}")
    fs = 1.0 / float(np.median(np.diff(t)))
    out: dict = {"n": int(r.size), "alpha": alpha, "rms_m": float(np.sqrt(np.mean(r * r))),
                 "mean_m": float(np.mean(r)), "max_abs_m": float(np.max(np.abs(r)))}
    if noise_std:
        out["rms_over_noise"] = out["rms_m"] / float(noise_std)
    if split_index is not None and 0 < split_index < r.size:
        a, b = r[:split_index], r[split_index:]
        out["phases"] = {"free_rms_m": float(np.sqrt(np.mean(a * a))), "free_n": int(a.size),
                         "clamped_rms_m": float(np.sqrt(np.mean(b * b))), "clamped_n": int(b.size)}
    out["whiteness"] = ljung_box(r, acf_lags, alpha)
    if u is not None:
        out["input_correlation"] = input_correlation_test(r, u, ccf_lags, ccf_step, alpha)
    if states:
        out["state_correlations"] = state_correlations(r, states, alpha)
    f, p = spectrum(r, fs)
    out["spectrum"] = {"fs_hz": fs, "resolution_hz": float(f[1] - f[0]) if f.size > 1 else 0.0,
                       "peaks": dominant_frequencies(f, p, 3)}
    white = bool(out["whiteness"]["white"])
    indep = bool(out["input_correlation"]["independent"]) if u is not None else True
    out["verdict"] = {"white": white, "input_independent": indep, "structure_left": not (white and indep)}
    return out


#: How far on either side :func:`glitches` looks for the noise's local level (±8 ms at 1 kHz: a quarter period
#: of the paper's fastest sweep, 40 Hz). White noise reaches twice its level over those 12 samples with chance
#: about 1e-5, so a glitch in it is judged as before.
LOCAL = 8


def glitches(r: Sequence[float], k: float = 8.0, protect: np.ndarray | None = None) -> np.ndarray:
    """Samples of the residual ``r`` that are glitches of the measurement, not of the model (bool mask).

    An encoder or transmission error puts one sample off the path and the next back on it. Each sample is predicted
    from its two neighbours on either side by four straight lines (the two interpolations and the two
    extrapolations); a sample is a glitch when it departs from *every* prediction by more than ``k`` robust standard
    deviations of the plain interpolation's departure (median absolute deviation scaled to σ for Gaussian noise,
    floored at half the standard deviation: an encoder's counts alone leave most departures at 0; where the noise is
    more than twice as loud as that, its local level, :data:`LOCAL`: noise whose level grows with speed is not a
    string of glitches) while its four neighbours depart from theirs by less than half that — it is alone. What
    the model leaves of the mechanism is never alone: a kink (an impact at another time than the model's) is predicted by the straight
    line on one side, and the ringing of the clamp's contact moves many samples in a row. Gaussian noise flags
    no sample of a 5000-sample record at k = 8 (chance about 1e-11); a glitch must exceed about 10 σ; two or more
    bad samples in a row are not flagged. The first and last two samples never are, nor those of ``protect``
    (bool mask: where the mechanism itself may jump — an impact between two samples, at another time in the model
    than in the record, leaves one sample off the path). ``k`` ≤ 0: none."""
    r = _vector(r, "residual")
    out = np.zeros(r.shape, dtype=bool)
    if not k > 0 or r.size < 10 or not np.all(np.isfinite(r)):
        return out
    a, b, c, d = r[:-4], r[1:-3], r[3:-1], r[4:]  # r[i-2], r[i-1], r[i+1], r[i+2] for i = 2 … n-3
    diff = r[2:-2][None, :] - np.stack([(b + c) / 2, (a + d) / 2, 2 * b - a, 2 * c - d])
    scale = max(float(stats.median_abs_deviation(diff[0], scale="normal")), 0.5 * float(np.std(diff[0])))
    if not scale > 0:
        return out
    # the noise's own level where it is more than twice as loud as on the whole (an encoder that vibrates at
    # speed): the rms departure of the samples 3 to LOCAL away on either side (a glitch moves only its own
    # departure and its two neighbours'; white noise's 2·(LOCAL − 2) departures stay below twice their σ)
    ring = np.r_[np.ones(LOCAL - 2), np.zeros(5), np.ones(LOCAL - 2)]
    local = np.sqrt(np.convolve(diff[0] ** 2, ring, mode="same") / np.convolve(np.ones(diff.shape[1]),
                                                                               ring, mode="same"))
    scale = np.where(local > 2.0 * scale, local, scale)
    dev = np.min(np.abs(diff), axis=0)
    padded = np.pad(dev, 2)
    neighbours = np.max(np.stack([padded[j:j + dev.size] for j in (0, 1, 3, 4)]), axis=0)
    out[2:-2] = (dev > k * scale) & (neighbours < 0.5 * k * scale)
    if protect is not None:
        out &= ~np.asarray(protect, dtype=bool)
    return out


def near_changes(*indicators: np.ndarray, width: int = 5) -> np.ndarray:
    """Samples within ``width`` of a change of any of the 0/1 ``indicators`` (e.g. the contact of the model and
    of the record): where :func:`glitches` must not look."""
    n = indicators[0].size
    out = np.zeros(n, dtype=bool)
    for ind in indicators:
        for i in np.flatnonzero(np.diff(np.asarray(ind, dtype=float)) != 0):
            out[max(i - width + 1, 0):i + width + 1] = True
    return out


def glitch_report(t: Sequence[float], r: Sequence[float], mask: np.ndarray, k: float) -> dict:
    """JSON-ready description of the glitches ``mask`` of residual ``r`` (from :func:`glitches` at ``k``)."""
    idx = np.flatnonzero(mask)
    t, r = _vector(t, "t"), _vector(r, "residual")
    return {"count": int(idx.size), "k_robust_sigma": float(k), "indices": idx.tolist(),
            "times_s": [float(t[i]) for i in idx], "residual_m": [float(r[i]) for i in idx],
            "rule": "departs from all four straight-line predictions by its two neighbours on either side by more "
                    "than k robust σ, its neighbours from theirs by less than k/2"}


def glitch_text(report: dict, most: int = 8) -> str:
    """``N sample(s) at t = …, … s`` of a :func:`glitch_report` (the first ``most`` times)."""
    times = ", ".join(f"{t:.3f}" for t in report["times_s"][:most]) + (" …" if report["count"] > most else "")
    return f"{report['count']} sample(s) at t = {times} s"


# ---------------------------------------------------------------------------------------------- figures
def diagnostics_figure(t: Sequence[float], r: Sequence[float], *, acf_lags: int = 100, alpha: float = ALPHA,
                       title: str | None = "Residual diagnostics") -> Figure:
    """Residual over time, its autocorrelation with the (1 − α) band, and its Welch spectrum
    (:func:`toggle_id.figures.residual_diagnostics`)."""
    from . import figures

    t = _vector(t, "t")
    r = _vector(r, "residual")
    dt = float(np.median(np.diff(t)))
    acf = autocorrelation(r, acf_lags)
    f, p = spectrum(r, 1.0 / dt)
    return figures.residual_diagnostics(t, r, acf, significance_band(r.size, alpha), f, p * 1e12, lag_dt=dt,
                                        title=title)


def glitches_figure(t: Sequence[float], r: Sequence[float], indices: Sequence[int], *,
                    title: str | None = None) -> Figure:
    """The residual with its glitches (:func:`glitches`) circled: the whole record, and ±15 samples around the
    largest."""
    t, r = _vector(t, "t"), _vector(r, "residual")
    idx = np.asarray(indices, dtype=int)
    fig = Figure(figsize=(10.0, 5.6), dpi=110, layout="constrained")
    whole, zoom = fig.subplots(2, 1)
    for ax, sl in ((whole, slice(None)),
                   (zoom, slice(max(int(idx[np.argmax(np.abs(r[idx]))]) - 15, 0), None) if idx.size else slice(None))):
        tt, rr = t[sl], r[sl]
        if ax is zoom and idx.size:
            tt, rr = tt[:31], rr[:31]
        ax.plot(tt, rr * 1e6, lw=0.7, marker="." if ax is zoom else None, color="tab:blue")
        shown = idx[(t[idx] >= tt[0]) & (t[idx] <= tt[-1])] if idx.size else idx
        ax.plot(t[shown], r[shown] * 1e6, "o", mfc="none", mec="tab:red", ms=9, label="glitch (left out)")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("residual [µm]")
        ax.grid(True, alpha=0.3)
    whole.legend(loc="upper right", fontsize="small")
    whole.set_title(title or f"{idx.size} glitch(es) of the measurement", fontsize="medium")
    zoom.set_title("around the largest", fontsize="small")
    return fig


def states_figure(r: Sequence[float], states: Mapping[str, Sequence[float]], u: Sequence[float] | None = None, *,
                  dt: float = 1e-3, ccf_lags: int = 200, alpha: float = ALPHA,
                  title: str | None = "Residual against the states and the input") -> Figure:
    """Scatter of the residual [µm] against each state signal, plus (if ``u`` is given) the cross-correlation
    with the input against the lag [s] with its (1 − α) band."""
    r = _vector(r, "residual")
    names = list(states)
    n_panels = len(names) + (u is not None)
    ncols = 3
    nrows = max(1, int(np.ceil(n_panels / ncols)))
    fig = Figure(figsize=(10.0, 2.9 * nrows + 0.5), dpi=110, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    corr = state_correlations(r, states, alpha)
    stride = max(1, r.size // 4000)
    for ax, name in zip(axes, names):
        label, _, scale, unit = STATE_LABELS.get(name, (name, "", 1.0, ""))
        s = np.asarray(states[name], float)
        ax.plot(s[::stride] * scale, r[::stride] * 1e6, ".", ms=1.5, alpha=0.5)
        c = corr[name]
        ax.set_title(f"{name}: ρ={c['corr']:.2f}{' *' if c['significant'] else ''}", fontsize="small", loc="left")
        ax.set_xlabel(f"{label} [{unit}]", fontsize="small")
        ax.set_ylabel("residual [µm]", fontsize="small")
        ax.grid(True, alpha=0.3)
    k = len(names)
    if u is not None:
        ax = axes[k]
        lags, ccf = cross_correlation(r, u, ccf_lags)
        band = significance_band(r.size, alpha)
        ax.plot(lags * dt, ccf, lw=0.8)
        ax.fill_between(lags * dt, -band, band, color="tab:orange", alpha=0.3, label=f"{1 - alpha:.0%} band")
        ax.set_xlabel("lag τ [s]", fontsize="small")
        ax.set_ylabel("corr(ε(t), u(t−τ))", fontsize="small")
        ax.set_title("input cross-correlation", fontsize="small", loc="left")
        ax.legend(fontsize="x-small")
        ax.grid(True, alpha=0.3)
        k += 1
    for ax in axes[k:]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    return fig


def comparison_figure(t: Sequence[float], residuals: Mapping[str, Sequence[float]], *, noise_std: float | None = None,
                      split_time: float | None = None, title: str | None = "Residual before and after discovery"
                      ) -> Figure:
    """Residuals [µm] of several models over time (e.g. before/after), with a ±noise band if known."""
    t = _vector(t, "t")
    fig = Figure(figsize=(9.0, 2.6 * len(residuals) + 0.6), dpi=110, layout="constrained")
    axes = fig.subplots(len(residuals), 1, squeeze=False, sharex=True).ravel()
    for ax, (label, r) in zip(axes, residuals.items()):
        r = _vector(r, f"residual {label!r}")
        ax.plot(t, r * 1e6, lw=0.6)
        if noise_std:
            ax.axhspan(-noise_std * 1e6, noise_std * 1e6, color="tab:green", alpha=0.2, label="±noise σ")
            ax.legend(fontsize="x-small")
        if split_time is not None:
            ax.axvline(split_time, color="tab:red", ls="--", lw=0.8)
        ax.set_ylabel("residual [µm]")
        ax.set_title(f"{label}: rms {np.sqrt(np.mean(r * r)) * 1e6:.3g} µm", loc="left", fontsize="medium")
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time t [s]")
    if title:
        fig.suptitle(title)
    return fig
