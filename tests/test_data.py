"""Measured-data files: every bad input is a one-line DataError; good files round-trip exactly."""
from __future__ import annotations

import glob
import os
from pathlib import Path

import numpy as np
import pytest

from toggle_id.data import check_two_stage, read_csv, validate_record, write_csv
from toggle_id.errors import DataError
from toggle_id.record import X_B0, Record

REFERENCE = sorted(glob.glob(str(Path(__file__).resolve().parent / "reference" / "*.csv")))
N = 60


def good_arrays(n: int = N) -> dict[str, np.ndarray]:
    """A small plausible record at 1 kHz: x_B from 0.020 m past the clamp at 0.056 m."""
    t = np.arange(n) / 1000.0
    x_B = X_B0 + 0.045 * (t / t[-1]) ** 2
    return {"t": t, "v_in": 0.05 + 0.01 * np.sin(40 * t), "x_B": x_B, "i_q": 2.0 * np.cos(30 * t)}


def good_lines(n: int = N, extra: bool = True) -> list[str]:
    """CSV lines (header first) of :func:`good_arrays`, with an ignored extra column."""
    a = good_arrays(n)
    head = "t,v_in,x_B,i_q" + (",theta1" if extra else "")
    rows = [f"{a['t'][i]:.17g},{a['v_in'][i]:.17g},{a['x_B'][i]:.17g},{a['i_q'][i]:.17g}" + (",1.4" if extra else "")
            for i in range(n)]
    return [head] + rows


def edit(lines: list[str], row: int, col: int, value: str) -> list[str]:
    """Replace field ``col`` of data row ``row`` (0-based, header excluded)."""
    out = list(lines)
    fields = out[row + 1].split(",")
    fields[col] = value
    out[row + 1] = ",".join(fields)
    return out


def scaled_x_B(lines: list[str], factor: float) -> list[str]:
    out = [lines[0]]
    for line in lines[1:]:
        f = line.split(",")
        f[2] = repr(float(f[2]) * factor)
        out.append(",".join(f))
    return out


def shifted_x_B(lines: list[str], offset: float) -> list[str]:
    out = [lines[0]]
    for line in lines[1:]:
        f = line.split(",")
        f[2] = repr(float(f[2]) + offset)
        out.append(",".join(f))
    return out


BAD_FILES = {
    # name: (text of the file, or bytes, expected fragment of the message)
    "non-numeric": ("\n".join(edit(good_lines(), 4, 2, "0.02x")), "malformed row at line 6"),
    "empty value": ("\n".join(edit(good_lines(), 4, 1, "")), "empty value"),
    "ragged": ("\n".join(good_lines()[:5] + ["0.004,0.05"] + good_lines()[6:]), "2 fields"),
    "empty file": ("", "is empty"),
    "blank lines only": ("\n\n  \n", "is empty"),
    "header only": ("t,v_in,x_B\n", "no data rows"),
    "no header": ("\n".join(good_lines()[1:]), "no header row"),
    "semicolons": ("\n".join(line.replace(",", ";") for line in good_lines()), "not comma-separated"),
    "missing column": ("\n".join(",".join(f for k, f in enumerate(line.split(",")) if k != 1)
                                 for line in good_lines()), "missing required column 'v_in'"),
    "misspelt column": ("\n".join(["t,v_in,xB,i_q,theta1"] + good_lines()[1:]), "column 'xB' — did you mean 'x_B'?"),
    "wrong case": ("\n".join(["t,V_in,x_B,i_q,theta1"] + good_lines()[1:]), "did you mean 'v_in'?"),
    "duplicate column": ("\n".join(["t,v_in,x_B,x_B,theta1"] + good_lines()[1:]), "'x_B' appears 2 times"),
    "NaN": ("\n".join(edit(good_lines(), 5, 2, "nan")), "NaN in column 'x_B' at line 7"),
    "Inf": ("\n".join(edit(good_lines(), 9, 1, "-inf")), "Inf in column 'v_in' at line 11"),
    "NaN in i_q": ("\n".join(edit(good_lines(), 3, 3, "NaN")), "NaN in column 'i_q' at line 5"),
    "duplicated time": ("\n".join(edit(good_lines(), 7, 0, "0.006")), "duplicated time stamp at line 9"),
    "unsorted time": ("\n".join(good_lines()[:8] + [good_lines()[9], good_lines()[8]] + good_lines()[10:]),
                      "time not sorted"),
    "non-uniform time": ("\n".join(edit(good_lines(), 20, 0, "0.0201")), "non-uniform sampling"),
    "missing sample": ("\n".join(good_lines()[:20] + good_lines()[21:]), "non-uniform sampling"),
    "x_B in mm": ("\n".join(scaled_x_B(good_lines(), 1000.0)), "x_B looks like millimetres (max 65"),
    "x_B in cm": ("\n".join(scaled_x_B(good_lines(), 100.0)), "centimetres or millimetres"),
    "x_B a displacement": ("\n".join(shifted_x_B(good_lines(), -X_B0)), "not a displacement"),
    "x_B beyond stroke": ("\n".join(shifted_x_B(good_lines(), 0.1)), "beyond the toggle stroke"),
    "x_B far from x_B0": ("\n".join(shifted_x_B(good_lines(), 0.01)), "from the initial position"),
    "v_in implausible": ("\n".join(edit(good_lines(), 2, 1, "5000")), "v_in implausible"),
    "too few samples": ("\n".join(good_lines(5)), "only 5 samples"),
    "not utf-8": (b"t,v_in,x_B\n\xff\xfe\x00\x01", "not a UTF-8"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_file_raises_one_line_data_error(tmp_path: Path, case: str) -> None:
    content, fragment = BAD_FILES[case]
    path = tmp_path / "meas.csv"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content + ("\n" if content.strip() else ""))
    with pytest.raises(DataError) as info:
        read_csv(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert str(path) in msg
    assert fragment in msg, msg


def test_good_lines_are_good(tmp_path: Path) -> None:
    """The base of every bad case reads fine, so each failure above is due to its one change."""
    path = tmp_path / "meas.csv"
    path.write_text("\n".join(good_lines()) + "\n")
    rec = read_csv(path, expect_rate_hz=1000.0)
    a = good_arrays()
    for name in ("t", "v_in", "x_B", "i_q"):
        np.testing.assert_array_equal(getattr(rec, name), a[name])
    assert rec.name == "meas" and rec.x_B0 == X_B0
    assert rec.meta["path"] == str(path) and rec.meta["ignored_columns"] == ["theta1"]


def test_nonexistent_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.csv"
    with pytest.raises(DataError, match="not found") as info:
        read_csv(path)
    assert str(path) in str(info.value)


def test_directory_is_not_a_file(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="is a directory"):
        read_csv(tmp_path)


def test_missing_x_B_allowed_for_input_only_file(tmp_path: Path) -> None:
    path = tmp_path / "input.csv"
    path.write_text("\n".join(",".join(line.split(",")[:2]) for line in good_lines()) + "\n")
    with pytest.raises(DataError, match="missing required column 'x_B'"):
        read_csv(path)
    rec = read_csv(path, require_x_B=False)
    assert rec.x_B is None and rec.i_q is None and rec.n == N


def test_whitespace_bom_blank_lines_and_crlf_are_tolerated(tmp_path: Path) -> None:
    lines = good_lines(extra=False)
    text = "\ufeff" + " t , v_in ,x_B,i_q\r\n" + "\r\n".join(lines[1:]) + "\r\n\r\n"
    path = tmp_path / "win.csv"
    path.write_bytes(text.encode("utf-8"))
    rec = read_csv(path)
    np.testing.assert_array_equal(rec.x_B, good_arrays()["x_B"])


def test_expected_rate_and_x_B0(tmp_path: Path) -> None:
    path = tmp_path / "meas.csv"
    path.write_text("\n".join(good_lines()) + "\n")
    with pytest.raises(DataError, match="sampling rate 1000 Hz, expected 2000 Hz"):
        read_csv(path, expect_rate_hz=2000.0)
    shifted = tmp_path / "shifted.csv"
    shifted.write_text("\n".join(shifted_x_B(good_lines(), 0.01)) + "\n")
    rec = read_csv(shifted, x_B0=0.030)
    assert rec.x_B0 == 0.030


def test_rounded_time_text_passes_but_jitter_fails(tmp_path: Path) -> None:
    """Time stamps printed with few digits are uniform after parsing; a 1e-5 relative jitter is not."""
    a = good_arrays(2000)
    path = tmp_path / "short.csv"
    rows = [f"{a['t'][i]:.3f},{a['v_in'][i]},{a['x_B'][i]}" for i in range(2000)]
    path.write_text("t,v_in,x_B\n" + "\n".join(rows) + "\n")
    assert read_csv(path).n == 2000
    rows[1000] = f"{float(a['t'][1000]) + 1e-8!r},{a['v_in'][1000]},{a['x_B'][1000]}"
    path.write_text("t,v_in,x_B\n" + "\n".join(rows) + "\n")
    with pytest.raises(DataError, match="non-uniform sampling.*line 1002"):
        read_csv(path)
    assert read_csv(path, rtol_dt=1e-4).n == 2000


@pytest.mark.parametrize("with_i_q", [True, False])
def test_write_read_round_trip_is_exact(tmp_path: Path, with_i_q: bool) -> None:
    rng = np.random.default_rng(1)
    a = good_arrays(500)
    rec = Record(t=a["t"], v_in=a["v_in"] + rng.normal(0, 1e-3, 500), x_B=a["x_B"] + rng.normal(0, 1e-6, 500),
                 i_q=rng.normal(0, 3, 500) if with_i_q else None, name="x")
    path = write_csv(rec, tmp_path / "rt.csv")
    assert path.read_text().splitlines()[0] == ("t,v_in,x_B,i_q" if with_i_q else "t,v_in,x_B")
    back = read_csv(path)
    for name in ("t", "v_in", "x_B", "i_q"):
        if getattr(rec, name) is None:
            assert getattr(back, name) is None
        else:
            assert np.array_equal(getattr(back, name), getattr(rec, name)), name
    assert back.name == "rt"
    assert sorted(os.listdir(tmp_path)) == ["rt.csv"]  # no temporary file left behind


def test_write_refuses_invalid_record_and_keeps_old_file(tmp_path: Path) -> None:
    a = good_arrays()
    path = write_csv(Record(t=a["t"], v_in=a["v_in"], x_B=a["x_B"]), tmp_path / "r.csv")
    before = path.read_bytes()
    bad_x = a["x_B"].copy()
    bad_x[3] = np.nan
    with pytest.raises(DataError, match="NaN in column 'x_B' at sample 3"):
        write_csv(Record(t=a["t"], v_in=a["v_in"], x_B=bad_x, name="bad"), path)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["r.csv"]


def test_validate_record_in_memory() -> None:
    rec = Record.from_sweep("simulation")
    assert validate_record(rec, require_x_B=False, expect_rate_hz=1000.0) is rec
    with pytest.raises(DataError, match="record 'record': no measured x_B"):
        validate_record(rec)
    a = good_arrays()
    t = a["t"].copy()
    t[10] = t[9]
    with pytest.raises(DataError, match=r"duplicated time stamp at sample 10 \(t = 0.009 s\)"):
        validate_record(Record(t=t, v_in=a["v_in"], x_B=a["x_B"]))
    with pytest.raises(DataError, match="x_B never moves"):
        validate_record(Record(t=a["t"], v_in=a["v_in"], x_B=np.full(N, X_B0)))
    with pytest.raises(DataError, match="i_q implausible"):
        validate_record(Record(t=a["t"], v_in=a["v_in"], x_B=a["x_B"], i_q=np.full(N, 1e6)))


def test_check_two_stage(tmp_path: Path) -> None:
    a = good_arrays()
    rec = Record(t=a["t"], v_in=a["v_in"], x_B=a["x_B"])
    k = check_two_stage(rec)
    assert rec.x_B[k] >= 0.056 > rec.x_B[k - 1]
    short = Record(t=a["t"][:40], v_in=a["v_in"][:40], x_B=a["x_B"][:40], name="short")
    pattern = r"too short to contain the clamping instant \(max x_B = .* m < x_B\^L = 0.056 m\)"
    with pytest.raises(DataError, match=pattern) as info:
        check_two_stage(short)
    assert "\n" not in str(info.value) and "short" in str(info.value)
    with pytest.raises(DataError, match="starts at or beyond the clamping position"):
        check_two_stage(Record(t=a["t"], v_in=a["v_in"], x_B=a["x_B"] + 0.04))
    with pytest.raises(DataError, match="no measured x_B"):
        check_two_stage(Record.from_sweep("simulation"))
    # a file that is valid but too short for the two-stage fit
    path = tmp_path / "short.csv"
    path.write_text("\n".join(good_lines()[:41]) + "\n")
    with pytest.raises(DataError, match="too short"):
        check_two_stage(read_csv(path))


def test_the_reference_trajectories_ship_with_the_repository():
    assert [Path(p).stem for p in REFERENCE] == ["assigned_exp_sweep", "assigned_sim_sweep", "table1_one_stage_sim_sweep"]


@pytest.mark.parametrize("path", REFERENCE, ids=lambda p: Path(p).stem)
def test_reference_files_read(path: str) -> None:
    rec = read_csv(path, expect_rate_hz=1000.0)
    assert rec.n == 5001 and rec.t[0] == 0.0 and rec.t[-1] == 5.0
    assert rec.i_q is not None and rec.meta["ignored_columns"] == ["theta1"]
    assert rec.x_B0 == X_B0 and rec.x_B[0] == X_B0 and rec.name == Path(path).stem
    k = check_two_stage(rec)
    assert 0 < k < rec.n and rec.x_B[k] >= 0.056 > rec.x_B[k - 1]


def test_cycling_command_file_round_trips_exactly(tmp_path: Path) -> None:
    """An input-only record of the cycling command (toggle_id.record.CYCLING) written and read back: the samples
    that define the command come back bit for bit, so a simulation from the file equals the simulated record's."""
    from toggle_id.record import CYCLING

    rec = Record.from_cycling(duration=5.0, name="cyc")
    assert rec.sweep is None and rec.meta["command"] == CYCLING.to_dict()
    back = read_csv(write_csv(rec, tmp_path / "cyc.csv"), require_x_B=False, expect_rate_hz=1000.0)
    assert np.array_equal(back.v_in, rec.v_in) and np.array_equal(back.t, rec.t) and back.x_B is None
    assert np.array_equal(CYCLING(rec.t), rec.v_in)
