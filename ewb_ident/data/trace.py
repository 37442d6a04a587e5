"""Rig traces: the in-memory record of one brake-rig recording, and its file formats.

A :class:`Trace` holds validated float64 NumPy arrays in SI units (angle in degrees,
as in the trace format v1). Reading, validation, column mapping and writing live here;
nothing in this module knows about the model.

Files
-----
``NAME.csv`` (comma separated, header row, ``.`` decimal point), ``NAME.parquet`` or a
MATLAB ``NAME.mat`` (each variable a vector of the same length, or one struct whose
fields are those vectors), with an optional JSON sidecar ``NAME.json`` beside it.
Other column names are accepted through a *mapping* ``{source: {"column": target,
"unit": unit}}`` (short form ``{source: target}``) that also converts the unit to the
SI unit of the target column; the units understood are listed in :data:`UNITS`.
Table columns that are neither trace columns nor mapped are ignored; their names are
kept in ``sidecar["_ignored_columns"]``.

Messages
--------
Every problem raises :class:`TraceError` with a one-line message::

    {file}: column '{col}', row {row}: {problem}; {what to do}

``row`` is the 1-based *data* row: the header is not counted, so row 1 is the first
sample (for Parquet and MATLAB files, the first element). Where no single row
applies the row reads ``row -``; where no column applies the column part is left out
(``{file}: {problem}; {what to do}``, or ``{file}: row {row}: ...`` for a malformed
CSV line). Sidecar problems name the sidecar file and the key
(``{file}.json: key '{key}': ...``). A column that was renamed by a mapping is
shown as ``column 'source' (mapped to 'target')``.

Checks, in this order
---------------------
1. The file: readable, not empty, a header row, no duplicate column names, every cell
   of a used column a number, a ``time_s`` column.
2. Missing (empty or ``nan``) and infinite values. ``nan_policy="raise"`` (default)
   refuses them; ``nan_policy="interpolate"`` (CLI ``--fill-gaps``) fills interior
   gaps of at most :data:`MAX_GAP` consecutive samples linearly in the sample index
   and records the counts in ``sidecar["_filled"]``; gaps at the start or end, longer
   gaps and infinite values are refused.
3. Time: strictly increasing, uniform (every interval within 1 % of the median), a
   sample rate from 100 Hz to 1 kHz (1 % slack), at least 50 samples and 0.2 s.
4. Sidecar: ``sample_rate_hz`` agrees with ``time_s`` within 1 %, ``r_eff_m`` a number
   in (0.02, 0.5) m, ``disc_mode`` ``drag`` or ``coast``, ``coast`` with
   ``disc_inertia_kg_m2``.
5. Units (``check_units=True``): values that look like millimetres, radians,
   millivolts or milliamperes, or an implausible force. A column mapped with an
   explicit unit is not checked.
6. Stages: for the force, torque and chain stages a force that rises by at least
   200 N (the brake clamped); the columns each requested stage needs.
"""

from __future__ import annotations

import csv
import json
import math
import numbers
import os
import re
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NoReturn

import numpy as np
import pandas as pd

from ewb_ident.data.outputs import atomic_write

#: Columns of the trace format v1, with their SI unit.
COLUMNS: dict[str, str] = {
    "time_s": "s",
    "voltage_V": "V",
    "current_A": "A",
    "theta_deg": "deg",
    "x_m": "m",
    "force_N": "N",
    "torque_Nm": "N*m",
    "disc_speed_rad_s": "rad/s",
}

#: Measured channels a model output can be compared with.
CHANNELS: tuple[str, ...] = ("theta_deg", "x_m", "force_N", "torque_Nm", "current_A")

#: Input and output columns of each stage of the chain (``chain``: the whole chain).
STAGE_COLUMNS: dict[str, tuple[str, str]] = {
    "motor": ("voltage_V", "theta_deg"),
    "gap": ("theta_deg", "x_m"),
    "force": ("x_m", "force_N"),
    "torque": ("force_N", "torque_Nm"),
}

DEFAULT_R_EFF_M = 0.15

#: Stage names accepted by :func:`read_trace`, :func:`validate` and :func:`check_stages`.
STAGES: tuple[str, ...] = (*STAGE_COLUMNS, "chain")

#: Units a mapping may declare: name -> (quantity, size of the unit in SI units).
#: Angles are measured in radians here; ``theta_deg`` is stored in degrees.
UNITS: dict[str, tuple[str, float]] = {
    "s": ("time", 1.0),
    "ms": ("time", 1e-3),
    "V": ("voltage", 1.0),
    "mV": ("voltage", 1e-3),
    "A": ("current", 1.0),
    "mA": ("current", 1e-3),
    "deg": ("angle", math.pi / 180.0),
    "rad": ("angle", 1.0),
    "m": ("length", 1.0),
    "mm": ("length", 1e-3),
    "um": ("length", 1e-6),
    "N": ("force", 1.0),
    "kN": ("force", 1e3),
    "N*m": ("torque", 1.0),
    "rad/s": ("angular speed", 1.0),
    "rpm": ("angular speed", 2.0 * math.pi / 60.0),
}

#: Other spellings of the units in :data:`UNITS`.
UNIT_ALIASES: dict[str, str] = {
    "Nm": "N*m",
    "N.m": "N*m",
    "N·m": "N*m",
    "µm": "um",
    "μm": "um",
}

#: Longest run of consecutive missing samples that ``nan_policy="interpolate"`` fills.
MAX_GAP = 5
#: Most samples a trace may have (10 minutes at 1 kHz), checked before parsing.
MAX_SAMPLES = 600_000

#: Table suffixes :func:`read_trace` understands.
SUFFIXES: tuple[str, ...] = (".csv", ".parquet", ".mat")

NanPolicy = Literal["raise", "interpolate"]

_MIN_RATE_HZ = 100.0
_MAX_RATE_HZ = 1000.0
_RATE_SLACK = 0.01
_UNIFORM_TOL = 0.01
_MIN_SAMPLES = 50
_MIN_DURATION_S = 0.2
_R_EFF_RANGE_M = (0.02, 0.5)
_DISC_MODES = ("drag", "coast")
_MIN_FORCE_RISE_N = 200.0
_FORCE_STAGES = ("force", "torque", "chain")
_NAN_HINT = 'nan_policy="interpolate" (CLI --fill-gaps)'
_UNIT_OVERRIDE = "pass check_units=False (CLI --no-unit-check)"


class TraceError(ValueError):
    """A trace file that cannot be used as it is.

    The message is one line naming the file, the column and the row where the
    problem is, and what to do about it.
    """


@dataclass(frozen=True)
class Trace:
    """One validated recording of the brake rig.

    Parameters
    ----------
    name
        Short name (the file stem for traces read from disk).
    time_s
        Sample times, s, strictly increasing and uniform.
    channels
        Measured columns other than ``time_s`` (keys from :data:`COLUMNS`), each a
        float64 array of the same length as ``time_s``, in the unit of its name.
    sidecar
        Facts about the rig (``r_eff_m``, ``disc_mode``, ...); unknown keys are kept.
    path
        The table's path, when the trace was read from disk.
    """

    name: str
    time_s: np.ndarray
    channels: Mapping[str, np.ndarray]
    sidecar: Mapping[str, Any] = field(default_factory=dict)
    path: Path | None = None

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.time_s.shape[0])

    @property
    def dt(self) -> float:
        """Sample interval, s (the median interval)."""
        return float(np.median(np.diff(self.time_s)))

    @property
    def sample_rate_hz(self) -> float:
        """Sample rate, Hz."""
        return 1.0 / self.dt

    @property
    def duration_s(self) -> float:
        """Time from the first to the last sample, s."""
        return float(self.time_s[-1] - self.time_s[0])

    @property
    def r_eff_m(self) -> float:
        """Effective pad radius, m (sidecar ``r_eff_m``, default 0.15 m)."""
        return float(self.sidecar.get("r_eff_m", DEFAULT_R_EFF_M))

    @property
    def r_eff_source(self) -> str:
        """Where :attr:`r_eff_m` comes from: ``"--r-eff"`` (given on the command line),
        ``"sidecar"`` or ``"default"`` (the seed paper's 0.15 m: nobody said)."""
        if "r_eff_m" not in self.sidecar:
            return "default"
        return str(self.sidecar.get("_r_eff_source", "sidecar"))

    @property
    def column_sources(self) -> dict[str, str]:
        """Column -> the file's column it was read from, for mapped columns (``--map``)."""
        return _sources(self.sidecar)

    @property
    def label(self) -> str:
        """The file path when there is one, else the name (for messages)."""
        return str(self.path) if self.path is not None else self.name

    @property
    def columns(self) -> tuple[str, ...]:
        """``time_s`` followed by the recorded channels, in the order of :data:`COLUMNS`."""
        return ("time_s", *(c for c in COLUMNS if c in self.channels))

    def has(self, column: str) -> bool:
        """Whether the trace records ``column``."""
        return column == "time_s" or column in self.channels

    def to_frame(self) -> pd.DataFrame:
        """The trace as a DataFrame, columns in :attr:`columns` order (SI units)."""
        return pd.DataFrame({c: self[c] for c in self.columns})

    def __getitem__(self, column: str) -> np.ndarray:
        if column == "time_s":
            return self.time_s
        try:
            return self.channels[column]
        except KeyError:
            raise KeyError(f"{self.label}: no column {column!r} in this trace") from None


# --------------------------------------------------------------------------- messages


def _one_line(text: str) -> str:
    return re.sub(r"\s*[\r\n]+\s*", " ", text)


def _fail(
    file: str,
    problem: str,
    fix: str,
    *,
    column: str | None = None,
    row: int | None = None,
    key: str | None = None,
) -> NoReturn:
    """Raise :class:`TraceError` with the one-line message of the module docstring."""
    parts = [str(file)]
    if key is not None:
        parts.append(f"key {key!r}")
    if column is not None:
        parts.append(f"{column}, row {row if row is not None else '-'}")
    elif row is not None:
        parts.append(f"row {row}")
    parts.append(f"{problem}; {fix}")
    raise TraceError(_one_line(": ".join(parts)))


def _col(name: str, sources: Mapping[str, str] | None = None) -> str:
    """``column 'name'``, or ``column 'source' (mapped to 'name')`` for a mapped column."""
    source = (sources or {}).get(name)
    if source is not None and source != name:
        return f"column {source!r} (mapped to {name!r})"
    return f"column {name!r}"


def _g(value: float) -> str:
    return f"{value:.6g}"


def _sources(sidecar: Mapping[str, Any]) -> dict[str, str]:
    mapped = sidecar.get("_mapped", {})
    return {t: str(m.get("source", t)) for t, m in mapped.items() if isinstance(m, Mapping)}


def _declared(sidecar: Mapping[str, Any]) -> set[str]:
    mapped = sidecar.get("_mapped", {})
    return {t for t, m in mapped.items() if isinstance(m, Mapping) and m.get("unit")}


# --------------------------------------------------------------------------- mapping


def _canonical_unit(unit: str) -> str | None:
    unit = unit.strip()
    unit = UNIT_ALIASES.get(unit, unit)
    return unit if unit in UNITS else None


def _units_for(target: str) -> list[str]:
    quantity = UNITS[COLUMNS[target]][0]
    names = [u for u, (q, _) in UNITS.items() if q == quantity]
    names += [a for a, u in UNIT_ALIASES.items() if UNITS[u][0] == quantity and a.isascii()]
    return names


def _load_mapping(
    mapping: Mapping[str, Any] | str | os.PathLike[str] | None,
) -> dict[str, tuple[str, str | None]]:
    """Parse a column mapping into ``{source: (target, canonical unit or None)}``."""
    if mapping is None:
        return {}
    label = "mapping"
    if isinstance(mapping, str | os.PathLike):
        path = Path(mapping)
        label = str(path)
        suffix = path.suffix.lower()
        if suffix not in (".json", ".toml"):
            _fail(label, "a mapping file must be .json or .toml", "rename or convert the file")
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            _fail(label, f"cannot read the mapping file ({err})", "check the path")
        try:
            mapping = json.loads(text) if suffix == ".json" else tomllib.loads(text)
        except (json.JSONDecodeError, tomllib.TOMLDecodeError) as err:
            _fail(label, f"invalid {suffix[1:].upper()} ({err})", "fix the mapping file")
    if not isinstance(mapping, Mapping):
        _fail(
            label,
            f"a mapping must be a table of source columns, got {type(mapping).__name__}",
            'write {"source": {"column": "theta_deg", "unit": "rad"}} or {"source": "x_m"}',
        )
    targets = ", ".join(COLUMNS)
    out: dict[str, tuple[str, str | None]] = {}
    seen: dict[str, str] = {}
    for source, spec in mapping.items():
        where = f"entry {str(source)!r}"
        if isinstance(spec, str):
            target, unit = spec, None
        elif isinstance(spec, Mapping):
            extra = sorted(set(spec) - {"column", "unit"})
            if extra or "column" not in spec:
                _fail(
                    label,
                    f"{where}: keys {sorted(spec)} (need 'column', optional 'unit')",
                    'write {"column": "theta_deg", "unit": "rad"}',
                )
            target, unit = spec["column"], spec.get("unit")
        else:
            _fail(
                label,
                f"{where}: {spec!r} is neither a column name nor a table",
                'write {"column": "theta_deg", "unit": "rad"} or "theta_deg"',
            )
        if not isinstance(target, str) or target not in COLUMNS:
            _fail(
                label,
                f"{where}: unknown target column {target!r}",
                f"target columns are {targets}",
            )
        canonical = None
        if unit is not None:
            canonical = _canonical_unit(unit) if isinstance(unit, str) else None
            if canonical is None or UNITS[canonical][0] != UNITS[COLUMNS[target]][0]:
                _fail(
                    label,
                    f"{where}: unit {unit!r} cannot be converted to {COLUMNS[target]!r}"
                    f" (column {target!r})",
                    f"units allowed for {target} are {', '.join(_units_for(target))}",
                )
        if target in seen:
            _fail(
                label,
                f"{where}: target column {target!r} is also the target of {seen[target]!r}",
                "map each target column from one source column",
            )
        seen[target] = str(source)
        out[str(source)] = (target, canonical)
    return out


def _convert(values: np.ndarray, unit: str | None, target: str) -> np.ndarray:
    if unit is None:
        return values
    factor = UNITS[unit][1] / UNITS[COLUMNS[target]][1]
    return values if factor == 1.0 else values * factor


# --------------------------------------------------------------------------- reading


@dataclass
class _Raw:
    """A table as read: column names in file order and their raw values."""

    names: list[str]
    values: dict[str, Any]


def _check_header(names: list[str], label: str) -> None:
    if not names or all(not n for n in names):
        _fail(label, "no header row", "add a header row with the column names (time_s, ...)")
    if len(names) == 1 and (";" in names[0] or "\t" in names[0]):
        sep = "';'" if ";" in names[0] else "a tab"
        _fail(
            label,
            f"the header {names[0]!r} is one column: the file seems to use {sep} as separator",
            "export with ',' between columns and '.' as decimal point",
        )

    def _is_number(text: str) -> bool:
        try:
            float(text)
        except ValueError:
            return False
        return True

    if all(_is_number(n) for n in names):
        _fail(
            label,
            f"no header row: the first row {','.join(names[:4])!r} holds numbers",
            "add a header row with the column names (time_s, voltage_V, ...)",
        )
    first: dict[str, int] = {}
    for j, name in enumerate(names, start=1):
        if not name:
            _fail(label, f"column {j} of the header has no name", "name every column")
        if name in first:
            _fail(
                label,
                f"the header names this column twice (columns {first[name]} and {j})",
                "rename or drop one of them",
                column=f"column {name!r}",
            )
        first[name] = j


def _count_lines(path: Path) -> int:
    """Lines in a file, counted in binary blocks (no parsing)."""
    n = 0
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            n += block.count(b"\n")
    return n


def _read_csv(path: Path, label: str) -> _Raw:
    lines = _count_lines(path)
    if lines > MAX_SAMPLES + 2:
        _fail(
            label,
            f"too long: about {lines - 1:,} rows; this tool reads at most {MAX_SAMPLES:,} "
            "samples (10 min at 1 kHz)",
            "split the recording into brake applications and fit them together",
        )
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            rows = list(csv.reader(handle))
    except UnicodeDecodeError:
        _fail(label, "not a UTF-8 text file", "export the log as a comma-separated CSV")
    except csv.Error as err:
        _fail(label, f"not a readable CSV file ({err})", "export the log as a plain CSV")
    while rows and not any(cell.strip() for cell in rows[-1]):
        rows.pop()
    if not rows:
        _fail(label, "the file is empty", "export the log with a header row and the samples")
    names = [name.strip() for name in rows[0]]
    _check_header(names, label)
    body = rows[1:]
    if not body:
        _fail(label, "the header has no data rows under it", "export the samples too")
    width = len(names)
    for i, fields in enumerate(body, start=1):
        if len(fields) != width:
            problem = (
                "blank line"
                if not fields
                else f"{len(fields)} fields {','.join(fields)[:60]!r}, the header has {width}"
            )
            _fail(
                label,
                problem,
                "every row needs one value per column (a missing value is an empty cell)",
                row=i,
            )
    columns = list(zip(*body, strict=True))
    values = {name: np.array(columns[j], dtype=object) for j, name in enumerate(names)}
    return _Raw(names, values)


def _read_parquet(path: Path, label: str) -> _Raw:
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
    except Exception as err:  # pyarrow raises several types for damaged files
        _fail(label, f"not a readable Parquet file ({type(err).__name__}: {err})", "re-export")
    names = [str(n).strip() for n in table.column_names]
    if not names:
        _fail(label, "the file has no columns", "export the log with its columns")
    _check_header(names, label)
    if table.num_rows == 0:
        _fail(label, "the table has no rows", "export the samples too")
    values = {name: table.column(j).to_numpy(zero_copy_only=False) for j, name in enumerate(names)}
    return _Raw(names, values)


def _read_mat(path: Path, label: str) -> _Raw:
    import scipy.io

    try:
        content = scipy.io.loadmat(path, simplify_cells=True)
    except NotImplementedError:
        _fail(
            label,
            "MATLAB v7.3 (HDF5) files are not supported",
            "save with save(..., '-v7') or export CSV",
        )
    except Exception as err:  # scipy raises several types for damaged files
        _fail(label, f"not a readable MATLAB file ({type(err).__name__}: {err})", "re-export")
    variables = {k: v for k, v in content.items() if not k.startswith("__")}
    if len(variables) == 1 and isinstance(next(iter(variables.values())), dict):
        variables = next(iter(variables.values()))
    if not variables:
        _fail(label, "the file holds no variables", "save the channels as vectors")
    structs = [k for k, v in variables.items() if isinstance(v, dict)]
    if structs:
        _fail(
            label,
            f"variable {structs[0]!r} is a struct, not a vector",
            "save the channels as vectors of the same length, or as one struct of vectors",
        )
    names = [str(n).strip() for n in variables]
    _check_header(names, label)
    return _Raw(names, dict(zip(names, variables.values(), strict=True)))


def _missing_text(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, float):
        return math.isnan(value)
    if isinstance(value, str | bytes):
        text = value.decode(errors="replace") if isinstance(value, bytes) else value
        return text.strip().lower() in ("", "nan")
    return False


def _to_float(raw: Any, label: str, column: str) -> np.ndarray:
    """Raw cells of one column -> float64 (missing cells NaN); non-numbers raise."""
    arr = np.asarray(raw)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        _fail(
            label,
            f"has shape {arr.shape}, not a vector",
            "save each channel as a vector (n, 1) or (1, n)",
            column=column,
        )
    kind = arr.dtype.kind
    if kind in "fiu":
        return arr.astype(np.float64)
    if kind == "b":
        _fail(label, "holds true/false values, not numbers", "export the numbers", column=column)
    if kind in "mM":
        _fail(
            label,
            f"holds {arr.dtype} values, not numbers",
            "export times as seconds (time_s) and other channels as numbers",
            column=column,
        )
    if kind not in "OUS":
        _fail(label, f"holds {arr.dtype} values, not numbers", "export numbers", column=column)
    cells = arr.astype(object)
    out = pd.to_numeric(pd.Series(cells, dtype=object), errors="coerce").to_numpy(
        dtype=np.float64, na_value=np.nan, copy=True
    )
    for i in np.flatnonzero(np.isnan(out)):
        if not _missing_text(cells[i]):
            cell = cells[i]
            shown = cell.decode(errors="replace") if isinstance(cell, bytes) else str(cell)
            _fail(
                label,
                f"cell {shown!r} is not a number",
                "fix the cell (numbers with '.' as decimal point, no units in cells,"
                " a missing value is an empty cell)",
                column=column,
                row=int(i) + 1,
            )
    return out


def _read_sidecar(path: Path) -> dict[str, Any]:
    side = path.with_suffix(".json")
    if not side.is_file():
        return {}
    try:
        data = json.loads(side.read_text(encoding="utf-8"))
    except RecursionError:
        _fail(
            str(side),
            "the sidecar is nested too deeply to be a sidecar",
            'write one flat JSON object, e.g. {"r_eff_m": 0.15}',
        )
    except json.JSONDecodeError as err:
        _fail(
            str(side),
            f"invalid JSON at line {err.lineno}, column {err.colno}: {err.msg}",
            "fix the sidecar (one JSON object) or remove it",
        )
    except (OSError, UnicodeDecodeError) as err:
        _fail(str(side), f"cannot read the sidecar ({err})", "fix or remove the sidecar")
    if not isinstance(data, dict):
        _fail(
            str(side),
            f"the sidecar holds a JSON {type(data).__name__}, not an object",
            'write one JSON object, e.g. {"r_eff_m": 0.15}',
        )
    return data


def _read_table(path: Path, label: str) -> _Raw:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        _fail(
            label,
            f"unknown file type {path.suffix!r}",
            f"use one of {', '.join(SUFFIXES)}",
        )
    if not path.exists():
        _fail(label, "no such file", "check the path")
    if not path.is_file():
        _fail(label, "not a file", "give the path of a trace table")
    try:
        if path.stat().st_size == 0:
            _fail(label, "the file is empty", "export the log with a header row and the samples")
        if suffix == ".csv":
            return _read_csv(path, label)
        if suffix == ".parquet":
            return _read_parquet(path, label)
        return _read_mat(path, label)
    except OSError as err:
        _fail(label, f"cannot read the file ({err.strerror or err})", "check the path and rights")


# --------------------------------------------------------------------------- gaps


def _first_nonfinite(
    columns: Mapping[str, np.ndarray], label: str, sources: Mapping[str, str], fix: str
) -> None:
    """Raise on the first (row-major) NaN or inf cell, if any."""
    first: tuple[int, int, str] | None = None
    for j, (name, values) in enumerate(columns.items()):
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size and (first is None or (int(bad[0]), j) < first[:2]):
            first = (int(bad[0]), j, name)
    if first is None:
        return
    i, _, name = first
    value = float(columns[name][i])
    if np.isnan(value):
        _fail(label, "empty cell (missing value)", fix, column=_col(name, sources), row=i + 1)
    _fail(
        label,
        f"value {value!r} is infinite",
        "fix the logger export (infinite values are never filled)",
        column=_col(name, sources),
        row=i + 1,
    )


def _nan_runs(missing: np.ndarray) -> list[tuple[int, int]]:
    """Runs of True as ``(start, stop)`` index pairs."""
    edges = np.diff(np.concatenate(([0], missing.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def _fill_gaps(
    columns: dict[str, np.ndarray], label: str, sources: Mapping[str, str]
) -> dict[str, int]:
    """Interpolate short interior gaps in place; return the count filled per column."""
    if any(np.isinf(values).any() for values in columns.values()):
        infinite_only = {n: np.where(np.isnan(v), 0.0, v) for n, v in columns.items()}
        _first_nonfinite(infinite_only, label, sources, "")
    problems: list[tuple[int, int, str, str]] = []
    for j, (name, values) in enumerate(columns.items()):
        n = values.shape[0]
        for start, stop in _nan_runs(np.isnan(values)):
            start, stop = int(start), int(stop)
            rows = f"rows {start + 1} to {stop}" if stop - start > 1 else f"row {start + 1}"
            if start == 0 or stop == n:
                where = "start" if start == 0 else "end"
                problems.append(
                    (
                        start,
                        j,
                        name,
                        f"{stop - start} missing value(s) ({rows}) at the {where} of the"
                        " recording cannot be interpolated; trim the recording to the"
                        " samples that have values",
                    )
                )
            elif stop - start > MAX_GAP:
                problems.append(
                    (
                        start,
                        j,
                        name,
                        f"a gap of {stop - start} missing values ({rows}) is longer than"
                        f" {MAX_GAP} samples; fill it in the log or trim the recording",
                    )
                )
    if problems:
        start, _, name, text = min(problems)
        problem, fix = text.split("; ", 1)
        _fail(label, problem, fix, column=_col(name, sources), row=start + 1)
    filled: dict[str, int] = {}
    for name, values in columns.items():
        missing = np.isnan(values)
        if missing.any():
            index = np.arange(values.shape[0])
            values[missing] = np.interp(index[missing], index[~missing], values[~missing])
            filled[name] = int(missing.sum())
    return filled


# --------------------------------------------------------------------------- public API


def _parse_stages(stages: Iterable[str] | str | None, label: str) -> tuple[str, ...]:
    if stages is None:
        return ()
    if isinstance(stages, str):
        stages = (stages,)
    out: list[str] = []
    for stage in stages:
        if stage not in STAGES:
            _fail(label, f"unknown stage {stage!r}", f"stages are {', '.join(STAGES)}")
        if stage not in out:
            out.append(stage)
    return tuple(out)


def read_trace(
    path: str | os.PathLike[str],
    *,
    mapping: Mapping[str, Any] | str | os.PathLike[str] | None = None,
    stages: Iterable[str] | str | None = None,
    nan_policy: NanPolicy = "raise",
    check_units: bool = True,
) -> Trace:
    """Read and validate one rig trace.

    Parameters
    ----------
    path
        ``NAME.csv``, ``NAME.parquet`` or ``NAME.mat``; a sidecar ``NAME.json`` beside
        it is read when present.
    mapping
        Column mapping, or the path of a ``.json`` / ``.toml`` file holding one:
        ``{source: {"column": target, "unit": unit}}`` or ``{source: target}``. Values
        are converted from ``unit`` to the SI unit of ``target`` (see :data:`UNITS`).
        A mapped source column that is not in the table is not an error; it is listed
        in ``sidecar["_unmatched_mapping"]``.
    stages
        Stages to be fitted (from :data:`STAGES`); their columns must be present.
    nan_policy
        ``"raise"`` refuses missing values; ``"interpolate"`` fills interior gaps of
        at most :data:`MAX_GAP` samples linearly (counts in ``sidecar["_filled"]``).
    check_units
        Refuse values whose size suggests a wrong unit (see :func:`validate`).

    Returns
    -------
    Trace
        Float64 arrays in SI units (angle in degrees); ``name`` is the file stem,
        ``path`` the table path. Bookkeeping keys of the sidecar start with ``_``:
        ``_mapped`` (``{target: {"source", "unit"}}``), ``_ignored_columns``,
        ``_unmatched_mapping`` and ``_filled``, each only when non-empty.

    Raises
    ------
    TraceError
        On the first problem found, in the order of the module docstring.
    """
    path = Path(path)
    label = str(path)
    if nan_policy not in ("raise", "interpolate"):
        raise ValueError(f"nan_policy must be 'raise' or 'interpolate', not {nan_policy!r}")
    stage_list = _parse_stages(stages, label)
    maps = _load_mapping(mapping)

    raw = _read_table(path, label)
    selected: dict[str, str] = {}  # target -> source
    ignored: list[str] = []
    for name in raw.names:
        target = maps[name][0] if name in maps else (name if name in COLUMNS else None)
        if target is None:
            ignored.append(name)
            continue
        if target in selected:
            _fail(
                label,
                f"column {target!r} comes from both {selected[target]!r} and {name!r}",
                "drop one of them or map it to another column",
                column=_col(target, {target: name}),
            )
        selected[target] = name
    sources = {t: s for t, s in selected.items() if s != t or s in maps}
    columns: dict[str, np.ndarray] = {}
    for target in sorted(selected, key=list(COLUMNS).index):
        source = selected[target]
        values = _to_float(raw.values[source], label, _col(target, sources))
        columns[target] = _convert(values, maps[source][1] if source in maps else None, target)
    lengths = {t: v.shape[0] for t, v in columns.items()}
    if "time_s" not in columns:
        found = ", ".join(raw.names[:8]) + (", ..." if len(raw.names) > 8 else "")
        _fail(
            label,
            f"missing (columns found: {found})",
            "add the sample times in seconds or map a column to it "
            "(mapping={'t': {'column': 'time_s', 'unit': 'ms'}})",
            column="column 'time_s'",
        )
    for target, length in lengths.items():
        if length != lengths["time_s"]:
            _fail(
                label,
                f"has {length} samples but time_s has {lengths['time_s']}",
                "save every channel as a vector of the same length",
                column=_col(target, sources),
            )
    if lengths["time_s"] == 0:
        _fail(label, "no samples", "export the samples too", column="column 'time_s'")

    sidecar = _read_sidecar(path)
    if nan_policy == "interpolate":
        filled = _fill_gaps(columns, label, sources)
    else:
        _first_nonfinite(
            columns,
            label,
            sources,
            f"fill the gap in the log, or pass {_NAN_HINT} to interpolate interior gaps"
            f" of up to {MAX_GAP} samples",
        )
        filled = {}

    sidecar = dict(sidecar)
    mapped = {
        t: {"source": s, "unit": maps[s][1] if s in maps else None} for t, s in sources.items()
    }
    unmatched = {s: t for s, (t, _) in maps.items() if s not in raw.names}
    for key, value in (
        ("_mapped", mapped),
        ("_ignored_columns", ignored),
        ("_unmatched_mapping", unmatched),
        ("_filled", filled),
    ):
        if value:
            sidecar[key] = value
    time_s = columns.pop("time_s")
    trace = Trace(name=path.stem, time_s=time_s, channels=columns, sidecar=sidecar, path=path)
    validate(trace, stages=stage_list, check_units=check_units)
    return trace


def _is_number(value: Any) -> bool:
    return (
        isinstance(value, numbers.Real)
        and not isinstance(value, bool | np.bool_)
        and math.isfinite(float(value))
    )


def _check_time(trace: Trace) -> None:
    label, t = trace.label, trace.time_s
    col = _col("time_s", _sources(trace.sidecar))
    fix_short = f"record at least {_MIN_SAMPLES} samples over at least {_MIN_DURATION_S} s"
    if t.shape[0] < 2:
        _fail(label, f"only {t.shape[0]} sample(s)", fix_short, column=col)
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        i = int(bad[0])
        _fail(
            label,
            f"time goes from {float(t[i])!r} s (row {i + 1}) to {float(t[i + 1])!r} s:"
            " not strictly increasing",
            "rows may not be reordered or repeated: export the log in time order without"
            " duplicate samples",
            column=col,
            row=i + 2,
        )
    median = float(np.median(dt))
    bad = np.flatnonzero(np.abs(dt - median) > _UNIFORM_TOL * median)
    if bad.size:
        i = int(bad[0])
        _fail(
            label,
            f"interval {_g(dt[i])} s from row {i + 1} to row {i + 2} deviates from the median"
            f" interval {_g(median)} s by {_g(100 * abs(dt[i] - median) / median)} % (> 1 %):"
            " sampling is not uniform",
            "export without dropped samples or resample the log to a constant rate",
            column=col,
            row=i + 2,
        )
    rate = 1.0 / median
    if not _MIN_RATE_HZ * (1 - _RATE_SLACK) <= rate <= _MAX_RATE_HZ * (1 + _RATE_SLACK):
        _fail(
            label,
            f"sample rate {_g(rate)} Hz (median interval {_g(median)} s) is outside"
            " 100 Hz to 1 kHz",
            "resample the log to a rate from 100 Hz to 1 kHz (is time_s in seconds?"
            " map it with its unit, e.g. 'ms')",
            column=col,
        )
    duration = float(t[-1] - t[0])
    if t.shape[0] < _MIN_SAMPLES or duration < _MIN_DURATION_S:
        _fail(
            label,
            f"too short: {t.shape[0]} samples over {_g(duration)} s",
            fix_short,
            column=col,
        )


def _check_sidecar(trace: Trace) -> None:
    side = trace.sidecar
    label = str(trace.path.with_suffix(".json")) if trace.path is not None else trace.label
    if "sample_rate_hz" in side:
        value = side["sample_rate_hz"]
        rate = trace.sample_rate_hz
        if not _is_number(value) or value <= 0:
            _fail(
                label,
                f"{value!r} is not a positive number of Hz",
                "fix or remove the key",
                key="sample_rate_hz",
            )
        if abs(float(value) - rate) > _RATE_SLACK * rate:
            _fail(
                label,
                f"{value!r} Hz disagrees with time_s ({_g(rate)} Hz, median interval"
                f" {_g(trace.dt)} s) by more than 1 %",
                "correct the sidecar or the time column",
                key="sample_rate_hz",
            )
    if "r_eff_m" in side:
        value = side["r_eff_m"]
        lo, hi = _R_EFF_RANGE_M
        if not _is_number(value) or not lo < float(value) < hi:
            _fail(
                label,
                f"{value!r} is not a number in ({lo}, {hi}) m",
                f"give the effective pad radius in metres (default {DEFAULT_R_EFF_M} m"
                " when the key is absent)",
                key="r_eff_m",
            )
    mode = side.get("disc_mode")
    if "disc_mode" in side and mode not in _DISC_MODES:
        _fail(
            label,
            f"{mode!r} is not 'drag' or 'coast'",
            "use 'drag' (a dynamometer holds the disc speed) or 'coast' (a flywheel"
            " decelerates freely)",
            key="disc_mode",
        )
    if mode == "coast":
        inertia = side.get("disc_inertia_kg_m2")
        if inertia is None:
            _fail(
                label,
                "disc_mode 'coast' needs disc_inertia_kg_m2, which is missing",
                "add disc_inertia_kg_m2 (disc + flywheel inertia, kg*m^2) to the sidecar",
                key="disc_inertia_kg_m2",
            )
        if not _is_number(inertia) or float(inertia) <= 0:
            _fail(
                label,
                f"{inertia!r} is not a positive number of kg*m^2",
                "give the disc + flywheel inertia in kg*m^2",
                key="disc_inertia_kg_m2",
            )


def _check_units(trace: Trace) -> None:
    sources = _sources(trace.sidecar)
    declared = _declared(trace.sidecar)

    def fix(name: str, unit: str) -> str:
        source = sources.get(name, name)
        if name in declared:  # the checks run on the converted values too
            said = trace.sidecar["_mapped"][name]["unit"]
            return (
                f"the mapping declares {source!r} in {said!r}: check that unit (is it "
                f"{unit!r}?), or if the values are right {_UNIT_OVERRIDE}"
            )
        return (
            f"map the column with its unit (mapping={{{source!r}: {{'column': "
            f"{name!r}, 'unit': {unit!r}}}}}), or if the values are right {_UNIT_OVERRIDE}"
        )

    def peak(name: str) -> tuple[float, int]:
        values = np.abs(trace.channels[name])
        i = int(np.argmax(values))
        return float(values[i]), i + 1

    checks = (
        ("x_m", "|x|", 0.01, "m", "looks like millimetres", "mm"),
        ("voltage_V", "|V|", 100.0, "V", "looks like millivolts", "mV"),
        ("current_A", "|i|", 200.0, "A", "looks like milliamperes", "mA"),
    )
    for name, symbol, limit, unit, looks, guess in checks:
        if name in trace.channels:
            value, row = peak(name)
            if value > limit:
                _fail(
                    trace.label,
                    f"{symbol} reaches {_g(value)} {unit}, above {_g(limit)} {unit}: {looks}",
                    fix(name, guess),
                    column=_col(name, sources),
                    row=row,
                )
    if "theta_deg" in trace.channels:
        value, _ = peak("theta_deg")
        if value < 4 * math.pi:
            _fail(
                trace.label,
                f"|theta| stays below {_g(value)} deg, less than 4*pi = 12.57: looks like radians",
                fix("theta_deg", "rad"),
                column=_col("theta_deg", sources),
            )
    if "force_N" in trace.channels:
        value, row = peak("force_N")
        if value > 50000.0:
            _fail(
                trace.label,
                f"|force| reaches {_g(value)} N, above 50000 N: implausible for this rig",
                "check the sensor scaling, map the column with its unit (e.g. 'kN' for"
                f" kilonewtons), or {_UNIT_OVERRIDE}",
                column=_col("force_N", sources),
                row=row,
            )


def check_stages(trace: Trace, stages: Iterable[str] | str | None) -> tuple[str, ...]:
    """Check that ``trace`` can serve the requested stages.

    Parameters
    ----------
    trace
        A trace.
    stages
        Stage names from :data:`STAGES` (``motor``, ``gap``, ``force``, ``torque``,
        ``chain``); ``None`` checks nothing.

    Returns
    -------
    tuple of str
        The stage names, without repeats.

    Raises
    ------
    TraceError
        For an unknown stage; when a force, torque or chain stage is asked for and
        ``force_N`` varies by less than 200 N (the brake never clamped); when a column
        a stage needs is missing. ``chain`` needs ``voltage_V`` and at least one of
        :data:`CHANNELS`.
    """
    label = trace.label
    stage_list = _parse_stages(stages, label)
    sources = _sources(trace.sidecar)
    if "force_N" in trace.channels and any(s in _FORCE_STAGES for s in stage_list):
        force = trace.channels["force_N"]
        top, rise = float(np.max(force)), float(np.max(force) - np.min(force))
        if rise < _MIN_FORCE_RISE_N:
            _fail(
                label,
                f"force never rises above {_g(top)} N (range {_g(rise)} N < 200 N): no"
                " clamping was reached, so the force stage cannot be fitted",
                "record an apply that clamps the brake",
                column=_col("force_N", sources),
            )
    unmatched = {t: s for s, t in trace.sidecar.get("_unmatched_mapping", {}).items()}
    present = ", ".join(trace.columns)
    for stage in stage_list:
        needed = STAGE_COLUMNS.get(stage, ("voltage_V",))
        for name in needed:
            if not trace.has(name):
                why = (
                    f" (the mapping's source column {unmatched[name]!r} is not in the table)"
                    if name in unmatched
                    else ""
                )
                flow = " -> ".join(STAGE_COLUMNS[stage]) if stage in STAGE_COLUMNS else ""
                _fail(
                    label,
                    f"missing, but stage {stage!r}{f' ({flow})' if flow else ''} needs it{why}"
                    f" (the trace has {present})",
                    f"add the column, map a source column to it (mapping={{'source': {name!r}}}),"
                    f" or leave out stage {stage!r}",
                    column=f"column {name!r}",
                )
        if stage == "chain" and not any(trace.has(c) for c in CHANNELS):
            _fail(
                label,
                f"stage 'chain' needs a measured output ({', '.join(CHANNELS)}) and the"
                f" trace has only {present}",
                "add a measured column or leave out stage 'chain'",
            )
    return stage_list


def _check_arrays(trace: Trace) -> None:
    label = trace.label
    t = trace.time_s
    if not isinstance(t, np.ndarray) or t.ndim != 1 or t.dtype != np.float64:
        _fail(
            label,
            "must be a 1-D float64 array",
            "build traces with from_arrays or read_trace",
            column="column 'time_s'",
        )
    for name, values in trace.channels.items():
        if name not in COLUMNS or name == "time_s":
            _fail(
                label,
                "not a trace channel",
                f"channels are {', '.join(c for c in COLUMNS if c != 'time_s')}",
                column=f"column {name!r}",
            )
        if not isinstance(values, np.ndarray) or values.shape != t.shape:
            shape = getattr(values, "shape", None)
            _fail(
                label,
                f"has shape {shape}, time_s has {t.shape}",
                "give every channel as a 1-D array of the same length as time_s",
                column=f"column {name!r}",
            )
        if values.dtype != np.float64:
            _fail(
                label,
                f"has dtype {values.dtype}, not float64",
                "build traces with from_arrays or read_trace",
                column=f"column {name!r}",
            )


def validate(
    trace: Trace,
    *,
    stages: Iterable[str] | str | None = None,
    check_units: bool = True,
) -> None:
    """Check a trace against the trace format v1 (called by :func:`read_trace`).

    Parameters
    ----------
    trace
        The trace to check.
    stages
        Stage names to check the trace can serve (see :func:`check_stages`).
    check_units
        Refuse values whose size suggests a wrong unit: ``x_m`` above 0.01 m
        (millimetres?), ``|theta_deg|`` never reaching 4*pi (radians?), ``force_N``
        above 50 kN, ``voltage_V`` above 100 V (millivolts?), ``current_A`` above
        200 A (milliamperes?). Columns mapped with an explicit unit are not checked.

    Raises
    ------
    TraceError
        On the first problem, in the order of the module docstring: arrays, missing
        or infinite values, time, sidecar, units, stages.
    """
    _check_arrays(trace)
    _first_nonfinite(
        {"time_s": trace.time_s, **trace.channels},
        trace.label,
        _sources(trace.sidecar),
        f"fill the gap, or read the file with {_NAN_HINT} to interpolate interior gaps",
    )
    _check_time(trace)
    _check_sidecar(trace)
    if check_units:
        _check_units(trace)
    check_stages(trace, stages)


def from_arrays(
    name: str,
    time_s: Any,
    sidecar: Mapping[str, Any] | None = None,
    **channels: Any,
) -> Trace:
    """Build a trace from arrays (the synthetic rig uses this).

    Only names and shapes are checked here; call :func:`validate` for the full checks.

    Parameters
    ----------
    name
        Short name of the trace.
    time_s
        Sample times, s, a 1-D array.
    sidecar
        Facts about the rig (see the trace format); copied.
    **channels
        Channels named as in :data:`COLUMNS` (``theta_deg=...``, ``force_N=...``), each
        1-D with the length of ``time_s``, in the unit of its name.

    Returns
    -------
    Trace
        Float64 copies of the arrays, channels in :data:`COLUMNS` order.

    Raises
    ------
    TraceError
        For an unknown channel name or a shape that is not that of ``time_s``.
    """
    t = np.array(time_s, dtype=np.float64)
    if t.ndim != 1:
        _fail(name, f"has shape {t.shape}, not 1-D", "give a 1-D array", column="column 'time_s'")
    allowed = [c for c in COLUMNS if c != "time_s"]
    arrays: dict[str, np.ndarray] = {}
    for key in channels:
        if key not in allowed:
            _fail(
                name,
                "not a trace channel",
                f"channels are {', '.join(allowed)}",
                column=f"column {key!r}",
            )
    for key in allowed:
        if key in channels:
            values = np.array(channels[key], dtype=np.float64)
            if values.shape != t.shape:
                _fail(
                    name,
                    f"has shape {values.shape}, time_s has {t.shape}",
                    "give every channel as a 1-D array of the same length as time_s",
                    column=f"column {key!r}",
                )
            arrays[key] = values
    return Trace(name=name, time_s=t, channels=arrays, sidecar=dict(sidecar or {}))


# --------------------------------------------------------------------------- writing


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def write_trace(trace: Trace, path: str | os.PathLike[str]) -> Path:
    """Write a trace as CSV or Parquet, with its sidecar JSON beside it.

    Columns are ``time_s`` then the channels in :data:`COLUMNS` order, in SI units; CSV
    floats are written in their shortest exact form (``float(text)`` gives back the
    same float64). The sidecar (keys starting with ``_`` dropped) goes to
    ``NAME.json`` when it is not empty; an existing ``NAME.json`` beside an empty
    sidecar is replaced by ``{}`` so that it cannot lend stale facts to the new table.
    Each file is written to a temporary file in the same folder and moved into place
    with :func:`os.replace`, so no half-written file is ever left under the target name.

    Parameters
    ----------
    trace
        The trace to write.
    path
        ``NAME.csv`` or ``NAME.parquet``.

    Returns
    -------
    Path
        The path of the table written.

    Raises
    ------
    TraceError
        For another suffix, a sidecar value that JSON cannot hold, or a folder that
        cannot be written.
    """
    path = Path(path)
    label = str(path)
    suffix = path.suffix.lower()
    if suffix not in (".csv", ".parquet"):
        _fail(label, f"cannot write {path.suffix!r} files", "write .csv or .parquet")
    side_path = path.with_suffix(".json")
    public = {k: v for k, v in trace.sidecar.items() if not str(k).startswith("_")}
    side_text: str | None = None
    if public or side_path.exists():
        try:
            side_text = json.dumps(public, indent=2, default=_json_default) + "\n"
        except (TypeError, ValueError) as err:
            _fail(str(side_path), f"sidecar cannot be written as JSON ({err})", "fix the value")

    frame = trace.to_frame()
    writers: list[tuple[Path, Callable[[Path], None]]] = []
    if suffix == ".csv":
        writers.append(
            (path, lambda tmp: frame.to_csv(tmp, index=False, na_rep="", lineterminator="\n"))
        )
    else:

        def _parquet(tmp: Path) -> None:
            import pyarrow as pa
            import pyarrow.parquet as pq

            pq.write_table(pa.table({c: pa.array(frame[c].to_numpy()) for c in frame}), tmp)

        writers.append((path, _parquet))
    if side_text is not None:
        text = side_text
        writers.append((side_path, lambda tmp: tmp.write_text(text, encoding="utf-8")))

    try:
        atomic_write(writers)
    except OSError as err:
        _fail(
            label,
            f"cannot write ({err.strerror or err})",
            "check the folder exists and is writable",
        )
    return path
