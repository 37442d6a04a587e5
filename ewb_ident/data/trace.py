"""Rig traces: the in-memory record of one brake-rig recording, and its file formats.

A :class:`Trace` holds validated float64 NumPy arrays in SI units (angle in degrees,
as in the trace format v1). This module holds the record, its columns and the message
format every problem uses; reading is :mod:`ewb_ident.data.readers`, column mapping and
units :mod:`ewb_ident.data.units`, validation :mod:`ewb_ident.data.validation` and
writing :mod:`ewb_ident.data.writers`. Nothing in this package knows about the model.

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
   from 0.02 to 0.5 m, ``disc_mode`` ``drag`` or ``coast``, ``coast`` with
   ``disc_inertia_kg_m2``.
5. Units (``check_units=True``): sizes after the mapping's conversion that are not
   physical for an EWB rig (stroke, pinion travel, gap lead, voltage, current, force,
   the friction coefficient torque and force imply, disc speed), whatever unit the
   mapping declared; the message names the likely unit.
6. Stages: for the force, torque and chain stages a force that rises by at least
   200 N (the brake clamped); the columns each requested stage needs.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, NoReturn

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

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


DEFAULT_R_EFF_M = 0.15


#: Longest run of consecutive missing samples that ``nan_policy="interpolate"`` fills.
MAX_GAP = 5

NanPolicy = Literal["raise", "interpolate"]


class EWBIdentError(Exception):
    """The base of every error the tool raises on purpose: :class:`InputError` (input
    the caller can fix, a ``ValueError``) and the study runner's ``ScriptError`` and
    ``ClusterError`` (each a ``RuntimeError``). ``except EWBIdentError`` catches them all
    and lets a bug through."""


class InputError(EWBIdentError, ValueError):
    """Input the caller can fix: a trace, a mapping, an option, a parameters or study
    file, a prior. The message is one line naming what and where and what to do (the
    command line prints it and exits with code 2). Every such error of the package
    derives from it, so ``except InputError`` catches them all; it is a ``ValueError``
    too, as it always was."""


class TraceError(InputError):
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
        return mapped_sources(self.sidecar)

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
        import pandas as pd

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


def error_line(err: BaseException) -> str:
    """An exception's message on one line (its whitespace collapsed), or its type's name
    when it has none."""
    return " ".join(str(err).split()) or type(err).__name__


def raise_trace_error(
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


def refuse_unknown_channel(file: str, name: str) -> NoReturn:
    """Raise :class:`TraceError`: ``name`` is not a channel of :data:`COLUMNS`."""
    raise_trace_error(
        file,
        "not a trace channel",
        f"channels are {', '.join(c for c in COLUMNS if c != 'time_s')}",
        column=f"column {name!r}",
    )


def refuse_channel_shape(file: str, name: str, shape: Any, time_shape: Any) -> NoReturn:
    """Raise :class:`TraceError`: channel ``name`` has ``shape``, not that of ``time_s``
    (``time_shape``)."""
    raise_trace_error(
        file,
        f"has shape {shape}, time_s has {time_shape}",
        "give every channel as a 1-D array of the same length as time_s",
        column=f"column {name!r}",
    )


def column_label(name: str, sources: Mapping[str, str] | None = None) -> str:
    """``column 'name'``, or ``column 'source' (mapped to 'name')`` for a mapped column."""
    source = (sources or {}).get(name)
    if source is not None and source != name:
        return f"column {source!r} (mapped to {name!r})"
    return f"column {name!r}"


def fmt6(value: float) -> str:
    return f"{value:.6g}"


def mapped_sources(sidecar: Mapping[str, Any]) -> dict[str, str]:
    mapped = sidecar.get("_mapped", {})
    return {t: str(m.get("source", t)) for t, m in mapped.items() if isinstance(m, Mapping)}


def declared_units(sidecar: Mapping[str, Any]) -> set[str]:
    mapped = sidecar.get("_mapped", {})
    return {t for t, m in mapped.items() if isinstance(m, Mapping) and m.get("unit")}
