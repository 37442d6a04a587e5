"""Validation of a trace: time base, sidecar, units, arrays and the channels each stage
needs. Every problem is one line naming file, column, row and what to do."""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from ewb_ident.data.stages import CHANNELS, STAGE_COLUMNS, STAGES
from ewb_ident.data.trace import (
    COLUMNS,
    DEFAULT_R_EFF_M,
    Trace,
    column_label,
    declared_units,
    fmt6,
    mapped_sources,
    raise_trace_error,
)

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
NAN_HINT = 'nan_policy="interpolate" (CLI --fill-gaps)'
_UNIT_OVERRIDE = "pass check_units=False (CLI --no-unit-check)"


# --------------------------------------------------------------------------- gaps


def first_nonfinite(
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
        raise_trace_error(
            label, "empty cell (missing value)", fix, column=column_label(name, sources), row=i + 1
        )
    raise_trace_error(
        label,
        f"value {value!r} is infinite",
        "fix the logger export (infinite values are never filled)",
        column=column_label(name, sources),
        row=i + 1,
    )


# --------------------------------------------------------------------------- public API


def parse_stages(stages: Iterable[str] | str | None, label: str) -> tuple[str, ...]:
    if stages is None:
        return ()
    if isinstance(stages, str):
        stages = (stages,)
    out: list[str] = []
    for stage in stages:
        if stage not in STAGES:
            raise_trace_error(label, f"unknown stage {stage!r}", f"stages are {', '.join(STAGES)}")
        if stage not in out:
            out.append(stage)
    return tuple(out)


def is_number(value: Any) -> bool:
    return (
        isinstance(value, numbers.Real)
        and not isinstance(value, bool | np.bool_)
        and math.isfinite(float(value))
    )


def _check_time(trace: Trace) -> None:
    label, t = trace.label, trace.time_s
    col = column_label("time_s", mapped_sources(trace.sidecar))
    fix_short = f"record at least {_MIN_SAMPLES} samples over at least {_MIN_DURATION_S} s"
    if t.shape[0] < 2:
        raise_trace_error(label, f"only {t.shape[0]} sample(s)", fix_short, column=col)
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        i = int(bad[0])
        raise_trace_error(
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
        raise_trace_error(
            label,
            f"interval {fmt6(dt[i])} s from row {i + 1} to row {i + 2} deviates from the median"
            f" interval {fmt6(median)} s by {fmt6(100 * abs(dt[i] - median) / median)} % (> 1 %):"
            " sampling is not uniform",
            "export without dropped samples or resample the log to a constant rate",
            column=col,
            row=i + 2,
        )
    rate = 1.0 / median
    if not _MIN_RATE_HZ * (1 - _RATE_SLACK) <= rate <= _MAX_RATE_HZ * (1 + _RATE_SLACK):
        raise_trace_error(
            label,
            f"sample rate {fmt6(rate)} Hz (median interval {fmt6(median)} s) is outside"
            " 100 Hz to 1 kHz",
            "resample the log to a rate from 100 Hz to 1 kHz (is time_s in seconds?"
            " map it with its unit, e.g. 'ms')",
            column=col,
        )
    duration = float(t[-1] - t[0])
    if t.shape[0] < _MIN_SAMPLES or duration < _MIN_DURATION_S:
        raise_trace_error(
            label,
            f"too short: {t.shape[0]} samples over {fmt6(duration)} s",
            fix_short,
            column=col,
        )


def _check_sidecar(trace: Trace) -> None:
    side = trace.sidecar
    label = str(trace.path.with_suffix(".json")) if trace.path is not None else trace.label
    if "sample_rate_hz" in side:
        value = side["sample_rate_hz"]
        rate = trace.sample_rate_hz
        if not is_number(value) or value <= 0:
            raise_trace_error(
                label,
                f"{value!r} is not a positive number of Hz",
                "fix or remove the key",
                key="sample_rate_hz",
            )
        if abs(float(value) - rate) > _RATE_SLACK * rate:
            raise_trace_error(
                label,
                f"{value!r} Hz disagrees with time_s ({fmt6(rate)} Hz, median interval"
                f" {fmt6(trace.dt)} s) by more than 1 %",
                "correct the sidecar or the time column",
                key="sample_rate_hz",
            )
    if "r_eff_m" in side:
        value = side["r_eff_m"]
        lo, hi = _R_EFF_RANGE_M
        if not is_number(value) or not lo < float(value) < hi:
            raise_trace_error(
                label,
                f"{value!r} is not a number in ({lo}, {hi}) m",
                f"give the effective pad radius in metres (default {DEFAULT_R_EFF_M} m"
                " when the key is absent)",
                key="r_eff_m",
            )
    mode = side.get("disc_mode")
    if "disc_mode" in side and mode not in _DISC_MODES:
        raise_trace_error(
            label,
            f"{mode!r} is not 'drag' or 'coast'",
            "use 'drag' (a dynamometer holds the disc speed) or 'coast' (a flywheel"
            " decelerates freely)",
            key="disc_mode",
        )
    if mode == "coast":
        inertia = side.get("disc_inertia_kg_m2")
        if inertia is None:
            raise_trace_error(
                label,
                "disc_mode 'coast' needs disc_inertia_kg_m2, which is missing",
                "add disc_inertia_kg_m2 (disc + flywheel inertia, kg*m^2) to the sidecar",
                key="disc_inertia_kg_m2",
            )
        if not is_number(inertia) or float(inertia) <= 0:
            raise_trace_error(
                label,
                f"{inertia!r} is not a positive number of kg*m^2",
                "give the disc + flywheel inertia in kg*m^2",
                key="disc_inertia_kg_m2",
            )


def _check_units(trace: Trace) -> None:
    sources = mapped_sources(trace.sidecar)
    declared = declared_units(trace.sidecar)

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
                raise_trace_error(
                    trace.label,
                    f"{symbol} reaches {fmt6(value)} {unit}, above {fmt6(limit)} {unit}: {looks}",
                    fix(name, guess),
                    column=column_label(name, sources),
                    row=row,
                )
    if "theta_deg" in trace.channels:
        value, _ = peak("theta_deg")
        if value < 4 * math.pi:
            raise_trace_error(
                trace.label,
                f"|theta| stays below {fmt6(value)} deg, less than 4*pi = 12.57: "
                "looks like radians",
                fix("theta_deg", "rad"),
                column=column_label("theta_deg", sources),
            )
    if "force_N" in trace.channels:
        value, row = peak("force_N")
        if value > 50000.0:
            raise_trace_error(
                trace.label,
                f"|force| reaches {fmt6(value)} N, above 50000 N: implausible for this rig",
                "check the sensor scaling, map the column with its unit (e.g. 'kN' for"
                f" kilonewtons), or {_UNIT_OVERRIDE}",
                column=column_label("force_N", sources),
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
    stage_list = parse_stages(stages, label)
    sources = mapped_sources(trace.sidecar)
    if "force_N" in trace.channels and any(s in _FORCE_STAGES for s in stage_list):
        force = trace.channels["force_N"]
        top, rise = float(np.max(force)), float(np.max(force) - np.min(force))
        if rise < _MIN_FORCE_RISE_N:
            raise_trace_error(
                label,
                f"force never rises above {fmt6(top)} N (range {fmt6(rise)} N < 200 N): no"
                " clamping was reached, so the force stage cannot be fitted",
                "record an apply that clamps the brake",
                column=column_label("force_N", sources),
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
                raise_trace_error(
                    label,
                    f"missing, but stage {stage!r}{f' ({flow})' if flow else ''} needs it{why}"
                    f" (the trace has {present})",
                    f"add the column, map a source column to it (mapping={{'source': {name!r}}}),"
                    f" or leave out stage {stage!r}",
                    column=f"column {name!r}",
                )
        if stage == "chain" and not any(trace.has(c) for c in CHANNELS):
            raise_trace_error(
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
        raise_trace_error(
            label,
            "must be a 1-D float64 array",
            "build traces with from_arrays or read_trace",
            column="column 'time_s'",
        )
    for name, values in trace.channels.items():
        if name not in COLUMNS or name == "time_s":
            raise_trace_error(
                label,
                "not a trace channel",
                f"channels are {', '.join(c for c in COLUMNS if c != 'time_s')}",
                column=f"column {name!r}",
            )
        if not isinstance(values, np.ndarray) or values.shape != t.shape:
            shape = getattr(values, "shape", None)
            raise_trace_error(
                label,
                f"has shape {shape}, time_s has {t.shape}",
                "give every channel as a 1-D array of the same length as time_s",
                column=f"column {name!r}",
            )
        if values.dtype != np.float64:
            raise_trace_error(
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
    first_nonfinite(
        {"time_s": trace.time_s, **trace.channels},
        trace.label,
        mapped_sources(trace.sidecar),
        f"fill the gap, or read the file with {NAN_HINT} to interpolate interior gaps",
    )
    _check_time(trace)
    _check_sidecar(trace)
    if check_units:
        _check_units(trace)
    check_stages(trace, stages)
