"""Input families within the machine's limits, each a map from a point of the unit cube to a sampled v_in(t),
and the check that a candidate drives slider B into the clamp and back within the stroke.

Every family is a small parametrisation (:data:`FAMILY_PARAMS`: name, lower, upper, in units of ``v_max`` for
levels), so a seeded search over the unit cube explores it; every input is clipped to |v_in| ≤ ``v_max`` and has
``duration·rate_hz + 1`` samples. The simulator interpolates the samples linearly, as for a measured record.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..record import Cycle, Cycling, Record, Sweep, time_grid

#: Each family's parameters: (name, lower, upper, log scale?). Levels are fractions of v_max, frequencies Hz,
#: times s. Levels and times span decades on a log scale: a friction shows at low speeds, a stroke needs high ones.
FAMILY_PARAMS: dict[str, tuple[tuple[str, float, float, bool], ...]] = {
    # v = A + B sin(ω(t)·τ), ω from 2π f0 to 2π f1 over the record (record.Sweep); A = offset·B, |A| + B ≤ v_max
    "sweep": (("amplitude", 0.01, 1.0, True), ("offset", -0.5, 1.5, False), ("f0_hz", 0.05, 2.0, True),
              ("f1_hz", 0.2, 8.0, True)),
    # repeated open/close cycles (record.Cycling): close, hold, pause, open, dwell; the close level down to 0.2 % of
    # v_max: a creep into the clamp over seconds, where a motor-side friction shows against the slider's
    "cycling": (("close_v", 0.002, 1.0, True), ("close_s", 0.05, 4.0, True), ("hold_v", 0.0, 0.5, False),
                ("hold_s", 0.05, 0.5, True), ("open_v", 0.02, 1.0, True), ("open_s", 0.04, 2.0, True),
                ("dwell_s", 0.05, 0.5, True)),
    # offset + a slow sine (the stroke: into the clamp and back) + amplitude · (Schroeder-phased sum of 8 sines
    # log-spaced in [f_lo, f_hi]) / its peak; the whole scaled down to v_max when its peak is over
    "multisine": (("offset", -0.2, 0.5, False), ("slow_v", 0.01, 1.0, True), ("slow_hz", 0.1, 1.5, True),
                  ("amplitude", 0.01, 1.0, True), ("f_lo_hz", 0.5, 3.0, True), ("f_hi_hz", 3.0, 30.0, True)),
    # smoothed square wave: close level for t_hi, open level for t_lo, durations jittered (seeded)
    "steps": (("v_hi", 0.02, 1.0, True), ("v_lo", 0.02, 1.0, True), ("t_hi_s", 0.05, 2.5, True),
              ("t_lo_s", 0.03, 2.0, True), ("jitter", 0.0, 0.6, False), ("ramp_s", 0.005, 0.05, True)),
}

N_SINES = 8


@dataclass(frozen=True)
class Candidate:
    """One input: its family, its point ``u`` in the family's unit cube and the seed of any random part."""

    family: str
    u: tuple[float, ...]
    seed: int = 0

    def params(self) -> dict[str, float]:
        """The family's parameters (physical: levels as fractions of v_max, Hz, s)."""
        spec = FAMILY_PARAMS[self.family]
        return {nm: float(lo * (hi / lo) ** x if log else lo + (hi - lo) * x) for (nm, lo, hi, log), x
                in zip(spec, self.u)}

    def to_dict(self) -> dict:
        return {"family": self.family, "u": [float(x) for x in self.u], "seed": int(self.seed),
                "params": self.params()}


def dimension(family: str) -> int:
    return len(FAMILY_PARAMS[family])


def input_signal(c: Candidate, v_max: float, duration: float, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """(t, v_in) of candidate ``c``: uniform samples, |v_in| ≤ ``v_max`` (V)."""
    t = time_grid(duration, rate_hz)
    p = c.params()
    if c.family == "sweep":
        B = p["amplitude"] * v_max
        A = p["offset"] * B
        if abs(A) + B > v_max:
            A, B = A * v_max / (abs(A) + B), B * v_max / (abs(A) + B)
        v = Sweep(A=A, B=B, omega0=2 * np.pi * p["f0_hz"], omega1=2 * np.pi * p["f1_hz"], T=duration)(t)
    elif c.family == "cycling":
        ramp = 0.03
        start = 0.05
        close_s, hold_s, open_s = (max(p[k], 1.5 * ramp) for k in ("close_s", "hold_s", "open_s"))
        open_at = start + close_s + hold_s + 2 * ramp
        period = open_at + open_s + max(p["dwell_s"], 2 * ramp)
        cyc = Cycle(close_v=p["close_v"] * v_max, close_s=close_s, hold_v=p["hold_v"] * v_max, hold_s=hold_s,
                    open_at=open_at, open_v=-p["open_v"] * v_max, open_s=open_s, start=start)
        v = Cycling(cycles=(cyc,), period=period, ramp=ramp)(t)
    elif c.family == "multisine":
        k = np.arange(1, N_SINES + 1)
        f = np.geomspace(p["f_lo_hz"], max(p["f_hi_hz"], p["f_lo_hz"] * 1.01), N_SINES)
        phase = -np.pi * k * (k - 1) / N_SINES  # Schroeder: a low crest factor
        s = np.sin(2 * np.pi * f[None, :] * t[:, None] + phase[None, :]).sum(axis=1)
        s /= max(float(np.max(np.abs(s))), 1e-12)
        v = v_max * (p["offset"] + p["slow_v"] * np.sin(2 * np.pi * p["slow_hz"] * t) + p["amplitude"] * s)
        peak = float(np.max(np.abs(v)))
        if peak > v_max:
            v *= v_max / peak
    elif c.family == "steps":
        rng = np.random.default_rng(c.seed)
        levels, times, now, hi = [], [], 0.0, True
        while now < duration:
            levels.append(p["v_hi"] * v_max if hi else -p["v_lo"] * v_max)
            times.append(now)
            base = p["t_hi_s"] if hi else p["t_lo_s"]
            now += max(base * (1.0 + p["jitter"] * rng.uniform(-1.0, 1.0)), 2 * p["ramp_s"])
            hi = not hi
        v = np.zeros_like(t)
        prev = 0.0
        for b, lev in zip(times, levels):  # raised-cosine steps of ramp_s centred after each switch time
            u = np.clip((t - b - 0.5 * p["ramp_s"]) / p["ramp_s"], -0.5, 0.5)
            v += (lev - prev) * 0.5 * (1.0 + np.sin(np.pi * u))
            prev = lev
    else:
        raise ValueError(f"unknown input family {c.family!r}")
    return t, np.clip(v, -v_max, v_max)


def candidate_record(c: Candidate, v_max: float, duration: float, rate_hz: float, x_B0: float) -> Record:
    t, v = input_signal(c, v_max, duration, rate_hz)
    rec = Record(t=t, v_in=v, x_B0=x_B0, name=f"excite_{c.family}")
    rec.meta["command"] = {"kind": "excite", **c.to_dict(), "v_max": v_max}
    return rec


def clamp_check(x_B: np.ndarray, x_B_L: float, *, x_B_min: float, clamp_margin: float, min_clamp_samples: int,
                min_exits: int) -> str:
    """"ok" when the slider trajectory ``x_B`` (m) goes into the clamp (x_B ≥ x_B^L + margin) after at least
    ``min_clamp_samples`` samples, leaves it again at least ``min_exits`` times and never drops below
    ``x_B_min``; else the reason (the status of a rejected candidate). NaN: "simulation failed"."""
    x = np.asarray(x_B, float)
    if not np.all(np.isfinite(x)):
        return "simulation failed"
    if x.min() < x_B_min:
        return f"leaves the stroke (x_B = {1e3 * x.min():.3g} mm < {1e3 * x_B_min:.3g} mm)"
    clamped = x >= x_B_L
    if not np.any(x >= x_B_L + clamp_margin):
        return f"never clamps (max x_B = {1e3 * x.max():.4g} mm)"
    first = int(np.argmax(clamped))
    if first < min_clamp_samples:
        return f"clamps after {first} samples (< {min_clamp_samples})"
    exits = int(np.count_nonzero(clamped[:-1] & ~clamped[1:]))
    if exits < min_exits:
        return f"leaves the clamp {exits} time(s) (< {min_exits})"
    return "ok"
