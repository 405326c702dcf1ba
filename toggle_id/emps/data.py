"""EMPS records: finding the benchmark's files, checking them, and loading them into a validated :class:`EmpsRecord`.

The EMPS (electro-mechanical positioning system, Janot, Gautier & Brunot 2019) is a DC motor driving a ball screw,
run in closed loop at 1 kHz. A record holds, on the sample grid: the time ``t`` (s), the controller output ``vir``
(the drive input ν, V; the force is τ = gtau·ν, N), the measured position ``qm`` (m, load side), the reference
``qg`` (m) and, for the validation record, the pulse train ``pulses`` (``pulses_N`` of the file), which enters the
loop at the controller output in the unit of ``vir``: ν = sat(control law + pulse). The controller constants
``gtau`` (N/V), ``kp`` (1/s) and ``kv`` (V/(m/s)) travel with the record.

The records are the benchmark's and are never shipped with this project. :func:`find_benchmark_files` looks for
them where a user has them — a configured directory (``emps.data_dir``, else ``$TOGGLE_ID_EMPS_DIR``), then the
cache of the benchmark's official loader (``nonlinear_benchmarks.EMPS()`` unpacks them into
``~/.nonlinear_benchmarks/EMPS/``) — and checks their sha256 against :data:`SHA256`.
"""
from __future__ import annotations

import hashlib
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import ConfigError, DataError

#: The benchmark's estimation record (MATLAB v5; keys t, vir, qm, qg, gtau, kp, kv).
ESTIMATION_FILE = "DATA_EMPS.mat"
#: The benchmark's validation record: the same loop and reference plus the pulse train ``pulses_N``.
VALIDATION_FILE = "DATA_EMPS_PULSES.mat"
#: sha256 of the benchmark's original files, as distributed in EMPS.zip (nonlinearbenchmark.org, EMPS) and
#: unpacked by the official loader ``nonlinear_benchmarks.EMPS()``. Citation: :data:`CITATION`.
SHA256: dict[str, str] = {
    ESTIMATION_FILE: "6cf6814ae14618795da0101aae2bb97ff0c6351b0501b5492751b02b07facf7e",
    VALIDATION_FILE: "0eab75bb1f6b16228ee78791343a88bf9bfd9a51036ac9807d7b5fc11c0e1704",
}
#: What a user cites for the records.
CITATION = ('A. Janot, M. Gautier, M. Brunot, "Data Set and Reference Models of EMPS", 2019 Workshop on Nonlinear '
            'System Identification Benchmarks, Eindhoven, The Netherlands')
#: Where a user gets them.
SOURCE = ("nonlinearbenchmark.org (EMPS), or `pip install nonlinear-benchmarks` then "
          "`python -c 'import nonlinear_benchmarks; nonlinear_benchmarks.EMPS()'`")
#: Environment variable naming a directory that holds the two files (used when ``emps.data_dir`` is unset).
ENV_DIR = "TOGGLE_ID_EMPS_DIR"
#: Name of the official loader's folder for this benchmark inside its cache directory.
LOADER_SUBDIR = "EMPS"

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


class EmpsRecordsNotFound(DataError):
    """The benchmark's records are in none of the places searched (the message says where to get and put them)."""


# ------------------------------------------------------------------------------------------ finding the records
def loader_cache_dir(env: Mapping[str, str] | None = None, platform: str | None = None) -> Path:
    """The folder where ``nonlinear_benchmarks.EMPS()`` unpacks the benchmark: ``~/.nonlinear_benchmarks/EMPS``
    on Linux (the loader's ``get_tmp_benchmark_directory``: ``~/Library/Application Support/nonlinear_benchmarks``
    on macOS, ``%LOCALAPPDATA%/nonlinear_benchmarks`` on Windows). ``~`` is ``$HOME`` of ``env``."""
    env = os.environ if env is None else env
    platform = sys.platform if platform is None else platform
    home = Path(env.get("HOME") or Path.home())
    if platform == "darwin":
        base = home / "Library" / "Application Support" / "nonlinear_benchmarks"
    elif platform == "win32":
        base = Path(env.get("LOCALAPPDATA") or home) / "nonlinear_benchmarks"
    else:
        base = home / ".nonlinear_benchmarks"
    return base / LOADER_SUBDIR


@dataclass(frozen=True)
class SearchPlace:
    """One directory searched for the records, and why (``emps.data_dir``, ``$TOGGLE_ID_EMPS_DIR``, loader cache)."""

    path: Path
    origin: str


def search_places(data_dir: str | Path | None = None, env: Mapping[str, str] | None = None) -> list[SearchPlace]:
    """Directories searched, in order: ``data_dir`` (or, when it is None, ``$TOGGLE_ID_EMPS_DIR``), then the loader's
    cache folder and each of its immediate subfolders (an archive unpacked by hand may keep a top folder).
    A configured ``data_dir`` that is not a directory raises :class:`ConfigError`."""
    env = os.environ if env is None else env
    places: list[SearchPlace] = []
    if data_dir is not None:
        d = Path(data_dir).expanduser()
        if not d.is_dir():
            raise ConfigError(f"emps.data_dir={d} is not a directory")
        places.append(SearchPlace(d, "emps.data_dir"))
    elif env.get(ENV_DIR):
        places.append(SearchPlace(Path(env[ENV_DIR]).expanduser(), f"${ENV_DIR}"))
    cache = loader_cache_dir(env)
    places.append(SearchPlace(cache, "loader cache"))
    if cache.is_dir():
        try:
            subs = sorted(p for p in cache.iterdir() if p.is_dir() and not p.name.startswith("__"))
        except OSError:
            subs = []
        places.extend(SearchPlace(p, "loader cache") for p in subs)
    return places


def sha256_of(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with Path(path).open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def verify_benchmark_file(path: str | Path, name: str | None = None) -> str:
    """Check that ``path`` is the benchmark's file ``name`` (default its own file name) by its sha256; return the
    digest. A mismatch raises a one-line :class:`DataError`."""
    path = Path(path)
    name = path.name if name is None else name
    if name not in SHA256:
        raise ConfigError(f"{name!r} is not one of the EMPS benchmark files {sorted(SHA256)}")
    digest = sha256_of(path)
    if digest != SHA256[name]:
        raise DataError(f"EMPS record {path} is not the benchmark's {name}: sha256 {digest} instead of "
                        f"{SHA256[name]}; get the original from {SOURCE} ({CITATION}, 2019)")
    return digest


@dataclass(frozen=True)
class FoundFile:
    """A benchmark file found and verified: its path, where it was found (``origin``) and its sha256."""

    name: str
    path: Path
    origin: str
    sha256: str

    def to_dict(self) -> dict:
        return {"file": self.name, "path": str(self.path), "found_in": self.origin, "sha256": self.sha256,
                "sha256_verified": True}


def find_benchmark_file(name: str, data_dir: str | Path | None = None,
                        env: Mapping[str, str] | None = None) -> FoundFile | None:
    """The first of :func:`search_places` holding ``name``, verified by sha256 (a wrong file is an error, not a
    reason to look further); None where no place holds it."""
    for place in search_places(data_dir, env):
        cand = place.path / name
        if cand.is_file():
            return FoundFile(name, cand.resolve(), place.origin, verify_benchmark_file(cand, name))
    return None


def not_found_message(names: list[str], data_dir: str | Path | None = None,
                      env: Mapping[str, str] | None = None) -> str:
    """One line: which files are missing, where they were looked for, where to get them and where to put them."""
    env = os.environ if env is None else env
    what = {ESTIMATION_FILE: "estimation", VALIDATION_FILE: "validation"}
    files = " and ".join(f"{n} ({what.get(n, 'record')})" for n in names)
    configured = (f"emps.data_dir={Path(data_dir).expanduser()}" if data_dir is not None
                  else f"${ENV_DIR}={env[ENV_DIR]}" if env.get(ENV_DIR) else None)
    searched = ((configured + ", " if configured else "") + f"{loader_cache_dir(env)}")
    return (f"EMPS benchmark record(s) {files} not found (searched {searched}); get them from {SOURCE} and put them "
            f"into a directory given as emps.data_dir=DIR (or ${ENV_DIR}=DIR) or into {loader_cache_dir(env)}/ "
            f"(where the loader unpacks them) — {CITATION}, 2019")


@dataclass(frozen=True)
class BenchmarkFiles:
    """The benchmark's estimation file (always found) and its validation file (None when it is in no place)."""

    estimation: FoundFile
    validation: FoundFile | None


def find_benchmark_files(data_dir: str | Path | None = None, env: Mapping[str, str] | None = None,
                         require_validation: bool = False) -> BenchmarkFiles:
    """Locate and verify :data:`ESTIMATION_FILE` and :data:`VALIDATION_FILE` (see :func:`search_places`).

    Raises :class:`EmpsRecordsNotFound` (one line, see :func:`not_found_message`) when the estimation file — or,
    with ``require_validation``, either file — is found nowhere, :class:`DataError` for a file with the wrong sha256
    and :class:`ConfigError` for a configured ``data_dir`` that is not a directory.
    """
    est = find_benchmark_file(ESTIMATION_FILE, data_dir, env)
    val = find_benchmark_file(VALIDATION_FILE, data_dir, env)
    missing = [n for n, f in ((ESTIMATION_FILE, est), (VALIDATION_FILE, val))
               if f is None and (n == ESTIMATION_FILE or require_validation)]
    if missing:
        if est is None and val is None:
            missing = [ESTIMATION_FILE, VALIDATION_FILE]
        raise EmpsRecordsNotFound(not_found_message(missing, data_dir, env))
    return BenchmarkFiles(est, val)


@dataclass
class EmpsRecord:
    """One closed-loop EMPS experiment on a uniform 1 kHz grid.

    Attributes: ``t`` (s), ``vir`` (V), ``qm`` (m), ``qg`` (m), ``pulses`` (the validation record's ``pulses_N``:
    a pulse train added to the controller output, in V; zeros when the record has none), controller constants ``gtau`` (N/V), ``kp`` (1/s), ``kv`` (V/(m/s)),
    sampling period ``dt`` (s), ``v_sat`` (V) and a ``name``. ``excluded`` (bool, one per sample, or None): samples
    the model takes as measured — glitches of the measurement (:func:`toggle_id.residuals.glitches`) — which then
    weigh in no residual (:meth:`residual`), sensitivity or test. Construction validates and raises
    :class:`DataError`.
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
    excluded: np.ndarray | None = None

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
        if self.excluded is not None:
            mask = np.asarray(self.excluded, dtype=bool).reshape(-1)
            if mask.size != n:
                raise DataError(f"EMPS excluded mask has {mask.size} entries, t has {n}")
            self.excluded = mask if mask.any() else None
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

    def residual(self, q: np.ndarray) -> np.ndarray:
        """qm − q, zero at the :attr:`excluded` samples (works row-wise on a batch ``q`` (k, n) too)."""
        r = self.qm - q
        return r if self.excluded is None else np.where(self.excluded, 0.0, r)

    @property
    def tau(self) -> np.ndarray:
        """Measured drive force gtau·vir, N."""
        return self.gtau * self.vir

    def slice(self, start: int = 0, stop: int | None = None) -> EmpsRecord:
        """A new record with samples ``start:stop`` (time kept as stored)."""
        sl = slice(start, stop)
        return EmpsRecord(t=self.t[sl], vir=self.vir[sl], qm=self.qm[sl], qg=self.qg[sl], pulses=self.pulses[sl],
                          gtau=self.gtau, kp=self.kp, kv=self.kv, dt=self.dt, v_sat=self.v_sat,
                          name=f"{self.name}[{start}:{'' if stop is None else stop}]", meta=dict(self.meta),
                          excluded=None if self.excluded is None else self.excluded[sl])


def load_emps_csv(path: str | Path, gtau: float = GTAU, kp: float = KP, kv: float = KV,
                  dt: float = DT, v_sat: float = V_SAT, name: str | None = None) -> EmpsRecord:
    """Read a CSV with header columns ``t,vir,qm,qg`` (optional ``pulses_N``) into an :class:`EmpsRecord`.

    Units: t s, vir V, qm and qg m, pulses_N V (added to the controller output). The controller constants are
    arguments (README values by default).
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


def load_emps_mat(path: str | Path, gtau: float | None = None, kp: float | None = None,
                  kv: float | None = None, dt: float = DT, v_sat: float = V_SAT,
                  name: str | None = None) -> EmpsRecord:
    """Read a benchmark ``.mat`` (keys ``t, vir, qm, qg``; optional ``gtau, kp, kv, pulses_N``) with scipy.io.loadmat.

    A constant given as an argument wins; otherwise the file's value is used, otherwise the README value.
    ``pulses_N`` (the validation record's pulse train, entering at the controller output in V) becomes
    ``record.pulses``.
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
