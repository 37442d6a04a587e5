"""Units a trace's columns may come in, and column mappings (source name -> trace
column and unit)."""

from __future__ import annotations

import json
import math
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ewb_ident.data.trace import COLUMNS, raise_trace_error

#: Units shown to a researcher instead of the SI ones (reports, summaries, tables):
#: SI unit -> (shown unit, factor).
SHOWN_UNITS = {"m": ("mm", 1e3), "m/deg": ("µm/deg", 1e6), "m/deg^2": ("nm/deg²", 1e9)}


def shown_unit(unit: str) -> tuple[str, float]:
    """The unit a value in the SI unit ``unit`` is shown in (mm for m; others as they
    are) and the factor from SI to it."""
    return SHOWN_UNITS.get(unit, (unit, 1.0))

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


def load_mapping(
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
            raise_trace_error(
                label, "a mapping file must be .json or .toml", "rename or convert the file"
            )
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            raise_trace_error(label, f"cannot read the mapping file ({err})", "check the path")
        try:
            mapping = json.loads(text) if suffix == ".json" else tomllib.loads(text)
        except (json.JSONDecodeError, tomllib.TOMLDecodeError) as err:
            raise_trace_error(
                label, f"invalid {suffix[1:].upper()} ({err})", "fix the mapping file"
            )
    if not isinstance(mapping, Mapping):
        raise_trace_error(
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
                raise_trace_error(
                    label,
                    f"{where}: keys {sorted(spec)} (need 'column', optional 'unit')",
                    'write {"column": "theta_deg", "unit": "rad"}',
                )
            target, unit = spec["column"], spec.get("unit")
        else:
            raise_trace_error(
                label,
                f"{where}: {spec!r} is neither a column name nor a table",
                'write {"column": "theta_deg", "unit": "rad"} or "theta_deg"',
            )
        if not isinstance(target, str) or target not in COLUMNS:
            raise_trace_error(
                label,
                f"{where}: unknown target column {target!r}",
                f"target columns are {targets}",
            )
        canonical = None
        if unit is not None:
            canonical = _canonical_unit(unit) if isinstance(unit, str) else None
            if canonical is None or UNITS[canonical][0] != UNITS[COLUMNS[target]][0]:
                raise_trace_error(
                    label,
                    f"{where}: unit {unit!r} cannot be converted to {COLUMNS[target]!r}"
                    f" (column {target!r})",
                    f"units allowed for {target} are {', '.join(_units_for(target))}",
                )
        if target in seen:
            raise_trace_error(
                label,
                f"{where}: target column {target!r} is also the target of {seen[target]!r}",
                "map each target column from one source column",
            )
        seen[target] = str(source)
        out[str(source)] = (target, canonical)
    return out


def convert_unit(values: np.ndarray, unit: str | None, target: str) -> np.ndarray:
    if unit is None:
        return values
    factor = UNITS[unit][1] / UNITS[COLUMNS[target]][1]
    return values if factor == 1.0 else values * factor
