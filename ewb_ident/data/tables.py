"""A table file's columns as read, before they are a trace: CSV (a fast Arrow parser for
any length, the detailed reader that names a bad row for files up to
:data:`MAX_SAMPLES` rows), Parquet (one column at a time) and MATLAB ``.mat``; the length
limits checked before parsing. :mod:`ewb_ident.data.readers` makes the trace."""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ewb_ident.data.trace import TraceError, raise_trace_error

#: Most samples a trace may have (10 minutes at 1 kHz), checked before parsing.
MAX_SAMPLES = 600_000
#: Most samples a long log may have (10 hours at 1 kHz; ``batch --cycles`` splits it).
MAX_LOG_SAMPLES = 36_000_000

#: Table suffixes :func:`read_table` (and so :func:`~ewb_ident.data.readers.read_trace`)
#: understands.
SUFFIXES: tuple[str, ...] = (".csv", ".parquet", ".mat")


# --------------------------------------------------------------------------- reading


@dataclass
class RawTable:
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
            f"too long: about {rows:,} rows; a log is at most {limit:,} samples (10 h at 1 kHz)",
            "split the log into shorter files",
        )


#: Bytes of a CSV's start read to find its separator and decimal mark.
_HEAD_BYTES = 1 << 16
#: Bytes of a CSV parsed at a time by the fast reader.
_BLOCK_BYTES = 1 << 20


def _floats(column: Any) -> np.ndarray:
    """The values of an Arrow float64 array without a missing cell: its data buffer, read
    by NumPy (the same numbers as ``column.to_numpy()``, whose first call imports pandas:
    0.3-0.4 s of every command that reads a CSV)."""
    offset = 8 * column.offset
    return np.frombuffer(column.buffers()[1], np.float64, count=len(column), offset=offset)


def _read_csv_fast(path: Path, label: str, rows: int) -> RawTable | None:
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
        first = pcsv.open_csv(
            path,
            read_options=read,
            parse_options=parse,
            convert_options=pcsv.ConvertOptions(null_values=nulls, strings_can_be_null=True),
        )
        schema = first.schema
        first.close()
        names = [name.strip() for name in schema.names]
        _check_header(names, label)
        numeric = [
            pa.types.is_integer(f.type) or pa.types.is_floating(f.type) or pa.types.is_null(f.type)
            for f in schema
        ]
        types = {
            f.name: pa.float64() if num else pa.string()
            for f, num in zip(schema, numeric, strict=True)
        }
        reader = pcsv.open_csv(
            path,
            read_options=read,
            parse_options=parse,
            convert_options=pcsv.ConvertOptions(
                column_types=types, null_values=nulls, strings_can_be_null=True
            ),
        )
        size = rows + 1
        columns: list[Any] = [np.empty(size) if num else [] for num in numeric]
        empty = np.empty(size, dtype=bool)
        n = 0
        for batch in reader:
            m = batch.num_rows
            if n + m > size:  # quoted line breaks: more lines than rows never happens
                grow = max(n + m, 2 * size)
                columns = [np.resize(c, grow) if isinstance(c, np.ndarray) else c for c in columns]
                empty = np.resize(empty, grow)
                size = grow
            null = np.ones(m, dtype=bool)
            for j, column in enumerate(batch.columns):
                missing = column.null_count > 0  # else no Arrow to_numpy: see _floats
                null &= column.is_null().to_numpy(zero_copy_only=False) if missing else False
                if numeric[j]:
                    plain = not missing and column.type == pa.float64()
                    columns[j][n : n + m] = (
                        _floats(column) if plain else column.to_numpy(zero_copy_only=False)
                    )
                else:
                    columns[j].append(column.to_numpy(zero_copy_only=False))
            empty[n : n + m] = null
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
        values[name] = (
            column[:last] if isinstance(column, np.ndarray) else np.concatenate(column)[:last]
        )
    sep = {";": "';'-separated", "\t": "tab-separated", ",": ""}[delim]
    return RawTable(names, values, sep)


def _read_csv(path: Path, label: str, limit: int = MAX_SAMPLES) -> RawTable:
    lines = _count_lines(path)
    if lines > limit + 2:
        _check_length(lines - 1, label, limit)
    fast = _read_csv_fast(path, label, lines - 1)
    if fast is not None:
        return fast
    return _read_csv_detailed(path, label)


def _read_csv_detailed(path: Path, label: str) -> RawTable:
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
    return RawTable(names, values, dialect)


def _read_parquet(path: Path, label: str, limit: int = MAX_SAMPLES) -> RawTable:
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
    return RawTable(names, values)


def _read_mat(path: Path, label: str, limit: int = MAX_SAMPLES) -> RawTable:
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
    return RawTable(names, dict(zip(names, variables.values(), strict=True)))


def read_table(path: Path, label: str, limit: int = MAX_SAMPLES) -> RawTable:
    """The columns of a ``.csv``, ``.parquet`` or ``.mat`` table of at most ``limit``
    rows (:class:`TraceError` naming the file otherwise)."""
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
