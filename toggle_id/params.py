"""The 15 physical parameters of the motor-toggle plant (docs/model.md §6, the paper's Table 1).

Parameter vectors travel as float64 arrays in the order of :data:`PARAM_NAMES`; names are used only at the
edges (configuration, reports). Everything here is data: names, units, assigned values, feasible domains.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np

from .errors import ConfigError


@dataclass(frozen=True)
class ParamSpec:
    """One identified parameter: its name (the paper's symbol spelled out), unit, assigned value and domain."""

    name: str
    unit: str
    assigned: float
    lower: float
    upper: float
    description: str


#: The paper's Table 1, in the project's one canonical order.
PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("B_m", "N·m·s/rad", 0.0112, 0.0, 1.0, "motor viscous damping"),
    ParamSpec("D", "N·s/m", 15_000.0, 0.0, 1e6, "clamping-unit damping"),
    ParamSpec("J_m", "N·m·s²", 6.70e-5, 0.0, 1e-3, "rotor inertia"),
    ParamSpec("K_i", "-", 100.0, 0.0, 1e4, "drive gain v_q = K_i v_in"),
    ParamSpec("K_l", "N/m", 5.0e7, 0.0, 1e8, "clamping-unit stiffness"),
    ParamSpec("K_t", "N·m/A", 0.5087, 0.0, 10.0, "torque constant"),
    ParamSpec("L_q", "H", 2.1e-3, 0.0, 0.01, "q-axis inductance"),
    ParamSpec("R_s", "Ω", 1.406e-2, 0.0, 1.0, "stator resistance"),
    ParamSpec("m_2", "kg", 1.610, 0.0, 10.0, "mass of the ternary link (body 2)"),
    ParamSpec("m_3", "kg", 1.820, 0.0, 10.0, "mass of link 3"),
    ParamSpec("m_5", "kg", 0.950, 0.0, 10.0, "mass of link 5"),
    ParamSpec("m_B", "kg", 4.000, 0.0, 10.0, "mass of slider B"),
    ParamSpec("m_C", "kg", 3.000, 0.0, 10.0, "mass of slider C"),
    ParamSpec("mu", "-", 0.170, 0.0, 10.0, "friction coefficient of slider B"),
    ParamSpec("lambda_d", "V·s/rad", 0.036, 0.0, 1.0, "stator flux linkage"),
)

PARAM_NAMES: tuple[str, ...] = tuple(p.name for p in PARAMS)
N_PARAMS = len(PARAMS)
INDEX: dict[str, int] = {name: i for i, name in enumerate(PARAM_NAMES)}
ASSIGNED = np.array([p.assigned for p in PARAMS])
LOWER = np.array([p.lower for p in PARAMS])
UPPER = np.array([p.upper for p in PARAMS])

#: The clamping parameters identified in stage 2; stage 1 identifies the other 13.
CLAMP_NAMES: tuple[str, ...] = ("D", "K_l")
FREE_NAMES: tuple[str, ...] = tuple(n for n in PARAM_NAMES if n not in CLAMP_NAMES)


def check_names(names: Iterable[str]) -> None:
    """Raise :class:`ConfigError` (a ``ValueError``) naming the first unknown parameter name."""
    for name in names:
        if name not in INDEX:
            raise ConfigError(f"unknown parameter {name!r}; known: {', '.join(PARAM_NAMES)}")


def to_vector(values: Mapping[str, float], base: Sequence[float] | None = None) -> np.ndarray:
    """Vector in canonical order from a name → value mapping; names not given come from ``base`` (assigned)."""
    check_names(values)
    vec = np.array(ASSIGNED if base is None else base, dtype=float).copy()
    for name, value in values.items():
        vec[INDEX[name]] = float(value)
    return vec


def to_dict(vector: Sequence[float], names: Sequence[str] = PARAM_NAMES) -> dict[str, float]:
    """Name → value mapping from a vector in the order of ``names``."""
    if len(vector) != len(names):
        raise ValueError(f"expected {len(names)} values, got {len(vector)}")
    return {name: float(v) for name, v in zip(names, vector)}


def indices(names: Sequence[str]) -> np.ndarray:
    """Positions of ``names`` in the canonical order."""
    check_names(names)
    return np.array([INDEX[n] for n in names], dtype=np.int64)


def bounds(names: Sequence[str] = PARAM_NAMES,
           overrides: Mapping[str, Sequence[float]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Feasible domain (lower, upper) of ``names``, with optional per-name ``[low, high]`` overrides.

    Raises :class:`ConfigError` (a ``ValueError``) for an unknown name, a malformed pair, a non-finite bound or an
    inverted/empty interval.
    """
    idx = indices(names)
    lo, hi = LOWER[idx].copy(), UPPER[idx].copy()
    for name, pair in (overrides or {}).items():
        check_names([name])
        if name not in names:
            continue
        try:
            low, high = (float(x) for x in pair)
        except (TypeError, ValueError):
            raise ConfigError(f"bounds of {name} must be a pair of numbers [low, high], got {pair!r}") from None
        k = list(names).index(name)
        lo[k], hi[k] = low, high
    for name, low, high in zip(names, lo, hi):
        if not (np.isfinite(low) and np.isfinite(high)):
            raise ConfigError(f"bounds of {name} must be finite, got [{low}, {high}]")
        if not low < high:
            raise ConfigError(f"bounds of {name} are inverted or empty: [{low}, {high}]")
    return lo, hi


def read_params_file(path: str) -> dict[str, float]:
    """Read a ``name=value`` per line file (the format of ``tests/reference/*.params``)."""
    out: dict[str, float] = {}
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            if "=" not in line:
                raise ValueError(f"{path}:{lineno}: expected name=value, got {line!r}")
            name, value = (s.strip() for s in line.split("=", 1))
            check_names([name])
            out[name] = float(value)
    return out
