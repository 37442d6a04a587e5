"""A batch's tables and its campaign report.

* :func:`results_table`: the tidy table, one row per trace and free parameter (a failed
  trace: one row), with the columns of ``shared/CONTRACTS.md`` (batch);
* :func:`population_table`: per parameter (and per group), the random-effects mean and
  the spread between traces (:mod:`ewb_ident.inference.population`);
* :func:`changes_table`: per parameter, the change of every group against the first;
* :func:`trend_table`: per parameter, its linear trend against a numeric metadata column
  (a long log's cycles against time: fade, wear, drift);
* :func:`split_figure`: where a long log was split into its apply cycles;
* :func:`campaign_page`: the HTML report with a, b, c, mu against a metadata column or
  the trace order, the flagged traces and the tables above.
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from ewb_ident.data.stages import CHANNELS
from ewb_ident.data.units import shown_unit
from ewb_ident.inference.population import group_change, random_effects, trend, two_level
from ewb_ident.model.params import MODEL_PARAMS, PARAMS
from ewb_ident.reporting.html import CSS
from ewb_ident.reporting.style import png_bytes, subplots

#: The results table's own columns, in order; the manifest's metadata columns come
#: after ``trace``. ``model`` and the columns after the metrics are more than the
#: contract asks.
PARAM_COLUMNS = ("parameter", "unit", "estimate", "stderr", "low_90", "high_90",
                 "interval_from", "converged", "status", "verdict", "findings")
METRIC_COLUMNS = tuple(f"{ch}_nrmse_pct" for ch in CHANNELS)
EXTRA_COLUMNS = ("message", "r_eff_m", "posterior_mean", "posterior_sd", "posterior_converged")
RESULT_COLUMNS = ("trace", *PARAM_COLUMNS, "model", *METRIC_COLUMNS, *EXTRA_COLUMNS)
_FLOATS = ("estimate", "stderr", "low_90", "high_90", "r_eff_m", "posterior_mean",
           "posterior_sd", *METRIC_COLUMNS)
#: Parameters the report plots (where the campaign fitted them).
PLOTTED = ("a", "b", "c", "mu")
#: The ``model`` of a row: the seed chain every trace is fitted with, or the chain
#: corrected by the trace's findings (``batch --diagnose``).
BASELINE, CORRECTED = "baseline", "corrected"


def _messages(*parts: str | None) -> str | None:
    said = [p for p in parts if p]
    return "; ".join(said) if said else None


def _rows(common, params, tail) -> list[dict[str, Any]]:
    if not params:
        return [common | dict.fromkeys(PARAM_COLUMNS[:7]) | tail]
    return [common | {"parameter": name} | p | tail for name, p in params.items()]


def results_table(
    records: Sequence[dict[str, Any]],
    metadata: Sequence[dict[str, Any]],
    metadata_columns: Sequence[str],
) -> pd.DataFrame:
    """The tidy results table (see the module docstring): per trace, a row per parameter
    of the fit (``model``: ``baseline``), and for a trace whose diagnosis found missing
    physics a row per parameter of the corrected model (``corrected``).

    Parameters
    ----------
    records
        Per trace, the record of :func:`ewb_ident.diagnosis.batch.run_job`.
    metadata
        Per trace, its metadata (the manifest's row), in the same order.
    metadata_columns
        The metadata columns, in the manifest's order.
    """
    rows = []
    for rec, meta in zip(records, metadata, strict=True):
        common = {"trace": rec["trace"], **{c: meta.get(c) for c in metadata_columns}}
        diagnosed = rec.get("verdict") is not None
        trace_level = {
            "verdict": rec.get("verdict"),  # None: not diagnosed (or the diagnosis failed)
            "findings": ";".join(rec.get("findings") or ()) if diagnosed else None,
            "r_eff_m": rec.get("r_eff_m"),
        }
        tail = trace_level | {
            "converged": rec.get("converged"),
            "status": rec["status"],
            "model": BASELINE,
            **{f"{ch}_nrmse_pct": rec["metrics"].get(ch) for ch in CHANNELS},
            "message": _messages(rec.get("message"), rec.get("posterior_message"),
                                 rec.get("diagnosis_message")),
            "posterior_converged": rec.get("posterior_converged"),
        }
        rows += _rows(common, rec["params"] if rec["status"] != "error" else {}, tail)
        fix = rec.get("corrected")
        if fix:
            rows += _rows(common, fix["params"], trace_level | {
                "converged": fix["converged"],
                "status": "ok" if fix["converged"] else "not_converged",
                "model": CORRECTED,
                **{f"{ch}_nrmse_pct": fix["metrics"].get(ch) for ch in CHANNELS},
                "message": _messages(
                    f"corrected by {', '.join(fix['mechanisms']) or 'learned terms'}",
                    fix.get("posterior_message")),
                "posterior_converged": fix.get("posterior_converged"),
            })
    order = ["trace", *metadata_columns, *RESULT_COLUMNS[1:]]
    table = pd.DataFrame(rows, columns=order)
    for col in _FLOATS:
        table[col] = table[col].astype("float64")
    for col in ("converged", "posterior_converged"):
        table[col] = table[col].astype("boolean")
    for col in ("trace", "parameter", "unit", "interval_from", "status", "verdict", "findings",
                "model", "message"):
        table[col] = table[col].astype("string")
    return table


def _usable(results: pd.DataFrame) -> pd.DataFrame:
    """Rows of the fit (``model`` baseline, the model every trace shares) of traces whose
    fit converged within the acceptance (status ``ok``)."""
    return results[(results["status"] == "ok") & results["parameter"].notna()
                   & (results["model"] == BASELINE)]


def _combined(rows: pd.DataFrame, units: str | None = None):
    """The random-effects combination of one parameter's rows (``None``: none usable);
    with ``units`` (a metadata column naming each trace's rig unit) the two-level one."""
    if units is not None:
        return two_level(rows["estimate"].to_numpy(), rows["stderr"].to_numpy(float),
                         rows[units].tolist())
    return random_effects(rows["estimate"].to_numpy(), rows["stderr"].to_numpy(float))


def _ordered(names) -> list[str]:
    return sorted(set(names), key=lambda n: MODEL_PARAMS.index(n) if n in MODEL_PARAMS else 99)


#: The population table's ``method`` without and with a unit column.
ONE_LEVEL = "Paule-Mandel tau, Hartung-Knapp mean interval, Q-profile tau interval"
TWO_LEVEL = ("unit means (pooled Paule-Mandel tau_trace within units), then Paule-Mandel "
             "tau_unit and Hartung-Knapp mean interval over the units; Q-profile tau intervals")


def population_table(results: pd.DataFrame, group_by: str | None = None,
                     units: str | None = None) -> pd.DataFrame:
    """Per parameter: the random-effects combination of the traces with status ``ok``;
    with ``group_by``, also per group (``group`` column; ``"all"``: every trace). With
    ``units`` (the metadata column naming each trace's rig unit), the mean and its
    interval are the two-level model's (:func:`~ewb_ident.inference.population.two_level`)
    and ``tau_unit``, ``tau_trace`` separate the unit-to-unit from the trace-to-trace
    spread; ``tau`` is always the spread between traces with the units ignored."""
    ok = _usable(results)
    groups: list[tuple[str, pd.DataFrame]] = [("all", ok)]
    if group_by is not None:
        groups += [(str(g), sub) for g, sub in ok.groupby(group_by, sort=True)]
    rows = []
    for label, sub in groups:
        for name in _ordered(sub["parameter"]):
            one = sub[sub["parameter"] == name]
            comb = _combined(one)
            if comb is None:
                continue
            two = _combined(one, units) if units is not None else None
            top = two if two is not None else comb
            rows.append({
                "group": label, "parameter": name, "unit": PARAMS[name].unit,
                "n_traces": comb.n, "mean": top.mean, "stderr": top.stderr,
                "low_90": top.low90, "high_90": top.high90, "tau": comb.tau,
                "tau_low_90": comb.tau_low90, "tau_high_90": comb.tau_high90, "q": comb.q,
                "unit_column": units, "n_units": None if two is None else two.units.n,
                "tau_unit": None if two is None else two.units.tau,
                "tau_unit_low_90": None if two is None else two.units.tau_low90,
                "tau_unit_high_90": None if two is None else two.units.tau_high90,
                "tau_trace": None if two is None else two.tau_trace,
                "tau_trace_low_90": None if two is None else two.tau_trace_low90,
                "tau_trace_high_90": None if two is None else two.tau_trace_high90,
                "method": ONE_LEVEL if two is None else TWO_LEVEL,
            })
    table = pd.DataFrame(rows)
    for col in ("n_units", *(c for c in table.columns if c.startswith("tau"))):
        table[col] = pd.to_numeric(table[col]).astype("float64")  # empty: NaN, not None
    return table


def changes_table(results: pd.DataFrame, group_by: str) -> pd.DataFrame:
    """Per parameter, the change of each later group (sorted) against the first: the
    groups' random-effects means (one level, every trace its own draw, also when the
    campaign names units: docs/batch.md), the difference with a 90 % interval, the
    practical tolerance, ``P(|change| > tolerance)`` and whether it changed (that
    probability above 0.95, as ``compare`` decides). Empty with fewer than two groups."""
    ok = _usable(results)
    ok = ok[ok[group_by].notna()]
    labels = sorted(ok[group_by].unique(), key=str)
    rows = []
    for after in labels[1:]:
        before = labels[0]
        for name in _ordered(ok["parameter"]):
            sides = [_combined(ok[(ok[group_by] == g) & (ok["parameter"] == name)])
                     for g in (before, after)]
            if None in sides:
                continue
            ch = group_change(name, *sides)
            rows.append({
                "parameter": name, "unit": PARAMS[name].unit, "group_by": group_by,
                "before": str(before), "after": str(after), "n_before": sides[0].n,
                "n_after": sides[1].n, "before_mean": ch.old, "after_mean": ch.new,
                "delta": ch.delta, "stderr": ch.stderr, "low_90": ch.low90,
                "high_90": ch.high90, "delta_pct": 100 * ch.delta / ch.old if ch.old else None,
                "tolerance": ch.tolerance, "p_changed": ch.p_changed, "changed": ch.changed,
            })
    table = pd.DataFrame(rows)
    if not table.empty:  # what changed first, the largest evidence first
        table = table.sort_values(["after", "changed", "p_changed"], ascending=[True, False,
                                                                                  False])
    return table.reset_index(drop=True)


def trend_table(results: pd.DataFrame, against: str) -> pd.DataFrame:
    """Per parameter (and per ``log`` when the table has several), the linear trend of the
    traces with status ``ok`` against the numeric column ``against``
    (:func:`ewb_ident.inference.population.trend`): the slope per unit of ``against``
    with its 90 % interval, the drift over the column's range, in SI units and % of the
    line's start, ``P(|drift| > tolerance)`` and whether there is a trend (that
    probability above 0.95, as ``compare`` decides a change)."""
    ok = _usable(results)
    ok = ok[pd.to_numeric(ok[against], errors="coerce").notna()]
    groups = [("all", ok)]
    if "log" in ok and ok["log"].nunique() > 1:
        groups += [(str(g), sub) for g, sub in ok.groupby("log", sort=True)]
    rows = []
    for label, sub in groups:
        for name in _ordered(sub["parameter"]):
            one = sub[sub["parameter"] == name]
            tr = trend(name, one[against].to_numpy(float), one["estimate"].to_numpy(),
                       one["stderr"].to_numpy(float))
            if tr is None:
                continue
            ch = tr.change
            rows.append({
                "group": label, "parameter": name, "unit": PARAMS[name].unit,
                "against": against, "n_traces": tr.n, "start": ch.old, "end": ch.new,
                "slope": tr.slope, "slope_stderr": tr.slope_stderr,
                "slope_low_90": tr.slope_low90, "slope_high_90": tr.slope_high90,
                "x_first": tr.x_first, "x_last": tr.x_last, "drift": ch.delta,
                "drift_low_90": ch.low90, "drift_high_90": ch.high90,
                "drift_pct": 100 * ch.delta / abs(ch.old) if ch.old else None,
                "drift_low_90_pct": 100 * ch.low90 / abs(ch.old) if ch.old else None,
                "drift_high_90_pct": 100 * ch.high90 / abs(ch.old) if ch.old else None,
                "tolerance": ch.tolerance, "p_trend": ch.p_changed, "trend": ch.changed,
                "tau": tr.tau,
                "method": "random-effects meta-regression (moments tau, Knapp-Hartung t)",
            })
    table = pd.DataFrame(rows)
    if not table.empty:
        table = table.sort_values(["group", "trend", "p_trend"], ascending=[True, False, False])
    return table.reset_index(drop=True)


def trend_figure(results: pd.DataFrame, against: str, trends: pd.DataFrame) -> bytes | None:
    """a, b, c, mu per trace with their 90 % intervals against the numeric column
    ``against``, with each parameter's trend line (all traces). ``None`` when no trace
    has these parameters."""
    ok = _usable(results)
    names = [n for n in PLOTTED if n in set(ok["parameter"])]
    if not names:
        return None
    fig, axes = subplots(len(names), 1, figsize=(7.5, 2.1 * len(names) + 0.6), squeeze=False,
                         sharex=True)
    for ax, name in zip(axes[:, 0], names, strict=True):
        unit, k = shown_unit(PARAMS[name].unit)
        one = ok[ok["parameter"] == name]
        x = one[against].to_numpy(float)
        y = one["estimate"].to_numpy() * k
        err = np.vstack([y - one["low_90"].to_numpy() * k, one["high_90"].to_numpy() * k - y])
        ax.errorbar(x, y, yerr=np.nan_to_num(err), fmt="o", ms=2.5, color="#b22", capsize=0,
                    elinewidth=0.6, alpha=0.7)
        row = trends[(trends["group"] == "all") & (trends["parameter"] == name)] \
            if not trends.empty else trends
        if not row.empty:
            r = row.iloc[0]
            ax.plot([r.x_first, r.x_last], [r.start * k, r.end * k], color="#246", lw=1.5,
                    label=f"trend {r.drift_pct:+.2f} % [{r.drift_low_90_pct:+.2f}, "
                          f"{r.drift_high_90_pct:+.2f}] over the range")
            ax.legend(fontsize=7, loc="best")
        ax.set_ylabel(f"{name} ({unit})" if unit != "1" else name)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel(against)
    fig.suptitle("Per-cycle estimates with 90 % intervals; linear trend (random-effects "
                 "meta-regression) with its 90 % interval", fontsize=9)
    fig.set_layout_engine("constrained")
    return png_bytes(fig)


def split_figure(logs: Sequence[Any]) -> bytes:
    """Where each log (at most four shown) was split: the split channel over the whole
    log with each cycle fitted marked above it (blue; partial: red); each cycle's apply
    length and the time since the previous apply over the log (a missed or merged apply
    stands out); and the first three cycles of the first log close up with the
    threshold. ``logs``: :class:`ewb_ident.data.cycles.LogSplit` s."""
    shown = list(logs)[:4]
    fig, axes = subplots(len(shown) + 2, 1, figsize=(7.5, 1.9 * (len(shown) + 2) + 0.5),
                         squeeze=False)
    for ax, log in zip(axes[:len(shown), 0], shown, strict=True):
        split = log.split
        ax.fill_between(*log.envelope, color="#999", lw=0.4, edgecolor="#999")
        level = split.top + 0.08 * (split.top - split.floor)
        for c in split.cycles:
            ax.plot([c.t_start_s, c.t_end_s], [level, level], lw=3, solid_capstyle="butt",
                    color="#e03030" if c.partial else "#2060c0")
        ax.set_ylabel(split.channel, fontsize=8)
        done = len(split.complete)
        ax.set_title(f"{log.name}: {done} cycles fitted (blue bars), "
                     f"{len(split.cycles) - done} partial (red)", fontsize=8)
    ax = axes[len(shown), 0]
    for log in shown:
        rise = np.array([c.rise_s for c in log.split.cycles])
        length = np.array([c.fall_s - c.rise_s for c in log.split.cycles])
        ax.plot(rise, length, ".", ms=3, label=f"apply length ({log.name})" if len(shown) > 1
                else "apply length")
        if rise.size > 1:
            ax.plot(rise[1:], np.diff(rise), ".", ms=3,
                    label="time since the previous apply")
    ax.set_ylabel("s", fontsize=8)
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=7, loc="best")
    ax.set_title("each apply's length and the time since the previous one (a missed or "
                 "merged apply stands out)", fontsize=8)
    ax = axes[-1, 0]
    log = shown[0]
    ax.plot(*log.zoom, color="#333", lw=0.7)
    for c in log.split.complete[:3]:
        ax.axvspan(c.t_start_s, c.t_end_s, color="#a8c8f0", alpha=0.5, lw=0)
        ax.axvline(c.rise_s, color="#246", lw=0.8, ls=":")
    ax.axhline(log.split.threshold, color="#b22", lw=0.8, ls="--",
               label=f"threshold {log.split.threshold:.4g}")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_xlabel("time in the log (s)")
    ax.set_ylabel(log.split.channel, fontsize=8)
    ax.set_title(f"{log.name}: the first cycles (shaded: the window fitted; dotted: the "
                 "rise)", fontsize=8)
    fig.set_layout_engine("constrained")
    return png_bytes(fig)


def flagged(results: pd.DataFrame) -> pd.DataFrame:
    """One row per trace that failed, did not converge or is outside the acceptance."""
    bad = results[(results["status"] != "ok") & (results["model"] == BASELINE)]
    return bad.drop_duplicates("trace")[["trace", "status", "message"]].reset_index(drop=True)


def with_findings(results: pd.DataFrame) -> pd.DataFrame:
    """One row per trace whose diagnosis located a mismatch (verdict ``found`` or
    ``unexplained``): its findings and a, b, c, mu of the fit beside the corrected
    model's (shown units)."""
    hit = results[results["verdict"].isin(["found", "unexplained"])]
    rows = []
    for trace, one in hit.groupby("trace", sort=False):
        first = one.iloc[0]
        row = {"trace": trace, "verdict": first["verdict"], "findings": first["findings"]}
        for name in PLOTTED:
            unit, k = shown_unit(PARAMS[name].unit)
            got = {m: one[(one["model"] == m) & (one["parameter"] == name)]["estimate"]
                   for m in (BASELINE, CORRECTED)}
            if got[BASELINE].empty:
                continue
            after = f"{got[CORRECTED].iloc[0] * k:.4g}" if not got[CORRECTED].empty else "–"
            label = name if unit == "1" else f"{name} ({unit})"
            row[f"{label} fit → corrected"] = f"{got[BASELINE].iloc[0] * k:.4g} → {after}"
        rows.append(row)
    return pd.DataFrame(rows)


def unconverged_posteriors(results: pd.DataFrame) -> pd.DataFrame:
    """One row per trace and model whose posterior was sampled and did not converge (or
    could not be sampled)."""
    bad = results[results["posterior_converged"].eq(False).fillna(False)]
    return bad.drop_duplicates(["trace", "model"])[["trace", "model", "message"]] \
        .reset_index(drop=True)


def parameter_figure(results: pd.DataFrame, against: str | None) -> bytes | None:
    """a, b, c, mu per trace with their 90 % intervals, against a metadata column (its
    values as categories) or the trace order; the population mean of each group as a
    line. ``None`` when no trace has these parameters."""
    ok = _usable(results)
    names = [n for n in PLOTTED if n in set(ok["parameter"])]
    if not names:
        return None
    traces = list(dict.fromkeys(results["trace"]))
    if against is not None:
        cats = sorted(ok[against].dropna().unique(), key=str)
        ok = ok[ok[against].notna()]
    fig, axes = subplots(len(names), 1, figsize=(7.5, 2.1 * len(names) + 0.6), squeeze=False)
    for ax, name in zip(axes[:, 0], names, strict=True):
        unit, k = shown_unit(PARAMS[name].unit)
        one = ok[ok["parameter"] == name]
        if against is None:
            x = np.array([traces.index(t) for t in one["trace"]], dtype=float)
        else:
            pos = {c: j for j, c in enumerate(cats)}
            x = np.array([pos[v] for v in one[against]], dtype=float)
            rank = one.groupby(against).cumcount().to_numpy()
            size = one.groupby(against)[against].transform("size").to_numpy()
            x = x + 0.3 * (rank - (size - 1) / 2) / np.maximum(size, 1)
            for c in cats:
                comb = _combined(one[one[against] == c])
                if comb is not None:
                    j = pos[c]
                    ax.fill_between([j - 0.25, j + 0.25], comb.low90 * k, comb.high90 * k,
                                    color="#c8d8f0", lw=0)
                    ax.plot([j - 0.25, j + 0.25], [comb.mean * k] * 2, color="#246", lw=1.5)
        y = one["estimate"].to_numpy() * k
        err = np.vstack([y - one["low_90"].to_numpy() * k, one["high_90"].to_numpy() * k - y])
        ax.errorbar(x, y, yerr=np.nan_to_num(err), fmt="o", ms=4, color="#b22", capsize=2,
                    label="fit")
        _corrected_points(ax, results, name, dict(zip(one["trace"], x, strict=True)), k)
        ax.set_ylabel(f"{name} ({unit})" if unit != "1" else name)
        if against is not None:
            ax.set_xticks(range(len(cats)), [str(c) for c in cats])
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel(against if against is not None else "trace (campaign order)")
    fig.suptitle("Per-trace estimates with 90 % intervals"
                 + ("; group means (random effects) with 90 % intervals" if against else ""),
                 fontsize=9)
    fig.set_layout_engine("constrained")
    return png_bytes(fig)


def _extras(provenance: dict[str, Any]) -> str:
    settings = provenance.get("settings", {})
    said = [w for w, on in (("posterior (emcee)", settings.get("posterior")),
                            ("diagnosis", settings.get("diagnose"))) if on]
    return "".join(f", {w}" for w in said)


def _corrected_points(ax, results: pd.DataFrame, name: str, where: dict, k: float) -> None:
    """The corrected model's estimates of ``name`` (``batch --diagnose``, traces with a
    finding) beside the fit's, as open markers at the fit's positions ``where``."""
    fix = results[(results["model"] == CORRECTED) & (results["parameter"] == name)
                  & results["trace"].isin(list(where))]
    if fix.empty:
        return
    x = np.array([where[t] for t in fix["trace"]]) + 0.08
    y = fix["estimate"].to_numpy() * k
    err = np.vstack([y - fix["low_90"].to_numpy() * k, fix["high_90"].to_numpy() * k - y])
    ax.errorbar(x, y, yerr=np.nan_to_num(err), fmt="o", ms=4, mfc="none", color="#264",
                capsize=2, label="corrected (a finding)")
    ax.legend(fontsize=7, loc="best")


def _html_table(frame: pd.DataFrame) -> str:
    if frame.empty:
        return "<p class=\"small\">none</p>"
    return frame.to_html(index=False, na_rep="–", float_format=lambda v: f"{v:.4g}",
                         border=0, escape=True)


def campaign_page(
    results: pd.DataFrame,
    population: pd.DataFrame,
    changes: pd.DataFrame | None,
    *,
    against: str | None,
    figure: str | None,
    provenance: dict[str, Any],
    trends: pd.DataFrame | None = None,
    cycles: pd.DataFrame | None = None,
    split_file: str | None = None,
) -> str:
    """The campaign report (HTML): headline, flagged traces, the parameters against
    ``against`` (the figure file ``figure``, beside the page), population and changes;
    a long log's trends and its split into cycles (the table ``cycles``, the figure file
    ``split_file``) when given."""
    e = html.escape
    bad = flagged(results)
    n = results["trace"].nunique()
    settings = provenance.get("settings", {})
    diagnosed, sampled = bool(settings.get("diagnose")), bool(settings.get("posterior"))
    where = provenance["where"]
    ran = ("in this process" if where["kind"] == "in-process" else
           f"on the Dask cluster {where['address']} ({where['workers']} workers)")
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>Campaign "
        f"{e(provenance['source'])}</title><style>{CSS}</style></head><body>",
        f"<h1>Campaign: {e(provenance['source'])}</h1>",
        f"<p>{n} traces, whole-chain least squares{_extras(provenance)}, {ran}; "
        f"{provenance['counts']['reused']} reused, {provenance['counts']['fitted']} fitted. "
        "Intervals are 90 % everywhere (per trace: "
        + ("the posterior's HDI" if sampled else "estimate ± 1.645 robust standard errors")
        + ").</p>",
    ]
    if len(bad):
        parts += [f"<div class='warn'>{len(bad)} of {n} traces flagged (failed, not converged "
                  "or outside the acceptance); they are left out of the population and the "
                  "changes.</div>", _html_table(bad)]
    else:
        parts.append(f"<div class='ok'>All {n} traces converged within the acceptance.</div>")
    if diagnosed:
        found = with_findings(results)
        parts.append(
            f"<div class='warn'>{len(found)} of {n} traces carry a finding: the diagnosis "
            "located physics the model leaves out (results.* rows with model = corrected hold "
            "the corrected model's parameters; the population and the changes are of the "
            "fit every trace shares).</div>" if len(found) else
            f"<div class='ok'>The diagnosis located no missing physics in any of the {n} "
            "traces.</div>")
        if len(found):
            parts.append(_html_table(found))
    unsettled = unconverged_posteriors(results)
    if len(unsettled):
        parts += [f"<div class='warn'>{unsettled['trace'].nunique()} of {n} traces have a "
                  "posterior that did not converge (its intervals are not yet trustworthy: "
                  "more --steps).</div>", _html_table(unsettled)]
    if changes is not None:
        moved = changes[changes["changed"]] if not changes.empty else changes
        said = (", ".join(f"{r.parameter} ({r.before} → {r.after}: {r.delta_pct:+.1f} %)"
                          for r in moved.itertuples()) or "no parameter")
        parts += [f"<h2>Changes by {e(changes.attrs.get('group_by', ''))}</h2>",
                  f"<p>Changed (P(|change| > tolerance) > 0.95): {e(said)}.</p>",
                  _html_table(changes)]
    if trends is not None:
        every = trends[trends["group"] == "all"] if not trends.empty else trends
        against_trend = every["against"].iloc[0] if not every.empty else ""
        moved = every[every["trend"]] if not every.empty else every
        said = (", ".join(f"{r.parameter} {r.drift_pct:+.2f} % [{r.drift_low_90_pct:+.2f}, "
                          f"{r.drift_high_90_pct:+.2f}] %" for r in moved.itertuples())
                or "no parameter")
        parts += [f"<h2>Trends against {e(against_trend)}</h2>",
                  f"<p>Drift over the range (P(|drift| > tolerance) > 0.95): {e(said)}.</p>",
                  "<p class='small'>slope per unit of the column; drift = slope × range, "
                  "from the line's start; random-effects meta-regression, 90 % "
                  "Knapp–Hartung intervals.</p>", _html_table(trends)]
    if cycles is not None:
        done = int((~cycles["partial"]).sum())
        parts += ["<h2>The split into apply cycles</h2>",
                  f"<p>{done} cycles fitted, {len(cycles) - done} partial (cut by the log's "
                  "start or end) not fitted. An apply starts when the split channel rises "
                  "above its floor + 10 % of its range; each cycle starts 1 s before the rise "
                  "and lasts as long as the longest apply plus 2 s (docs/batch.md, long "
                  "recordings). Every boundary is in cycles.csv.</p>"]
        if split_file is not None:
            parts.append(f"<img src='{e(split_file)}' alt='the log and its cycles'>")
        parts.append(_html_table(cycles.head(12)))
    if figure is not None:
        parts += [f"<h2>a, b, c, μ across the {'log' if cycles is not None else 'campaign'}"
                  "</h2>",
                  f"<img src='{e(figure)}' alt='a, b, c, mu per trace'>"]
    units = population["unit_column"].dropna() if "unit_column" in population else ()
    shown = population.drop(columns=["method", "unit_column"], errors="ignore")
    if len(units):
        level = (f"<p class='small'>Two levels, the rig units of column {e(units.iloc[0])}: "
                 "tau_trace, the spread between traces of one unit (pooled Paule–Mandel), "
                 "then the unit means combined: mean with weights 1/(var_i + tau_unit²), "
                 "Hartung–Knapp 90 % interval on units − 1 degrees of freedom; tau_unit, the "
                 "spread between units beyond their means' errors; tau, the spread between "
                 "traces with the units ignored; 90 % Q-profile intervals. Only traces with "
                 "status ok, their fits (model baseline).</p>")
    else:
        shown = shown.drop(columns=[c for c in shown.columns if c.startswith(("tau_unit",
                                    "tau_trace")) or c == "n_units"])
        level = ("<p class='small'>mean: weights 1/(s² + tau²), Hartung–Knapp 90 % interval; "
                 "tau: spread between traces beyond their measurement errors, 90 % Q-profile "
                 "interval. Only traces with status ok, their fits (model baseline).</p>")
    parts += ["<h2>Population (random effects)</h2>", level, _html_table(shown),
              "<h2>Files</h2><p>results.csv / results.parquet (one row per trace and "
              "parameter), population.*"
              + (", changes.*" if changes is not None else "")
              + (", trend.*" if trends is not None else "")
              + (", cycles.* and cycles/ (the cycles as traces)" if cycles is not None else "")
              + ", batch.json (settings, inputs with hashes, "
              f"where it ran, versions).</p><p class='small'>{e(provenance['command'])}</p>",
              "</body></html>"]
    return "\n".join(parts)
