"""A campaign of recorded traces: which files, with which metadata and settings.

A campaign is named by a folder (its trace files), a glob, or a manifest table (CSV or
Parquet) with a ``path`` column (relative to the manifest's folder) and any metadata
columns (unit, date, hardware version, operator ...). Optional per-row ``map`` (a
column-mapping file, relative to the manifest) and ``r_eff_m`` (pad radius, m) columns
override the campaign-wide ones. Everything is checked here, before any trace is read
for fitting: a missing file, an unreadable manifest, a missing ``path`` column or an
empty campaign is a :class:`CampaignError` naming the file, column or row.
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ewb_ident.data.readers import SUFFIXES
from ewb_ident.data.trace import InputError, Trace, TraceError, error_line
from ewb_ident.data.units import load_mapping
from ewb_ident.data.validation import R_EFF_RANGE_M, r_eff_ok

#: Manifest columns that are settings, not metadata.
SETTING_COLUMNS = ("path", "map", "r_eff_m")


class CampaignError(InputError):
    """A campaign that cannot be run as named (the message says where and what to do)."""


# A frozen record of its fields, like the package's other records: alike in shape only.
@dataclass(frozen=True)
class Entry:
    """One trace of a campaign.

    Attributes
    ----------
    trace
        The path as given (the manifest's cell, or the file the folder or glob found).
    path
        The file to read.
    metadata
        The manifest's metadata columns for this row (plain values; ``None`` for empty).
    mapping
        Column-mapping file, or ``None``.
    r_eff_m
        Pad radius override, m, or ``None`` (the sidecar's, else the default).
    """

    trace: str
    path: Path
    metadata: dict[str, Any] = field(default_factory=dict)
    mapping: Path | None = None
    r_eff_m: float | None = None


@dataclass(frozen=True)
class Campaign:
    """The traces of a campaign and where they came from."""

    source: str
    kind: str  # "folder", "glob" or "manifest"
    entries: tuple[Entry, ...]
    metadata_columns: tuple[str, ...] = ()
    #: Manifest columns renamed in the results table (``unit`` -> ``meta_unit``: the
    #: table's own ``unit`` is the parameter's).
    renamed: dict[str, str] = field(default_factory=dict)


def file_hash(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def with_pad_radius(trace: Trace, r_eff_m: float | None) -> Trace:
    """``trace`` with its sidecar's pad radius overridden by ``r_eff_m`` (m; ``None``:
    unchanged), marked as coming from ``--r-eff``."""
    if r_eff_m is None:
        return trace
    side = dict(trace.sidecar) | {"r_eff_m": float(r_eff_m), "_r_eff_source": "--r-eff"}
    return dataclasses.replace(trace, sidecar=side)


def _check_r_eff(value: float, where: str) -> float:
    lo, hi = R_EFF_RANGE_M
    if not r_eff_ok(value):
        raise CampaignError(f"{where}: r_eff_m must be a pad radius within {lo} to {hi} m, "
                            f"got {value!r}")
    return float(value)


def _check_mapping(path: Path, where: str) -> Path:
    if not path.is_file():
        raise CampaignError(f"{where}: mapping file {path} not found; fix the path")
    try:
        load_mapping(path)
    except TraceError as err:
        raise CampaignError(f"{where}: {err}") from None
    return path


def _plain(value: Any) -> Any:
    if hasattr(value, "item") and not isinstance(value, str | bytes):
        value = value.item()
    if isinstance(value, float) and math.isnan(value):
        return None
    if hasattr(value, "isoformat"):  # dates and timestamps
        return value.isoformat()
    return value


def _is_empty(value: Any) -> bool:
    return value is None or (isinstance(value, str) and not value.strip())


def read_manifest(
    path: Path,
    *,
    mapping: Path | None = None,
    r_eff_m: float | None = None,
    reserved: tuple[str, ...] = (),
) -> Campaign:
    """The campaign a manifest table lists (see the module docstring).

    Parameters
    ----------
    path
        ``.csv`` or ``.parquet`` manifest.
    mapping, r_eff_m
        Campaign-wide column mapping and pad radius (m), for rows that name none.
    reserved
        Column names the results table uses itself: a metadata column of that name is
        renamed ``meta_<name>`` (:attr:`Campaign.renamed`).

    Raises
    ------
    CampaignError
        Naming the manifest, and the column or row, and what to do.
    """
    import pandas as pd

    suffix = path.suffix.lower()
    try:
        if suffix == ".csv":
            table = pd.read_csv(path, dtype={"path": str, "map": str}, skipinitialspace=True)
        elif suffix == ".parquet":
            table = pd.read_parquet(path)
        else:
            raise CampaignError(f"{path}: a manifest must be .csv or .parquet; give a folder, "
                                "a glob, or a manifest table")
    except CampaignError:
        raise
    except Exception as err:  # pandas' and pyarrow's parser errors have no common base
        raise CampaignError(f"{path}: cannot read the manifest ({error_line(err)}); give a CSV or "
                            "Parquet table with a 'path' column") from None
    table.columns = [str(c).strip() for c in table.columns]
    if "path" not in table.columns:
        hint = ("it looks like a trace, not a manifest: give its folder or a glob, or list it "
                "in a manifest's 'path' column" if "time_s" in table.columns else
                "add a 'path' column with each trace's file, relative to the manifest")
        raise CampaignError(f"{path}: no 'path' column (columns: {', '.join(table.columns)}); "
                            f"{hint}")
    if table.empty:
        raise CampaignError(f"{path}: the manifest has no rows; list at least one trace")
    given_cols = [c for c in table.columns if c not in SETTING_COLUMNS]
    renamed = {c: f"meta_{c}" for c in given_cols if c in reserved}
    taken = [n for n in renamed.values() if n in given_cols]
    if taken:
        raise CampaignError(f"{path}: column {taken[0]!r} is taken, and the metadata column "
                            f"{taken[0][5:]!r} is renamed to it in the results table (a column "
                            "of that name is the table's own); rename one of them")
    meta_cols = tuple(renamed.get(c, c) for c in given_cols)
    table = table.rename(columns=renamed)
    base = path.parent
    entries = []
    for k, row in enumerate(table.to_dict("records"), start=1):
        where = f"{path}: row {k}"
        given = row["path"]
        if _is_empty(_plain(given)):
            raise CampaignError(f"{where}: the path cell is empty; name the trace file")
        given = str(given).strip()
        file = base / given
        if not file.is_file():
            raise CampaignError(f"{where}: trace {given} not found (looked for {file}); fix the "
                                "path (relative to the manifest's folder)")
        row_map = _plain(row.get("map"))
        row_mapping = (_check_mapping(base / str(row_map).strip(), f"{where}, column map")
                       if not _is_empty(row_map) else mapping)
        row_r = _plain(row.get("r_eff_m"))
        if _is_empty(row_r):
            row_r = r_eff_m
        else:
            try:
                row_r = _check_r_eff(float(row_r), f"{where}, column r_eff_m")
            except (TypeError, ValueError):
                raise CampaignError(f"{where}, column r_eff_m: {row_r!r} is not a number; give "
                                    "the pad radius in metres or leave the cell empty") from None
        entries.append(Entry(given, file, {c: _plain(row[c]) for c in meta_cols}, row_mapping,
                             row_r))
    return Campaign(str(path), "manifest", tuple(entries), meta_cols, renamed)


def _is_manifest(path: Path) -> bool:
    """Whether a table has a ``path`` column (a manifest), from its header alone."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".csv":
            with open(path, encoding="utf-8-sig", errors="replace") as handle:
                header = handle.readline()
            return "path" in [c.strip().strip('"') for c in header.replace(";", ",").split(",")]
        if suffix == ".parquet":
            import pyarrow.parquet as pq

            return "path" in pq.ParquetFile(path).schema_arrow.names
    except Exception:  # an unreadable file: the log reader says what is wrong
        return False
    return False


def resolve_campaign(
    source: str,
    *,
    mapping: Path | None = None,
    r_eff_m: float | None = None,
    reserved: tuple[str, ...] = (),
    exclude: Path | None = None,
    logs: bool = False,
) -> Campaign:
    """The campaign named by a folder, a glob or a manifest (see :func:`read_manifest`).

    ``exclude``: a folder whose files a folder or glob never takes (the batch's own
    output folder, whose tables are not traces). ``logs``: the files are long logs to
    split into cycles, and a single file without a ``path`` column is one such log, not a
    manifest.

    Raises
    ------
    CampaignError
        A source that names no trace, or a setting out of range.
    """
    if r_eff_m is not None:
        _check_r_eff(r_eff_m, "--r-eff")
    if mapping is not None:
        _check_mapping(mapping, "--map")
    path = Path(source)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in SUFFIXES)
        kind = "folder"
        if not files:
            raise CampaignError(f"{source}: the folder holds no trace files "
                                f"({', '.join(SUFFIXES)}); name another folder or a manifest")
    elif path.is_file() and logs and not _is_manifest(path):
        return Campaign(source, "file", (Entry(source, path, {}, mapping, r_eff_m),), ())
    elif path.is_file():
        return read_manifest(path, mapping=mapping, r_eff_m=r_eff_m, reserved=reserved)
    elif any(ch in source for ch in "*?["):
        kind = "glob"
        files = sorted(Path(p) for p in glob.glob(source, recursive=True)
                       if Path(p).is_file() and Path(p).suffix.lower() in SUFFIXES)
        if not files:
            raise CampaignError(f"{source}: the pattern matches no trace files "
                                f"({', '.join(SUFFIXES)}); check it (quote it in the shell)")
    else:
        raise CampaignError(f"{source}: no such file or folder; give a manifest (.csv or "
                            ".parquet), a folder of traces, or a glob")
    if exclude is not None:
        skip = exclude.resolve()
        files = [p for p in files if not p.resolve().is_relative_to(skip)]
        if not files:
            raise CampaignError(f"{source}: every trace file it names is in the output folder "
                                f"{exclude}; choose another --out")
    entries = tuple(Entry(str(p), p, {}, mapping, r_eff_m) for p in files)
    return Campaign(source, kind, entries, ())
