"""Reading traces: CSV, Parquet and MATLAB tables with a JSON sidecar, or arrays;
missing samples; then validation."""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ewb_ident.data.tables import MAX_LOG_SAMPLES as MAX_LOG_SAMPLES
from ewb_ident.data.tables import MAX_SAMPLES as MAX_SAMPLES
from ewb_ident.data.tables import SUFFIXES as SUFFIXES
from ewb_ident.data.tables import read_table
from ewb_ident.data.trace import (
    COLUMNS,
    MAX_GAP,
    NanPolicy,
    Trace,
    column_label,
    raise_trace_error,
    refuse_channel_shape,
    refuse_unknown_channel,
)
from ewb_ident.data.units import convert_unit, load_mapping
from ewb_ident.data.validation import (
    NAN_HINT,
    UNITS_UNCHECKED,
    first_nonfinite,
    parse_stages,
    validate,
)


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

    raw = read_table(path, label, min(max_samples, MAX_LOG_SAMPLES))
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
            refuse_unknown_channel(name, key)
    for key in allowed:
        if key in channels:
            values = np.array(channels[key], dtype=np.float64)
            if values.shape != t.shape:
                refuse_channel_shape(name, key, values.shape, t.shape)
            arrays[key] = values
    return Trace(name=name, time_s=t, channels=arrays, sidecar=dict(sidecar or {}))
