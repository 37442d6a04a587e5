"""A long recording (an endurance log) split into its apply cycles.

The rule (:func:`split_cycles`), on one *split channel*: the clamping force
``force_N`` when recorded, else the piston travel ``x_m``, else the pinion angle
``theta_deg`` (each rises when the brake applies):

1. ``floor`` and ``top`` are the channel's 1st and 99th percentiles over the log; the
   brake is *applied* where the channel is above ``floor + on_fraction (top - floor)``
   (default 10 % of the way from released to fully applied).
2. Applied stretches closer than ``merge_gap_s`` (0.2 s) are one apply; an apply shorter
   than ``min_apply_s`` (0.1 s) is noise and dropped.
3. Each apply's *cycle* starts ``lead_s`` (1.0 s) before the channel rises above the
   threshold, so that it begins at rest, before the motor moves, and lasts
   ``lead_s + (the log's longest apply) + tail_s`` (tail 1.0 s): every cycle of a log is
   equally long, and their fits share one compiled program. A cycle never reaches past
   the start of the next one, nor starts before the end of the previous one; an apply
   cut by the log's start or end (applied at its first or last sample) is *partial* and
   not fitted.

Each cycle becomes an ordinary trace (time from 0, SI units, the log's sidecar plus
``log`` and ``log_t_start_s``), fitted as one trace of a campaign.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ewb_ident.data.trace import InputError, Trace

#: Split channels, in the order of preference.
SPLIT_CHANNELS = ("force_N", "x_m", "theta_deg")
#: Metadata columns each cycle gets (after its log's own), see :func:`cycle_campaign`.
CYCLE_COLUMNS = ("log", "cycle", "t_start_s", "t_rise_s", "time_h")


class CycleError(InputError):
    """A log that cannot be split into apply cycles (the message says why)."""


@dataclass(frozen=True)
class CycleRule:
    """The settings of the split (see the module docstring); times in s."""

    channel: str | None = None
    on_fraction: float = 0.1
    merge_gap_s: float = 0.2
    min_apply_s: float = 0.1
    lead_s: float = 1.0
    tail_s: float = 1.0


@dataclass(frozen=True)
class Cycle:
    """One apply cycle of a log.

    Attributes
    ----------
    index
        1-based, in time order (partial cycles counted too).
    start, stop
        Sample indices of the cycle's window, ``[start, stop)``.
    t_start_s, t_end_s
        The window's first and last sample time, s (the log's time).
    rise_s, fall_s
        When the split channel rose above and fell back below the threshold, s.
    partial
        Cut by the log's start or end: not fitted.
    """

    index: int
    start: int
    stop: int
    t_start_s: float
    t_end_s: float
    rise_s: float
    fall_s: float
    partial: bool = False

    def as_row(self) -> dict[str, Any]:
        return dataclasses.asdict(self) | {"samples": self.stop - self.start}


@dataclass(frozen=True)
class Split:
    """The cycles of a log and how they were found."""

    channel: str
    threshold: float
    floor: float
    top: float
    rule: CycleRule
    cycles: tuple[Cycle, ...]

    @property
    def complete(self) -> tuple[Cycle, ...]:
        """The cycles that are fitted (not partial)."""
        return tuple(c for c in self.cycles if not c.partial)


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and stop indices (``[start, stop)``) of the runs of True."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def split_channel(trace: Trace, channel: str | None = None) -> str:
    """The channel the split reads: ``channel`` if given, else the first of
    :data:`SPLIT_CHANNELS` the log records."""
    if channel is not None:
        if not trace.has(channel) or channel == "time_s":
            raise CycleError(f"{trace.label}: cannot split on {channel!r}: the log has no such "
                             f"channel (it has {', '.join(trace.channels)})")
        return channel
    for name in SPLIT_CHANNELS:
        if trace.has(name):
            return name
    raise CycleError(f"{trace.label}: none of {', '.join(SPLIT_CHANNELS)} is recorded; the "
                     "apply cycles are found from the force, piston travel or pinion angle")


def split_cycles(trace: Trace, rule: CycleRule = CycleRule()) -> Split:  # noqa: B008
    """Find the apply cycles of a log by the rule of the module docstring.

    Raises
    ------
    CycleError
        No split channel, a channel that does not move, or no complete apply cycle.
    """
    name = split_channel(trace, rule.channel)
    y = trace[name]
    t = trace.time_s
    dt = trace.dt
    floor, top = (float(v) for v in np.percentile(y, [1.0, 99.0]))
    if not top > floor:
        raise CycleError(f"{trace.label}: {name} does not move (its 1st and 99th percentiles "
                         f"are both {floor:.6g}): no apply to split the log at")
    threshold = floor + rule.on_fraction * (top - floor)
    starts, stops = _runs(y > threshold)
    if starts.size > 1:  # merge applies separated by less than merge_gap_s
        keep = np.concatenate(([True], (starts[1:] - stops[:-1]) * dt >= rule.merge_gap_s))
        starts, stops = starts[keep], np.concatenate((stops[:-1][keep[1:]], stops[-1:]))
    long_enough = (stops - starts) * dt >= rule.min_apply_s
    starts, stops = starts[long_enough], stops[long_enough]
    if starts.size == 0:
        raise CycleError(f"{trace.label}: no apply found ({name} above {threshold:.6g} for at "
                         f"least {rule.min_apply_s:g} s)")
    n = trace.n
    partial = (starts == 0) | (stops == n)
    whole = ~partial
    longest = int(np.max(stops[whole] - starts[whole])) if whole.any() else 0

    def samples(seconds: float) -> int:  # (1.0 s at 200 Hz is 200 samples, not 201)
        return int(math.ceil(seconds / dt - 1e-6))

    lead = samples(rule.lead_s)
    length = lead + longest + samples(rule.tail_s)
    cycles = []
    for k, (a, b, cut) in enumerate(zip(starts, stops, partial, strict=True)):
        lo = a - lead
        if k > 0:
            lo = max(lo, int(stops[k - 1]))
        hi = lo + length
        if k + 1 < starts.size:
            hi = min(hi, int(starts[k + 1]) - lead)
        lo, hi = max(lo, 0), min(hi, n)
        cut = bool(cut) or hi <= b  # a window that cannot hold its apply
        cycles.append(Cycle(k + 1, int(lo), int(hi), float(t[lo]), float(t[hi - 1]),
                            float(t[a]), float(t[b - 1]), cut))
    split = Split(name, threshold, floor, top, rule, tuple(cycles))
    if not split.complete:
        raise CycleError(f"{trace.label}: every apply found is cut by the log's start or end "
                         "(no complete cycle); give a longer log")
    return split


def cycle_trace(trace: Trace, cycle: Cycle, log: str) -> Trace:
    """The samples of one cycle as a trace: time from 0, the log's sidecar (its public
    keys) with ``log`` (the log's path) and ``log_t_start_s`` (the cycle's start in the
    log, s)."""
    window = slice(cycle.start, cycle.stop)
    side = {k: v for k, v in trace.sidecar.items() if not str(k).startswith("_")}
    side |= {"log": log, "log_cycle": cycle.index, "log_t_start_s": cycle.t_start_s}
    if "_r_eff_source" in trace.sidecar:
        side["_r_eff_source"] = trace.sidecar["_r_eff_source"]
    return Trace(
        name=f"cycle_{cycle.index:05d}",
        time_s=trace.time_s[window] - trace.time_s[cycle.start],
        channels={c: v[window] for c, v in trace.channels.items()},
        sidecar=side,
    )


@dataclass(frozen=True)
class LogSplit:
    """One log of a campaign as split, kept small for the report: its name (the path as
    given), the :class:`Split`, the split channel's envelope over the whole log (time,
    min and max per bin of at most ``bins`` bins) and its samples over the first three
    complete cycles (time, value)."""

    name: str
    split: Split
    envelope: tuple[np.ndarray, np.ndarray, np.ndarray]
    zoom: tuple[np.ndarray, np.ndarray]

    @classmethod
    def of(cls, name: str, trace: Trace, split: Split, bins: int = 4000) -> LogSplit:
        t, y = trace.time_s, trace[split.channel]
        step = max(1, y.size // bins)
        m = y.size // step * step
        envelope = (t[:m:step].copy(), y[:m].reshape(-1, step).min(1),
                    y[:m].reshape(-1, step).max(1))
        first = split.complete[:3]
        window = slice(first[0].start, first[-1].stop)
        return cls(name, split, envelope, (t[window].copy(), y[window].copy()))


def cycle_campaign(
    campaign,
    folder,
    *,
    rule: CycleRule = CycleRule(),  # noqa: B008
    fill_gaps: bool = False,
    check_units: bool = True,
):
    """Read each log of ``campaign``, split it into its apply cycles and write every
    complete cycle as a Parquet trace ``folder/<log stem>/cycle_NNNNN.parquet`` (with its
    sidecar): the campaign of cycles, whose entries carry the log's metadata plus
    ``log``, ``cycle``, ``t_start_s`` (the window's start in the log), ``t_rise_s`` and
    ``time_h`` (the rise, hours from the log's first sample).

    Returns
    -------
    cycles, splits, table
        The campaign of cycles (:class:`ewb_ident.data.campaign.Campaign`, kind
        ``"cycles"``), the :class:`LogSplit` of each log, and the split as a table: one
        row per cycle found (``log``, ``cycle``, ``trace`` (the file written; empty for a
        partial cycle), ``start``, ``stop``, ``samples``, ``t_start_s``, ``t_end_s``,
        ``rise_s``, ``fall_s``, ``partial``, ``channel``, ``threshold``).

    Raises
    ------
    TraceError, CycleError
        A log that cannot be read (the reader's message), or split.
    """
    from pathlib import Path

    import pandas as pd

    from ewb_ident.data.campaign import Campaign, Entry, with_pad_radius
    from ewb_ident.data.readers import MAX_LOG_SAMPLES, read_trace
    from ewb_ident.data.writers import write_trace

    folder = Path(folder)
    splits, entries, rows = [], [], []
    stems = [e.path.stem for e in campaign.entries]
    for entry in campaign.entries:
        log = read_trace(entry.path, mapping=entry.mapping, stages=("chain",),
                         nan_policy="interpolate" if fill_gaps else "raise",
                         check_units=check_units, max_samples=MAX_LOG_SAMPLES)
        log = with_pad_radius(log, entry.r_eff_m)
        split = split_cycles(log, rule)
        splits.append(LogSplit.of(entry.trace, log, split))
        stem = entry.path.stem if stems.count(entry.path.stem) == 1 else \
            f"{len(splits)}_{entry.path.stem}"
        t0 = float(log.time_s[0])
        for cycle in split.cycles:
            path = folder / stem / f"cycle_{cycle.index:05d}.parquet"
            rows.append({"log": entry.trace, "cycle": cycle.index,
                         "trace": None if cycle.partial else str(path),
                         **{k: v for k, v in cycle.as_row().items() if k != "index"},
                         "channel": split.channel, "threshold": split.threshold})
            if cycle.partial:
                continue
            path.parent.mkdir(parents=True, exist_ok=True)
            write_trace(cycle_trace(log, cycle, entry.trace), path)
            meta = dict(entry.metadata) | {
                "log": entry.trace, "cycle": cycle.index, "t_start_s": cycle.t_start_s,
                "t_rise_s": cycle.rise_s, "time_h": (cycle.rise_s - t0) / 3600.0}
            entries.append(Entry(str(path), path, meta, None, entry.r_eff_m))
        del log  # one log in memory at a time
    columns = (*campaign.metadata_columns, *CYCLE_COLUMNS)
    cycles = Campaign(campaign.source, "cycles", tuple(entries), columns, campaign.renamed)
    return cycles, splits, pd.DataFrame(rows)
