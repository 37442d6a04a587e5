"""Reading traces: CSV, Parquet and MATLAB tables with a JSON sidecar, or arrays;
missing samples; then validation."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ewb_ident.data.trace import (
    COLUMNS,
    MAX_GAP,
    NanPolicy,
    Trace,
    TraceError,
    column_label,
    raise_trace_error,
)
from ewb_ident.data.units import convert_unit, load_mapping
from ewb_ident.data.validation import (
    NAN_HINT,
    UNITS_UNCHECKED,
    first_nonfinite,
    parse_stages,
    validate,
)

#: Most samples a trace may have (10 minutes at 1 kHz), checked before parsing.
MAX_SAMPLES = 600_000
#: Most samples a long log may have (10 hours at 1 kHz; ``batch --cycles`` splits it).
MAX_LOG_SAMPLES = 36_000_000

#: Table suffixes :func:`read_trace` understands.
SUFFIXES: tuple[str, ...] = (".csv", ".parquet", ".mat")


# --------------------------------------------------------------------------- reading


@dataclass
class _Raw:
    """A table as read: column names in file order and their raw values."""

    names: list[str]
    values: dict[str, Any]
    #: How a CSV was read when not comma-separated with decimal points (e.g. "';'-
    #: separated, decimal comma"), else "".
    dialect: str = ""


#: A cell written with a decimal comma (``-1,25``, ``3,5E-3``, ``1.234,5``).
_DECIMAL_COMMA = re.compile(r"\s*[+-]?(?:\d{1,3}(?:\.\d{3})+|\d*),\d+(?:[eE][+-]?\d+)?\s*")


def _dialect(text: str) -> tuple[str, bool]:
    """The separator of a CSV text (``,``, ``;`` or a tab, from its header) and whether
    its numbers use a decimal comma (only possible when the separator is not a comma)."""
    first = text.split("\n", 1)[0]
    delim = ","
    if ";" in first and first.count(";") >= first.count(","):
        delim = ";"
    elif "\t" in first and first.count("\t") >= first.count(","):
        delim = "\t"
    if delim == ",":
        return delim, False
    head = text.split("\n", 200)[1:200]
    comma = any(_DECIMAL_COMMA.fullmatch(c) for line in head for c in line.split(delim))
    return delim, comma


def _decimal_point(cell: str) -> str:
    """A decimal-comma number written with a point (thousands points dropped)."""
    if not _DECIMAL_COMMA.fullmatch(cell):
        return cell
    return cell.replace(".", "").replace(",", ".")


def _check_header(names: list[str], label: str) -> None:
    if not names or all(not n for n in names):
        raise_trace_error(
            label, "no header row", "add a header row with the column names (time_s, ...)"
        )
    if len(names) == 1 and (";" in names[0] or "\t" in names[0]):
        sep = "';'" if ";" in names[0] else "a tab"
        raise_trace_error(
            label,
            f"the header {names[0]!r} is one column: the file seems to use {sep} as separator",
            "export with ',' between columns and '.' as decimal point",
        )

    def is_number(text: str) -> bool:
        try:
            float(text)
        except ValueError:
            return False
        return True

    if all(is_number(n) for n in names):
        raise_trace_error(
            label,
            f"no header row: the first row {','.join(names[:4])!r} holds numbers",
            "add a header row with the column names (time_s, voltage_V, ...)",
        )
    first: dict[str, int] = {}
    for j, name in enumerate(names, start=1):
        if not name:
            raise_trace_error(label, f"column {j} of the header has no name", "name every column")
        if name in first:
            raise_trace_error(
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


def _check_length(rows: int, label: str, limit: int = MAX_SAMPLES) -> None:
    """Refuse a table longer than ``limit`` samples, from its size before it is read
    (CSV lines, Parquet footer, MATLAB headers): one limit for every format."""
    if rows > limit:
        if limit < MAX_LOG_SAMPLES:
            raise_trace_error(
                label,
                f"too long: about {rows:,} rows; a trace is at most {limit:,} samples "
                "(10 min at 1 kHz)",
                "a long log of many brake applications is read by `ewb-ident batch LOG "
                "--cycles`, which splits it into its apply cycles",
            )
        raise_trace_error(
            label,
            f"too long: about {rows:,} rows; a log is at most {limit:,} samples "
            "(10 h at 1 kHz)",
            "split the log into shorter files",
        )


#: Bytes of a CSV's start read to find its separator and decimal mark.
_HEAD_BYTES = 1 << 16
#: Bytes of a CSV parsed at a time by the fast reader.
_BLOCK_BYTES = 1 << 20


def _read_csv_fast(path: Path, label: str, rows: int) -> _Raw | None:
    """A comma-, semicolon- or tab-separated CSV with decimal points, read by Arrow's
    parser block by block into typed columns (float64 for numbers; a column with any
    other cell stays text, for :func:`_to_float` to name the cell). ``None`` when this
    parser cannot take the file (a decimal comma, a row of another width, a blank line
    inside the table, not UTF-8): the detailed reader then reads it, and names the row
    — only for files of at most :data:`MAX_SAMPLES` rows, which it holds as text."""
    import pyarrow as pa
    import pyarrow.csv as pcsv

    with open(path, "rb") as handle:
        head = handle.read(_HEAD_BYTES)
    try:
        text = head.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        if err.start < len(head) - 4:  # not a character cut at the block's end
            return None
        text = head[: err.start].decode("utf-8-sig")
    delim, comma = _dialect(text)
    if comma:
        if rows > MAX_SAMPLES:
            raise_trace_error(
                label,
                f"a decimal-comma CSV of {rows:,} rows: the fast reader of long logs takes "
                "'.' as decimal point only",
                "export with '.' as decimal point, or as Parquet or .mat",
            )
        return None
    parse = pcsv.ParseOptions(delimiter=delim, ignore_empty_lines=False)
    nulls = ["", "nan", "NaN", "NAN", "Nan"]
    # One thread, one block at a time: the threaded reader parses ahead of a slow
    # consumer (a busy machine), and its memory then grows with the lead.
    read = pcsv.ReadOptions(block_size=_BLOCK_BYTES, use_threads=False)
    try:
        # Column types from the first block (whole numbers read as float64), so that
        # every block converts alike; the columns are filled block by block into arrays
        # allocated once: the memory is the float64 columns plus one block.
        first = pcsv.open_csv(path, read_options=read, parse_options=parse,
                              convert_options=pcsv.ConvertOptions(null_values=nulls,
                                                                  strings_can_be_null=True))
        schema = first.schema
        first.close()
        names = [name.strip() for name in schema.names]
        _check_header(names, label)
        numeric = [pa.types.is_integer(f.type) or pa.types.is_floating(f.type)
                   or pa.types.is_null(f.type) for f in schema]
        types = {f.name: pa.float64() if num else pa.string()
                 for f, num in zip(schema, numeric, strict=True)}
        reader = pcsv.open_csv(path, read_options=read, parse_options=parse,
                               convert_options=pcsv.ConvertOptions(
                                   column_types=types, null_values=nulls,
                                   strings_can_be_null=True))
        size = rows + 1
        columns: list[Any] = [np.empty(size) if num else [] for num in numeric]
        empty = np.empty(size, dtype=bool)
        n = 0
        for batch in reader:
            m = batch.num_rows
            if n + m > size:  # quoted line breaks: more lines than rows never happens
                grow = max(n + m, 2 * size)
                columns = [np.resize(c, grow) if isinstance(c, np.ndarray) else c
                           for c in columns]
                empty = np.resize(empty, grow)
                size = grow
            null = np.ones(m, dtype=bool)
            for j, column in enumerate(batch.columns):
                null &= column.is_null().to_numpy(zero_copy_only=False)
                if numeric[j]:
                    columns[j][n:n + m] = column.to_numpy(zero_copy_only=False)
                else:
                    columns[j].append(column.to_numpy(zero_copy_only=False))
            empty[n:n + m] = null
            n += m
    except (pa.ArrowInvalid, UnicodeDecodeError) as err:
        if rows > MAX_SAMPLES:
            reason = " ".join(str(err).split())
            raise_trace_error(
                label,
                f"not a readable CSV file ({reason[:200]})",
                "every row needs one value per column (a missing value is an empty cell)",
            )
        return None
    # A row whose every cell is empty: at the end dropped (as the detailed reader does);
    # inside the table, the detailed reader says whether it is a blank line.
    filled = np.flatnonzero(~empty[:n])
    last = int(filled[-1]) + 1 if filled.size else 0
    if last < n and empty[:last].any() and rows <= MAX_SAMPLES:
        return None
    if last == 0:
        raise_trace_error(label, "the header has no data rows under it", "export the samples too")
    values: dict[str, Any] = {}
    for name, column in zip(names, columns, strict=True):
        values[name] = (column[:last] if isinstance(column, np.ndarray)
                        else np.concatenate(column)[:last])
    sep = {";": "';'-separated", "\t": "tab-separated", ",": ""}[delim]
    return _Raw(names, values, sep)


def _read_csv(path: Path, label: str, limit: int = MAX_SAMPLES) -> _Raw:
    lines = _count_lines(path)
    if lines > limit + 2:
        _check_length(lines - 1, label, limit)
    fast = _read_csv_fast(path, label, lines - 1)
    if fast is not None:
        return fast
    return _read_csv_detailed(path, label)


def _read_csv_detailed(path: Path, label: str) -> _Raw:
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            text = handle.read()
        delim, comma = _dialect(text)
        rows = list(csv.reader(io.StringIO(text, newline=""), delimiter=delim))
    except UnicodeDecodeError:
        raise_trace_error(label, "not a UTF-8 text file", "export the log as a comma-separated CSV")
    except csv.Error as err:
        raise_trace_error(
            label, f"not a readable CSV file ({err})", "export the log as a plain CSV"
        )
    while rows and not any(cell.strip() for cell in rows[-1]):
        rows.pop()
    if not rows:
        raise_trace_error(
            label, "the file is empty", "export the log with a header row and the samples"
        )
    names = [name.strip() for name in rows[0]]
    _check_header(names, label)
    body = rows[1:]
    if not body:
        raise_trace_error(label, "the header has no data rows under it", "export the samples too")
    width = len(names)
    for i, fields in enumerate(body, start=1):
        if len(fields) != width:
            problem = (
                "blank line"
                if not fields
                else f"{len(fields)} fields {','.join(fields)[:60]!r}, the header has {width}"
            )
            raise_trace_error(
                label,
                problem,
                "every row needs one value per column (a missing value is an empty cell)",
                row=i,
            )
    if comma:
        body = [[_decimal_point(c) for c in fields] for fields in body]
    columns = list(zip(*body, strict=True))
    values = {name: np.array(columns[j], dtype=object) for j, name in enumerate(names)}
    dialect = ""
    if delim != "," or comma:
        sep = {";": "';'-separated", "\t": "tab-separated", ",": "comma-separated"}[delim]
        dialect = sep + (", decimal comma" if comma else "")
    return _Raw(names, values, dialect)


def _read_parquet(path: Path, label: str, limit: int = MAX_SAMPLES) -> _Raw:
    import pyarrow.parquet as pq

    try:
        rows = pq.ParquetFile(path).metadata.num_rows  # from the footer, nothing loaded
    except Exception as err:  # pyarrow raises several types for damaged files
        raise_trace_error(
            label, f"not a readable Parquet file ({type(err).__name__}: {err})", "re-export"
        )
    _check_length(rows, label, limit)
    try:
        # One column at a time: the memory is the columns as arrays plus one column
        # of Arrow's, not the whole table twice.
        handle = pq.ParquetFile(path)
        given = list(handle.schema_arrow.names)
        names = [str(n).strip() for n in given]
        if not names:
            raise_trace_error(label, "the file has no columns", "export the log with its columns")
        _check_header(names, label)
        if rows == 0:
            raise_trace_error(label, "the table has no rows", "export the samples too")
        values = {}
        for name, column in zip(names, given, strict=True):
            array = handle.read(columns=[column]).column(0).to_numpy(zero_copy_only=False)
            # Arrow's buffer is read-only; a copy of our own, made while only this
            # column is held, can have its gaps filled in place.
            values[name] = array if array.flags.writeable else array.copy()
    except TraceError:
        raise
    except Exception as err:  # pyarrow raises several types for damaged files
        raise_trace_error(
            label, f"not a readable Parquet file ({type(err).__name__}: {err})", "re-export"
        )
    return _Raw(names, values)


def _read_mat(path: Path, label: str, limit: int = MAX_SAMPLES) -> _Raw:
    import scipy.io

    try:  # the variables' shapes from the file's headers, nothing loaded
        shapes = [shape for _, shape, _ in scipy.io.whosmat(path)]
    except Exception:  # v7.3 and damaged files: loadmat below says which
        shapes = []
    _check_length(max((math.prod(shape) for shape in shapes), default=0), label, limit)
    try:
        content = scipy.io.loadmat(path, simplify_cells=True)
    except NotImplementedError:
        raise_trace_error(
            label,
            "MATLAB v7.3 (HDF5) files are not supported",
            "save with save(..., '-v7') or export CSV",
        )
    except Exception as err:  # scipy raises several types for damaged files
        raise_trace_error(
            label, f"not a readable MATLAB file ({type(err).__name__}: {err})", "re-export"
        )
    variables = {k: v for k, v in content.items() if not k.startswith("__")}
    if len(variables) == 1 and isinstance(next(iter(variables.values())), dict):
        variables = next(iter(variables.values()))
    if not variables:
        raise_trace_error(label, "the file holds no variables", "save the channels as vectors")
    structs = [k for k, v in variables.items() if isinstance(v, dict)]
    if structs:
        raise_trace_error(
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


#: A cell that is a plain decimal number (ASCII digits, optional sign, point, exponent).
_PLAIN_NUMBER = re.compile(r"[ \t]*[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?[ \t]*", re.ASCII)


def _to_float(raw: Any, label: str, column: str) -> np.ndarray:
    """Raw cells of one column -> float64 (missing cells NaN); non-numbers raise."""
    arr = np.asarray(raw)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise_trace_error(
            label,
            f"has shape {arr.shape}, not a vector",
            "save each channel as a vector (n, 1) or (1, n)",
            column=column,
        )
    kind = arr.dtype.kind
    if kind in "fiu":
        return arr.astype(np.float64, copy=False)  # the table's own array: no copy
    if kind == "b":
        raise_trace_error(
            label, "holds true/false values, not numbers", "export the numbers", column=column
        )
    if kind in "mM":
        raise_trace_error(
            label,
            f"holds {arr.dtype} values, not numbers",
            "export times as seconds (time_s) and other channels as numbers",
            column=column,
        )
    if kind not in "OUS":
        raise_trace_error(
            label, f"holds {arr.dtype} values, not numbers", "export numbers", column=column
        )
    cells = arr.astype(object)
    if all(isinstance(c, str) and _PLAIN_NUMBER.fullmatch(c) for c in cells):
        # Plain decimal numbers, the common case: Python's parser, which gives pandas's
        # numbers bit for bit (checked on 600,000 cells of 6 to 20 digits) without
        # importing pandas (0.3 s of every command's start).
        return np.array([float(c) for c in cells], dtype=np.float64)
    import pandas as pd

    out = pd.to_numeric(pd.Series(cells, dtype=object), errors="coerce").to_numpy(
        dtype=np.float64, na_value=np.nan, copy=True
    )
    for i in np.flatnonzero(np.isnan(out)):
        if not _missing_text(cells[i]):
            cell = cells[i]
            shown = cell.decode(errors="replace") if isinstance(cell, bytes) else str(cell)
            raise_trace_error(
                label,
                f"cell {shown!r} is not a number",
                "fix the cell (numbers with '.' as decimal point, no units in cells,"
                " a missing value is an empty cell)",
                column=column,
                row=int(i) + 1,
            )
    return out


class _DuplicateKey(ValueError):
    """A JSON object with a key given twice (the key is the message)."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def _read_sidecar(path: Path) -> dict[str, Any]:
    side = path.with_suffix(".json")
    if not side.is_file():
        return {}
    try:
        data = json.loads(side.read_text(encoding="utf-8"), object_pairs_hook=_unique_keys)
    except _DuplicateKey as err:
        raise_trace_error(
            str(side),
            "the key is given twice (JSON would keep the last one silently)",
            "give each key once",
            key=str(err),
        )
    except RecursionError:
        raise_trace_error(
            str(side),
            "the sidecar is nested too deeply to be a sidecar",
            'write one flat JSON object, e.g. {"r_eff_m": 0.15}',
        )
    except json.JSONDecodeError as err:
        raise_trace_error(
            str(side),
            f"invalid JSON at line {err.lineno}, column {err.colno}: {err.msg}",
            "fix the sidecar (one JSON object) or remove it",
        )
    except (OSError, UnicodeDecodeError) as err:
        raise_trace_error(
            str(side), f"cannot read the sidecar ({err})", "fix or remove the sidecar"
        )
    if not isinstance(data, dict):
        raise_trace_error(
            str(side),
            f"the sidecar holds a JSON {type(data).__name__}, not an object",
            'write one JSON object, e.g. {"r_eff_m": 0.15}',
        )
    return data


def _read_table(path: Path, label: str, limit: int = MAX_SAMPLES) -> _Raw:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise_trace_error(
            label,
            f"unknown file type {path.suffix!r}",
            f"use one of {', '.join(SUFFIXES)}",
        )
    if not path.exists():
        raise_trace_error(label, "no such file", "check the path")
    if not path.is_file():
        raise_trace_error(label, "not a file", "give the path of a trace table")
    try:
        if path.stat().st_size == 0:
            raise_trace_error(
                label, "the file is empty", "export the log with a header row and the samples"
            )
        if suffix == ".csv":
            return _read_csv(path, label, limit)
        if suffix == ".parquet":
            return _read_parquet(path, label, limit)
        return _read_mat(path, label, limit)
    except OSError as err:
        raise_trace_error(
            label, f"cannot read the file ({err.strerror or err})", "check the path and rights"
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
        first_nonfinite(infinite_only, label, sources, "")
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
        raise_trace_error(label, problem, fix, column=column_label(name, sources), row=start + 1)
    filled: dict[str, int] = {}
    for name, values in columns.items():
        missing = np.isnan(values)
        if missing.any():
            index = np.arange(values.shape[0])
            values[missing] = np.interp(index[missing], index[~missing], values[~missing])
            filled[name] = int(missing.sum())
    return filled


def read_trace(
    path: str | os.PathLike[str],
    *,
    mapping: Mapping[str, Any] | str | os.PathLike[str] | None = None,
    stages: Iterable[str] | str | None = None,
    nan_policy: NanPolicy = "raise",
    check_units: bool = True,
    max_samples: int = MAX_SAMPLES,
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
    max_samples
        Longest table read (:data:`MAX_SAMPLES`, 10 min at 1 kHz, for a trace to fit;
        up to :data:`MAX_LOG_SAMPLES` for a long log that is split into cycles).

    Returns
    -------
    Trace
        Float64 arrays in SI units (angle in degrees); ``name`` is the file stem,
        ``path`` the table path. Bookkeeping keys of the sidecar start with ``_``:
        ``_mapped`` (``{target: {"source", "unit"}}``), ``_ignored_columns``,
        ``_unmatched_mapping``, ``_filled`` and ``_units_unchecked`` (read with
        ``check_units=False``: the library's functions do not check the units again),
        each only when non-empty.

    Raises
    ------
    TraceError
        On the first problem found, in the order of the module docstring.
    """
    path = Path(path)
    label = str(path)
    if nan_policy not in ("raise", "interpolate"):
        raise ValueError(f"nan_policy must be 'raise' or 'interpolate', not {nan_policy!r}")
    stage_list = parse_stages(stages, label)
    maps = load_mapping(mapping)

    raw = _read_table(path, label, min(max_samples, MAX_LOG_SAMPLES))
    selected: dict[str, str] = {}  # target -> source
    ignored: list[str] = []
    for name in raw.names:
        target = maps[name][0] if name in maps else (name if name in COLUMNS else None)
        if target is None:
            ignored.append(name)
            continue
        if target in selected:
            raise_trace_error(
                label,
                f"column {target!r} comes from both {selected[target]!r} and {name!r}",
                "drop one of them or map it to another column",
                column=column_label(target, {target: name}),
            )
        selected[target] = name
    sources = {t: s for t, s in selected.items() if s != t or s in maps}
    columns: dict[str, np.ndarray] = {}
    for target in sorted(selected, key=list(COLUMNS).index):
        source = selected[target]
        values = _to_float(raw.values[source], label, column_label(target, sources))
        columns[target] = convert_unit(values, maps[source][1] if source in maps else None, target)
    lengths = {t: v.shape[0] for t, v in columns.items()}
    if "time_s" not in columns:
        found = ", ".join(raw.names[:8]) + (", ..." if len(raw.names) > 8 else "")
        raise_trace_error(
            label,
            f"missing (columns found: {found})",
            "add the sample times in seconds or map a column to it "
            "(mapping={'t': {'column': 'time_s', 'unit': 'ms'}})",
            column="column 'time_s'",
        )
    for target, length in lengths.items():
        if length != lengths["time_s"]:
            raise_trace_error(
                label,
                f"has {length} samples but time_s has {lengths['time_s']}",
                "save every channel as a vector of the same length",
                column=column_label(target, sources),
            )
    if lengths["time_s"] == 0:
        raise_trace_error(label, "no samples", "export the samples too", column="column 'time_s'")

    sidecar = _read_sidecar(path)
    if nan_policy == "interpolate":
        filled = _fill_gaps(columns, label, sources)
    else:
        first_nonfinite(
            columns,
            label,
            sources,
            f"fill the gap in the log, or pass {NAN_HINT} to interpolate interior gaps"
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
        ("_csv_dialect", raw.dialect),
        (UNITS_UNCHECKED, not check_units),
    ):
        if value:
            sidecar[key] = value
    time_s = columns.pop("time_s")
    trace = Trace(name=path.stem, time_s=time_s, channels=columns, sidecar=sidecar, path=path)
    validate(trace, stages=stage_list, check_units=check_units)
    return trace


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
        raise_trace_error(
            name, f"has shape {t.shape}, not 1-D", "give a 1-D array", column="column 'time_s'"
        )
    allowed = [c for c in COLUMNS if c != "time_s"]
    arrays: dict[str, np.ndarray] = {}
    for key in channels:
        if key not in allowed:
            raise_trace_error(
                name,
                "not a trace channel",
                f"channels are {', '.join(allowed)}",
                column=f"column {key!r}",
            )
    for key in allowed:
        if key in channels:
            values = np.array(channels[key], dtype=np.float64)
            if values.shape != t.shape:
                raise_trace_error(
                    name,
                    f"has shape {values.shape}, time_s has {t.shape}",
                    "give every channel as a 1-D array of the same length as time_s",
                    column=f"column {key!r}",
                )
            arrays[key] = values
    return Trace(name=name, time_s=t, channels=arrays, sidecar=dict(sidecar or {}))
