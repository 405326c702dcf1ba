"""EMPS records: loading the benchmark's CSV / MATLAB files into a validated :class:`EmpsRecord`.

The EMPS (electro-mechanical positioning system, Janot, Gautier & Brunot 2019) is a DC motor driving a ball screw,
run in closed loop at 1 kHz. A record holds, on the sample grid: the time ``t`` (s), the controller output ``vir``
(the drive input ν, V; the force is τ = gtau·ν, N), the measured position ``qm`` (m, load side), the reference
``qg`` (m) and, for the validation record, the force pulses ``pulses`` (N) applied to the rig. The controller
constants ``gtau`` (N/V), ``kp`` (1/s) and ``kv`` (V/(m/s)) travel with the record.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DataError

#: Where the shared copy of the benchmark lives on the project's machines (see its README.md).
DEFAULT_DIR = Path("/work/shared/data/emps")
DEFAULT_CSV = DEFAULT_DIR / "emps_estimation.csv"
DEFAULT_MAT = DEFAULT_DIR / "DATA_EMPS.mat"

#: Drive gain g_τ, N/V (README; the .mat stores 35.15065188…).
GTAU = 35.1507
#: Outer position-loop gain k_p, 1/s.
KP = 160.18
#: Inner velocity-loop gain k_v, V/(m/s).
KV = 243.45
#: Controller sampling period, s (the documented 1 kHz; the stored ``t`` jitters by ~2e-8 s).
DT = 1e-3
#: Saturation of the controller output, V (``viradm`` in the authors' scripts).
V_SAT = 10.0

#: Largest accepted deviation of a sample interval from ``dt``, relative.
_DT_RTOL = 1e-3


@dataclass
class EmpsRecord:
    """One closed-loop EMPS experiment on a uniform 1 kHz grid.

    Attributes: ``t`` (s), ``vir`` (V), ``qm`` (m), ``qg`` (m), ``pulses`` (N, external force added to the drive
    force; zeros when the record has none), controller constants ``gtau`` (N/V), ``kp`` (1/s), ``kv`` (V/(m/s)),
    sampling period ``dt`` (s), ``v_sat`` (V) and a ``name``. Construction validates and raises :class:`DataError`.
    """

    t: np.ndarray
    vir: np.ndarray
    qm: np.ndarray
    qg: np.ndarray
    pulses: np.ndarray | None = None
    gtau: float = GTAU
    kp: float = KP
    kv: float = KV
    dt: float = DT
    v_sat: float = V_SAT
    name: str = "emps"
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        arrays = {}
        for key in ("t", "vir", "qm", "qg", "pulses"):
            val = getattr(self, key)
            if val is None:
                continue
            try:
                arr = np.asarray(val, dtype=float)
            except (TypeError, ValueError) as exc:
                raise DataError(f"EMPS column {key!r} is not numeric: {exc}") from None
            if arr.ndim == 0 or arr.size != max(arr.shape):
                raise DataError(f"EMPS column {key!r} must be a vector, got shape {arr.shape}")
            arrays[key] = np.ascontiguousarray(arr.reshape(-1))
        n = arrays["t"].size
        for key, arr in arrays.items():
            if arr.size != n:
                raise DataError(f"EMPS column {key!r} has {arr.size} samples, t has {n}")
            if not np.all(np.isfinite(arr)):
                raise DataError(f"EMPS column {key!r} contains NaN or inf (first at sample {int(np.argmin(np.isfinite(arr)))})")
        if n < 3:
            raise DataError(f"EMPS record needs at least 3 samples, got {n}")
        if "pulses" not in arrays:
            arrays["pulses"] = np.zeros(n)
        for key, arr in arrays.items():
            setattr(self, key, arr)
        for key in ("gtau", "kp", "kv", "dt", "v_sat"):
            val = getattr(self, key)
            try:
                val = float(val)
            except (TypeError, ValueError):
                raise DataError(f"EMPS constant {key} must be a number, got {val!r}") from None
            if not (np.isfinite(val) and val > 0):
                raise DataError(f"EMPS constant {key} must be positive and finite, got {val}")
            setattr(self, key, val)
        steps = np.diff(self.t)
        if np.any(steps <= 0):
            raise DataError(f"EMPS time t is not strictly increasing (sample {int(np.argmin(steps > 0)) + 1})")
        worst = float(np.max(np.abs(steps - self.dt)))
        if worst > _DT_RTOL * self.dt:
            raise DataError(f"EMPS time grid is not uniform at dt={self.dt} s (worst step deviates by {worst:.3g} s)")

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t.size)

    @property
    def tau(self) -> np.ndarray:
        """Measured drive force gtau·vir, N."""
        return self.gtau * self.vir

    def slice(self, start: int = 0, stop: int | None = None) -> "EmpsRecord":
        """A new record with samples ``start:stop`` (time kept as stored)."""
        sl = slice(start, stop)
        return EmpsRecord(t=self.t[sl], vir=self.vir[sl], qm=self.qm[sl], qg=self.qg[sl], pulses=self.pulses[sl],
                          gtau=self.gtau, kp=self.kp, kv=self.kv, dt=self.dt, v_sat=self.v_sat,
                          name=f"{self.name}[{start}:{'' if stop is None else stop}]", meta=dict(self.meta))


def load_emps_csv(path: str | Path = DEFAULT_CSV, gtau: float = GTAU, kp: float = KP, kv: float = KV,
                  dt: float = DT, v_sat: float = V_SAT, name: str | None = None) -> EmpsRecord:
    """Read a CSV with header columns ``t,vir,qm,qg`` (optional ``pulses_N``) into an :class:`EmpsRecord`.

    Units: t s, vir V, qm and qg m, pulses_N N. The controller constants are arguments (README values by default).
    Raises :class:`DataError` for a missing file, missing columns, non-numeric or non-finite values or a bad grid.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"EMPS CSV not found: {path}")
    with path.open() as fh:
        header = [h.strip() for h in fh.readline().strip().split(",")]
    missing = [c for c in ("t", "vir", "qm", "qg") if c not in header]
    if missing:
        raise DataError(f"EMPS CSV {path.name} lacks column(s) {missing}; header is {header}")
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise DataError(f"EMPS CSV {path.name} is not numeric: {exc}") from None
    if data.shape[1] != len(header):
        raise DataError(f"EMPS CSV {path.name} has {data.shape[1]} columns but {len(header)} header names")
    col = {h: data[:, i] for i, h in enumerate(header)}
    return EmpsRecord(t=col["t"], vir=col["vir"], qm=col["qm"], qg=col["qg"], pulses=col.get("pulses_N"),
                      gtau=gtau, kp=kp, kv=kv, dt=dt, v_sat=v_sat, name=name or path.stem,
                      meta={"source": str(path)})


def load_emps_mat(path: str | Path = DEFAULT_MAT, gtau: float | None = None, kp: float | None = None,
                  kv: float | None = None, dt: float = DT, v_sat: float = V_SAT,
                  name: str | None = None) -> EmpsRecord:
    """Read a benchmark ``.mat`` (keys ``t, vir, qm, qg``; optional ``gtau, kp, kv, pulses_N``) with scipy.io.loadmat.

    A constant given as an argument wins; otherwise the file's value is used, otherwise the README value.
    ``pulses_N`` (N, the validation record's applied force pulses) becomes ``record.pulses``.
    Raises :class:`DataError` for a missing/unreadable file or missing keys.
    """
    from scipy.io import loadmat

    path = Path(path)
    if not path.is_file():
        raise DataError(f"EMPS .mat not found: {path}")
    try:
        mat = loadmat(str(path))
    except Exception as exc:  # scipy raises several types for corrupt files
        raise DataError(f"EMPS .mat {path.name} cannot be read: {exc}") from None
    missing = [k for k in ("t", "vir", "qm", "qg") if k not in mat]
    if missing:
        raise DataError(f"EMPS .mat {path.name} lacks key(s) {missing}")

    def const(key: str, given: float | None, default: float) -> float:
        if given is not None:
            return float(given)
        if key in mat:
            arr = np.asarray(mat[key], dtype=float)
            if arr.size != 1:
                raise DataError(f"EMPS .mat {path.name}: {key} must be a scalar, got shape {arr.shape}")
            return float(arr.item())
        return default

    return EmpsRecord(t=mat["t"], vir=mat["vir"], qm=mat["qm"], qg=mat["qg"], pulses=mat.get("pulses_N"),
                      gtau=const("gtau", gtau, GTAU), kp=const("kp", kp, KP), kv=const("kv", kv, KV),
                      dt=dt, v_sat=v_sat, name=name or path.stem, meta={"source": str(path)})
