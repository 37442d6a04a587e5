"""The validation report: one self-contained HTML page plus its PNG figures.

Sections, each present when its input is: data overview; measured against simulated per
channel with residuals by phase (as the seed's Figures 12-13); the bell curve with its
gapping / clamping / saturation regions from the fitted parameters (the seed's Figure
8); the parameter table (least-squares estimate and standard error, posterior mean and
90 % interval, the seed's Table 2 value); the metrics table beside the seed's reported
errors; MCMC diagnostics with the pair plot; and the diagnosis of missing physics (where,
what physics, before and after).

Figures are drawn with matplotlib's Agg backend and embedded in the page as data URIs, so
the HTML file can be mailed on its own; the PNG files are written beside it as well.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ewb_ident.data.metrics import SEED_ACCEPTANCE_PCT, SEED_PERCENT_ERROR
from ewb_ident.data.outputs import write_run
from ewb_ident.data.trace import Trace
from ewb_ident.data.units import shown_unit
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.inference.priors import param_info
from ewb_ident.model.params import SEED
from ewb_ident.reporting.figures import figure_bytes
from ewb_ident.reporting.provenance import provenance_rows
from ewb_ident.reporting.report_figures import (
    figure_bell,
    figure_fit,
    figure_overview,
    pair_figure,
    phase_table,
)
from ewb_ident.reporting.style import CHANNEL_LABELS, PHASE_COLOURS, SCALE, png_bytes
from ewb_ident.reporting.summaries import ls_posterior_note

# ----------------------------------------------------------------------------- HTML

CSS = """
body{font-family:system-ui,Segoe UI,Helvetica,Arial,sans-serif;max-width:1000px;margin:2em auto;
color:#222;line-height:1.45}
h1{font-size:1.6em;border-bottom:2px solid #b22;padding-bottom:.2em}
h2{font-size:1.25em;margin-top:1.8em;color:#822}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f4f4f4} td.l,th.l{text-align:left}
.warn{background:#fff6e0;border-left:4px solid #e0a000;padding:.4em .8em;margin:.4em 0}
.banner{font-size:1.05em;border-left-width:8px}
.ok{background:#eef8ee;border-left:4px solid #393;padding:.4em .8em;margin:.4em 0}
.finding{background:#f3f0fb;border-left:4px solid #63a;padding:.5em .9em;margin:.6em 0}
img{max-width:100%;border:1px solid #ddd;margin:.4em 0}
.small{font-size:.85em;color:#555}
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _shown(name: str) -> tuple[str, float]:
    """The unit a parameter is shown in (mm, not m) and the factor from SI to it."""
    unit = param_info(name.split("[")[0] if "." not in name else name).unit
    return shown_unit(unit)


def _times(v: Any, k: float) -> Any:
    return v * k if isinstance(v, float | int | np.floating) else v


def _interval(lo: Any, hi: Any, k: float = 1.0) -> str:
    return f"{_num(_times(lo, k))} … {_num(_times(hi, k))}"


def _num(v: Any, digits: int = 4) -> str:
    if v is None:
        return "–"
    if isinstance(v, float | int | np.floating):
        return f"{float(v):.{digits}g}"
    return _e(v)


def _table(head: Sequence[str], rows: Sequence[Sequence[Any]], left: int = 1) -> str:
    th = "".join(f'<th class="{"l" if j < left else ""}">{_e(h)}</th>' for j, h in enumerate(head))
    body = "".join(
        "<tr>"
        + "".join(f'<td class="{"l" if j < left else ""}">{v}</td>' for j, v in enumerate(row))
        + "</tr>"
        for row in rows
    )
    return f"<table><tr>{th}</tr>{body}</table>"


def _slug(name: str, limit: int = 40) -> str:
    """A short, safe file-name part for a trace name (any length, any characters)."""
    import hashlib
    import re

    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", name)[:limit]
    if safe == name:
        return safe
    return f"{safe}_{hashlib.sha1(name.encode()).hexdigest()[:8]}"


def _img(name: str, data: bytes, alt: str) -> str:
    b64 = base64.b64encode(data).decode()
    return f'<img src="data:image/png;base64,{b64}" alt="{_e(alt)}" title="{_e(name)}">'


def build_report(
    traces: Sequence[Trace],
    fit: FitResult,
    *,
    posterior: Any | None = None,
    diagnosis: Any | None = None,
    corrected_posterior: Any | None = None,
    corrected_note: str | None = None,
    command: str | None = None,
    title: str | None = None,
) -> tuple[str, dict[str, bytes]]:
    """The report page and its figures (nothing is written).

    Parameters
    ----------
    traces
        The traces, in the order of ``fit``.
    fit
        A whole-chain or stage fit of those traces.
    posterior
        Optional :class:`~ewb_ident.inference.posterior.PosteriorResult` (its ``to_summary_json()``
        feeds the parameter table and the MCMC section; its pair plot is included).
    diagnosis
        Optional :class:`~ewb_ident.diagnosis.result.DiagnosisResult` (its ``to_json()``).
    corrected_posterior
        Optional posterior of the corrected model
        (:func:`~ewb_ident.inference.posterior.sample_corrected`): its HDIs are the corrected
        model's intervals; without it they are linearised.
    corrected_note
        Why there is no corrected posterior (printed in its place).
    command
        The command line that made the report (for its provenance).

    Returns
    -------
    html : str
        The self-contained page.
    figures : dict
        PNG bytes by file name.
    """
    figures: dict[str, bytes] = {}
    names = ", ".join(t.name for t in traces)
    title = title or f"EWB validation report: {names}"
    status = "converged" if fit.converged else f"did NOT converge: {fit.message}"
    ddoc = diagnosis.to_json() if diagnosis is not None else None
    post = posterior.to_summary_json() if posterior is not None else None
    parts = [
        f"<h1>{_e(title)}</h1>",
        f'<p class="small">Least squares, stage <b>{_e(fit.stage)}</b> ({status}); '
        f"{len(traces)} trace(s).</p>",
        _summary(fit, posterior, ddoc, corrected_posterior),
        _banner(ddoc),
        _data_section(traces, figures),
        _parameter_section(fit, traces, post),
    ]
    corrected = ddoc is not None and (
        ddoc.get("verdict") == "found" or any(not f.get("catalog", True) for f in ddoc["findings"])
    )
    if corrected:
        parts.append(_corrected_section(fit, ddoc, post, corrected_posterior, corrected_note))
    parts.append(_fit_section(fit, traces, posterior, figures))
    parts.append("<h2>4. The clamping-force curve</h2>")
    figures["bell.png"] = figure_bell(fit.params[0], traces)
    parts.append(_img("bell.png", figures["bell.png"], "bell curve with regions"))
    if post:
        parts.append(_posterior_section(post, posterior, figures, corrected_posterior))
    if diagnosis is not None:
        parts.append(_diagnosis_section(ddoc, diagnosis, figures))
    seeds = [p.seed for p in (posterior, corrected_posterior) if p is not None]
    rows = provenance_rows(traces, command, seeds)
    parts.append("<h2>7. Provenance</h2>" + _table(["item", "value"], rows))
    page = (
        f"<!doctype html><html lang=en><head><meta charset=utf-8><title>{_e(title)}</title>"
        f"<style>{CSS}</style></head><body>{''.join(parts)}</body></html>"
    )
    return page, figures


def _banner(ddoc: Mapping[str, Any] | None) -> str:
    """A warning at the top when the diagnosis rejects the baseline model."""
    parts: list[str] = []
    if ddoc is not None and ddoc.get("verdict") == "found":
        found = ", ".join(f["effect"] for f in ddoc["findings"] if f.get("catalog", True))
        parts.append(
            '<div class="warn banner"><b>The diagnosis rejects the baseline model</b>: it '
            f"leaves out {_e(found)} (section 6). The baseline parameters and their intervals "
            "in sections 2 and 5 are conditional on a model that leaves this physics out, "
            "and are biased by it; the corrected model's parameters are in section 2b.</div>"
        )
    elif ddoc is not None and ddoc.get("verdict") == "unexplained":
        parts.append(
            '<div class="warn banner"><b>The diagnosis locates a mismatch it cannot '
            "explain</b> (section 6): the parameters below are conditional on a model that "
            "misses something in this recording.</div>"
        )

    return "".join(parts)


def _data_section(traces: Sequence[Trace], figures: dict[str, bytes]) -> str:
    """Section 1: each trace's rate, length, pad radius and channels, and an overview."""
    parts: list[str] = []
    parts.append("<h2>1. Data</h2>")
    rows = []
    for k, t in enumerate(traces):
        cols = ", ".join(c for c in CHANNEL_LABELS if t.has(c))
        rows.append(
            [_e(t.name), _num(t.sample_rate_hz), _num(t.duration_s), _num(t.r_eff_m), _e(cols)]
        )
        key = f"overview_{k}_{_slug(t.name)}.png"
        figures[key] = figure_overview(t)
        parts.append(_img(key, figures[key], f"recorded channels of {t.name}"))
    parts.insert(
        -len(traces),
        _table(["trace", "rate (Hz)", "length (s)", "r_eff (m)", "channels"], rows),
    )

    return "".join(parts)


def _parameter_section(fit: FitResult, traces: Sequence[Trace], post) -> str:
    """Section 2: least-squares values, posterior intervals and the seed's Table 2."""
    parts: list[str] = []
    parts.append("<h2>2. Parameters</h2>")
    seed = SEED.as_dict()
    head = ["parameter", "unit", "least squares", "std. error"]
    if post:
        head += [
            "posterior mean",
            f"{int(100 * post.get('hdi_prob', 0.9))} % interval",
            "ESS",
            "R-hat",
        ]
    head += ["seed (Table 2)"]
    rows = []
    values = fit.values
    for name in fit.free:
        if name in fit.per_trace and len(traces) > 1:
            continue
        se = fit.stderr.get(name, fit.stderr.get(f"{name}[0]"))
        unit, k = _shown(name)
        row = [_e(name), _e(unit), _num(_times(values[name], k)), _num(_times(se, k), 2)]
        if post:
            p = post["params"].get(name) or post["params"].get(f"{name}[0]") or {}
            row += [
                _num(_times(p.get("mean"), k)),
                _interval(p.get("hdi_low"), p.get("hdi_high"), k) if p else "–",
                _num(p.get("ess"), 3),
                _num(p.get("r_hat"), 3),
            ]
        row.append(_num(_times(seed.get(name), k)))
        rows.append(row)
    parts.append(_table(head, rows, left=2))
    if post and (why := ls_posterior_note(fit, post)):
        parts.append(f'<p class="small">{_e(why)}</p>')
    parts.append(
        '<p class="small">b is dimensionless (the seed paper prints 2.820e-4 m, a units '
        "slip: with that value the bell is a flat 1750 N). Fixed parameters: "
        + _e(
            ", ".join(
                f"{n} = {seed_v * _shown(n)[1]:.4g} {_shown(n)[0]}".rstrip(" 1")
                for n, seed_v in fit.params[0].as_dict().items()
                if n not in fit.free
            )
        )
        + ".</p>"
    )
    for w in fit.warnings:
        parts.append(f'<div class="warn">{_e(w)}</div>')

    return "".join(parts)


def _fit_section(fit: FitResult, traces: Sequence[Trace], posterior, figures) -> str:
    """Section 3: errors beside the seed's, measured against simulated, residual by phase."""
    parts: list[str] = []
    parts.append("<h2>3. Measured against simulated</h2>")
    rows = []
    for ch, m in fit.metrics.items():
        rows.append(
            [
                _e(CHANNEL_LABELS.get(ch, ch)),
                _num(_times(m["rmse"], SCALE.get(ch, 1.0))),
                _num(m["nrmse_pct"], 3),
                _num(m["percent_error"], 3),
                _num(SEED_PERCENT_ERROR.get(ch), 2),
            ]
        )
    parts.append(_table(["channel", "RMSE", "NRMSE %", "% error", "seed's reported % error"], rows))
    parts.append(
        '<p class="small">RMSE in the unit of the channel\'s heading; NRMSE: RMSE over the '
        "measured range; % error: relative L2 error 100·‖sim−meas‖/‖meas‖ (the paper does not "
        "define its percent error; compare loosely).</p>"
    )
    for k, t in enumerate(traces):
        key = f"fit_{k}_{_slug(t.name)}.png"
        figures[key] = figure_fit(
            t,
            fit.predictions[k],
            f"{t.name}: measured vs simulated ({fit.stage})",
            _predictive_bands(posterior, t),
        )
        parts.append(_img(key, figures[key], f"measured against simulated, {t.name}"))
        rows = [
            [_e(CHANNEL_LABELS.get(r["channel"], r["channel"]))]
            + [
                _num(_times(r[q], SCALE.get(r["channel"], 1.0)), 3)
                for q in ("noise", *PHASE_COLOURS)
            ]
            for r in phase_table(t, fit.predictions[k])
        ]
        parts.append(f"<p>RMS residual by phase, {_e(t.name)}, beside the sensor noise:</p>")
        parts.append(_table(["channel", "sensor noise", *PHASE_COLOURS], rows))

    return "".join(parts)


def _predictive_bands(posterior: Any, trace: Trace) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Channel -> 5 % and 95 % quantiles of the posterior's replicated data for one trace
    (none without a posterior)."""
    if posterior is None:
        return {}
    pr = posterior.predictive
    y = np.asarray(pr["y_rep"], float)
    y = y.reshape(-1, y.shape[-1])
    out = {}
    for ch in set(pr["obs_channel"]):
        mask = (pr["obs_trace"] == trace.name) & (pr["obs_channel"] == ch)
        if int(mask.sum()) == trace.n:
            lo, hi = np.quantile(y[:, mask], [0.05, 0.95], axis=0)
            out[str(ch)] = (lo, hi)
    return out


def _summary(fit: FitResult, posterior: Any, ddoc: Any, cpost: Any) -> str:
    """The verdict at the top: the fit's status and errors against the seed's acceptance,
    a, b, c, mu with 90 % intervals (baseline, and corrected when the diagnosis found
    missing physics), and the diagnosis in one line."""
    words = {
        "ok": "converged, and the errors are within the seed's acceptance",
        "poor_fit": "converged to a POOR fit (see the warnings under section 2)",
        "not_converged": "did NOT converge (see the warnings under section 2)",
    }
    errs = [
        f"{ch} {m['percent_error']:.2f} %"
        for ch, m in fit.metrics.items()
        if ch in ("force_N", "torque_Nm") and m.get("percent_error") is not None
    ]
    items = [
        f"<b>Fit</b> ({_e(fit.stage)}): {words.get(fit.status, _e(fit.status))}"
        + (
            f"; % error {', '.join(errs)} (seed's acceptance {SEED_ACCEPTANCE_PCT:g} %)"
            if errs
            else ""
        )
        + "."
    ]
    post = posterior.to_summary_json()["params"] if posterior is not None else {}
    items.append("<b>Baseline</b> (90 % intervals): " + _key_params(fit.values, fit.stderr, post))
    aug = (ddoc or {}).get("augmented", {})
    if (ddoc or {}).get("verdict") == "found" and aug.get("params"):
        cp = cpost.to_summary_json()["params"] if cpost is not None else {}
        items.append(
            f"<b>Corrected</b> with {_e(', '.join(aug.get('mechanisms', [])))}: "
            + _key_params(aug["params"], aug.get("stderr", {}), cp)
        )
    verdict = (ddoc or {}).get("verdict")
    if verdict is None:
        items.append("<b>Diagnosis</b>: not run.")
    elif verdict == "none":
        items.append("<b>Diagnosis</b>: none — every stage fits to the sensor noise.")
    elif verdict == "found":
        items.append(
            "<b>Diagnosis</b>: the model leaves out "
            + _e(", ".join(f["effect"] for f in ddoc["findings"] if f.get("catalog", True)))
            + " (section 6); the corrected model is in section 2b."
        )
    else:
        items.append(
            "<b>Diagnosis</b>: unexplained — a mismatch is located that no catalog mechanism "
            "explains (section 6)."
        )
    kind = "ok" if fit.status == "ok" and verdict in (None, "none") else "warn"
    return (
        f'<div class="{kind}"><b>Summary</b><ul>'
        + "".join(f"<li>{i}</li>" for i in items)
        + "</ul></div>"
    )


def _key_params(values: Mapping[str, float], stderr: Mapping[str, Any], post: Mapping) -> str:
    """``a = 0.63 mm [0.62 … 0.65]`` for a, b, c, mu: the posterior's HDI when sampled,
    else the linearised least-squares interval; no interval for a held parameter."""
    from ewb_ident.data.metrics import Z90 as z

    out = []
    for n in ("a", "b", "c", "mu"):
        if n not in values:
            continue
        unit, k = _shown(n)
        p = post.get(n) or {}
        se = stderr.get(n)
        if p.get("source") == "posterior":
            ci = f" [{_interval(p['hdi_low'], p['hdi_high'], k)}]"
        elif se:
            ci = f" [{_interval(values[n] - z * se, values[n] + z * se, k)}]"
        else:
            ci = " (held)"
        shown = "" if unit == "1" else f" {unit}"
        out.append(f"{n} = {_num(_times(values[n], k))}{_e(shown)}{ci}")
    return "; ".join(out) + "."


def _posterior_section(
    post: Mapping[str, Any], posterior: Any, figures: dict[str, bytes], corrected: Any = None
) -> str:
    """Section 5, for a posterior (``post`` is its ``to_summary_json()``); the pair plot
    is of the model the report recommends (the corrected one when there is one)."""
    out = ["<h2>5. Posterior (MCMC)</h2>"]
    conv = post.get("converged")
    out.append(
        f'<div class="{"ok" if conv else "warn"}">'
        + (
            "Chains converged: R-hat between independent ensembles and ESS within limits."
            if conv
            else "Chains did NOT converge; treat the intervals as provisional."
        )
        + "</div>"
    )
    rows = []
    for name, p in post["params"].items():
        if isinstance(p, dict) and p.get("mean") is not None:
            rows.append(
                [_e(name), _num(p.get("ess"), 4), _num(p.get("r_hat"), 4), _num(p.get("sd"), 3)]
            )
    out.append(_table(["parameter", "ESS", "R-hat (between ensembles)", "posterior sd"], rows))
    diag = post.get("diagnostics") or {}
    flat = {k: v for k, v in diag.items() if isinstance(v, int | float | str | bool)}
    if flat:
        table = _table(["diagnostic", "value"], [[_e(k), _num(v)] for k, v in flat.items()])
        out.append(f"<details><summary>Sampler diagnostics</summary>{table}</details>")
    for w in post.get("warnings", []) or []:
        out.append(f'<div class="warn">{_e(w)}</div>')
    for item in post.get("identifiability", []) or []:
        text = item.get("statement") if isinstance(item, dict) else item
        if text:
            out.append(f'<div class="warn">{_e(text)}</div>')
    shown = corrected if corrected is not None else posterior
    figures["pair.png"] = png_bytes(pair_figure(shown))
    which = "the corrected model" if corrected is not None else "the model"
    out.append(_img("pair.png", figures["pair.png"], f"pair plot of a, b, c, mu of {which}"))
    names, corr = posterior.correlation()
    out.append("<p>Posterior correlation of a, b, c, mu:</p>")
    out.append(
        _table(
            ["", *names],
            [[_e(n), *(_num(v, 3) for v in row)] for n, row in zip(names, corr, strict=True)],
        )
    )
    return "".join(out)


def _corrected_section(
    fit: FitResult, ddoc: Mapping[str, Any], post: Any, cpost: Any | None, note: str | None
) -> str:
    """Baseline (the report's own fit: the numbers of sections 2 and 3, computed once)
    and corrected parameters side by side, with 90 % intervals."""
    from ewb_ident.data.metrics import Z90 as z

    aug = ddoc.get("augmented", {})
    if not aug.get("params"):
        return (
            '<h2>2b. Corrected model</h2><div class="warn">The whole-chain refit with the '
            "findings failed, so no corrected parameters are available.</div>"
        )
    cdoc = cpost.to_summary_json() if cpost is not None else None
    if cdoc is not None:
        state = "converged" if cdoc["converged"] else "did NOT converge: see its warnings below"
        how = (
            f"The corrected model's 90 % intervals are the HDIs of its posterior (MCMC, "
            f"{state}); its values are the least-squares estimates."
        )
    else:
        how = (
            "The corrected model's 90 % intervals are linearised (estimate &plusmn; 1.645 "
            "standard errors of the least-squares fit)" + (f": {_e(note)}." if note else ".")
        )
    out = [
        "<h2>2b. Corrected model: parameters with the missing physics added</h2>",
        "<p>The whole chain refitted from the voltage with "
        + _e(", ".join(aug.get("mechanisms", [])))
        + " switched on (ewb-ident fit TRACE --with-diagnosis DIR). "
        + how
        + " The baseline columns repeat sections 2 and 3.</p>",
    ]
    rows = []
    hp = post["params"] if post else {}
    cp = cdoc["params"] if cdoc else {}
    names = [n for n in ("a", "b", "c", "mu", "F_rt") if n in aug["params"]]
    # A learned term's coefficients are in its basis's units: its equation, refitted
    # with intervals, is in the diagnosis section.
    names += [n for n in aug["params"] if "." in n and not n.startswith("learned[")]
    for n in names:
        v, se = aug["params"][n], aug.get("stderr", {}).get(n)
        b, bs = fit.values.get(n), fit.stderr.get(n)
        hdi, chdi = hp.get(n, {}), cp.get(n, {})
        unit, k = _shown(n)
        if hdi:
            b_int = _interval(hdi["hdi_low"], hdi["hdi_high"], k) + " (MCMC)"
        else:
            b_int = _interval(b - z * bs, b + z * bs, k) if b is not None and bs else "–"
        if chdi and chdi.get("source") == "posterior":
            c_int = _interval(chdi["hdi_low"], chdi["hdi_high"], k) + " (MCMC)"
        else:
            c_int = _interval(v - z * se, v + z * se, k) if se else "–"
        rows.append([_e(n), _e(unit), _num(_times(b, k)), b_int, _num(_times(v, k)), c_int])
    out.append(
        _table(
            ["parameter", "unit", "baseline", "baseline 90 %", "corrected", "corrected 90 %"],
            rows,
            left=2,
        )
    )
    if cdoc is not None:
        out += [f'<div class="warn">{_e(w)}</div>' for w in cdoc["warnings"]]
    rows = []
    for ch, m in fit.metrics.items():
        a = aug.get("metrics", {}).get(ch, {})
        seed = SEED_PERCENT_ERROR.get(ch)
        rows.append(
            [
                _e(ch),
                _num(m.get("nrmse_pct"), 3),
                _num(a.get("nrmse_pct"), 3),
                _num(m.get("percent_error"), 3),
                _num(a.get("percent_error"), 3),
                _num(seed, 2) if seed else "–",
            ]
        )
    out.append(
        _table(
            [
                "channel",
                "NRMSE % baseline",
                "NRMSE % corrected",
                "% error baseline",
                "% error corrected",
                "seed paper %",
            ],
            rows,
        )
    )
    return "".join(out)


def _diagnosis_section(doc: Mapping[str, Any], diagnosis: Any, figures: dict[str, bytes]) -> str:
    out = ["<h2>6. Diagnosis: physics the model leaves out</h2>"]
    verdict = doc.get("verdict")
    words = {
        "none": "The baseline model fits every stage to the sensor noise: nothing is missing.",
        "found": "The baseline model leaves physics out; the catalog explains it:",
        "unexplained": "A mismatch is located, but no catalog mechanism explains it:",
    }
    kind = "ok" if verdict == "none" else "warn"
    out.append(f'<div class="{kind}">{_e(words.get(verdict, verdict))}</div>')
    out.append('<p class="small">Before/after: the diagnosis\'s own noise-weighted fits.</p>')
    out += [f"<p>Note: {_e(note)}</p>" for note in doc.get("notes", [])]
    for f in doc.get("findings", []):
        head = f"<b>{_e(f['effect'])}</b> ({_e(f['stage'])} stage)"
        out.append(f'<div class="finding">{head}: {_e(f["explanation"])}</div>')
        rows = []
        for ch, before in f.get("metrics_before", {}).items():
            after = f.get("metrics_after", {}).get(ch, {})
            rows.append([_e(ch), _num(before.get("nrmse_pct"), 3), _num(after.get("nrmse_pct"), 3)])
        if rows:
            out.append(_table(["channel", "NRMSE % before", "NRMSE % after"], rows))
    if doc.get("mismatches"):
        rows = [
            [
                _e(m["stage"]),
                _e(m["phase"]),
                _e(m["channel"]),
                _num(m["t_start_s"], 3),
                _num(m["t_end_s"], 3),
                _num(m["score"], 3),
                _e(m["summary"]),
            ]
            for m in doc["mismatches"]
        ]
        out.append("<p>Located mismatches, most severe first:</p>")
        out.append(
            _table(
                ["stage", "phase", "channel", "from (s)", "to (s)", "score", "summary"],
                rows,
                left=3,
            )
        )
    if diagnosis is not None:
        for name, data in figure_bytes(diagnosis).items():
            figures[name] = data
            out.append(_img(name, data, name))
    return "".join(out)


def write_report(out_dir: str | Path, page: str, figures: Mapping[str, bytes]) -> Path:
    """Write ``index.html`` and the PNG figures into ``out_dir``, atomically, replacing an
    earlier run's files there as a set (:func:`~ewb_ident.data.outputs.write_run`)."""
    out = Path(out_dir)
    writers = [
        (out / name, lambda tmp, d=data: tmp.write_bytes(d)) for name, data in figures.items()
    ]
    writers.append((out / "index.html", lambda tmp: tmp.write_text(page, encoding="utf-8")))
    write_run(out, "report", writers)
    return out / "index.html"
