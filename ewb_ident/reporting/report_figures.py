"""Figures of the validation report, of ``validate`` and of ``sample``: the recorded
channels, measured against simulated (with posterior-predictive bands), the fitted bell,
the posterior's pair plot."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.figure import Figure

from ewb_ident.data.metrics import noise_sigma
from ewb_ident.data.trace import Trace
from ewb_ident.inference.log_posterior import CONTRACT_PARAMS, info_of
from ewb_ident.inference.validate import ValidationResult
from ewb_ident.model.params import SEED
from ewb_ident.reporting.style import (
    CHANNEL_LABELS,
    PHASE_COLOURS,
    SCALE,
    fixed_margins,
    legend_with_phases,
    png_bytes,
    shade_phases,
    short_text,
    subplots,
)

if TYPE_CHECKING:
    from ewb_ident.inference.posterior_result import PosteriorResult


def phases_of(trace: Trace) -> np.ndarray:
    from ewb_ident.diagnosis.locate import phase_labels

    return phase_labels(trace)


def phase_table(trace: Trace, predictions: Mapping[str, np.ndarray]) -> list[dict[str, Any]]:
    """RMS residual per channel and phase, beside the channel's sensor noise."""
    phases = phases_of(trace)
    rows = []
    for c, pred in predictions.items():
        if not trace.has(c):
            continue
        r = trace[c] - pred
        row: dict[str, Any] = {"channel": c, "noise": noise_sigma(trace[c])}
        for ph in PHASE_COLOURS:
            sel = phases == ph
            row[ph] = float(np.sqrt(np.mean(r[sel] ** 2))) if sel.sum() > 5 else None
        rows.append(row)
    return rows


def figure_overview(trace: Trace) -> bytes:
    """Every recorded channel against time."""
    cols = [c for c in CHANNEL_LABELS if trace.has(c)]
    fig, axes = subplots(
        len(cols), 1, figsize=(8, 1.6 * len(cols)), sharex=True, layout="constrained"
    )
    for ax, c in zip(np.atleast_1d(axes), cols, strict=True):
        ax.plot(trace.time_s, trace[c] * SCALE.get(c, 1.0), lw=0.8, color="k")
        ax.set_ylabel(CHANNEL_LABELS[c], fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel("time (s)")
    fig.suptitle(f"{short_text(trace.name)}: recorded channels", fontsize=10)
    return png_bytes(fig)


def figure_fit(
    trace: Trace,
    predictions: Mapping[str, np.ndarray],
    title: str,
    bands: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
) -> bytes:
    """Measured against simulated per channel, residuals below, phases shaded; with
    ``bands`` (channel -> lower, upper), the 90 % posterior-predictive band shaded."""
    cols = [c for c in CHANNEL_LABELS if c in predictions]
    phases = phases_of(trace)
    fig, axes = subplots(
        2 * len(cols),
        1,
        figsize=(8, 2.2 * len(cols)),
        sharex=True,
        gridspec_kw={"height_ratios": [2, 1] * len(cols)},
        layout="constrained",
    )
    t = trace.time_s
    for j, c in enumerate(cols):
        s = SCALE.get(c, 1.0)
        top, bottom = axes[2 * j], axes[2 * j + 1]
        shade_phases(top, t, phases)
        top.plot(t, trace[c] * s, lw=0.8, color="k", label="measured")
        top.plot(t, predictions[c] * s, lw=1.0, color="tab:red", label="simulated")
        top.set_ylabel(CHANNEL_LABELS[c], fontsize=8)
        if bands and c in bands:  # where the residual should lie if the model is right
            lo, hi = (b - predictions[c] for b in bands[c])
            bottom.fill_between(
                t, lo * s, hi * s, color="tab:red", alpha=0.2, lw=0,
                label="90 % posterior predictive",
            )  # fmt: skip
        bottom.plot(t, (trace[c] - predictions[c]) * s, lw=0.6, color="tab:blue", label="residual")
        bottom.axhline(0, color="k", lw=0.5)
        bottom.set_ylabel("residual", fontsize=8)
    legend_with_phases(axes[0], loc="lower left", bbox_to_anchor=(0.0, 1.02))
    if bands:
        axes[1].legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(short_text(title, 90), fontsize=10)
    return png_bytes(fig)


def figure_bell(params, traces: Sequence[Trace]) -> bytes:
    """Clamping force against gap from the fitted bell, with its three regions."""
    F_rt, a, b, c = (float(getattr(params, n)) for n in ("F_rt", "a", "b", "c"))
    x = np.linspace(c - 3.0 * a, c + 0.5 * a, 600)
    F = F_rt / (1 + np.abs((x - c) / a) ** (2 * b))
    fig, ax = subplots(figsize=(7, 4), layout="constrained")
    rising = x < c  # F increases with x here
    lo, hi = (float(np.interp(q, F[rising] / F_rt, x[rising])) for q in (0.05, 0.95))
    regions = (((x[0], lo), "gapping"), ((lo, hi), "clamping"), ((hi, x[-1]), "saturation"))
    for (x0, x1), name in regions:
        ax.axvspan(x0 * 1e3, x1 * 1e3, color=PHASE_COLOURS[name], lw=0)
        ax.text((x0 + x1) / 2 * 1e3, 0.5 * F_rt, name, ha="center", fontsize=8, color="0.3")
    for tr in traces:
        if tr.has("x_m") and tr.has("force_N"):
            label = short_text(tr.name, 40)
            ax.plot(tr["x_m"] * 1e3, tr["force_N"], ".", ms=2, alpha=0.4, label=label)
    ax.plot(x * 1e3, F, color="tab:red", lw=1.5, label="fitted bell")
    Fs = float(SEED.F_rt) / (1 + np.abs((x - float(SEED.c)) / float(SEED.a)) ** (2 * float(SEED.b)))
    ax.plot(x * 1e3, Fs, "--", color="0.4", lw=1, label="seed Table 2 (b = 2.82)")
    ax.axvline(c * 1e3, color="tab:red", lw=0.6, ls=":")
    ax.set_xlabel("piston gap x (mm)")
    ax.set_ylabel("clamping force (N)")
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("Clamping force: the generalized bell (seed Figure 8)", fontsize=10)
    return png_bytes(fig)


def validation_figure(trace: Trace, result: ValidationResult):
    """Measured against simulated, one panel per recorded channel, with residuals."""
    chans = list(result.metrics)
    fig, axes = subplots(
        len(chans), 1, figsize=(10, 1.9 * len(chans) + 0.8), layout="constrained",
        sharex=True, squeeze=False,
    )  # fmt: skip
    axes = axes[:, 0]
    for ax, ch in zip(axes, chans, strict=True):
        k, label = SCALE.get(ch, 1.0), CHANNEL_LABELS.get(ch, ch)
        ax.plot(trace.time_s, trace[ch] * k, ".", ms=1.5, color="k", label="measured")
        ax.plot(trace.time_s, result.simulated[ch] * k, color="C1", lw=1, label="simulated")
        m = result.metrics[ch]
        if m["noise_ratio"] is not None and m["nrmse_pct"] is not None:
            ax.set_title(
                f"{ch}: NRMSE {m['nrmse_pct']:.2f} %, RMSE {m['noise_ratio']:.1f}x noise",
                fontsize=9,
                loc="left",
            )
        ax.set_ylabel(label, fontsize=8)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time, s")
    fig.suptitle(f"validation on {trace.name}: {result.verdict}", fontsize=10)
    return fig


def pair_figure(posterior: PosteriorResult) -> Figure:
    """The posterior's pair plot: pairwise scatter and marginal histograms of a, b, c, mu
    (those sampled; else the first four parameters), the HDIs dashed."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.ticker import MaxNLocator

    draws, stats = posterior.draws, posterior.stats
    names = [n for n in CONTRACT_PARAMS if n in draws] or list(posterior.names[:4])
    k = len(names)
    fig = Figure(figsize=(2.4 * k + 0.6, 2.4 * k + 0.6))
    FigureCanvasAgg(fig)
    flat = {n: draws[n].reshape(-1) for n in names}
    pick = np.linspace(0, flat[names[0]].size - 1, min(3000, flat[names[0]].size)).astype(int)
    for i, ni in enumerate(names):
        for j, nj in enumerate(names[: i + 1]):
            ax = fig.add_subplot(k, k, i * k + j + 1)
            if i == j:
                ax.hist(flat[ni], bins=40, color="0.45")
                for v in (stats[ni]["hdi_low"], stats[ni]["hdi_high"]):
                    ax.axvline(v, ls="--", color="k", lw=0.8)
                ax.set_yticks([])
            else:
                ax.plot(flat[nj][pick], flat[ni][pick], ".", ms=1.5, alpha=0.3, color="0.2")
            if i == k - 1:
                ax.set_xlabel(f"{nj} [{info_of(nj).unit}]")
            if j == 0 and i > 0:
                ax.set_ylabel(f"{ni} [{info_of(ni).unit}]")
            ax.tick_params(labelsize=7)
            for axis in (ax.xaxis, ax.yaxis):
                axis.set_major_locator(MaxNLocator(3))
                axis.get_major_formatter().set_powerlimits((-3, 4))
    fig.suptitle(f"posterior of {', '.join(posterior.trace_names)} ({'+'.join(posterior.stages)})")
    fixed_margins(fig, left=0.8, right=0.25, bottom=0.6, top=0.55, gap=0.6, column_gap=0.7)
    return fig
