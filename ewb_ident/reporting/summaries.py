"""Human-readable summaries of results (terminal text now; the HTML report builds on it)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ewb_ident.data.metrics import SEED_PERCENT_ERROR
from ewb_ident.inference.fit_result import FitResult
from ewb_ident.model.params import PARAMS, SEED


def _fmt(value: float | None, digits: int = 4) -> str:
    return "-" if value is None else f"{value:.{digits}g}"


def fit_summary(result: FitResult) -> str:
    """A short plain-text summary of a fit: parameters, metrics, warnings."""
    lines = [
        f"fit of {', '.join(result.trace_names)} (stage: {result.stage}) - "
        + {
            "ok": "converged",
            "poor_fit": "converged, but POOR FIT (see the warnings)",
            "not_converged": f"NOT CONVERGED: {result.message}",
        }[result.status],
        "",
        f"  {'param':<11}{'estimate':>13}{'std. error':>13}{'seed':>12}  unit",
    ]
    seed = SEED.as_dict()
    for name in result.free:
        if name in result.per_trace:
            values = [result.params[j].as_dict().get(name) for j in range(len(result.params))]
            if name == "theta0_deg":
                values = list(result.theta0_deg)
            for j, v in enumerate(values):
                se = result.stderr.get(f"{name}[{j}]")
                label = f"{name}[{j}]" if len(values) > 1 else name
                lines.append(
                    f"  {label:<11}{_fmt(v):>13}{_fmt(se, 2):>13}{_fmt(seed.get(name)):>12}  "
                    f"{PARAMS[name].unit}"
                )
            continue
        v = result.params[0].as_dict()[name]
        lines.append(
            f"  {name:<11}{_fmt(v):>13}{_fmt(result.stderr.get(name), 2):>13}"
            f"{_fmt(seed.get(name)):>12}  {PARAMS[name].unit}"
        )
    lines += ["", f"  {'channel':<11}{'RMSE':>12}{'NRMSE %':>10}{'% error':>10}{'seed %':>9}"]
    for ch, m in result.metrics.items():
        lines.append(
            f"  {ch:<11}{_fmt(m['rmse']):>12}{_fmt(m['nrmse_pct'], 3):>10}"
            f"{_fmt(m['percent_error'], 3):>10}{_fmt(SEED_PERCENT_ERROR.get(ch), 2):>9}"
        )
    lines.append(
        "  (NRMSE: RMSE over the channel's range; % error: relative L2 error, "
        "see ewb_ident.data.metrics)"
    )
    if result.warnings:
        lines.append("")
        lines += [f"  warning: {w}" for w in result.warnings]
    return "\n".join(lines)


def posterior_summary(result) -> str:
    """A short plain-text summary of a posterior
    (:class:`ewb_ident.inference.posterior.PosteriorResult`):
    intervals, diagnostics, the a-b-c-mu correlations, identifiability and warnings."""
    d = result.diagnostics
    pct = f"{100 * result.hdi_prob:g} %"
    # No finite tau when the chains are too short to estimate it (the warnings say so).
    tau = "not estimable" if d["tau_max"] is None else f"up to {d['tau_max']:.0f} steps"
    lines = [
        f"posterior of {', '.join(result.trace_names)} (stage: {'+'.join(result.stages)}"
        + (f", corrected by {', '.join(result.mechanisms)}" if result.mechanisms else "")
        + ") - "
        + ("converged" if result.converged else "NOT CONVERGED (see the warnings)"),
        f"  {d['n_ensembles']} ensembles x {d['n_walkers']} walkers x {d['n_steps']} steps; "
        f"burn-in {d['burn']}, thin {d['thin']}, tau {tau}, "
        f"acceptance {', '.join(f'{a:.2f}' for a in d['acceptance'])}",
        "",
        f"  {'param':<19}{'mean':>11}{'sd':>10}{pct + ' HDI':>27}{'ESS':>8}{'R-hat':>7}  unit",
    ]
    for name, s in result.stats.items():
        hdi = f"[{_fmt(s['hdi_low'])}, {_fmt(s['hdi_high'])}]"
        ess = "-" if s["ess"] is None else f"{s['ess']:.0f}"
        rhat = "-" if s["r_hat"] is None else f"{s['r_hat']:.3f}"
        src = "" if s["source"] == "posterior" else f"  ({s['source']})"
        lines.append(
            f"  {name:<19}{_fmt(s['mean']):>11}{_fmt(s['sd'], 2):>10}{hdi:>27}{ess:>8}{rhat:>7}"
            f"  {s['unit']}{src}"
        )
    names, corr = result.correlation()
    if len(names) > 1:
        lines += ["", f"  {'posterior correlation':<22}" + "".join(f"{n:>8}" for n in names)]
        for n, row in zip(names, corr, strict=True):
            lines.append(f"  {n:<22}" + "".join(f"{v:>8.3f}" for v in row))
    if result.identifiability:
        lines += ["", "  identifiability:"]
        lines += [f"  - {s['statement']}" for s in result.identifiability]
    if result.warnings:
        lines.append("")
        lines += [f"  warning: {w}" for w in result.warnings]
    return "\n".join(lines)


def corrected_summary(result) -> str:
    """Plain text of a fit with mechanisms (:class:`ewb_ident.diagnosis.corrected.CorrectedFit`):
    baseline beside corrected values, errors before and after, evidence, warnings."""
    lines = [
        f"fit of {result.trace_name} with {', '.join(result.mechanisms)} (whole chain) - "
        + ("converged" if result.converged else "NOT CONVERGED"),
        f"  {'param':<28}{'baseline':>13}{'corrected':>13}{'std. error':>12}",
    ]
    for name, v in result.params.items():
        b, se = result.baseline_params.get(name), result.stderr.get(name)
        lines.append(f"  {name:<28}{_fmt(b):>13}{_fmt(v):>13}{_fmt(se, 2):>12}")
    lines.append("  whole chain NRMSE %, baseline -> corrected:")
    for ch, m in result.metrics.items():
        b = result.baseline_metrics.get(ch, {}).get("nrmse_pct")
        lines.append(f"   - {ch}: {_fmt(b, 3)} -> {_fmt(m['nrmse_pct'], 3)}")
    lines.append(f"  evidence: dBIC {result.delta_bic:.1f}")
    for t in result.learned:
        lines.append(f"  learned term at {t['place']}, refitted: {t['equation']}")
    lines += [f"  warning: {w}" for w in result.warnings]
    return "\n".join(lines)


def validation_summary(result, params_label: str) -> str:
    """Plain text of a validation (:class:`ewb_ident.inference.validate.ValidationResult`)."""
    model = f" (corrected by {', '.join(result.mechanisms)})" if result.mechanisms else ""
    lines = [f"validation of {params_label}{model} on {result.trace_name}: {result.verdict}"]
    lines.append(f"  {result.words}")
    for ch, m in result.metrics.items():
        if m["rmse"] is None:
            lines.append(f"  {ch:<11} not finite (the simulation diverged)")
            continue
        lines.append(
            f"  {ch:<11} RMSE {_fmt(m['rmse'])}  NRMSE {_fmt(m['nrmse_pct'], 3)} %  "
            f"% error {_fmt(m['percent_error'], 3)}  {_fmt(m['noise_ratio'], 3)}x noise"
        )
    return "\n".join(lines)


def headline(result: FitResult, posterior=None, diagnosis=None, corrected_posterior=None) -> str:
    """a, b, c, mu with their 90 % intervals: the baseline fit's and, when the diagnosis
    corrected the model, the corrected one's (MCMC HDIs where a posterior ran, else the
    estimate ± 1.645 standard errors), in the report's units."""
    from ewb_ident.data.units import shown_unit
    from ewb_ident.diagnosis.corrected import merged_spread
    from ewb_ident.inference.log_posterior import CONTRACT_PARAMS
    from ewb_ident.mechanisms.base import RESOLVED_Z as Z

    rows = [("baseline", result.values, result.stderr, posterior)]
    if diagnosis is not None and diagnosis.augmented_params and diagnosis.findings:
        rows.append(
            (
                "corrected",
                diagnosis.augmented_params,
                diagnosis.augmented_stderr,
                corrected_posterior,
            )
        )
    # A corrected parameter whose value depends on the learned term's form keeps the
    # interval that includes that spread (the MCMC's is conditional on the form).
    findings = diagnosis.findings if diagnosis is not None else ()
    spread = {
        k for k, v in merged_spread(f.basis.get("spread") or {} for f in findings).items() if v > 0
    }
    lines = ["a, b, c, mu with 90 % intervals:"]
    for name in CONTRACT_PARAMS:
        unit, k = shown_unit(PARAMS[name].unit)
        for model, values, stderr, post in rows:
            v, se = values.get(name), stderr.get(name)
            if v is None:
                continue
            stats = post.stats.get(name, {}) if post is not None else {}
            if model == "corrected" and name in spread and se is not None:
                lo, hi, how = v - Z * se, v + Z * se, f"± {Z:g} s.e., form spread in"
            elif stats.get("source", "posterior") == "posterior" and "hdi_low" in stats:
                lo, hi, how = stats["hdi_low"], stats["hdi_high"], "MCMC"
            elif se is not None:
                lo, hi, how = v - Z * se, v + Z * se, f"± {Z:g} s.e."
            else:
                lo = hi = None
                how = "held, not estimated"
            interval = "-" if lo is None else f"{_fmt(lo * k)} … {_fmt(hi * k)}"
            lines.append(
                f"  {name:<3}{model:<10}{_fmt(v * k):>10}  {interval:<22} {unit:<3} ({how})"
            )
    return "\n".join(lines)


def ls_posterior_note(fit: FitResult, post: Mapping[str, Any]) -> str:
    """Why the least-squares and posterior intervals differ, for the parameters whose
    least-squares 90 % interval (estimate ± Z90 standard errors) and posterior interval
    (``post``: a posterior's ``to_summary_json()``) differ in width by more than a factor
    1.5; ``""`` when none does."""
    from ewb_ident.data.metrics import Z90

    out = []
    for name in fit.free:
        se = fit.stderr.get(name)
        p = post["params"].get(name) or {}
        lo, hi = p.get("hdi_low"), p.get("hdi_high")
        if se and lo is not None and hi is not None and hi > lo:
            ratio = (hi - lo) / (2 * Z90 * se)
            if not 1 / 1.5 <= ratio <= 1.5:
                out.append(name)
    if not out:
        return ""
    return (
        "The least-squares standard error is the linearisation at the best fit; the "
        "posterior interval is the MCMC's, under the priors, and sees the curvature and the "
        f"bounds the linearisation does not. For {', '.join(out)} they differ by more than "
        "half: quote the posterior interval."
    )
