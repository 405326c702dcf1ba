"""Report figures (matplotlib). Every function returns a :class:`matplotlib.figure.Figure`; nothing is shown.

Figures are built with :class:`matplotlib.figure.Figure` directly, not through ``pyplot``: they render with
the Agg canvas whatever the session's backend, never pop up windows, and are not kept alive by pyplot's
figure manager (no "more than 20 figures" leak in long jobs). :func:`save` writes a PNG atomically.

Units: time in s, positions given in m and drawn in mm, differences drawn in µm, forces given in N and
drawn in kN, voltages in V. NaN samples (failed simulations) are simply not drawn.
"""
from __future__ import annotations

import os
import sys
import uuid
from typing import Mapping, Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from .errors import DataError

DPI = 120
_WIDTH = 8.0  # in


def _new_figure(nrows: int = 1, ncols: int = 1, *, height: float | None = None, width: float = _WIDTH,
                sharex: bool = False) -> tuple[Figure, np.ndarray]:
    """A constrained-layout figure and its axes as a flat array."""
    height = height if height is not None else 3.0 * nrows + 0.4
    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    axes = fig.subplots(nrows, ncols, sharex=sharex, squeeze=False).ravel()
    return fig, axes


def _arr(x: Sequence[float] | np.ndarray, what: str) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{what} must be numeric: {exc}") from None
    if a.ndim != 1:
        raise DataError(f"{what} must be one-dimensional, got shape {a.shape}")
    return a


def _same_length(t: np.ndarray, y: np.ndarray, what: str) -> None:
    if y.shape != t.shape:
        raise DataError(f"{what} has {y.size} samples but t has {t.size}")


def _log_scale_if_possible(ax: Axes, data: Sequence[np.ndarray], axis: str = "y") -> bool:
    """Use a log scale when some finite positive value exists (else matplotlib warns and shows nothing)."""
    if any(np.any(np.isfinite(d) & (d > 0)) for d in data if d.size):
        (ax.set_yscale if axis == "y" else ax.set_xscale)("log")
        return True
    return False


def _legend(ax: Axes, **kw) -> None:
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize="small", **kw)


def _finish(fig: Figure, title: str | None) -> Figure:
    if title:
        fig.suptitle(title)
    return fig


# ------------------------------------------------------------------------------------------ figures


def fitness_history(histories: Mapping[str, Sequence[float]], *, title: str | None = "Best fitness per generation",
                    ylabel: str = "best fitness", logy: bool = True, start: int = 0) -> Figure:
    """Best fitness per generation, one line per stage/method (the paper's Fig. 7(a)).

    ``histories``: label → values for generations ``start, start+1, …``. Log y-axis when ``logy`` and some
    value is positive; NaN and (on a log axis) non-positive values are left out.
    """
    fig, (ax,) = _new_figure(height=4.0)
    series = {label: _arr(v, f"history {label!r}") for label, v in histories.items()}
    use_log = logy and _log_scale_if_possible(ax, list(series.values()))
    for label, y in series.items():
        gen = np.arange(start, start + y.size)
        yy = np.where(y > 0, y, np.nan) if use_log else y
        ax.plot(gen, yy, lw=1.5, marker="." if y.size <= 60 else None, label=f"{label} (final {_fmt_last(y)})")
    ax.set_xlabel("generation")
    ax.set_ylabel(ylabel + (" (log scale)" if use_log else ""))
    ax.grid(True, which="both", alpha=0.3)
    _legend(ax)
    return _finish(fig, title)


def _fmt_last(y: np.ndarray) -> str:
    finite = y[np.isfinite(y)]
    return f"{finite[-1]:.4g}" if finite.size else "n/a"


def response_comparison(t: Sequence[float], x_measured: Sequence[float], x_models: Mapping[str, Sequence[float]],
                        stage_boundary: float | None = None, *, forces: Mapping[str, Sequence[float]] | None = None,
                        v_in: Sequence[float] | None = None, measured_label: str = "measured",
                        title: str | None = "Measured and model responses") -> Figure:
    """The paper's Fig. 7/8 panels on a shared time axis.

    (a) slider position x_B [mm] measured and per model; (b) model − measured [µm]; (c) impulse force F_i
    [kN] per model, if ``forces`` is given; (d) voltage command v_in [V], if given. Inputs: ``t`` [s],
    positions [m], forces [N], voltage [V]. ``stage_boundary`` [s] (e.g. the clamping onset separating the
    two identification stages) is drawn as a dashed vertical line on every panel.
    """
    t_ = _arr(t, "t")
    xm = _arr(x_measured, "x_measured")
    _same_length(t_, xm, "x_measured")
    models = {k: _arr(v, f"x_models[{k!r}]") for k, v in x_models.items()}
    for k, v in models.items():
        _same_length(t_, v, f"x_models[{k!r}]")
    force_map = {k: _arr(v, f"forces[{k!r}]") for k, v in (forces or {}).items()}
    for k, v in force_map.items():
        _same_length(t_, v, f"forces[{k!r}]")
    v = None if v_in is None else _arr(v_in, "v_in")
    if v is not None:
        _same_length(t_, v, "v_in")

    n = 2 + bool(force_map) + (v is not None)
    fig, axes = _new_figure(n, 1, height=2.3 * n + 0.6, sharex=True)
    letters = iter("abcd")

    ax = axes[0]
    ax.plot(t_, xm * 1e3, color="k", lw=2.0, alpha=0.5, label=measured_label)
    for label, x in models.items():
        ax.plot(t_, x * 1e3, lw=1.0, label=label)
    ax.set_ylabel("$x_B$ [mm]")
    ax.set_title(f"({next(letters)}) slider position", loc="left", fontsize="medium")

    ax = axes[1]
    for label, x in models.items():
        ax.plot(t_, (x - xm) * 1e6, lw=1.0, label=f"{label}: rms {_rms(x - xm) * 1e6:.3g} µm")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_ylabel(r"$x_B^{model} - x_B^{meas}$ [µm]")
    ax.set_title(f"({next(letters)}) position difference", loc="left", fontsize="medium")
    _legend(ax)

    k = 2
    if force_map:
        ax = axes[k]
        k += 1
        for label, f in force_map.items():
            ax.plot(t_, f * 1e-3, lw=1.0, label=label)
        ax.set_ylabel("$F_i$ [kN]")
        ax.set_title(f"({next(letters)}) impulse force of the clamping unit", loc="left", fontsize="medium")
        _legend(ax)
    if v is not None:
        ax = axes[k]
        ax.plot(t_, v, lw=0.8, color="tab:purple")
        ax.set_ylabel("$v_{in}$ [V]")
        ax.set_title(f"({next(letters)}) voltage command", loc="left", fontsize="medium")

    for i, ax in enumerate(axes):
        ax.grid(True, alpha=0.3)
        if stage_boundary is not None and np.isfinite(stage_boundary):
            ax.axvline(float(stage_boundary), color="tab:red", ls="--", lw=0.8,
                       label=f"stage boundary ({float(stage_boundary):.3g} s)" if i == 0 else None)
    _legend(axes[0])
    axes[-1].set_xlabel("time t [s]")
    return _finish(fig, title)


def _rms(e: np.ndarray) -> float:
    finite = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(finite ** 2))) if finite.size else float("nan")


def residual_diagnostics(t: Sequence[float], residual: Sequence[float], acf: Sequence[float],
                         acf_band: float | Sequence[float], spectrum_f: Sequence[float],
                         spectrum_p: Sequence[float], *, lag_dt: float | None = None, scale: float = 1e6,
                         residual_label: str = "residual [µm]", spectrum_label: str = "PSD [µm²/Hz]",
                         marks: Mapping[str, float] | None = None, logy_spectrum: bool = True,
                         title: str | None = "Residual diagnostics") -> Figure:
    """Residual over time, its autocorrelation with a significance band, and its spectrum.

    ``residual`` is drawn times ``scale`` (default m → µm) with ``residual_label``; ``acf`` holds lags
    0…K (in samples, or in seconds when ``lag_dt`` [s] is given); ``acf_band`` is the ± significance half
    width (scalar, e.g. 1.96/√N, or one per lag); ``spectrum_f`` [Hz] and ``spectrum_p`` (already in the
    units of ``spectrum_label``). ``marks``: label → frequency [Hz] drawn as vertical lines on the spectrum.
    """
    t_ = _arr(t, "t")
    r = _arr(residual, "residual")
    _same_length(t_, r, "residual")
    a = _arr(acf, "acf")
    band = np.broadcast_to(np.asarray(acf_band, dtype=float), a.shape) if np.ndim(acf_band) == 0 else \
        _arr(acf_band, "acf_band")
    if band.shape != a.shape:
        raise DataError(f"acf_band has {band.size} values but acf has {a.size}")
    f = _arr(spectrum_f, "spectrum_f")
    p = _arr(spectrum_p, "spectrum_p")
    if f.shape != p.shape:
        raise DataError(f"spectrum_p has {p.size} values but spectrum_f has {f.size}")

    fig, axes = _new_figure(3, 1, height=8.4)
    ax = axes[0]
    ax.plot(t_, r * scale, lw=0.7)
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel("time t [s]")
    ax.set_ylabel(residual_label)
    ax.set_title(f"(a) residual, rms {_rms(r * scale):.3g}", loc="left", fontsize="medium")

    ax = axes[1]
    lags = np.arange(a.size) * (lag_dt if lag_dt else 1.0)
    ax.vlines(lags, 0.0, a, lw=1.0)
    ax.plot(lags, a, ".", ms=3)
    ax.fill_between(lags, -band, band, color="tab:orange", alpha=0.25, label="significance band")
    ax.axhline(0.0, color="k", lw=0.5)
    outside = np.isfinite(a) & (np.abs(a) > band)
    outside[:1] = False  # lag 0 is 1 by definition
    ax.set_xlabel("lag [s]" if lag_dt else "lag [samples]")
    ax.set_ylabel("autocorrelation [-]")
    ax.set_title(f"(b) autocorrelation: {int(outside.sum())} of {max(a.size - 1, 0)} lags outside the band",
                 loc="left", fontsize="medium")
    _legend(ax)

    ax = axes[2]
    if logy_spectrum:
        _log_scale_if_possible(ax, [p])
    ax.plot(f, np.where(p > 0, p, np.nan) if ax.get_yscale() == "log" else p, lw=0.8)
    for label, freq in (marks or {}).items():
        ax.axvline(float(freq), ls="--", lw=0.8, color="tab:red", label=f"{label} ({float(freq):.3g} Hz)")
    ax.set_xlabel("frequency f [Hz]")
    ax.set_ylabel(spectrum_label)
    ax.set_title("(c) spectrum", loc="left", fontsize="medium")
    _legend(ax)
    for ax in axes:
        ax.grid(True, alpha=0.3)
    return _finish(fig, title)


def parameter_errors(names: Sequence[str], pct_errors: Mapping[str, Sequence[float]], *,
                     threshold: float | None = None, logy: bool = False,
                     title: str | None = "Identification error per parameter") -> Figure:
    """Grouped bars of |A−B|/|A|·100 [%] per parameter, one colour per method (the paper's Table 1 as a chart).

    ``pct_errors``: label → one value per name (NaN → no bar). ``threshold`` [%] draws a reference line
    (e.g. the paper's 2 %).
    """
    names = list(names)
    errs = {label: _arr(v, f"pct_errors[{label!r}]") for label, v in pct_errors.items()}
    for label, e in errs.items():
        if e.size != len(names):
            raise DataError(f"pct_errors[{label!r}] has {e.size} values for {len(names)} names")
    fig, (ax,) = _new_figure(height=4.2, width=max(_WIDTH, 0.55 * len(names) * max(len(errs), 1) + 2))
    x = np.arange(len(names))
    width = 0.8 / max(len(errs), 1)
    if logy:
        _log_scale_if_possible(ax, list(errs.values()))
    for i, (label, e) in enumerate(errs.items()):
        shown = np.where(np.isfinite(e) & ((e > 0) | (ax.get_yscale() != "log")), e, np.nan)
        bars = ax.bar(x + (i - (len(errs) - 1) / 2) * width, np.nan_to_num(shown, nan=0.0), width, label=label)
        if len(names) * len(errs) <= 48:
            ax.bar_label(bars, labels=["" if not np.isfinite(v) else f"{v:.2g}" for v in shown],
                         fontsize="x-small", padding=1)
    if threshold is not None:
        ax.axhline(float(threshold), color="tab:red", ls="--", lw=0.8, label=f"{float(threshold):g} %")
    ax.set_xticks(x, names, rotation=45, ha="right")
    ax.set_ylabel("error |A−B|/|A| [%]")
    ax.grid(True, axis="y", alpha=0.3)
    _legend(ax)
    return _finish(fig, title)


# ---------------------------------------------------------------------------------------------- save


def save(fig: Figure, path: str | os.PathLike, *, dpi: int | None = None) -> str:
    """Write ``fig`` as PNG to ``path`` atomically (temporary file + rename), close it, return the path.

    Parent directories are created. The figure is released afterwards (``pyplot.close`` if pyplot manages
    it, else cleared), so log it to MLflow before saving it.
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    tmp = os.path.join(directory, f".{os.path.basename(path)}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "xb") as fh:  # honours the umask, unlike mkstemp's 0600
            fig.savefig(fh, format="png", dpi=dpi or fig.dpi)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    finally:
        close(fig)
    return path


def close(fig: Figure) -> None:
    """Release a figure: ``pyplot.close`` when pyplot knows it, else clear it."""
    plt = sys.modules.get("matplotlib.pyplot")
    number = getattr(fig, "number", None)
    if plt is not None and number is not None and plt.fignum_exists(number):
        plt.close(fig)
    else:
        fig.clear()
