"""Records (time grid, input, measured output) and the swept-sine excitation of MODEL.md §5."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Initial position of slider B, a constant of the plant (MODEL.md §1), m.
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

    def clamp_index(self, x_B_L: float) -> int:
        """Index of the first sample with measured x_B ≥ x_B_L (MODEL.md §7); ``n`` if never reached."""
        if self.x_B is None:
            raise ValueError("record has no measured x_B")
        hit = np.flatnonzero(self.x_B >= x_B_L)
        return int(hit[0]) if hit.size else self.n
