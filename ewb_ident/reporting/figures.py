"""Figures of a diagnosis: where the model misses, and how each finding fixes it.

PNG files drawn with matplotlib's Agg backend (no display needed); every function
returns the figure and leaves global matplotlib state alone (no pyplot). The set that
``ewb-ident diagnose`` writes:

``mismatch.png``
    Residual over its noise floor, stage by stage, before (grey) and after (colour) the
    findings were added, with the phases of the brake application shaded.
``finding_<k>_<effect>.png``
    For each finding, the view an engineer would check: a discovered term against the
    signal it depends on (with the data's partial residuals where it adds to the
    output), displacement against angle
    (gap stage), force against displacement (force stage), apparent friction
    coefficient against disc speed or dissipated energy (torque stage), or the channels
    against time (motor and sensor mechanisms); model before and after, and the
    residual.
``chain.png``
    The whole chain from the voltage, each channel, before and after.

:func:`write_diagnosis` writes them with ``diagnosis.json``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

from ewb_ident.data.stages import STAGE_CHANNELS
from ewb_ident.reporting.style import (
    CHANNEL_LABELS,
    SCALE,
    fixed_margins,
    legend_with_phases,
    png_bytes,
    shade_phases,
)

if TYPE_CHECKING:
    from ewb_ident.diagnosis.result import DiagnosisResult, Finding


def mismatch_figure(result: DiagnosisResult) -> Figure:
    """Normalised residuals per stage before and after, phases shaded."""
    rows = [(s, ch) for s, ch in STAGE_CHANNELS if (s, ch) in result.checks_before]
    fig = Figure(figsize=(10, 1.9 * max(len(rows), 1) + 0.8))
    axes = fig.subplots(max(len(rows), 1), 1, sharex=True, squeeze=False)[:, 0]
    t = result.trace.time_s
    flagged = {(m.stage, m.channel) for m in result.mismatches}
    for ax, (stage, ch) in zip(axes, rows, strict=False):
        shade_phases(ax, t, result.labels)
        before = result.checks_before[(stage, ch)]
        ax.plot(t, before.normalized, color="0.6", lw=0.7, label="before")
        after = result.checks_after.get((stage, ch))
        if after is not None:
            ax.plot(t, after.normalized, color="C0", lw=0.7, label="after")
        ax.axhline(2, color="k", lw=0.5, ls=":")
        ax.axhline(-2, color="k", lw=0.5, ls=":")
        mark = "  <- mismatch located" if (stage, ch) in flagged else ""
        ax.set_ylabel(f"{stage}\n{ch}\nr / noise", fontsize=8)
        ax.set_title(f"{stage} stage, {ch}{mark}", fontsize=9, loc="left")
    legend_with_phases(axes[0], loc="upper right")
    axes[-1].set_xlabel("time, s")
    fig.suptitle(
        f"{result.trace_name[:60]}: residual over the noise floor  -  verdict: {result.verdict}",
        fontsize=10,
    )
    fixed_margins(fig, top=0.6, gap=0.35)
    return fig


def chain_figure(result: DiagnosisResult) -> Figure:
    """The whole chain from the voltage, each channel, before and after."""
    chans = [ch for _, ch in STAGE_CHANNELS if ch in result.chain_before and result.trace.has(ch)]
    fig = Figure(figsize=(10, 1.8 * max(len(chans), 1) + 0.8))
    axes = fig.subplots(max(len(chans), 1), 1, sharex=True, squeeze=False)[:, 0]
    t = result.trace.time_s
    for ax, ch in zip(axes, chans, strict=False):
        k = SCALE.get(ch, 1.0)
        ax.plot(t, result.trace[ch] * k, ".", ms=1.5, color="k", label="measured")
        ax.plot(t, result.chain_before[ch] * k, color="0.5", lw=1, label="model before")
        if ch in result.chain_after:
            ax.plot(t, result.chain_after[ch] * k, color="C1", lw=1, label="model after")
        b = result.baseline_metrics.get(ch, {}).get("nrmse_pct")
        a = result.augmented_metrics.get(ch, {}).get("nrmse_pct")
        if b is not None and a is not None:
            ax.set_title(f"{ch}: NRMSE {b:.2f} % -> {a:.2f} %", fontsize=9, loc="left")
        ax.set_ylabel(CHANNEL_LABELS.get(ch, ch), fontsize=8)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time, s")
    fig.suptitle(f"{result.trace_name[:60]}: whole chain from the voltage", fontsize=10)
    fixed_margins(fig, left=0.85, top=0.6, gap=0.35)
    return fig


def finding_figure(result: DiagnosisResult, finding: Finding) -> Figure:
    """The characteristic view of one finding, before and after, and its residual."""
    fig = Figure(figsize=(10, 6.5))
    top, bottom = fig.subplots(2, 1, height_ratios=(2, 1))
    tr = result.trace
    stage = finding.stage
    ch = _finding_channel(finding)
    before = result.checks_before.get((stage, ch))
    after = result.checks_after.get((stage, ch))
    drawn = False
    if finding.place and finding.term_series is not None and finding.term_input is not None:
        drawn = _learned_view(top, finding, after)
    if not drawn and before is not None and after is not None:
        view = _VIEWS.get(finding.effect) or _VIEWS.get(stage)
        if view is not None:
            drawn = view(top, tr, before, after)
    if not drawn and before is not None:
        k = SCALE.get(ch, 1.0)
        top.plot(tr.time_s, before.measured * k, ".", ms=1.5, color="k", label="measured")
        top.plot(tr.time_s, before.predicted * k, color="0.5", label="model before")
        if after is not None:
            top.plot(tr.time_s, after.predicted * k, color="C1", label="model after")
        top.set_xlabel("time, s")
        top.set_ylabel(CHANNEL_LABELS.get(ch, ch))
        top.legend(fontsize=8)
    if before is not None:
        shade_phases(bottom, tr.time_s, result.labels)
        k = SCALE.get(ch, 1.0)
        bottom.plot(tr.time_s, before.residual * k, color="0.6", lw=0.7, label="before")
        if after is not None:
            bottom.plot(tr.time_s, after.residual * k, color="C0", lw=0.7, label="after")
        bottom.set_ylabel(f"residual\n{CHANNEL_LABELS.get(ch, ch)}", fontsize=8)
        bottom.set_xlabel("time, s")
        legend_with_phases(bottom, loc="upper right")
    title = _wrap(f"{finding.effect}: {finding.explanation}", 130)
    fig.suptitle(title, fontsize=8)
    fixed_margins(fig, top=0.25 + 0.14 * (title.count("\n") + 1), gap=0.65)
    return fig


#: Places where a term adds to the stage's output channel, so that the residual plus
#: the term is the data's view of it (its partial residual).
_ADDITIVE = ("drive", "force.output", "torque.output", "sensor.")


def _learned_view(ax, finding: Finding, after) -> bool:
    """A discovered term against the signal it depends on first; where the term adds to
    the stage's output, the data's partial residuals (the residual with the term on,
    plus the term) beside it."""
    x, y = finding.term_input, finding.term_series
    additive = (
        finding.place.startswith(_ADDITIVE)
        and (not finding.place.startswith("sensor.") or finding.place.endswith(after.channel))
        if after is not None
        else False
    )
    if additive:
        part = after.residual + y
        ax.plot(x, part, ".", ms=1.5, color="0.6", label="data: residual + learned term")
    order = np.argsort(x, kind="stable")
    ax.plot(x[order], y[order], ".", ms=2.5, color="C1", label=f"learned term at {finding.place}")
    ax.set_xlabel(finding.term_input_label)
    ax.set_ylabel(finding.equation.split(" = ")[0] + f" [{finding.units.get('c0', '')}]")
    ax.legend(fontsize=8)
    return True


def _finding_channel(finding: Finding) -> str:
    if finding.effect in ("sensor_delay", "sensor_offset"):
        for name in ("force_N", "torque_Nm", "x_m", "theta_deg", "current_A"):
            if name in finding.variant:
                stage_of = {
                    "theta_deg": "motor",
                    "current_A": "motor",
                    "x_m": "gap",
                    "force_N": "force",
                    "torque_Nm": "torque",
                }
                if stage_of[name] == finding.stage:
                    return name
    return {"motor": "theta_deg", "gap": "x_m", "force": "force_N", "torque": "torque_Nm"}[
        finding.stage
    ]


def _gap_view(ax, tr, before, after) -> bool:
    th = tr["theta_deg"]
    # The play shows where the motion reverses: the top of the stroke.
    top = th > float(np.max(th)) - 0.03 * float(np.ptp(th))
    labels = ("pinion angle, deg", "displacement, mm")
    return _curve_view(ax, th, _curves(before, after, 1e3), labels, top, "reversal")


def _force_view(ax, tr, before, after) -> bool:
    x = tr["x_m"] * 1e3
    # A hysteresis loop is widest where the force is high.
    f = before.measured
    high = f > 0.5 * float(np.max(f))
    labels = ("displacement, mm", "force, N")
    return _curve_view(ax, x, _curves(before, after, 1.0), labels, high, "loop")


def _curve_view(ax, x: np.ndarray, series, labels: tuple[str, str], sel, what: str) -> bool:
    """The ``series`` (:func:`_curves`) against ``x``, axis ``labels`` (x, y), and an
    inset enlarging the samples ``sel`` (:func:`_zoom`)."""
    for y, style in series:
        ax.plot(x, y, **style)
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.legend(fontsize=8, loc="lower right")
    _zoom(ax, x, series, sel, what)
    return True


def _curves(before, after, k: float) -> list[tuple[np.ndarray, dict]]:
    """Measured, model before and model after, scaled by ``k``, with their styles."""
    return [
        (before.measured * k, dict(ls="", marker=".", ms=1.5, color="k", label="measured")),
        (before.predicted * k, dict(ls="", marker=".", ms=1, color="0.5", label="model before")),
        (after.predicted * k, dict(ls="", marker=".", ms=1, color="C1", label="model after")),
    ]


def _zoom(ax, x: np.ndarray, series, sel: np.ndarray, what: str) -> None:
    """An inset of ``ax`` enlarging the samples ``sel``, where the effect lives."""
    if int(np.sum(sel)) < 10:
        return
    inset = ax.inset_axes([0.04, 0.45, 0.42, 0.5])
    for y, style in series:
        inset.plot(x[sel], y[sel], **style)
    ys = np.concatenate([y[sel] for y, _ in series])
    pad = 0.05 * max(float(np.ptp(ys)), 1e-12)
    inset.set_ylim(float(np.min(ys)) - pad, float(np.max(ys)) + pad)
    inset.set_title(f"zoom: the {what}", fontsize=7)
    inset.tick_params(labelsize=6)
    ax.indicate_inset_zoom(inset, edgecolor="0.4")


def _mu_view(ax, tr, before, after, against: str) -> bool:
    if not (tr.has("force_N") and tr.has("torque_Nm")):
        return False
    F = tr["force_N"]
    sel = F > 0.3 * float(np.max(F))
    if np.sum(sel) < 10:
        return False
    den = 2.0 * F[sel] * tr.r_eff_m
    if against == "speed" and tr.has("disc_speed_rad_s"):
        xv, xl = tr["disc_speed_rad_s"][sel], "disc speed, rad/s"
    elif against == "energy" and tr.has("disc_speed_rad_s"):
        power = np.abs(tr["torque_Nm"] * tr["disc_speed_rad_s"])
        e = np.concatenate([[0.0], np.cumsum(power[:-1])]) * tr.dt / 1e3
        xv, xl = e[sel], "energy dissipated, kJ"
    else:
        xv, xl = tr.time_s[sel], "time, s"
    ax.plot(xv, before.measured[sel] / den, ".", ms=1.5, color="k", label="measured T / (2 F r)")
    ax.plot(xv, before.predicted[sel] / den, ".", ms=1, color="0.5", label="model before")
    ax.plot(xv, after.predicted[sel] / den, ".", ms=1, color="C1", label="model after")
    ax.set_xlabel(xl)
    ax.set_ylabel("apparent friction coefficient")
    ax.legend(fontsize=8)
    return True


_VIEWS: dict[str, Callable] = {
    "gap": _gap_view,
    "force": _force_view,
    "backlash": _gap_view,
    "force_hysteresis": _force_view,
    "friction_speed": lambda ax, tr, b, a: _mu_view(ax, tr, b, a, "speed"),
    "friction_fade": lambda ax, tr, b, a: _mu_view(ax, tr, b, a, "energy"),
}


def _wrap(text: str, width: int) -> str:
    words, lines, line = text.split(), [], ""
    for w in words:
        if len(line) + len(w) + 1 > width:
            lines.append(line)
            line = w
        else:
            line = f"{line} {w}".strip()
    lines.append(line)
    return "\n".join(lines[:6])


def figures_of(result: DiagnosisResult) -> list[tuple[str, Figure]]:
    """Every figure of a diagnosis, with its file name."""
    figs: list[tuple[str, Figure]] = [("mismatch.png", mismatch_figure(result))]
    for k, f in enumerate(result.findings, start=1):
        figs.append((f"finding_{k}_{f.effect}.png", finding_figure(result, f)))
    if result.chain_before:
        figs.append(("chain.png", chain_figure(result)))
    return figs


def figure_bytes(result: DiagnosisResult) -> dict[str, bytes]:
    """The figures of a diagnosis as PNG bytes, keyed by file name."""
    return {name: png_bytes(fig, dpi=90, tight=False) for name, fig in figures_of(result)}


def write_diagnosis(
    result: DiagnosisResult,
    folder: str | Path,
    *,
    extra: dict | None = None,
    figures: bool = True,
) -> list[Path]:
    """Write ``diagnosis.json`` and the figures into ``folder`` (created), atomically:
    every file is complete under its name or absent, and an earlier run's files there are
    replaced as a set (:func:`~ewb_ident.data.outputs.write_run`). Returns the paths
    written.

    Parameters
    ----------
    result
        The diagnosis.
    folder
        Output folder.
    extra
        More keys for ``diagnosis.json`` (e.g. the trace's path).
    figures
        Whether to draw the figures too.
    """
    from ewb_ident.data.outputs import json_text, write_run

    folder = Path(folder)
    text = json_text(result.to_json() | dict(extra or {}))
    writers = [(folder / "diagnosis.json", lambda tmp: tmp.write_text(text, encoding="utf-8"))]
    if figures:
        for name, data in figure_bytes(result).items():
            writers.append((folder / name, lambda tmp, d=data: tmp.write_bytes(d)))
    return write_run(folder, "diagnose", writers)
