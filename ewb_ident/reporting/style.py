"""One style for every figure: the phase palette, the channel labels and scales, and
figures drawn on :class:`matplotlib.figure.Figure` (no pyplot, no global backend: the
library never switches matplotlib's backend for its user)."""

from __future__ import annotations

import io

import numpy as np
from matplotlib.figure import Figure

#: One phase palette for every figure, the report's and the diagnosis's.
PHASE_COLOURS = {
    "gapping": "#f0f0f0",
    "clamping": "#fde8c8",
    "saturation": "#d8ecd8",
    "release": "#d8e4f4",
}

CHANNEL_LABELS = {
    "voltage_V": "voltage (V)",
    "current_A": "current (A)",
    "theta_deg": "pinion angle (deg)",
    "x_m": "piston gap x (mm)",
    "force_N": "clamping force (N)",
    "torque_Nm": "brake torque (N m)",
    "disc_speed_rad_s": "disc speed (rad/s)",
}
SCALE = {"x_m": 1e3}  # shown in mm


def subplots(*args, figsize=None, layout=None, **kwargs):
    """A figure and its axes, on a :class:`matplotlib.figure.Figure`."""
    fig = Figure(figsize=figsize, layout=layout)
    return fig, fig.subplots(*args, **kwargs)


def fixed_margins(
    fig: Figure,
    *,
    left: float = 0.95,
    right: float = 0.2,
    top: float = 0.45,
    bottom: float = 0.55,
    gap: float = 0.4,
    column_gap: float | None = None,
) -> None:
    """Place the axes of ``fig``'s grid with fixed margins and gaps between rows (and,
    given ``column_gap``, between columns), in inches: a layout that costs nothing to
    draw. (Matplotlib's constrained layout measures every label first; that took half
    the drawing of a diagnosis's figures, a tight layout a quarter of a pair plot's.)"""
    w, h = fig.get_size_inches()
    grid = fig.axes[0].get_gridspec()
    rows, cols = grid.nrows, grid.ncols
    height = (h - top - bottom - (rows - 1) * gap) / rows  # of an axes, on average
    wspace = None  # Matplotlib's own
    if column_gap is not None:
        wspace = column_gap / ((w - left - right - (cols - 1) * column_gap) / cols)
    fig.subplots_adjust(
        left=left / w, right=1 - right / w, top=1 - top / h, bottom=bottom / h,
        hspace=gap / height, wspace=wspace,
    )  # fmt: skip


def png_bytes(fig: Figure, *, dpi: int = 110, tight: bool = True) -> bytes:
    """The figure as PNG bytes."""
    buf = io.BytesIO()
    if tight:
        fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    else:
        fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def short_text(text: str, limit: int = 60) -> str:
    """``text`` cut to ``limit`` characters for a figure title."""
    return text if len(text) <= limit else text[: limit - 1] + "…"


def shade_phases(ax, t: np.ndarray, labels: np.ndarray) -> None:
    """Shade each phase of the apply (:func:`ewb_ident.diagnosis.locate.phase_labels`) behind the
    curves of ``ax`` (time axis ``t``, s): every run of one label from its first sample
    to the next run's first (the last to the end), full height, in its phase's colour.

    One collection of rectangles per colour, not one ``axvspan`` per run: a chattering
    stiction trace has dozens of runs, and their patches took a third of a diagnosis's
    figure time; the pixels are the same (``tests/test_report.py``)."""
    from matplotlib.collections import PolyCollection

    labels = np.asarray(labels)
    if t.size == 0:
        return
    edges = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    starts = np.concatenate([[0], edges])
    ends = np.concatenate([edges, [t.size - 1]])
    runs: dict[str, list] = {}
    for s, e in zip(starts, ends, strict=True):
        x0, x1 = t[s], t[e]
        runs.setdefault(str(labels[s]), []).append([(x0, 0), (x1, 0), (x1, 1), (x0, 1)])
    for name, rects in runs.items():
        shade = PolyCollection(
            rects, facecolors=PHASE_COLOURS.get(name, "#ffffff"), linewidths=0, zorder=0,
            transform=ax.get_xaxis_transform(),
        )  # fmt: skip
        ax.add_collection(shade, autolim=False)
    ax.update_datalim([(t[0], 0.0), (t[-1], 0.0)], updatey=False)  # as axvspan: x only


def legend_with_phases(ax, **kwargs) -> None:
    """The legend of ``ax`` with one patch per phase colour added."""
    from matplotlib.patches import Patch

    handles, _ = ax.get_legend_handles_labels()
    handles += [Patch(color=c, label=name) for name, c in PHASE_COLOURS.items()]
    ax.legend(handles=handles, fontsize=7, ncols=4, **kwargs)
