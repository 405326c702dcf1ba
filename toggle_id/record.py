"""Records (time grid, input, measured output), the swept-sine excitation of docs/model.md §5, an open/close cycling
command, and the measurement model of synthetic records (white or AR(1) Gaussian noise, encoder quantisation)."""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np

#: Initial position of slider B, a constant of the plant (docs/model.md §1), m.
X_B0 = 0.020


@dataclass(frozen=True)
class Sweep:
    """Swept sine v_in(t) = A + B sin(ω(t)·mod(t, T)), ω(t) = ω0 + (ω1 − ω0)·mod(t/T, 1) (eq. 31–32), V."""

    A: float
    B: float
    omega0: float
    omega1: float
    T: float

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        tau = np.mod(t, self.T)
        omega = self.omega0 + (self.omega1 - self.omega0) * np.mod(t / self.T, 1.0)
        return self.A + self.B * np.sin(omega * tau)

    def as_array(self) -> np.ndarray:
        return np.array([self.A, self.B, self.omega0, self.omega1, self.T], dtype=float)


#: The two excitations of the paper: numerical study (Table 1) and experiment (Table 2).
SWEEPS: dict[str, Sweep] = {
    "simulation": Sweep(A=0.05, B=0.01, omega0=0.5, omega1=40.0, T=5.0),
    "experiment": Sweep(A=0.25, B=0.01, omega0=0.5, omega1=40.0, T=5.0),
}


@dataclass(frozen=True)
class Cycle:
    """One open/close cycle of :class:`Cycling`, times in s from the cycle's start, levels in V.

    Close at ``close_v`` from ``start`` for ``close_s``, then hold at ``hold_v`` for ``hold_s``; 0 V until
    ``open_at``, open at ``open_v`` (negative: opening is x_B decreasing) for ``open_s``; 0 V (dwell) to the end
    of the cycle. A partial cycle has ``hold_s = 0`` and a close pulse too short to reach the clamp.
    """

    close_v: float
    close_s: float
    hold_v: float
    hold_s: float
    open_at: float
    open_v: float
    open_s: float
    start: float = 0.05

    def breakpoints(self) -> list[tuple[float, float]]:
        """(time, level from that time on) of the piecewise-constant level sequence of the cycle."""
        t1 = self.start + self.close_s
        t2 = t1 + self.hold_s
        pts = [(self.start, self.close_v), (t1, self.hold_v if self.hold_s > 0 else 0.0)]
        if self.hold_s > 0:
            pts.append((t2, 0.0))
        pts += [(self.open_at, self.open_v), (self.open_at + self.open_s, 0.0)]
        return pts


@dataclass(frozen=True)
class Cycling:
    """Open/close cycling of the mould, v_in in V: the cycles repeat every ``period`` s (cycle k is
    ``cycles[k % len(cycles)]``); between the levels of a cycle the command moves along a raised-cosine step of
    ``ramp`` s, so it is smooth on the sampling scale.

    Closing is v_in > 0 (x_B increasing towards the clamping position x_B^L = 56 mm of docs/model.md §1). The default
    cycles (see :data:`CYCLING`) drive slider B from its rest position into the clamp, hold a clamping force,
    open part of the way back (about 22 mm) and dwell; one cycle in four only moves slider B part of the way
    and back without reaching the clamp. |v_in| ≤ 0.3 V. A record of this command is defined by its samples:
    the simulator interpolates them linearly (as for a measured record), so the simulated record and its CSV
    give the same trajectory.
    """

    cycles: tuple[Cycle, ...]
    period: float = 1.25
    ramp: float = 0.03

    def __post_init__(self) -> None:
        if not self.cycles:
            raise ValueError("a cycling command needs at least one cycle")
        if not (np.isfinite(self.period) and self.period > 0 and np.isfinite(self.ramp) and self.ramp > 0):
            raise ValueError(f"cycling period and ramp must be positive, got {self.period}, {self.ramp}")
        for c in self.cycles:
            pts = c.breakpoints()
            times = [0.0] + [p[0] for p in pts] + [self.period]
            if any(b - a < self.ramp for a, b in pairwise(times)) or min(c.close_s, c.open_s) <= 0:
                raise ValueError(f"cycle {c} has a segment shorter than the ramp ({self.ramp} s) or leaves the "
                                 f"period ({self.period} s)")

    @property
    def v_max(self) -> float:
        return max(abs(v) for c in self.cycles for v in (c.close_v, c.hold_v, c.open_v))

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        k = np.floor(t / self.period).astype(np.int64)
        tau = t - k * self.period
        out = np.zeros(t.shape)
        for j, c in enumerate(self.cycles):
            sel = (k % len(self.cycles)) == j
            if not np.any(sel):
                continue
            level, v = 0.0, np.zeros(int(np.sum(sel)))
            for b, new in c.breakpoints():
                u = np.clip((tau[sel] - b) / self.ramp, -0.5, 0.5)
                v += (new - level) * 0.5 * (1.0 + np.sin(np.pi * u))
                level = new
            out[sel] = v
        return out

    def to_dict(self) -> dict:
        return {"kind": "cycling", "period": self.period, "ramp": self.ramp,
                "cycles": [dict(c.__dict__) for c in self.cycles]}


#: The default cycling command: a 5-s record holds four cycles, the second a partial one.
CYCLING = Cycling(cycles=(
    Cycle(close_v=0.15, close_s=0.25, hold_v=0.05, hold_s=0.30, open_at=0.65, open_v=-0.15, open_s=0.10),
    Cycle(close_v=0.10, close_s=0.08, hold_v=0.0, hold_s=0.0, open_at=0.55, open_v=-0.10, open_s=0.08),
    Cycle(close_v=0.25, close_s=0.12, hold_v=0.08, hold_s=0.35, open_at=0.65, open_v=-0.20, open_s=0.07),
    Cycle(close_v=0.10, close_s=0.30, hold_v=0.03, hold_s=0.30, open_at=0.75, open_v=-0.12, open_s=0.12),
))

#: Commands of a synthetic record: the paper's sweeps (continuous time) or the cycling command (sampled).
COMMANDS = ("sweep", "cycling")


def time_grid(duration: float = 5.0, rate_hz: float = 1000.0) -> np.ndarray:
    """Uniform sample times 0 … duration inclusive (5001 samples for the paper's record)."""
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a positive number of seconds, got {duration}")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"sampling rate must be positive, got {rate_hz}")
    n = int(round(duration * rate_hz)) + 1
    return np.arange(n) / rate_hz


@dataclass
class Record:
    """One experiment: uniform time grid ``t`` (s), input ``v_in`` (V) and, when measured, ``x_B`` (m), ``i_q`` (A).

    ``sweep`` is set for simulated records whose input is known in continuous time; a measured record
    (``sweep is None``) gives v_in at the samples only and the simulator interpolates it linearly.
    """

    t: np.ndarray
    v_in: np.ndarray
    x_B: np.ndarray | None = None
    i_q: np.ndarray | None = None
    sweep: Sweep | None = None
    x_B0: float = X_B0
    name: str = "record"
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.t = np.ascontiguousarray(self.t, dtype=float)
        self.v_in = np.ascontiguousarray(self.v_in, dtype=float)
        if self.t.ndim != 1 or self.t.shape != self.v_in.shape:
            raise ValueError("t and v_in must be 1-D arrays of the same length")
        for name in ("x_B", "i_q"):
            arr = getattr(self, name)
            if arr is not None:
                arr = np.ascontiguousarray(arr, dtype=float)
                if arr.shape != self.t.shape:
                    raise ValueError(f"{name} must have the length of t ({self.t.size}), got {arr.shape}")
                setattr(self, name, arr)

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0])

    @property
    def n(self) -> int:
        return int(self.t.size)

    @classmethod
    def from_sweep(cls, sweep: Sweep | str = "simulation", duration: float = 5.0, rate_hz: float = 1000.0,
                   **kw) -> "Record":
        """An input-only record of the swept sine (by name: ``simulation`` or ``experiment``)."""
        if isinstance(sweep, str):
            if sweep not in SWEEPS:
                raise ValueError(f"unknown sweep {sweep!r}; known: {', '.join(SWEEPS)}")
            sweep = SWEEPS[sweep]
        t = time_grid(duration, rate_hz)
        return cls(t=t, v_in=sweep(t), sweep=sweep, **kw)

    @classmethod
    def from_cycling(cls, cycling: Cycling | None = None, duration: float = 5.0, rate_hz: float = 1000.0,
                     **kw) -> Record:
        """An input-only record of an open/close cycling command (default :data:`CYCLING`), given by its samples
        (``sweep`` is None: the simulator interpolates them linearly, exactly as when read back from a CSV)."""
        cycling = CYCLING if cycling is None else cycling
        t = time_grid(duration, rate_hz)
        rec = cls(t=t, v_in=cycling(t), **kw)
        rec.meta.setdefault("command", cycling.to_dict())
        return rec

    def clamp_index(self, x_B_L: float) -> int:
        """Index of the first sample with measured x_B ≥ x_B_L (docs/model.md §7); ``n`` if never reached."""
        if self.x_B is None:
            raise ValueError("record has no measured x_B")
        hit = np.flatnonzero(self.x_B >= x_B_L)
        return int(hit[0]) if hit.size else self.n

    def clamp_count(self, x_B_L: float, release: float = 1e-3) -> int:
        """How many times the measured x_B closes on the clamp: reaches x_B_L from below x_B_L − ``release`` (m; a
        reading that only jitters about x_B_L while clamped does not reopen it). 1 for the paper's sweeps, which
        clamp and hold; one per closing cycle on the cycling command."""
        if self.x_B is None:
            raise ValueError("record has no measured x_B")
        count, open_ = 0, True
        for x in self.x_B:
            if open_ and x >= x_B_L:
                count, open_ = count + 1, False
            elif not open_ and x < x_B_L - release:
                open_ = True
        return count


# ------------------------------------------------------------------------------------------ measurement model
def ar1_noise(n: int, sigma: float, rho: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` samples of stationary AR(1) Gaussian noise of marginal standard deviation ``sigma`` (m) and lag-1
    coefficient ``rho`` ∈ [0, 1): e_0 ~ N(0, σ²), e_k = ρ·e_{k−1} + √(1−ρ²)·σ·w_k. ``rho = 0`` is white noise,
    σ·w_k, drawn exactly as before this option existed (same numbers for the same generator state)."""
    if not (np.isfinite(rho) and 0.0 <= rho < 1.0):
        raise ValueError(f"the AR(1) coefficient must be in [0, 1), got {rho}")
    w = rng.standard_normal(n)
    if rho == 0.0:
        return sigma * w
    from scipy.signal import lfilter

    u = np.sqrt(1.0 - rho * rho) * sigma * w
    u[0] = sigma * w[0]  # stationary start
    return lfilter([1.0], [1.0, -rho], u)


def quantise(x: np.ndarray, quantum: float) -> np.ndarray:
    """``x`` rounded to the nearest multiple of ``quantum`` (an encoder's resolution, m); 0: unchanged."""
    if not (np.isfinite(quantum) and quantum >= 0.0):
        raise ValueError(f"the quantum must be a non-negative number, got {quantum}")
    if quantum == 0.0:
        return np.asarray(x, dtype=float)
    return np.round(np.asarray(x, dtype=float) / quantum) * quantum


def gross_errors(n: int, fraction: float, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` samples of gross errors (Tukey's contaminated normal): each sample, with probability ``fraction``,
    carries an extra Gaussian error of standard deviation ``sigma`` (m) — an encoder's glitches, a reading that
    jumps and comes back. ``fraction = 0`` draws nothing from ``rng`` (zeros)."""
    if not (np.isfinite(fraction) and 0.0 <= fraction < 1.0):
        raise ValueError(f"the fraction of gross errors must be in [0, 1), got {fraction}")
    if not (np.isfinite(sigma) and sigma >= 0.0):
        raise ValueError(f"the gross errors' standard deviation must be a non-negative number, got {sigma}")
    if fraction == 0.0 or sigma == 0.0:
        return np.zeros(n)
    hit = rng.random(n) < fraction
    return np.where(hit, sigma * rng.standard_normal(n), 0.0)


def measure(x_true: np.ndarray, *, noise_m: float = 0.0, noise_ar: float = 0.0, quantum_m: float = 0.0,
            outlier_fraction: float = 0.0, outlier_m: float = 0.0, seed: int = 0) -> np.ndarray:
    """The recorded x_B of a synthetic record: the true x_B plus AR(1) noise (``noise_m``, ``noise_ar``) and
    gross errors on a fraction ``outlier_fraction`` of the samples (standard deviation ``outlier_m``), then
    quantised to multiples of ``quantum_m``. The noise comes from ``numpy.random.default_rng(seed)``; the gross
    errors are drawn after it, so a record without them has the numbers it had before they existed."""
    if not (np.isfinite(noise_m) and noise_m >= 0.0):
        raise ValueError(f"the noise standard deviation must be a non-negative number, got {noise_m}")
    rng = np.random.default_rng(int(seed))
    n = np.size(x_true)
    x = np.asarray(x_true, dtype=float) + ar1_noise(n, noise_m, noise_ar, rng)
    x = x + gross_errors(n, outlier_fraction, outlier_m, rng)
    return quantise(x, quantum_m)
