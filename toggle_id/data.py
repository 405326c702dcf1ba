"""Measured-data files (docs/model.md §8) and the checks every record must pass before it is fitted.

A data file is a CSV with a header row, SI units, one row per sample, uniform sampling, sorted by time:
``t`` (s), ``v_in`` (V, the command before the gain K_i), ``x_B`` (m) and optionally ``i_q`` (A). Other
columns are ignored. Every problem raises :class:`~toggle_id.errors.DataError` with a one-line message
naming the problem and the file (or record), with the file line of the first offending sample.
"""
from __future__ import annotations

import csv
import difflib
import io
import os
from pathlib import Path
from typing import NoReturn, Sequence

import numpy as np

from .checkpoint import atomic_write_text
from .errors import DataError
from .record import X_B0, Record

#: Clamping position x_B^L of docs/model.md §1, m.
X_B_L = 0.056
#: Plausible range of the measured x_B, m: the toggle stroke is 0 < x_B ≤ 2 r1 = 0.12 m (docs/model.md §2),
#: widened a little for sensor noise and offsets.
X_B_RANGE = (0.0, 0.125)
#: Largest plausible |v_in|, V (the command before the drive gain K_i).
V_IN_MAX = 1e3
#: Largest plausible |i_q|, A (the assigned plant stalls near 350 A while clamped, docs/model.md §9).
I_Q_MAX = 1e5
#: Fewest samples a record may have.
MIN_SAMPLES = 10

REQUIRED_COLUMNS = ("t", "v_in", "x_B")
OPTIONAL_COLUMNS = ("i_q",)
UNITS = {"t": "s", "v_in": "V", "x_B": "m", "i_q": "A"}


# --------------------------------------------------------------------------------------------------
# validation (shared by files and in-memory records)
# --------------------------------------------------------------------------------------------------

def validate_record(record: Record, *, require_x_B: bool = True, expect_rate_hz: float | None = None,
                    rtol_dt: float = 1e-6, min_samples: int = MIN_SAMPLES,
                    x_B_range: tuple[float, float] = X_B_RANGE, x_B0_tol: float | None = 0.005,
                    v_in_max: float = V_IN_MAX, i_q_max: float = I_Q_MAX,
                    source: str | None = None, lines: Sequence[int] | None = None) -> Record:
    """Check a record for use in a fit; return it unchanged or raise DataError (one line).

    Checks, in order: enough samples (``min_samples``); x_B present if ``require_x_B``; no NaN/Inf in t,
    v_in, x_B, i_q; time strictly increasing (no duplicates, sorted); uniform sampling (every step within
    ``rtol_dt`` relative of the mean step; the first bad step and the worst are reported); the sampling
    rate if ``expect_rate_hz`` (Hz) is given; units: x_B a position in metres inside ``x_B_range`` (m), not
    constant, its first sample within ``x_B0_tol`` (m) of ``record.x_B0`` (None skips); |v_in| ≤ ``v_in_max``
    (V); |i_q| ≤ ``i_q_max`` (A).

    ``source`` names the record in messages (default: ``record '<name>'``); ``lines`` gives the file line of
    each sample (read_csv passes it), else messages say ``sample i``.
    """
    src = source if source is not None else f"record {record.name!r}"

    def where(i: int) -> str:
        pos = f"line {lines[i]}" if lines is not None else f"sample {i}"
        return f"{pos} (t = {record.t[i]:.9g} s)" if np.isfinite(record.t[i]) else pos

    def fail(msg: str) -> NoReturn:
        raise DataError(_one_line(f"{src}: {msg}"))

    n = record.n
    min_samples = max(int(min_samples), 2)  # a time step needs two samples
    if n < min_samples:
        fail(f"only {n} sample{'s' if n != 1 else ''}; at least {min_samples} needed")
    if require_x_B and record.x_B is None:
        fail("no measured x_B")

    columns = {"t": record.t, "v_in": record.v_in, "x_B": record.x_B, "i_q": record.i_q}
    for name, arr in columns.items():
        if arr is None:
            continue
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            i = int(bad[0])
            kind = "NaN" if np.isnan(arr[i]) else "Inf"
            pos = f"line {lines[i]}" if lines is not None else f"sample {i}"
            fail(f"{kind} in column '{name}' at {pos} ({bad.size} non-finite value{'s' if bad.size > 1 else ''})")

    _check_time(record.t, expect_rate_hz, rtol_dt, where, fail)
    if record.x_B is not None:
        _check_x_B(record, x_B_range, x_B0_tol, where, fail)
    k = int(np.argmax(np.abs(record.v_in)))
    if abs(record.v_in[k]) > v_in_max:
        fail(f"v_in implausible: |v_in| = {abs(record.v_in[k]):.6g} V > {v_in_max:g} V at {where(k)}; "
             "v_in must be the command in volts")
    if record.i_q is not None:
        k = int(np.argmax(np.abs(record.i_q)))
        if abs(record.i_q[k]) > i_q_max:
            fail(f"i_q implausible: |i_q| = {abs(record.i_q[k]):.6g} A > {i_q_max:g} A at {where(k)}; "
                 "i_q must be in amperes")
    return record


def _check_time(t: np.ndarray, expect_rate_hz: float | None, rtol_dt: float, where, fail) -> None:
    """Strictly increasing, uniformly sampled time (s); optionally at ``expect_rate_hz``."""
    dt = np.diff(t)
    dup = np.flatnonzero(dt == 0)
    if dup.size:
        i = int(dup[0])
        fail(f"duplicated time stamp at {where(i + 1)}, same as the previous sample")
    back = np.flatnonzero(dt < 0)
    if back.size:
        i = int(back[0])
        fail(f"time not sorted: {where(i + 1)} comes after t = {t[i]:.9g} s; rows must be sorted by time")
    dt_mean = (t[-1] - t[0]) / (t.size - 1)
    dev = np.abs(dt - dt_mean) / dt_mean
    over = np.flatnonzero(dev > rtol_dt)
    if over.size:
        k = int(over[0])
        fail(f"non-uniform sampling: step {dt[k]:.9g} s before {where(k + 1)} differs from the mean step "
             f"{dt_mean:.9g} s by {dev[k]:.3g} relative (tolerance {rtol_dt:g}; {over.size} such step"
             f"{'s' if over.size > 1 else ''}, worst {dev.max():.3g} before {where(int(np.argmax(dev)) + 1)})")
    if expect_rate_hz is not None:
        rate = 1.0 / dt_mean
        if not abs(rate - expect_rate_hz) <= max(rtol_dt, 1e-12) * expect_rate_hz:
            fail(f"sampling rate {rate:.9g} Hz, expected {expect_rate_hz:g} Hz")


def _check_x_B(record: Record, x_B_range: tuple[float, float], x0_tol: float | None, where, fail) -> None:
    """x_B a position in metres on the toggle stroke, moving, starting near the plant's x_B0."""
    x = record.x_B
    lo, hi = x_B_range
    amax = float(np.max(np.abs(x)))
    if amax > 1.0:
        if amax <= 1000.0 * hi:
            unit = "millimetres" if amax > 100.0 * hi else "centimetres or millimetres"
            fail(f"x_B looks like {unit} (max {amax:.6g}); the file must be in metres")
        fail(f"x_B is not a position in metres (max |x_B| = {amax:.6g} > 1 m)")
    k = int(np.argmin(x))
    if x[k] <= lo:
        fail(f"x_B = {x[k]:.6g} m at {where(k)} is not above {lo:g} m; x_B must be the absolute position of "
             f"slider B from pivot O (x_B(0) = {record.x_B0:g} m), not a displacement")
    k = int(np.argmax(x))
    if x[k] > hi:
        fail(f"x_B = {x[k]:.6g} m at {where(k)} is beyond the toggle stroke ({hi:g} m)")
    if np.ptp(x) == 0.0:
        fail(f"x_B never moves (constant {x[0]:.6g} m)")
    off = abs(float(x[0]) - record.x_B0)
    if x0_tol is not None and off > x0_tol:
        fail(f"first sample x_B = {x[0]:.6g} m is {off * 1e3:.3g} mm from the initial position "
             f"x_B0 = {record.x_B0:g} m; set x_B0 for this record if it starts elsewhere")


def check_two_stage(record: Record, x_B_L: float = X_B_L) -> int:
    """Index of the clamping instant (first sample with x_B ≥ ``x_B_L``, m) for a two-stage fit.

    Raises DataError when the record has no x_B, never reaches ``x_B_L`` (stage 2 would be empty) or is
    already there at the first sample (stage 1 would be empty).
    """
    if record.x_B is None:
        raise DataError(f"record {record.name!r}: no measured x_B; a two-stage fit needs one")
    k = record.clamp_index(x_B_L)
    if k >= record.n:
        raise DataError(f"record {record.name!r} too short to contain the clamping instant "
                        f"(max x_B = {np.max(record.x_B):.6g} m < x_B^L = {x_B_L:g} m)")
    if k == 0:
        raise DataError(f"record {record.name!r} starts at or beyond the clamping position "
                        f"(x_B[0] = {record.x_B[0]:.6g} m ≥ x_B^L = {x_B_L:g} m); stage 1 would have no samples")
    return k


# --------------------------------------------------------------------------------------------------
# CSV files
# --------------------------------------------------------------------------------------------------

def read_csv(path: str | os.PathLike, *, x_B0: float | None = None, require_x_B: bool = True,
             expect_rate_hz: float | None = None, rtol_dt: float = 1e-6, **checks) -> Record:
    """Read a measured record (docs/model.md §8) and validate it; raise DataError (one line) on any problem.

    ``x_B0`` (m) is the record's initial position, default the plant constant :data:`toggle_id.record.X_B0`.
    ``require_x_B=False`` accepts input-only files (no x_B column). ``expect_rate_hz`` (Hz) checks the
    sampling rate; ``rtol_dt`` is the relative tolerance on each time step. Further keyword arguments
    (``min_samples``, ``x_B_range``, ``x_B0_tol``, ``v_in_max``, ``i_q_max``) go to :func:`validate_record`.
    The record's ``name`` is the file stem; ``meta`` holds ``path``, ``columns`` and ``ignored_columns``.
    """
    path = Path(path)
    src = f"data file {path}"
    header, rows, lines = _read_rows(path, src)
    col = _locate_columns(header, require_x_B, src)
    values: dict[str, np.ndarray] = {}
    for name, j in col.items():
        out = np.empty(len(rows))
        for i, row in enumerate(rows):
            text = row[j].strip()
            try:
                out[i] = float(text)
            except ValueError:
                what = "empty value" if not text else f"{text[:40]!r} is not a number"
                raise DataError(_one_line(f"{src}: malformed row at line {lines[i]}, column '{name}': {what}")) \
                    from None
        values[name] = out
    record = Record(t=values["t"], v_in=values["v_in"], x_B=values.get("x_B"), i_q=values.get("i_q"),
                    x_B0=X_B0 if x_B0 is None else float(x_B0), name=path.stem,
                    meta={"path": str(path), "columns": list(header),
                          "ignored_columns": [h for k, h in enumerate(header) if k not in col.values()]})
    validate_record(record, require_x_B=require_x_B, expect_rate_hz=expect_rate_hz, rtol_dt=rtol_dt,
                    source=src, lines=lines, **checks)
    return record


def read_input(path: str | os.PathLike, *, rate_hz: float, v_max: float, max_duration: float,
               x_B0: float | None = None) -> Record:
    """An input to simulate under (e.g. the excite job's ``excitation.csv``): a CSV with columns ``t`` (s, from 0,
    uniform at ``rate_hz``) and ``v_in`` (V, |v_in| ≤ ``v_max``, the machine's limit), at most ``max_duration``
    s long; any other column is dropped. DataError (one line) otherwise."""
    rec = read_csv(path, x_B0=x_B0, require_x_B=False, expect_rate_hz=rate_hz)
    src = f"input file {path}"
    k = int(np.argmax(np.abs(rec.v_in)))
    if abs(rec.v_in[k]) > v_max:
        raise DataError(f"{src}: |v_in| = {abs(rec.v_in[k]):.6g} V at t = {rec.t[k]:.9g} s is over the machine's "
                        f"limit input.v_max = {v_max:g} V")
    duration = float(rec.t[-1] - rec.t[0])
    if duration > max_duration:
        raise DataError(f"{src}: {duration:g} s long, longer than input.max_duration = {max_duration:g} s")
    if rec.t[0] != 0.0:
        raise DataError(f"{src}: time must start at 0 s, starts at {rec.t[0]:.9g} s")
    rec.x_B, rec.i_q = None, None
    return rec


def _read_rows(path: Path, src: str) -> tuple[list[str], list[list[str]], list[int]]:
    """Header, data rows (all with the header's field count) and the file line of each row."""
    if not path.exists():
        raise DataError(_one_line(f"{src} not found"))
    if path.is_dir():
        raise DataError(_one_line(f"{src} is a directory, not a CSV file"))
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise DataError(_one_line(f"{src} is not a UTF-8 text CSV file")) from None
    except OSError as exc:
        raise DataError(_one_line(f"{src} cannot be read ({exc.strerror or exc})")) from None
    reader = csv.reader(io.StringIO(text, newline=""))
    header: list[str] | None = None
    rows: list[list[str]] = []
    lines: list[int] = []
    try:
        for row in reader:
            if not any(field.strip() for field in row):
                continue  # blank line
            if header is None:
                header = [h.strip() for h in row]
                _check_header(header, src)
                continue
            if len(row) != len(header):
                raise DataError(_one_line(f"{src}: malformed row at line {reader.line_num}: {len(row)} fields, "
                                          f"the header has {len(header)}"))
            rows.append(row)
            lines.append(reader.line_num)
    except csv.Error as exc:
        raise DataError(_one_line(f"{src}: malformed CSV at line {reader.line_num} ({exc})")) from None
    if header is None:
        raise DataError(_one_line(f"{src} is empty (expected a header row {','.join(REQUIRED_COLUMNS)} and data)"))
    if not rows:
        raise DataError(_one_line(f"{src} has a header but no data rows"))
    return header, rows, lines


def _check_header(header: list[str], src: str) -> None:
    """Reject a first row of numbers (no header) or a file that is not comma-separated."""
    if all(_is_number(h) for h in header):
        raise DataError(_one_line(f"{src} has no header row (line 1 holds numbers); expected a header such as "
                                  f"{','.join(REQUIRED_COLUMNS)}"))
    if len(header) == 1 and any(sep in header[0] for sep in (";", "\t", " ")):
        raise DataError(_one_line(f"{src} is not comma-separated (header {header[0][:60]!r})"))


def _locate_columns(header: list[str], require_x_B: bool, src: str) -> dict[str, int]:
    """Column index of each used name; DataError for missing (with a suggestion) or duplicated names."""
    wanted = [c for c in REQUIRED_COLUMNS if require_x_B or c != "x_B"]
    col: dict[str, int] = {}
    for name in REQUIRED_COLUMNS + OPTIONAL_COLUMNS:
        hits = [j for j, h in enumerate(header) if h == name]
        if len(hits) > 1:
            raise DataError(_one_line(f"{src}: column '{name}' appears {len(hits)} times in the header"))
        if hits:
            col[name] = hits[0]
    missing = [c for c in wanted if c not in col]
    if missing:
        unused = [h for j, h in enumerate(header) if j not in col.values()]
        hints = [f"column {s!r} — did you mean {m!r}?" for m in missing if (s := _suggest(m, unused))]
        names = ", ".join(f"'{m}'" for m in missing)
        raise DataError(_one_line(
            f"{src}: missing required column{'s' if len(missing) > 1 else ''} {names}"
            + (f"; {' '.join(hints)}" if hints else "") + f" (header: {', '.join(header)})"))
    return col


def _suggest(name: str, candidates: list[str]) -> str | None:
    """The header name closest to ``name`` (case-insensitive match first, then difflib), if any is close."""
    for c in candidates:
        if c.lower() == name.lower():
            return c
    lowered = {c.lower(): c for c in candidates}
    close = difflib.get_close_matches(name.lower(), list(lowered), n=1, cutoff=0.6)
    return lowered[close[0]] if close else None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def write_csv(record: Record, path: str | os.PathLike, *, validate: bool = True) -> Path:
    """Write ``record`` as a data file: ``t,v_in[,x_B][,i_q]`` with ``%.17g`` (exact round trip).

    The file appears atomically (temporary file in the same directory, then rename), so a reader never
    sees a half-written record. ``validate`` first runs :func:`validate_record` (x_B not required), so
    nothing is written that :func:`read_csv` would refuse. Returns the path.
    """
    path = Path(path)
    if validate:
        validate_record(record, require_x_B=False, source=f"record {record.name!r} (writing {path})")
    names = ["t", "v_in"] + [c for c in ("x_B", "i_q") if getattr(record, c) is not None]
    table = np.column_stack([getattr(record, c) for c in names])
    buf = io.StringIO()
    np.savetxt(buf, table, fmt="%.17g", delimiter=",", header=",".join(names), comments="")
    return atomic_write_text(path, buf.getvalue())


def _one_line(msg: str) -> str:
    """``msg`` with any line breaks (e.g. from a file name) replaced, so every message is one line."""
    return " ".join(msg.splitlines())
