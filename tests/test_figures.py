"""Tests of the report figures (toggle_id.figures) and console reporting (toggle_id.console)."""
from __future__ import annotations

import csv
import io
import os

import numpy as np
import pytest

from toggle_id import figures
from toggle_id.console import (markdown_table, param_rows, param_table, pct_error, progress, text_table,
                               write_csv_table)
from toggle_id.errors import ConfigError, DataError
from toggle_id.params import ASSIGNED, PARAM_NAMES, to_dict

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _assert_png(path) -> None:
    with open(path, "rb") as fh:
        head = fh.read(8)
    assert head == PNG_MAGIC
    assert os.path.getsize(path) > 2000
    leftovers = [f for f in os.listdir(os.path.dirname(path)) if f.endswith(".tmp")]
    assert leftovers == []


@pytest.fixture(scope="module")
def signals():
    t = np.linspace(0.0, 5.0, 5001)
    x = 0.020 + 0.036 * (1.0 - np.exp(-t))
    rng = np.random.default_rng(0)
    measured = x + 1e-6 * rng.standard_normal(t.size)
    model_nan = x.copy()
    model_nan[1000:1200] = np.nan  # a failed stretch of simulation
    force = np.where(x > 0.056, (x - 0.056) * 5e7, 0.0)
    v_in = 0.05 + 0.01 * np.sin(2 * np.pi * t)
    return t, x, measured, model_nan, force, v_in


# ---------------------------------------------------------------------------------------- figures


def test_fitness_history_png_with_nan(tmp_path):
    hist = {"one-stage": np.r_[np.nan, np.logspace(3, 6, 99)], "two-stage": np.logspace(3, 6.1, 100)}
    fig = figures.fitness_history(hist)
    ax = fig.axes[0]
    assert ax.get_yscale() == "log" and ax.get_xlabel() == "generation"
    assert len(ax.get_lines()) == 2
    _assert_png(figures.save(fig, tmp_path / "fit.png"))


def test_fitness_history_without_positive_values_falls_back_to_linear(tmp_path):
    fig = figures.fitness_history({"all nan": [np.nan] * 5, "negative": [-3.0, -2.0, -1.0]})
    assert fig.axes[0].get_yscale() == "linear"
    _assert_png(figures.save(fig, tmp_path / "sub" / "dir" / "fit.png"))


def test_response_comparison_panels(tmp_path, signals):
    t, x, measured, model_nan, force, v_in = signals
    fig = figures.response_comparison(t, measured, {"one-stage": x, "two-stage": model_nan}, stage_boundary=2.0,
                                      forces={"one-stage": force}, v_in=v_in)
    assert len(fig.axes) == 4
    assert fig.axes[0].get_ylabel() == "$x_B$ [mm]"
    assert "µm" in fig.axes[1].get_ylabel() and "kN" in fig.axes[2].get_ylabel()
    assert fig.axes[-1].get_xlabel() == "time t [s]"
    # panel (a) in mm, panel (b) in µm, panel (c) in kN
    y_meas = fig.axes[0].get_lines()[0].get_ydata()
    np.testing.assert_allclose(y_meas, measured * 1e3)
    diff = fig.axes[1].get_lines()[0].get_ydata()
    np.testing.assert_allclose(diff, (x - measured) * 1e6)
    np.testing.assert_allclose(fig.axes[2].get_lines()[0].get_ydata(), force * 1e-3)
    _assert_png(figures.save(fig, tmp_path / "resp.png"))

    fig2 = figures.response_comparison(t, measured, {"model": model_nan})
    assert len(fig2.axes) == 2
    _assert_png(figures.save(fig2, tmp_path / "resp2.png"))


def test_response_comparison_rejects_mismatched_lengths(signals):
    t, x, measured, *_ = signals
    with pytest.raises(DataError, match="samples"):
        figures.response_comparison(t, measured, {"short": x[:-1]})


def test_residual_diagnostics(tmp_path, signals):
    t, x, measured, *_ = signals
    acf = np.exp(-np.arange(60) / 5.0)
    acf[7] = np.nan
    f = np.linspace(0.0, 500.0, 2501)
    p = 1.0 / (1.0 + f)
    p[3] = np.nan
    band = 1.96 / np.sqrt(t.size)
    fig = figures.residual_diagnostics(t, measured - x, acf, band, f, p, lag_dt=1e-3, marks={"drive": 12.5})
    assert len(fig.axes) == 3
    n_out = int(np.sum(np.abs(acf[1:]) > band))
    assert f"{n_out} of 59 lags outside" in fig.axes[1].get_title(loc="left")
    assert fig.axes[2].get_yscale() == "log"
    _assert_png(figures.save(fig, tmp_path / "res.png"))
    with pytest.raises(DataError):
        figures.residual_diagnostics(t, measured - x, acf, np.ones(3), f, p)


def test_parameter_errors(tmp_path):
    names = list(PARAM_NAMES)
    one = np.linspace(5.0, 13.0, len(names))
    two = np.linspace(0.2, 2.0, len(names))
    two[1] = np.nan
    fig = figures.parameter_errors(names, {"one-stage": one, "two-stage": two}, threshold=2.0)
    ax = fig.axes[0]
    assert [lbl.get_text() for lbl in ax.get_xticklabels()] == names
    heights = [patch.get_height() for patch in ax.patches]
    np.testing.assert_allclose(heights[:len(names)], one)
    assert heights[len(names) + 1] == 0.0  # NaN → no bar
    _assert_png(figures.save(fig, tmp_path / "err.png"))
    with pytest.raises(DataError):
        figures.parameter_errors(names, {"bad": [1.0, 2.0]})


# ----------------------------------------------------------------------------------------- tables


def test_pct_error():
    assert pct_error(0.0112, 0.0124) == pytest.approx(10.714285714)
    assert pct_error(15_000, 15_300) == pytest.approx(2.0)
    assert pct_error(-2.0, -1.0) == pytest.approx(50.0)
    assert np.isnan(pct_error(0.0, 1.0)) and np.isnan(pct_error(1.0, np.nan))


def test_param_table_like_table_1():
    assigned = to_dict(ASSIGNED)
    one = {"B_m": 0.0124, "D": 16_400.0, "K_t": 0.5743}
    two = [0.01137, 15_300.0, 0.5031]
    text = param_table(["B_m", "D", "K_t"], {"one-stage": one, "two-stage": two}, assigned)
    lines = text.splitlines()
    assert lines[0].split() == ["parameter", "unit", "assigned", "(A)", "one-stage", "%", "error", "(one-stage)",
                                "two-stage", "%", "error", "(two-stage)"]
    b_m = lines[2].split()
    assert b_m == ["B_m", "N·m·s/rad", "0.0112", "0.0124", "10.71%", "0.01137", "1.52%"]
    assert lines[3].split()[-3:] == ["9.33%", "15300", "2.00%"]
    assert lines[4].split()[-1] == "1.10%"

    header, rows = param_rows(["B_m"], {"B_m": 0.0124}, {"B_m": 0.0112})
    assert header == ["parameter", "unit", "assigned (A)", "identified", "% error (identified)"]
    assert rows[0][-1] == pytest.approx(10.714285714)


def test_param_table_without_assigned_and_missing_values():
    text = param_table(["B_m", "mu"], {"x": {"B_m": 0.5}}, None, units={"mu": "1"})
    lines = text.splitlines()
    assert lines[0].split() == ["parameter", "unit", "x"]
    assert lines[3].split() == ["mu", "1", "—"]
    with pytest.raises(ConfigError):
        param_table(["B_m", "D"], {"x": [1.0]}, None)
    md = param_table(["B_m"], {"B_m": 0.0124}, {"B_m": 0.0112}, style="markdown")
    assert md.splitlines()[2] == "| B_m | N·m·s/rad | 0.0112 | 0.0124 | 10.71% |"


def test_markdown_and_text_tables():
    md = markdown_table(["name", "value"], [["a|b", 1.5], ["c", float("nan")], ["d", None]])
    lines = md.splitlines()
    assert lines[0] == "| name | value |"
    assert lines[1] == "| --- | ---: |"
    assert lines[2] == r"| a\|b | 1.5 |"
    assert lines[3] == "| c | — |" and lines[4] == "| d | — |"
    txt = text_table(["k", "v"], [["long name", 1], ["x", 22]])
    assert txt.splitlines()[2] == "long name   1"
    with pytest.raises(ConfigError):
        markdown_table(["a", "b"], [[1]])


def test_write_csv_table_roundtrip(tmp_path):
    path = tmp_path / "out" / "table.csv"
    write_csv_table(path, ["name", "value", "note"], [["B_m", 0.1 + 0.2, None], ["D", float("nan"), "x,y"]])
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    assert rows == [["name", "value", "note"], ["B_m", repr(0.1 + 0.2), ""], ["D", "", "x,y"]]
    assert [f for f in os.listdir(path.parent) if f.endswith(".tmp")] == []
    with pytest.raises(ConfigError):
        write_csv_table(path, ["a", "b"], [[1, 2, 3]])
    with open(path, newline="", encoding="utf-8") as fh:  # the old file survives a failed write
        assert list(csv.reader(fh)) == rows
    assert [f for f in os.listdir(path.parent) if f.endswith(".tmp")] == []


# --------------------------------------------------------------------------------------- progress


def test_progress_compact_lines_when_not_a_tty():
    lines: list[str] = []
    stream = io.StringIO()
    with progress(25, "stage-1", every=10, stream=stream, sink=lines.append) as bar:
        for gen in range(25):
            bar.update(1000.0 + gen, extra={"sigma": 0.125})
    assert not bar.bar_shown
    assert [line.split()[2] for line in lines] == ["10/25", "20/25", "25/25"]
    assert "best 1024" in lines[-1] and "sigma=0.125" in lines[-1]
    assert stream.getvalue() == ""


def test_progress_final_line_on_early_close_and_silence():
    lines: list[str] = []
    with progress(100, "s", every=10, stream=io.StringIO(), sink=lines.append) as bar:
        for gen in range(13):
            bar.update(float(gen))
    assert [line.split()[2] for line in lines] == ["10/100", "13/100"]
    quiet: list[str] = []
    with progress(10, "q", every=0, sink=quiet.append) as bar:
        bar.update(1.0)
    assert quiet == []


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_on_a_tty():
    stream = _Tty()
    lines: list[str] = []
    with progress(5, "ga", stream=stream, sink=lines.append) as bar:
        for gen in range(5):
            bar.update(2.5 * gen)
    assert bar.bar_shown and lines == []
    out = stream.getvalue()
    assert "ga" in out and "5/5" in out and "best=10" in out
    stream2 = _Tty()
    with progress(5, "off", stream=stream2, enabled=False, every=5, sink=lines.append) as bar:
        for gen in range(5):
            bar.update(1.0)
    assert stream2.getvalue() == "" and len(lines) == 1


def test_progress_rejects_bad_arguments():
    with pytest.raises(ConfigError):
        progress(-1, "x")
