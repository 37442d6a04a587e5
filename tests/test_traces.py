"""Tests of reading, validating, mapping and writing rig traces (ewb_ident.data.trace)."""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.io

from ewb_ident.data import writers
from ewb_ident.data.readers import from_arrays, read_trace
from ewb_ident.data.trace import COLUMNS, Trace, TraceError
from ewb_ident.data.validation import check_stages, validate
from ewb_ident.data.writers import write_trace

FS_HZ = 200.0
N = 600  # 3 s at 200 Hz


def signals(n: int = N, fs: float = FS_HZ) -> dict[str, np.ndarray]:
    """A smooth apply: theta ramps 0 -> 500 deg, the chain of the seed paper follows."""
    t = np.arange(n) / fs
    theta = 500.0 * t / t[-1]
    x = 3.8e-9 * theta**2 + 1.5e-6 * theta - 8.4e-4
    force = 3500.0 / (1.0 + np.abs((x - 9.57e-4) / 6.295e-4) ** 5.64)
    torque = 2 * 0.35 * force * 0.15
    voltage = np.select([t < 0.5, t < 2.0], [0.0, 12.0], default=-6.0)
    current = 0.2 * voltage + 0.01 * np.sin(2 * np.pi * t)
    disc = np.full(n, 20.0)
    return {
        "time_s": t,
        "voltage_V": voltage,
        "current_A": current,
        "theta_deg": theta,
        "x_m": x,
        "force_N": force,
        "torque_Nm": torque,
        "disc_speed_rad_s": disc,
    }


def frame(**kwargs: float) -> pd.DataFrame:
    return pd.DataFrame(signals(**kwargs))


def write_csv(
    folder: Path,
    df: pd.DataFrame,
    name: str = "trace",
    sidecar: dict | str | None = None,
) -> Path:
    path = folder / f"{name}.csv"
    df.to_csv(path, index=False)
    if sidecar is not None:
        text = sidecar if isinstance(sidecar, str) else json.dumps(sidecar)
        path.with_suffix(".json").write_text(text)
    return path


def set_cell(df: pd.DataFrame, row: int, column: str, value: object) -> pd.DataFrame:
    """Copy of ``df`` with data row ``row`` (1-based) of ``column`` set to ``value``."""
    out = df.astype(object)
    out.loc[row - 1, column] = value
    return out


# --------------------------------------------------------------------------- good input


def test_read_valid_csv(tmp_path: Path) -> None:
    path = write_csv(tmp_path, frame(), sidecar={"r_eff_m": 0.14, "rig": "B2"})
    trace = read_trace(path, stages=["motor", "gap", "force", "torque", "chain"])
    assert trace.name == "trace"
    assert trace.path == path
    assert trace.n == N
    assert trace.sample_rate_hz == pytest.approx(FS_HZ)
    assert trace.columns == tuple(COLUMNS)
    assert trace.r_eff_m == 0.14
    assert trace.sidecar["rig"] == "B2"  # unknown keys are kept
    for name, values in signals().items():
        assert trace[name].dtype == np.float64
        np.testing.assert_array_equal(trace[name], values)


def test_only_time_is_required_and_extra_columns_are_ignored(tmp_path: Path) -> None:
    df = frame()[["time_s", "theta_deg"]].assign(status="ok", temp_C=21.0)
    trace = read_trace(write_csv(tmp_path, df))
    assert set(trace.channels) == {"theta_deg"}
    assert trace.sidecar["_ignored_columns"] == ["status", "temp_C"]


def test_csv_round_trip_is_exact(tmp_path: Path) -> None:
    sidecar = {"r_eff_m": 0.15, "disc_mode": "drag", "note": "x"}
    first = read_trace(write_csv(tmp_path, frame().assign(extra=1.0), sidecar=sidecar))
    out = write_trace(first, tmp_path / "copy.csv")
    second = read_trace(out)
    assert second.columns == first.columns
    for name in first.columns:
        np.testing.assert_array_equal(second[name], first[name])
    assert json.loads(out.with_suffix(".json").read_text()) == sidecar  # "_" keys dropped
    again = write_trace(second, tmp_path / "again.csv")
    assert again.read_text() == out.read_text()
    assert out.read_text().splitlines()[0] == ",".join(COLUMNS)
    assert not [p for p in tmp_path.iterdir() if p.suffix == ".tmp"]


def test_parquet_round_trip_is_exact(tmp_path: Path) -> None:
    first = read_trace(write_csv(tmp_path, frame(), sidecar={"hardware": "rev C"}))
    out = write_trace(first, tmp_path / "copy.parquet")
    second = read_trace(out)
    assert second.name == "copy"
    for name in first.columns:
        np.testing.assert_array_equal(second[name], first[name])
    assert second.sidecar == {"hardware": "rev C"}


def test_write_without_sidecar_leaves_none(tmp_path: Path) -> None:
    trace = from_arrays("synthetic", **signals())
    out = write_trace(trace, tmp_path / "syn.csv")
    assert not out.with_suffix(".json").exists()
    assert read_trace(out).n == N


def test_write_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    trace = from_arrays("synthetic", **signals())
    target = tmp_path / "syn.csv"
    target.write_text("old contents\n")

    def broken_replace(src: object, dst: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(writers.os, "replace", broken_replace)
    with pytest.raises(TraceError, match=r"syn\.csv: cannot write \(No space left on device\)"):
        write_trace(trace, target)
    assert target.read_text() == "old contents\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["syn.csv"]


def test_write_rejects_other_suffix(tmp_path: Path) -> None:
    trace = from_arrays("synthetic", **signals())
    with pytest.raises(TraceError, match=r"syn\.mat: cannot write '\.mat' files"):
        write_trace(trace, tmp_path / "syn.mat")
    with pytest.raises(TraceError, match=r"syn\.csv: cannot write \(No such file or directory\)"):
        write_trace(trace, tmp_path / "absent" / "syn.csv")


@pytest.mark.parametrize("layout", ["flat", "struct", "columns"])
def test_read_mat(tmp_path: Path, layout: str) -> None:
    data = signals()
    if layout == "flat":
        content = {k: v[:, None] for k, v in data.items()}  # (n, 1) vectors
    elif layout == "columns":
        content = {k: v[None, :] for k, v in data.items()} | {"fs": 200.0}
    else:
        content = {"rec": data}
    path = tmp_path / "rig.mat"
    scipy.io.savemat(path, content)
    trace = read_trace(path)
    assert trace.name == "rig"
    for name, values in data.items():
        np.testing.assert_array_equal(trace[name], values)
    if layout == "columns":
        assert trace.sidecar["_ignored_columns"] == ["fs"]


def test_mat_vectors_of_different_length(tmp_path: Path) -> None:
    data = signals()
    data["x_m"] = data["x_m"][:-1]
    scipy.io.savemat(tmp_path / "rig.mat", data)
    with pytest.raises(TraceError, match=r"rig\.mat: column 'x_m', row -: has 599 samples"):
        read_trace(tmp_path / "rig.mat")


def test_mat_matrix_is_refused(tmp_path: Path) -> None:
    data = signals()
    data["force_N"] = np.stack([data["force_N"], data["force_N"]], axis=1)
    scipy.io.savemat(tmp_path / "rig.mat", data)
    with pytest.raises(TraceError, match=r"column 'force_N', row -: has shape \(600, 2\)"):
        read_trace(tmp_path / "rig.mat")


MAPPING = {
    "t": {"column": "time_s", "unit": "ms"},
    "angle": {"column": "theta_deg", "unit": "rad"},
    "lvdt": {"column": "x_m", "unit": "mm"},
    "F": "force_N",
    "speed": {"column": "disc_speed_rad_s", "unit": "rpm"},
}


def mapped_frame() -> pd.DataFrame:
    s = signals()
    return pd.DataFrame(
        {
            "t": s["time_s"] * 1e3,
            "angle": np.deg2rad(s["theta_deg"]),
            "lvdt": s["x_m"] * 1e3,
            "F": s["force_N"],
            "speed": s["disc_speed_rad_s"] * 60 / (2 * np.pi),
            "comment": "free text",
        }
    )


def check_mapped(trace: Trace) -> None:
    s = signals()
    assert set(trace.channels) == {"theta_deg", "x_m", "force_N", "disc_speed_rad_s"}
    for name in trace.columns:
        np.testing.assert_allclose(trace[name], s[name], rtol=1e-12, atol=1e-15)
    assert trace.sidecar["_mapped"]["theta_deg"] == {"source": "angle", "unit": "rad"}
    assert trace.sidecar["_ignored_columns"] == ["comment"]


def test_mapping_dict(tmp_path: Path) -> None:
    check_mapped(read_trace(write_csv(tmp_path, mapped_frame()), mapping=MAPPING))


def test_mapping_json_file(tmp_path: Path) -> None:
    mapping = tmp_path / "rig_b.json"
    mapping.write_text(json.dumps(MAPPING))
    check_mapped(read_trace(write_csv(tmp_path, mapped_frame()), mapping=mapping))


def test_mapping_toml_file(tmp_path: Path) -> None:
    mapping = tmp_path / "rig_b.toml"
    mapping.write_text(
        'F = "force_N"\n'
        't = { column = "time_s", unit = "ms" }\n'
        "[angle]\ncolumn = 'theta_deg'\nunit = 'rad'\n"
        "[lvdt]\ncolumn = 'x_m'\nunit = 'mm'\n"
        "[speed]\ncolumn = 'disc_speed_rad_s'\nunit = 'rpm'\n"
    )
    check_mapped(read_trace(write_csv(tmp_path, mapped_frame()), mapping=str(mapping)))


@pytest.mark.parametrize(
    ("unit", "scale"),
    [("Nm", 1.0), ("N.m", 1.0), ("N*m", 1.0), ("kN", None)],
)
def test_mapping_unit_aliases(tmp_path: Path, unit: str, scale: float | None) -> None:
    df = frame()[["time_s"]].assign(M=signals()["torque_Nm"])
    if scale is None:
        with pytest.raises(
            TraceError,
            match=r"mapping: entry 'M': unit 'kN' cannot be converted to 'N\*m' \(column "
            r"'torque_Nm'\); units allowed for torque_Nm are N\*m, Nm, N\.m",
        ):
            read_trace(
                write_csv(tmp_path, df), mapping={"M": {"column": "torque_Nm", "unit": unit}}
            )
        return
    trace = read_trace(
        write_csv(tmp_path, df), mapping={"M": {"column": "torque_Nm", "unit": unit}}
    )
    np.testing.assert_array_equal(trace["torque_Nm"], signals()["torque_Nm"])


def test_mapping_missing_source_is_recorded(tmp_path: Path) -> None:
    df = frame().drop(columns=["x_m"])
    path = write_csv(tmp_path, df)
    trace = read_trace(path, mapping={"LVDT": "x_m"})
    assert trace.sidecar["_unmatched_mapping"] == {"LVDT": "x_m"}
    with pytest.raises(
        TraceError,
        match=r"column 'x_m', row -: missing, but stage 'gap' \(theta_deg -> x_m\) needs it "
        r"\(the mapping's source column 'LVDT' is not in the table\)",
    ):
        read_trace(path, mapping={"LVDT": "x_m"}, stages=["gap"])


def test_nan_interpolate(tmp_path: Path) -> None:
    df = frame().astype(object)
    df.loc[9, "theta_deg"] = ""  # row 10
    df.loc[99:103, "theta_deg"] = ""  # rows 100-104: a gap of 5
    df.loc[49, "x_m"] = "nan"
    path = write_csv(tmp_path, df)
    trace = read_trace(path, nan_policy="interpolate")
    assert trace.sidecar["_filled"] == {"theta_deg": 6, "x_m": 1}
    s = signals()
    np.testing.assert_allclose(trace["theta_deg"], s["theta_deg"], rtol=1e-12)  # linear
    x_fill = 0.5 * (s["x_m"][48] + s["x_m"][50])
    assert trace["x_m"][49] == pytest.approx(x_fill, rel=1e-15)
    with pytest.raises(TraceError, match=r"column 'theta_deg', row 10: empty cell"):
        read_trace(path)


def test_check_units_can_be_turned_off(tmp_path: Path) -> None:
    path = write_csv(tmp_path, frame().assign(x_m=signals()["x_m"] * 1e3))
    trace = read_trace(path, check_units=False)
    assert trace["x_m"].max() > 0.01


def test_declared_units_are_still_checked_after_conversion(tmp_path: Path) -> None:
    """Issue 11.7: radians declared 'deg' (or mm declared 'm') are caught after the
    declared conversion, with a message naming the declaration; check_units=False is
    the one override."""
    df = frame().assign(theta_deg=np.linspace(0.0, 10.0, N))  # small: radians?
    path = write_csv(tmp_path, df)
    with pytest.raises(TraceError, match="looks like radians"):
        read_trace(path)
    declared = {"theta_deg": {"column": "theta_deg", "unit": "deg"}}
    with pytest.raises(TraceError, match="the mapping declares 'theta_deg' in 'deg'"):
        read_trace(path, mapping=declared)
    trace = read_trace(path, mapping=declared, check_units=False)
    np.testing.assert_array_equal(trace["theta_deg"], df["theta_deg"].to_numpy())
    mm = write_csv(tmp_path, frame().assign(x_m=signals()["x_m"] * 1e3), name="mm")
    with pytest.raises(TraceError, match="the mapping declares 'x_m' in 'm'"):
        read_trace(mm, mapping={"x_m": {"column": "x_m", "unit": "m"}})


def test_from_arrays_and_validate() -> None:
    trace = from_arrays("syn", sidecar={"disc_mode": "drag"}, **signals())
    assert trace.columns == tuple(COLUMNS)
    assert trace.path is None and trace.label == "syn"
    validate(trace, stages=["chain"])
    assert check_stages(trace, ["gap", "gap", "force"]) == ("gap", "force")
    with pytest.raises(TraceError, match=r"syn: column 'x_m', row -: has shape \(3,\)"):
        from_arrays("syn", time_s=[0.0, 1.0], x_m=[1.0, 2.0, 3.0])
    with pytest.raises(TraceError, match=r"syn: column 'x_mm', row -: not a trace channel"):
        from_arrays("syn", time_s=[0.0, 1.0], x_mm=[1.0, 2.0])
    short = from_arrays("syn", time_s=np.arange(10) / FS_HZ)
    with pytest.raises(TraceError, match=r"syn: column 'time_s', row -: too short: 10 samples"):
        validate(short)


# --------------------------------------------------------------------------- bad input

Maker = Callable[[Path], Path]


def csv_text(name: str, text: str) -> Maker:
    def make(folder: Path) -> Path:
        path = folder / name
        path.write_text(text)
        return path

    return make


def csv_of(df: pd.DataFrame, sidecar: dict | str | None = None) -> Maker:
    return lambda folder: write_csv(folder, df, sidecar=sidecar)


def ragged(folder: Path) -> Path:
    path = write_csv(folder, frame())
    lines = path.read_text().splitlines()
    lines[12] = lines[12] + ",7"  # data row 12
    path.write_text("\n".join(lines) + "\n")
    return path


def swapped(folder: Path) -> Path:
    df = frame()
    df.iloc[[19, 20]] = df.iloc[[20, 19]].to_numpy()  # rows 20 and 21
    return write_csv(folder, df)


def scaled(column: str, factor: float) -> pd.DataFrame:
    return frame().assign(**{column: signals()[column] * factor})


def gap(start: int, length: int) -> pd.DataFrame:
    df = frame().astype(object)
    df.loc[start - 1 : start + length - 2, "force_N"] = ""
    return df


FLAT_FORCE = frame().assign(force_N=100.0 + signals()["force_N"] * 0.01)
HEADER = ",".join(COLUMNS)

# (id, maker, read_trace keyword arguments, expected message pattern)
BAD_CASES: list[tuple[str, Maker, dict, str]] = [
    ("suffix", csv_text("trace.txt", "time_s\n0\n"), {}, r"trace\.txt: unknown file type '\.txt'"),
    ("no-file", lambda folder: folder / "absent.csv", {}, r"absent\.csv: no such file"),
    ("empty", csv_text("trace.csv", ""), {}, r"trace\.csv: the file is empty"),
    ("header-only", csv_text("trace.csv", HEADER + "\n"), {}, r"trace\.csv: .*no data rows"),
    (
        "no-header",
        csv_text("trace.csv", "0.0,1.0\n0.005,1.0\n"),
        {},
        r"trace\.csv: no header row: the first row '0\.0,1\.0' holds numbers; add a header",
    ),
    (
        "duplicate",
        csv_text("trace.csv", "time_s,x_m,force_N,x_m\n0,0,0,0\n"),
        {},
        r"trace\.csv: column 'x_m', row -: the header names this column twice "
        r"\(columns 2 and 4\); rename",
    ),
    ("ragged", ragged, {}, r"trace\.csv: row 12: 9 fields .*the header has 8; every row"),
    (
        "non-numeric",
        csv_of(set_cell(frame(), 7, "force_N", "12,5 kN")),
        {},
        r"trace\.csv: column 'force_N', row 7: cell '12,5 kN' is not a number; fix the cell",
    ),
    (
        "non-numeric-mapped",
        csv_of(set_cell(frame().rename(columns={"x_m": "LVDT"}), 3, "LVDT", "err")),
        {"mapping": {"LVDT": "x_m"}},
        r"column 'LVDT' \(mapped to 'x_m'\), row 3: cell 'err' is not a number",
    ),
    (
        "no-time",
        csv_of(frame().drop(columns=["time_s"])),
        {},
        r"trace\.csv: column 'time_s', row -: missing \(columns found: voltage_V, .*\); add",
    ),
    (
        "nan-raise",
        csv_of(set_cell(set_cell(frame(), 40, "theta_deg", ""), 10, "x_m", "")),
        {},
        r"trace\.csv: column 'x_m', row 10: empty cell \(missing value\); fill the gap in the "
        r"log, or pass nan_policy=\"interpolate\" \(CLI --fill-gaps\)",
    ),
    (
        "nan-first-column-wins",
        csv_of(set_cell(set_cell(frame(), 10, "force_N", ""), 10, "theta_deg", "")),
        {},
        r"column 'theta_deg', row 10: empty cell",
    ),
    (
        "inf",
        csv_of(set_cell(frame(), 5, "theta_deg", "inf")),
        {},
        r"trace\.csv: column 'theta_deg', row 5: value inf is infinite; fix the logger export",
    ),
    (
        "inf-interpolate",
        csv_of(set_cell(set_cell(frame(), 3, "x_m", ""), 5, "theta_deg", "-inf")),
        {"nan_policy": "interpolate"},
        r"column 'theta_deg', row 5: value -inf is infinite",
    ),
    (
        "gap-too-long",
        csv_of(gap(100, 6)),
        {"nan_policy": "interpolate"},
        r"column 'force_N', row 100: a gap of 6 missing values \(rows 100 to 105\) is longer "
        r"than 5 samples; fill it",
    ),
    (
        "gap-at-start",
        csv_of(gap(1, 2)),
        {"nan_policy": "interpolate"},
        r"column 'force_N', row 1: 2 missing value\(s\) \(rows 1 to 2\) at the start of the "
        r"recording cannot be interpolated; trim",
    ),
    (
        "gap-at-end",
        csv_of(gap(N, 1)),
        {"nan_policy": "interpolate"},
        rf"column 'force_N', row {N}: 1 missing value\(s\) \(row {N}\) at the end",
    ),
    (
        "time-decreasing",
        swapped,
        {},
        r"trace\.csv: column 'time_s', row 21: time goes from 0\.1 s \(row 20\) to 0\.095 s: "
        r"not strictly increasing; rows may not be reordered",
    ),
    (
        "time-not-uniform",
        csv_of(frame().drop(index=30).reset_index(drop=True)),
        {},
        r"column 'time_s', row 31: interval 0\.01 s from row 30 to row 31 deviates from the "
        r"median interval 0\.005 s by 100 % \(> 1 %\): sampling is not uniform; export",
    ),
    (
        "rate-too-high",
        csv_of(frame(n=3000, fs=2000.0)),
        {},
        r"column 'time_s', row -: sample rate 2000 Hz .* outside 100 Hz to 1 kHz; resample",
    ),
    (
        "rate-too-low",
        csv_of(frame(n=100, fs=50.0)),
        {},
        r"column 'time_s', row -: sample rate 50 Hz",
    ),
    (
        "too-few-samples",
        csv_of(frame(n=40, fs=100.0)),
        {},
        r"column 'time_s', row -: too short: 40 samples over 0\.39 s; record at least 50",
    ),
    (
        "too-brief",
        csv_of(frame(n=60, fs=1000.0)),
        {},
        r"column 'time_s', row -: too short: 60 samples over 0\.059 s",
    ),
    (
        "sidecar-json",
        csv_of(frame(), sidecar='{"r_eff_m": 0.15,}'),
        {},
        r"trace\.json: invalid JSON at line 1, column 18: .*; fix the sidecar",
    ),
    (
        "sidecar-not-object",
        csv_of(frame(), sidecar="[0.15]"),
        {},
        r"trace\.json: the sidecar holds a JSON list, not an object",
    ),
    (
        "sample-rate",
        csv_of(frame(), sidecar={"sample_rate_hz": 250}),
        {},
        r"trace\.json: key 'sample_rate_hz': 250 Hz disagrees with time_s \(200 Hz",
    ),
    (
        "r-eff-mm",
        csv_of(frame(), sidecar={"r_eff_m": 150}),
        {},
        r"trace\.json: key 'r_eff_m': 150 is not a number from 0\.02 to 0\.5 m; give",
    ),
    (
        "r-eff-text",
        csv_of(frame(), sidecar={"r_eff_m": "0.15"}),
        {},
        r"key 'r_eff_m': '0\.15' is not a number",
    ),
    (
        "disc-mode",
        csv_of(frame(), sidecar={"disc_mode": "spin"}),
        {},
        r"trace\.json: key 'disc_mode': 'spin' is not 'drag' or 'coast'; use 'drag'",
    ),
    (
        "coast-inertia",
        csv_of(frame(), sidecar={"disc_mode": "coast"}),
        {},
        r"trace\.json: key 'disc_inertia_kg_m2': disc_mode 'coast' needs disc_inertia_kg_m2",
    ),
    (
        "x-mm",
        csv_of(scaled("x_m", 1e3)),
        {},
        r"trace\.csv: column 'x_m', row 600: the piston's \|x\| reaches [\d.]+ m, outside the "
        r"plausible 1e-05 to 0\.01 m: looks like millimetres \('mm'\); map the column with its "
        r"unit \(mapping=\{'x_m': \{'column': "
        r"'x_m', 'unit': 'mm'\}\}\).*check_units=False \(CLI --no-unit-check\)",
    ),
    (
        "theta-rad",
        csv_of(scaled("theta_deg", math.pi / 180)),
        {},
        r"column 'theta_deg', row -: the pinion's \|theta\| stays below 8\.72665 deg, outside "
        r"the plausible 12\.5664 to 40000 deg: looks like radians \('rad'\); map the column "
        r"with its unit .*'unit': 'rad'",
    ),
    (
        "theta-rad-mapped",
        csv_of(scaled("theta_deg", math.pi / 180).rename(columns={"theta_deg": "pot"})),
        {"mapping": {"pot": "theta_deg"}},
        r"column 'pot' \(mapped to 'theta_deg'\), row -: .*looks like radians \('rad'\); "
        r".*\{'pot': ",
    ),
    (
        "force-huge",
        csv_of(scaled("force_N", 1e3)),
        {},
        r"column 'force_N', row \d+: the clamping force's peak \|F\| is 3\.49991e\+06 N, "
        r"outside the plausible 0 "
        r"to 50000 N; check the sensor's scaling",
    ),
    (
        "voltage-mV",
        csv_of(scaled("voltage_V", 1e3)),
        {},
        r"column 'voltage_V', row 101: .*millivolts",
    ),
    (
        "current-mA",
        csv_of(scaled("current_A", 1e3)),
        {},
        r"column 'current_A', row \d+: .*milliamp",
    ),
    (
        "force-flat",
        csv_of(FLAT_FORCE),
        {"stages": ["torque"]},
        r"column 'force_N', row -: force never rises above 134\.999 N \(range 34\.905 N < "
        r"200 N\): no clamping was reached, so the force stage cannot be fitted; record an "
        r"apply that clamps the brake",
    ),
    (
        "stage-missing-column",
        csv_of(frame().drop(columns=["x_m"])),
        {"stages": ["motor", "gap"]},
        r"trace\.csv: column 'x_m', row -: missing, but stage 'gap' \(theta_deg -> x_m\) "
        r"needs it \(the trace has time_s, voltage_V, .*\); add the column, map a source",
    ),
    (
        "chain-no-voltage",
        csv_of(frame().drop(columns=["voltage_V"])),
        {"stages": ["chain"]},
        r"column 'voltage_V', row -: missing, but stage 'chain' needs it",
    ),
    (
        "chain-no-output",
        csv_of(frame()[["time_s", "voltage_V", "disc_speed_rad_s"]]),
        {"stages": ["chain"]},
        r"trace\.csv: stage 'chain' needs a measured output \(theta_deg, x_m, force_N, "
        r"torque_Nm, current_A\) and the trace has only time_s, voltage_V, disc_speed_rad_s; "
        r"add a measured column",
    ),
    (
        "unknown-stage",
        csv_of(frame()),
        {"stages": ["gap", "brake"]},
        r"trace\.csv: unknown stage 'brake'; stages are motor, gap, force, torque, chain",
    ),
    (
        "unknown-unit",
        csv_of(frame()),
        {"mapping": {"x_m": {"column": "x_m", "unit": "inch"}}},
        r"mapping: entry 'x_m': unit 'inch' cannot be converted to 'm' \(column 'x_m'\); "
        r"units allowed for x_m are m, mm, um$",
    ),
    (
        "unknown-target",
        csv_of(frame()),
        {"mapping": {"angle": "theta"}},
        r"mapping: entry 'angle': unknown target column 'theta'; target columns are time_s, "
        r"voltage_V, current_A, theta_deg, x_m, force_N, torque_Nm, disc_speed_rad_s",
    ),
    (
        "two-sources",
        csv_of(frame().assign(pot=signals()["theta_deg"])),
        {"mapping": {"pot": "theta_deg"}},
        r"column 'pot' \(mapped to 'theta_deg'\), row -: column 'theta_deg' comes from both "
        r"'theta_deg' and 'pot'",
    ),
]


@pytest.mark.parametrize(
    ("make", "kwargs", "pattern"),
    [case[1:] for case in BAD_CASES],
    ids=[case[0] for case in BAD_CASES],
)
def test_bad_input(tmp_path: Path, make: Maker, kwargs: dict, pattern: str) -> None:
    path = make(tmp_path)
    with pytest.raises(TraceError, match=pattern) as info:
        read_trace(path, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    assert message.count("; ") >= 1


def test_bad_mapping_files(tmp_path: Path) -> None:
    path = write_csv(tmp_path, frame())
    bad_json = tmp_path / "map.json"
    bad_json.write_text('{"a": ')
    with pytest.raises(TraceError, match=r"map\.json: invalid JSON"):
        read_trace(path, mapping=bad_json)
    bad_toml = tmp_path / "map.toml"
    bad_toml.write_text("a = ")
    with pytest.raises(TraceError, match=r"map\.toml: invalid TOML"):
        read_trace(path, mapping=bad_toml)
    with pytest.raises(TraceError, match=r"map\.yaml: a mapping file must be \.json or \.toml"):
        read_trace(path, mapping=tmp_path / "map.yaml")


def test_parquet_non_numeric_and_nulls(tmp_path: Path) -> None:
    df = frame()
    df["x_m"] = df["x_m"].astype(object)
    df.loc[4, "x_m"] = None  # row 5
    path = tmp_path / "trace.parquet"
    df.assign(x_m=df["x_m"].astype("float64")).to_parquet(path)
    with pytest.raises(TraceError, match=r"trace\.parquet: column 'x_m', row 5: empty cell"):
        read_trace(path)
    assert read_trace(path, nan_policy="interpolate").sidecar["_filled"] == {"x_m": 1}
    df.astype({"force_N": str}).assign(x_m=1e-4).to_parquet(path)
    read_trace(path)  # numbers stored as text are accepted
    set_cell(frame(), 8, "force_N", "n/a").astype({"force_N": str}).to_parquet(path)
    with pytest.raises(TraceError, match=r"column 'force_N', row 8: cell 'n/a' is not a number"):
        read_trace(path)


def test_write_then_read_leaves_no_temporaries(tmp_path: Path) -> None:
    trace = from_arrays("syn", sidecar={"r_eff_m": 0.15, "_filled": {"x_m": 1}}, **signals())
    write_trace(trace, tmp_path / "syn.parquet")
    write_trace(trace, tmp_path / "syn.csv")
    assert sorted(os.listdir(tmp_path)) == ["syn.csv", "syn.json", "syn.parquet"]
    assert json.loads((tmp_path / "syn.json").read_text()) == {"r_eff_m": 0.15}


def test_plain_numbers_parse_as_pandas_parses_them_and_other_forms_by_its_rules(
    tmp_path: Path,
) -> None:
    """Cells of plain decimal numbers are parsed without pandas, to the same float64
    values bit for bit; a column with any other form ('nan', '1_000', a unit) takes
    pandas's rules as before."""
    from ewb_ident.data.readers import _to_float

    rng = np.random.default_rng(3)
    x = rng.standard_normal(3000) * 10.0 ** rng.integers(-9, 9, 3000)
    cells = [repr(float(v)) for v in x] + [f"{v:.6g}" for v in x] + [f" {v:.17e}" for v in x]
    cells += ["+1.5", ".5", "5.", "1E+05", "-0"]
    want = pd.to_numeric(pd.Series(cells, dtype=object), errors="coerce").to_numpy(np.float64)
    got = _to_float(np.array(cells), "trace.csv", "x_m")
    assert got.dtype == np.float64 and np.array_equal(got, want)
    mixed = _to_float(np.array(["1.5", "nan", "inf"]), "trace.csv", "x_m")
    assert np.isnan(mixed[1]) and mixed[2] == np.inf and mixed[0] == 1.5
    with pytest.raises(TraceError, match=r"x_m, row 2: cell '1_000' is not a number"):
        _to_float(np.array(["1.5", "1_000"]), "trace.csv", "x_m")  # float() would take it
    with pytest.raises(TraceError, match=r"row 1: cell '١٢' is not a number"):
        _to_float(np.array(["١٢", "3"]), "trace.csv", "x_m")  # non-ASCII digits too
    shipped = sorted((Path(__file__).parents[1] / "datasets").rglob("*.csv"))
    assert len(shipped) >= 18
    for path in shipped:  # every column of every shipped trace, as pandas reads it
        with path.open(newline="") as handle:
            rows = list(csv.reader(handle))
        for j, column in enumerate(rows[0]):
            cells = np.array([r[j] for r in rows[1:]])
            want = pd.to_numeric(pd.Series(cells, dtype=object), errors="coerce")
            got = _to_float(cells, path.name, column)
            assert np.array_equal(got, want.to_numpy(np.float64), equal_nan=True), path


@pytest.mark.parametrize("sep", [";", "\t"])
def test_a_european_csv_reads_as_the_comma_one(tmp_path, sep):
    """A ';'- or tab-separated export with decimal commas (Excel in much of Europe,
    thousands points included) gives the same trace as the comma-separated one, and says
    how it was read."""
    plain = tmp_path / "plain.csv"
    write_trace(from_arrays("plain", **signals()), plain)
    lines = plain.read_text().splitlines()
    eu = [lines[0].replace(",", sep)]
    for line in lines[1:]:
        cells = [c.replace(".", ",") for c in line.split(",")]
        eu.append(sep.join(cells))
    # A force of 1234.5 N written with a thousands point, 1.234,5.
    eu[1] = sep.join([*eu[1].split(sep)[:5], "1.234,5", *eu[1].split(sep)[6:]])
    (tmp_path / "eu.csv").write_text("\n".join(eu) + "\n")
    a, b = read_trace(plain), read_trace(tmp_path / "eu.csv")
    assert b.sidecar["_csv_dialect"] == ("';'" if sep == ";" else "tab") + (
        "-separated, decimal comma"
    )
    assert "_csv_dialect" not in a.sidecar
    for col in a.channels:
        want = a[col].copy()
        if col == "force_N":
            want[0] = 1234.5
        np.testing.assert_array_equal(b[col], want)
