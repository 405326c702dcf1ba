"""Console reporting: a per-generation progress bar and parameter tables (text, Markdown, CSV).

The progress bar is tqdm on a terminal. When the stream is not a terminal (batch jobs, Hydra logs, CI)
or the bar is switched off, a compact line is emitted every ``every`` generations (and at the end) so
logs still show progress; lines go to the ``toggle_id.progress`` logger when logging is configured
(Hydra configures it, so the lines land in the job log too), else to the stream.
"""
from __future__ import annotations

import csv
import logging
import math
import os
import sys
import time
import uuid
from typing import Any, Callable, Mapping, Sequence, TextIO

import numpy as np

from .errors import ConfigError
from .params import PARAMS

progress_logger = logging.getLogger("toggle_id.progress")

_UNITS = {p.name: p.unit for p in PARAMS}


# ------------------------------------------------------------------------------------------ progress


def _fmt_extra(extra: Mapping[str, Any] | None) -> str:
    if not extra:
        return ""
    parts = []
    for key, value in extra.items():
        if isinstance(value, (float, np.floating)):
            parts.append(f"{key}={float(value):.4g}")
        else:
            parts.append(f"{key}={value}")
    return " ".join(parts)


class Progress:
    """Progress of a run of ``total`` generations; see :func:`progress`."""

    def __init__(self, total: int, desc: str = "", *, enabled: bool = True, every: int = 10,
                 stream: TextIO | None = None, initial: int = 0, sink: Callable[[str], None] | None = None):
        if int(total) < 0 or int(every) < 0 or int(initial) < 0:
            raise ConfigError(f"progress: total, every and initial must be ≥ 0, got {total}, {every}, {initial}")
        self.total = int(total)
        self.desc = desc
        self.every = int(every)
        self.n = int(initial)
        self.best: float = float("nan")
        self.extra: Mapping[str, Any] | None = None
        self._stream = stream if stream is not None else sys.stderr
        self._sink = sink
        self._t0 = time.perf_counter()
        self._n0 = self.n
        self._last_line_n = -1
        self._closed = False
        isatty = getattr(self._stream, "isatty", None)
        self.bar_shown = bool(enabled) and bool(isatty and isatty())
        self._bar = None
        if self.bar_shown:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=desc, initial=self.n, file=self._stream, dynamic_ncols=True,
                             leave=True, unit="gen")

    def update(self, best_fitness: float, extra: Mapping[str, Any] | None = None, n: int = 1) -> None:
        """Record ``n`` more finished generations with the current best fitness (and optional extra values)."""
        if self._closed:
            return
        self.n += int(n)
        self.best = float(best_fitness)
        self.extra = extra
        if self._bar is not None:
            postfix = f"best={self.best:.6g}"
            if extra:
                postfix += " " + _fmt_extra(extra)
            self._bar.set_postfix_str(postfix, refresh=False)
            self._bar.update(int(n))
        elif self.every and (self.n % self.every == 0 or self.n == self.total):
            self._line()

    def line(self) -> str:
        """The compact progress line, e.g. ``stage-1 gen 20/100 best 1.0909e+06 (12.3 s, 0.62 s/gen)``."""
        elapsed = time.perf_counter() - self._t0
        done = self.n - self._n0
        rate = f", {elapsed / done:.3g} s/gen" if done > 0 else ""
        best = f"{self.best:.6g}" if math.isfinite(self.best) else str(self.best)
        text = f"{self.desc + ' ' if self.desc else ''}gen {self.n}/{self.total} best {best} ({elapsed:.1f} s{rate})"
        extra = _fmt_extra(self.extra)
        return text + (f" {extra}" if extra else "")

    def _line(self) -> None:
        if self.n == self._last_line_n:
            return
        self._last_line_n = self.n
        text = self.line()
        if self._sink is not None:
            self._sink(text)
        elif logging.getLogger().handlers or progress_logger.handlers:
            progress_logger.info(text)
        else:
            print(text, file=self._stream, flush=True)

    def close(self) -> None:
        """Finish the bar (or print the last compact line if it was not printed yet)."""
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
        elif self.every and self.n != self._n0:
            self._line()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def progress(total: int, desc: str = "", *, enabled: bool = True, every: int = 10, stream: TextIO | None = None,
             initial: int = 0, sink: Callable[[str], None] | None = None) -> Progress:
    """A per-generation progress reporter (context manager): ``update(best_fitness, extra=None)``, ``close()``.

    ``enabled`` shows a tqdm bar when ``stream`` (default stderr) is a terminal; otherwise a compact line
    every ``every`` generations and at the end (``every=0``: silent). ``initial``: generations already done
    (resumed runs). ``sink``: where compact lines go (default: the ``toggle_id.progress`` logger when
    logging is configured, else ``stream``).
    """
    return Progress(total, desc, enabled=enabled, every=every, stream=stream, initial=initial, sink=sink)


# -------------------------------------------------------------------------------------------- tables


def _cell(value: Any, fmt: str = ".6g") -> str:
    """Format one table cell: numbers with ``fmt`` (NaN/None → ``—``), everything else with ``str``."""
    if value is None:
        return "—"
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, float, np.integer, np.floating)):
        v = float(value)
        if math.isnan(v):
            return "—"
        if isinstance(value, (int, np.integer)):
            return str(int(value))
        return format(v, fmt)
    return str(value)


def text_table(header: Sequence[str], rows: Sequence[Sequence[Any]], *, align_numbers: bool = True) -> str:
    """A plain aligned text table (header, rule, rows); numeric columns right-aligned."""
    cells = [[_cell(c) for c in row] for row in rows]
    ncol = len(header)
    for i, row in enumerate(cells):
        if len(row) != ncol:
            raise ConfigError(f"table row {i} has {len(row)} cells for {ncol} columns")
    widths = [max([len(str(h))] + [len(r[j]) for r in cells]) for j, h in enumerate(header)]
    numeric = [align_numbers and all(_is_number(row[j]) for row in rows) and bool(rows) for j in range(ncol)]

    def fmt_row(values: Sequence[str]) -> str:
        return "  ".join(v.rjust(w) if num else v.ljust(w) for v, w, num in zip(values, widths, numeric)).rstrip()

    lines = [fmt_row([str(h) for h in header]), "  ".join("-" * w for w in widths)]
    lines += [fmt_row(r) for r in cells]
    return "\n".join(lines)


def _is_number(value: Any) -> bool:
    return value is None or (isinstance(value, (int, float, np.integer, np.floating))
                             and not isinstance(value, (bool, np.bool_))) or (isinstance(value, str) and
                                                                              _looks_numeric(value))


def _looks_numeric(text: str) -> bool:
    try:
        float(text.rstrip("%"))
        return True
    except ValueError:
        return text == "—"


def pct_error(assigned: float, identified: float) -> float:
    """|A − B| / |A| · 100 [%]; NaN when A is 0 or either value is not finite."""
    a, b = float(assigned), float(identified)
    if a == 0.0 or not (math.isfinite(a) and math.isfinite(b)):
        return float("nan")
    return abs(a - b) / abs(a) * 100.0


def _as_columns(names: Sequence[str], identified: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """Normalise ``identified`` to label → {name: value}.

    Accepts a single method (name → value) or several (label → {name: value} or label → vector in the
    order of ``names``).
    """
    if not identified:
        return {}
    first = next(iter(identified.values()))
    if np.ndim(first) == 0 and not isinstance(first, Mapping):  # name → value: one method
        return {"identified": {str(k): float(v) for k, v in identified.items()}}
    out: dict[str, dict[str, float]] = {}
    for label, values in identified.items():
        if isinstance(values, Mapping):
            out[str(label)] = {str(k): float(v) for k, v in values.items()}
        else:
            vec = np.asarray(values, dtype=float).ravel()
            if vec.size != len(names):
                raise ConfigError(f"identified[{label!r}] has {vec.size} values for {len(names)} names")
            out[str(label)] = dict(zip(names, vec.tolist()))
    return out


def param_rows(names: Sequence[str], identified: Mapping[str, Any], assigned: Mapping[str, float] | None = None,
               units: Mapping[str, str] | None = None) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of the paper's Table 1: name, unit, [assigned], then per method the identified value
    and, when ``assigned`` is given, its % error |A−B|/|A|·100. Missing values are ``None`` (shown ``—``)."""
    columns = _as_columns(names, identified)
    unit_of = dict(_UNITS)
    unit_of.update(units or {})
    header = ["parameter", "unit"] + (["assigned (A)"] if assigned is not None else [])
    for label in columns:
        header.append(label)
        if assigned is not None:
            header.append(f"% error ({label})")
    rows: list[list[Any]] = []
    for name in names:
        row: list[Any] = [name, unit_of.get(name, "")]
        a = None if assigned is None else assigned.get(name)
        if assigned is not None:
            row.append(a)
        for values in columns.values():
            b = values.get(name)
            row.append(b)
            if assigned is not None:
                row.append(None if a is None or b is None else pct_error(a, b))
        rows.append(row)
    return header, rows


def param_table(names: Sequence[str], identified: Mapping[str, Any], assigned: Mapping[str, float] | None = None,
                units: Mapping[str, str] | None = None, *, value_fmt: str = ".5g", pct_fmt: str = ".2f",
                style: str = "text") -> str:
    """A text table like the paper's Table 1 (name, unit, assigned, identified, % error = |A−B|/A·100).

    ``identified``: name → value (one method) or label → {name: value} / vector in the order of ``names``
    (several methods, e.g. one-stage and two-stage). ``units`` default to the units of :mod:`toggle_id.params`.
    ``style``: ``"text"`` (aligned columns) or ``"markdown"``.
    """
    if style not in ("text", "markdown"):
        raise ConfigError(f"param_table style must be 'text' or 'markdown', got {style!r}")
    header, rows = param_rows(names, identified, assigned, units)
    pct_cols = {j for j, h in enumerate(header) if h.startswith("% error")}
    shown = []
    for row in rows:
        out = []
        for j, v in enumerate(row):
            if j < 2:
                out.append(v)
            elif v is None or (isinstance(v, float) and math.isnan(v)):
                out.append("—")
            else:
                out.append(format(float(v), pct_fmt) + "%" if j in pct_cols else format(float(v), value_fmt))
        shown.append(out)
    return text_table(header, shown) if style == "text" else markdown_table(header, shown)


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table; numbers formatted ``.6g``, NaN/None as ``—``, ``|`` escaped."""
    ncol = len(header)

    def esc(v: Any) -> str:
        return _cell(v).replace("|", r"\|").replace("\n", " ")

    for i, row in enumerate(rows):
        if len(row) != ncol:
            raise ConfigError(f"table row {i} has {len(row)} cells for {ncol} columns")
    lines = ["| " + " | ".join(esc(h) for h in header) + " |",
             "| " + " | ".join("---:" if rows and all(_is_number(r[j]) for r in rows) else "---"
                               for j in range(ncol)) + " |"]
    for row in rows:
        lines.append("| " + " | ".join(esc(v) for v in row) + " |")
    return "\n".join(lines)


def write_csv_table(path: str | os.PathLike, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """Write a CSV table atomically (temporary file + rename; parents created). Floats are written with
    ``repr`` precision, NaN/None as empty cells. Returns the path."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    ncol = len(header)
    tmp = os.path.join(directory, f".{os.path.basename(path)}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "x", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(list(header))
            for i, row in enumerate(rows):
                if len(row) != ncol:
                    raise ConfigError(f"table row {i} has {len(row)} cells for {ncol} columns")
                writer.writerow([_csv_cell(v) for v in row])
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def _csv_cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return "" if math.isnan(v) else repr(v)
    if isinstance(value, np.integer):
        return int(value)
    return value
