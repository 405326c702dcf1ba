"""Is the final fit at the optimum of its own cost? The error profiled along each named effect's parameters.

A fit that ends far above the noise with an effect named leaves two explanations: the model still lacks
something, or the search did not reach the optimum of the model it has. Output-error costs of threshold and
impact effects at a user's magnitudes can be needles: a 0.2-mm screw backlash on the cycling command reads
1.1 µm at the truth and 12–27 µm at ±2.5 % of the lash, with local minima between (docs/discovery.md, item 11).
No local search finds such an optimum from a start outside its needle, and no structure test can tell that
residual from missing physics. The profile can: the raw RMS of the final model on a fine grid of one parameter,
the others held, and the number of local minima along it (:func:`scipy.signal.find_peaks` on the negated
profile, with a prominence of a fraction of the noise). More than one means the cost is rough there and the error
left may be the search's; a grid point below the fit means a better optimum was missed.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.signal import find_peaks

from ..effects import ALL_INDEX, EFFECT_PARAMS, EFFECTS_BY_NAME
from .model import Model


@dataclass
class Profile:
    """The raw RMS (m) of the model along one parameter, the others held at the fit."""

    name: str
    value: float
    rmse_m: float
    values: np.ndarray
    rmse: np.ndarray
    minima: int
    prominence_m: float

    @property
    def rough(self) -> bool:
        """More than one local minimum deeper than the prominence along the profile."""
        return self.minima > 1

    @property
    def lowest(self) -> tuple[float, float]:
        """The grid's lowest point (value, RMS m)."""
        k = int(np.nanargmin(self.rmse))
        return float(self.values[k]), float(self.rmse[k])

    def below_fit(self) -> bool:
        """A grid point lower than the fit by more than the prominence: the search missed a better optimum."""
        return self.lowest[1] < self.rmse_m - self.prominence_m

    def to_dict(self) -> dict:
        lo_v, lo_r = self.lowest
        return {"name": self.name, "value": self.value, "rmse_m": self.rmse_m, "minima": self.minima,
                "rough": self.rough, "prominence_m": self.prominence_m, "lowest": {"value": lo_v, "rmse_m": lo_r},
                "below_fit": self.below_fit(), "values": self.values.tolist(),
                "rmse_grid_m": [None if not np.isfinite(x) else float(x) for x in self.rmse]}


def profiled_names(effect_names: Sequence[str]) -> list[str]:
    """The parameters of the named effects worth profiling: every one but a phase (periodic by construction, its
    cost has a minimum per period) and an integer count (a cogging order)."""
    out = []
    for en in effect_names:
        for p in EFFECTS_BY_NAME[en].params:
            if p.name.startswith("phi_") or p.name.startswith("n_"):
                continue
            out.append(p.name)
    return out


def grid(value: float, domain: tuple[float, float], span: float, points: int) -> np.ndarray:
    """``points`` values within ``span`` (relative) of ``value``, clipped to ``domain``, ``value`` among them; a
    value at zero is profiled over the first ``span`` of its domain's width."""
    lo, hi = domain
    half = abs(value) * span if value != 0.0 else span * (hi - lo)
    g = np.linspace(max(lo, value - half), min(hi, value + half), max(int(points), 3))
    return np.unique(np.append(g, value))


def profile(model: Model, theta: np.ndarray, name: str, span: float, points: int, prominence_m: float) -> Profile:
    """The raw RMS of ``model`` along parameter ``name`` around ``theta`` (:func:`grid`), one batch; the model's
    state (:attr:`~.model.Model.stiff`) as it was, so a profile never changes the fits that follow it."""
    i = ALL_INDEX[name]
    value = float(theta[i])
    values = grid(value, model.domain(name), span, points)
    thetas = np.repeat(np.asarray(theta, float)[None, :], len(values), axis=0)
    thetas[:, i] = values
    stiff = set(model.stiff)
    r = model.residuals(thetas)
    model.stiff = stiff  # a look, not a fit: the effect sets the later fits send to the fallback stay as they were
    rmse = np.sqrt(np.mean(r * r, axis=1))
    rmse[~np.isfinite(rmse)] = np.nan
    at = float(rmse[np.searchsorted(values, value)])
    return Profile(name, value, at, values, rmse, count_minima(rmse, prominence_m), prominence_m)


def count_minima(rmse: np.ndarray, prominence_m: float) -> int:
    """The local minima of a profile deeper than ``prominence_m`` (failed simulations, NaN, left out: a gap is not a
    minimum); one at an end of the grid counts when the profile rises from it by that much."""
    y = rmse[np.isfinite(rmse)]
    if y.size < 2:
        return int(y.size)
    minima = len(find_peaks(-y, prominence=prominence_m)[0])
    return minima + int(y[1] - y[0] > prominence_m) + int(y[-2] - y[-1] > prominence_m)


def profiles(model: Model, theta: np.ndarray, effect_names: Sequence[str], span: float, points: int,
             prominence_m: float) -> list[Profile]:
    """:func:`profile` of every parameter :func:`profiled_names` picks from ``effect_names``."""
    return [profile(model, theta, nm, span, points, prominence_m) for nm in profiled_names(effect_names)]


def rough_text(found: Sequence[Profile], noise_m: float) -> str:
    """The conclusion's sentence for the profiles among ``found`` that are rough or hold a point below the fit
    (empty when none does)."""
    parts = []
    for p in found:
        unit = EFFECT_PARAMS[p.name].unit
        bits = []
        if p.rough:
            bits.append(f"{p.minima} local minima")
        if p.below_fit():
            lo_v, lo_r = p.lowest
            bits.append(f"{1e6 * lo_r:.4g} µm at {lo_v:.4g} {unit}, below the fit's {1e6 * p.rmse_m:.4g} µm")
        if bits:
            parts.append(f"{p.name} around {p.value:.4g} {unit}: " + ", ".join(bits))
    if not parts:
        return ""
    return (" Profiled along the named effects' parameters, the others held, the error has more than one minimum "
            "or a point below the fit (" + "; ".join(parts) + "): the fit may not be at the optimum of its own model, "
            "so the error left may be the search's rather than physics the model lacks (the record's noise "
            f"{1e6 * noise_m:.3g} µm; profiles in the report).")


def figure(reports: Sequence[dict], noise_m: float, title: str | None = None):
    """The profiles of :func:`profiles` (their :meth:`Profile.to_dict` reports), one panel each: the error against
    the parameter, the fit marked, the record's noise as a line (a matplotlib Figure)."""
    from ..figures import _finish, _new_figure

    fig, axes = _new_figure(1, len(reports), height=3.4, width=max(6.0, 4.5 * len(reports)))
    for ax, rep in zip(axes, reports):
        y = np.array([np.nan if v is None else v for v in rep["rmse_grid_m"]], float) * 1e6
        ax.plot(rep["values"], y, ".-", lw=0.8)
        ax.plot([rep["value"]], [rep["rmse_m"] * 1e6], "o", color="tab:red", label="the fit")
        if rep["below_fit"]:
            ax.plot([rep["lowest"]["value"]], [rep["lowest"]["rmse_m"] * 1e6], "v", color="tab:green",
                    label="lowest point")
        if noise_m > 0:
            ax.axhline(noise_m * 1e6, color="0.6", lw=0.8, ls="--", label="the record's noise")
        ax.set_xlabel(f"{rep['name']} ({EFFECT_PARAMS[rep['name']].unit})")
        ax.set_ylabel("rms error (µm)")
        ax.set_title(f"{rep['minima']} local minima", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    return _finish(fig, title or "The error along the named effects' parameters, the others held at the fit")
