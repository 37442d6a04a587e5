"""Validation of a trace: time base, sidecar, units, arrays and the channels each stage
needs. Every problem is one line naming file, column, row and what to do."""

from __future__ import annotations

import math
import numbers
import os
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
    refuse_channel_shape,
    refuse_unknown_channel,
)

_MIN_RATE_HZ = 100.0
_MAX_RATE_HZ = 1000.0
_RATE_SLACK = 0.01
_UNIFORM_TOL = 0.01
_MIN_SAMPLES = 50
_MIN_DURATION_S = 0.2
#: The effective pad radius, m, from the sidecar (``r_eff_m``) or the CLI (``--r-eff``):
#: one range for both.
R_EFF_RANGE_M = (0.02, 0.5)
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


def r_eff_ok(value: Any) -> bool:
    """Whether ``value`` is a pad radius in :data:`R_EFF_RANGE_M` (sidecar and CLI)."""
    lo, hi = R_EFF_RANGE_M
    return is_number(value) and lo <= float(value) <= hi


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
        lo, hi = 1.0 / (_MAX_RATE_HZ * (1 + _RATE_SLACK)), 1.0 / (_MIN_RATE_HZ * (1 - _RATE_SLACK))
        likely = likely_unit(trace, "time_s", median, lo, hi)
        looks = f": looks like {UNIT_WORDS[likely]} ({likely!r})" if likely else ""
        raise_trace_error(
            label,
            f"sample rate {fmt6(rate)} Hz (median interval {fmt6(median)} s) is outside"
            f" 100 Hz to 1 kHz{looks}",
            unit_fix(trace, "time_s", likely)
            if likely
            else "resample the log to a rate from 100 Hz to 1 kHz",
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
        lo, hi = R_EFF_RANGE_M
        if not r_eff_ok(value):
            raise_trace_error(
                label,
                f"{value!r} is not a number from {lo} to {hi} m",
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


# Plausible sizes of each channel after unit conversion, from the rig's physics rather
# than from this project's rig: other rigs (pad radius 0.1-0.3 m, 12-48 V supplies,
# 100 Hz to 1 kHz) sit well inside them, and a wrong unit (a factor 1000, or 57.3 for
# degrees and radians) lands outside.
#: The piston's stroke: the wedge closes a gap and compresses the caliper, a fraction of
#: a millimetre to a few millimetres; an apply moves it by at least 10 um (the LVDT's
#: noise is ~1 um) and never by a centimetre (the bell's half-width a < 1 cm).
STROKE_M = (1.0e-5, 1.0e-2)
#: The gap's lead dx/dtheta (the gap polynomial's slope, p1 + 2 p2 theta): 0.09 to 9 mm
#: per pinion revolution (the seed rig 0.54 mm).
LEAD_M_PER_DEG = (2.5e-7, 2.5e-5)
#: The pinion's travel: at least 4*pi degrees (less looks like radians), at most the
#: largest stroke at the smallest lead (40,000 deg, 111 turns).
THETA_TRAVEL_DEG = (4.0 * math.pi, STROKE_M[1] / LEAD_M_PER_DEG[0])
#: The motor voltage's peak: at least 1 % of the smallest supply (12 V), at most twice
#: the largest (48 V).
VOLTAGE_V = (0.12, 100.0)
#: The motor current's peak: at least a small motor's no-load current, at most the
#: largest supply's stall current on a 0.25 Ohm armature (48 V / 0.25 Ohm ~ 200 A).
CURRENT_A = (0.05, 200.0)
#: The clamping force's peak: at most 50 kN (the seed rig's 3.5 kN rated force times 14).
FORCE_MAX_N = 50000.0
#: The pad friction coefficient a torque and force imply, T / (2 F r_eff): brake pads
#: hold 0.1 to 0.6; the margins leave room for a wrong pad radius.
APPARENT_MU = (0.02, 1.2)
#: The disc speed's peak: a road wheel at 300 km/h on a 0.25 m rolling radius turns at
#: 333 rad/s.
DISC_SPEED_MAX_RAD_S = 400.0


#: Unit symbols in words, for messages.
UNIT_WORDS = {
    "s": "seconds", "ms": "milliseconds", "V": "volts", "mV": "millivolts",
    "A": "amperes", "mA": "milliamperes", "deg": "degrees", "rad": "radians",
    "m": "metres", "mm": "millimetres", "um": "micrometres", "N": "newtons",
    "kN": "kilonewtons", "rad/s": "radians per second", "rpm": "revolutions per minute",
}  # fmt: skip


def unit_fix(trace: Trace, name: str, likely: str | None) -> str:
    """What to do about a channel whose size suggests a wrong unit: the mapping's
    declared unit to check, or the mapping to write, and the override."""
    sources = mapped_sources(trace.sidecar)
    source = sources.get(name, name)
    said = _declared(trace, name)
    if said is not None:
        guess = f" (is it {likely!r}?)" if likely else ""
        return (
            f"the mapping declares {source!r} in {said!r}: check that unit{guess}, or if the"
            f" values are right {_UNIT_OVERRIDE}"
        )
    if likely is None:
        return f"check the sensor's scaling, or if the values are right {_UNIT_OVERRIDE}"
    return (
        f"map the column with its unit (mapping={{{source!r}: {{'column': "
        f"{name!r}, 'unit': {likely!r}}}}}), or if the values are right {_UNIT_OVERRIDE}"
    )


def _declared(trace: Trace, name: str) -> str | None:
    if name not in declared_units(trace.sidecar):
        return None
    return str(trace.sidecar["_mapped"][name]["unit"])


def likely_unit(trace: Trace, name: str, value: float, lo: float, hi: float) -> str | None:
    """The unit of ``name``'s quantity that would put ``value`` (a size after conversion
    from the declared unit, or the column's own) inside ``[lo, hi]``; the one nearest
    the range's middle (in log), or None."""
    from ewb_ident.data.units import UNITS

    unit = COLUMNS[name]
    said = _declared(trace, name) or unit
    quantity, size = UNITS[said]
    middle = math.log(math.sqrt(lo * hi)) if lo > 0 else math.log(hi)
    best: tuple[float, str] | None = None
    for u, (q, s) in UNITS.items():
        if q != quantity or u == said:
            continue
        v = value * s / size
        if lo <= v <= hi and v > 0:
            score = abs(math.log(v) - middle)
            if best is None or score < best[0]:
                best = (score, u)
    return None if best is None else best[1]


def _check_units(trace: Trace) -> None:
    sources = mapped_sources(trace.sidecar)
    ch = trace.channels

    def refuse(name: str, what: str, value: float, lo: float, hi: float, row=None) -> None:
        unit = "deg" if name == "theta_deg" else COLUMNS[name]
        said = _declared(trace, name)
        after = f" (after conversion from {said!r})" if said and said != unit else ""
        likely = likely_unit(trace, name, value, lo, hi)
        looks = f": looks like {UNIT_WORDS.get(likely, likely)} ({likely!r})" if likely else ""
        raise_trace_error(
            trace.label,
            f"{what} {fmt6(value)} {unit}{after}, outside the plausible {fmt6(lo)} to"
            f" {fmt6(hi)} {unit}{looks}",
            unit_fix(trace, name, likely),
            column=column_label(name, sources),
            row=row,
        )

    def peak(name: str) -> tuple[float, int]:
        values = np.abs(ch[name])
        i = int(np.argmax(values))
        return float(values[i]), i + 1

    def travel(name: str) -> float:
        return float(np.max(ch[name]) - np.min(ch[name]))

    if "x_m" in ch:
        value, row = peak("x_m")
        if value > STROKE_M[1]:
            refuse("x_m", "the piston's |x| reaches", value, *STROKE_M, row=row)
        if 0.0 < travel("x_m") < STROKE_M[0]:  # (a constant column is no unit's fault)
            refuse("x_m", "the piston's stroke (max - min of x) is", travel("x_m"), *STROKE_M)
    if "theta_deg" in ch:
        lo, hi = THETA_TRAVEL_DEG
        value, _ = peak("theta_deg")
        if 0.0 < value < lo:
            refuse("theta_deg", "the pinion's |theta| stays below", value, lo, hi)
        if travel("theta_deg") > hi:
            refuse("theta_deg", "the pinion's travel (max - min of theta) is",
                   travel("theta_deg"), lo, hi)  # fmt: skip
    for name, what, (lo, hi) in (
        ("voltage_V", "the motor voltage's peak |V| is", VOLTAGE_V),
        ("current_A", "the motor current's peak |i| is", CURRENT_A),
        ("force_N", "the clamping force's peak |F| is", (0.0, FORCE_MAX_N)),
        ("disc_speed_rad_s", "the disc speed's peak is", (0.0, DISC_SPEED_MAX_RAD_S)),
    ):
        if name in ch:
            value, row = peak(name)
            if value > hi or 0.0 < value < lo:
                refuse(name, what, value, lo, hi, row=row if value > hi else None)
    if "x_m" in ch and "theta_deg" in ch:
        # Both sizes are plausible alone; their ratio is the gap's lead, which a wrong
        # unit on either (degrees declared radians: 57.3 times) puts outside its range.
        lead = travel("x_m") / max(travel("theta_deg"), 1e-300)
        lo, hi = LEAD_M_PER_DEG
        if travel("x_m") > 0.0 and travel("theta_deg") > 0.0 and not lo <= lead <= hi:
            x_travel = travel("x_m")
            fits = (x_travel / hi, x_travel / lo)  # the pinion travels that would fit x
            raise_trace_error(
                trace.label,
                f"the piston moves {fmt6(x_travel)} m over {fmt6(travel('theta_deg'))} deg of"
                f" pinion travel, a gap lead of {fmt6(lead)} m/deg, outside the plausible"
                f" {fmt6(lo)} to {fmt6(hi)} m/deg (0.09 to 9 mm per turn): theta_deg and x_m"
                " cannot both be in the units read",
                unit_fix(
                    trace, "theta_deg", likely_unit(trace, "theta_deg", travel("theta_deg"), *fits)
                ),
                column=column_label("theta_deg", sources),
            )
    if "force_N" in ch and "torque_Nm" in ch:
        force, _ = peak("force_N")
        torque, row = peak("torque_Nm")
        if force >= _MIN_FORCE_RISE_N:
            mu = torque / (2.0 * force * trace.r_eff_m)
            lo, hi = APPARENT_MU
            if not lo <= mu <= hi:
                raise_trace_error(
                    trace.label,
                    f"the torque's peak {fmt6(torque)} N*m at a force peak of {fmt6(force)} N"
                    f" and pad radius {fmt6(trace.r_eff_m)} m means a pad friction coefficient"
                    f" T/(2 F r_eff) of {fmt6(mu)}, outside the plausible {lo} to {hi}",
                    "check the torque sensor's scaling, the force column's unit and the"
                    f" sidecar's r_eff_m, or if the values are right {_UNIT_OVERRIDE}",
                    column=column_label("torque_Nm", sources),
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
            # A clamping force logged in kN and read as N (a rise of a few "N", below a
            # force sensor's noise band of tens of N) is as small as one never reached.
            likely = (
                likely_unit(trace, "force_N", rise, _MIN_FORCE_RISE_N, FORCE_MAX_N)
                if rise < 0.1 * _MIN_FORCE_RISE_N
                else None
            )
            looks = f" (or looks like {UNIT_WORDS[likely]}, {likely!r})" if likely else ""
            raise_trace_error(
                label,
                f"force never rises above {fmt6(top)} N (range {fmt6(rise)} N < 200 N): no"
                f" clamping was reached{looks}, so the force stage cannot be fitted",
                "record an apply that clamps the brake"
                + (f"; or {unit_fix(trace, 'force_N', likely)}" if likely else ""),
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
            refuse_unknown_channel(label, name)
        if not isinstance(values, np.ndarray) or values.shape != t.shape:
            refuse_channel_shape(label, name, getattr(values, "shape", None), t.shape)
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
        Refuse values whose size, after the mapping's conversion, is not physical for an
        EWB rig (a wrong unit, declared or not): the piston's stroke (:data:`STROKE_M`),
        the pinion's travel (:data:`THETA_TRAVEL_DEG`), the gap's lead x/theta
        (:data:`LEAD_M_PER_DEG`), the voltage's and current's peaks (:data:`VOLTAGE_V`,
        :data:`CURRENT_A`), the force's (:data:`FORCE_MAX_N`), the friction coefficient
        torque and force imply (:data:`APPARENT_MU`) and the disc speed's. The message
        names the column, the size, the plausible range and the likely unit.

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


# --------------------------------------------------------------------------- API entry

#: Sidecar bookkeeping key: the trace was read with ``check_units=False`` (CLI
#: ``--no-unit-check``), so the library does not check its units again.
UNITS_UNCHECKED = "_units_unchecked"


def check_traces(
    traces: Any, *, argument: str = "traces", stages: Iterable[str] | str | None = None
) -> tuple[Trace, ...]:
    """The one check of the traces a command or a library function is given.

    ``fit``, ``sample``, ``diagnose`` and ``validate`` of the Python API call this on
    what they are given, and the command line on the traces it read, so both refuse
    the same things in the same words: anything that is not a :class:`Trace` (a path
    string: read it first), a trace that fails :func:`validate` (arrays, missing
    values, a time base that is not uniform and increasing, sidecar, units unless the
    trace was read with ``check_units=False``), and the same samples given twice.

    Parameters
    ----------
    traces
        One trace or a sequence of traces.
    argument
        The argument's name, for messages.
    stages
        Stages the traces are to serve (:func:`check_stages`: their columns, and a force
        that clamps for the force, torque and chain stages).

    Returns
    -------
    tuple of Trace

    Raises
    ------
    TypeError
        For anything that is not a trace or a sequence of traces.
    TraceError
        For a trace that fails a check, or a trace whose samples repeat another's.
    """
    if isinstance(traces, Trace):
        traces = (traces,)
    elif isinstance(traces, str | bytes | os.PathLike):
        raise TypeError(
            f"{argument}: got the path {os.fsdecode(traces)!r}, not a Trace; read it first:"
            f" ewb_ident.read_trace({os.fsdecode(traces)!r})"
        )
    elif not isinstance(traces, Iterable) or isinstance(traces, Mapping):
        raise TypeError(
            f"{argument}: got an object of type {type(traces).__name__}, not a Trace or a"
            " sequence of traces; read traces with ewb_ident.read_trace"
        )
    out = tuple(traces)
    for k, tr in enumerate(out):
        if not isinstance(tr, Trace):
            what = "the path" if isinstance(tr, str | os.PathLike) else "a"
            shown = repr(os.fsdecode(tr)) if isinstance(tr, str | os.PathLike) else ""
            raise TypeError(
                f"{argument}[{k}]: got {what} {shown or 'object of type ' + type(tr).__name__},"
                " not a Trace;"
                " read it first with ewb_ident.read_trace"
            )
        validate(tr, stages=stages, check_units=not tr.sidecar.get(UNITS_UNCHECKED, False))
    check_repeats(out)
    return out


def check_trace(trace: Any, *, argument: str = "trace") -> Trace:
    """:func:`check_traces` of exactly one trace (``diagnose``, ``validate``)."""
    if not isinstance(trace, Trace) and isinstance(trace, Iterable):
        if not isinstance(trace, str | bytes | os.PathLike | Mapping):
            raise TypeError(f"{argument}: give one Trace, got a {type(trace).__name__}")
    (out,) = check_traces(trace, argument=argument)
    return out


def check_repeats(traces: tuple[Trace, ...]) -> None:
    """Refuse a recording given twice: its evidence would count twice (every standard
    error shrunk by 1/sqrt(2)) without a second measurement behind it."""
    for j, b in enumerate(traces):
        for i, a in enumerate(traces[:j]):
            if (
                a.n == b.n
                and a.channels
                and set(a.channels) == set(b.channels)
                and all(np.array_equal(a.channels[c], b.channels[c]) for c in a.channels)
            ):
                raise_trace_error(
                    b.label,
                    f"trace {j + 1} has the same samples as trace {i + 1} ({a.label}: every"
                    " column equal): a recording given"
                    " twice counts its evidence twice and shrinks every standard error by"
                    " 1/sqrt(2)",
                    "give each recording once",
                )
