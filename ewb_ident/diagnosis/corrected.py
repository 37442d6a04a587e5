"""The corrected model: the seed chain with the diagnosed (or named) catalog
mechanisms, refitted from the voltage, with every parameter's value and standard error."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ewb_ident.data.trace import Trace
from ewb_ident.diagnosis.session import (
    BIC_THRESHOLD,
    DiagnoseError,
    Session,
    bic_evidence,
    chain_baseline,
    chain_metrics,
    metrics_json,
    stage_order,
)
from ewb_ident.inference.augmented import (
    AugFit,
    fit_mechanisms,
)
from ewb_ident.mechanisms import AbstractMechanism, variants
from ewb_ident.model.numerics import numerics


def corrected_of(trace: Trace, chain_fits, data, sigma) -> CorrectedFit | None:
    """The diagnosis's corrected whole chain as a :class:`CorrectedFit` (catalog
    mechanisms only: a discovered term has no physical parameters to sample)."""
    catalog = {m.variant for m in variants()}
    f0, f1 = chain_fits[0], chain_fits[-1]
    if not f1.mechanisms or any(m.variant not in catalog for m in f1.mechanisms):
        return None
    notes = () if f1.converged else ("the corrected whole-chain fit did not converge",)
    return corrected_record(trace, f0, f1, data, bic_evidence(f1, f0, sigma), notes)


def corrected_record(trace: Trace, f0, f1, data, ev, notes) -> CorrectedFit:
    """A :class:`CorrectedFit` from the baseline ``f0`` and corrected ``f1`` chain fits."""
    tables = model_tables([f0, f1], True)
    return CorrectedFit(
        trace_name=trace.name,
        mechanisms=tuple(m.variant for m in f1.mechanisms),
        params=tables["augmented_params"],
        stderr=tables["augmented_stderr"],
        metrics=chain_metrics(trace, f1),
        baseline_params=tables["baseline_params"],
        baseline_stderr=tables["baseline_stderr"],
        baseline_metrics=chain_metrics(trace, f0),
        stderr_white=tables["augmented_stderr_white"],
        baseline_stderr_white=tables["baseline_stderr_white"],
        converged=bool(f1.converged),
        delta_bic=float(ev["delta_bic"]),
        warnings=tuple(notes),
        predictions={k: np.asarray(v) for k, v in f1.predictions.items()},
        fit=f1,
        data=data,
    )


def model_tables(chain_fits: Sequence[AugFit], ok: bool) -> dict[str, dict]:
    """Parameter values and standard errors of the baseline and the corrected chain."""
    if not ok or not chain_fits:
        return {}

    def table(f: AugFit):
        values = {k: float(v) for k, v in f.values.items()}
        for m in f.mechanisms:
            values |= {f"{m.variant}.{k}": float(v) for k, v in m.values().items()}
        stderr = {k: f.stderr.get(k) for k in values}
        white = {k: f.stderr_white.get(k) for k in values}
        return values, stderr, white

    bp, bs, bw = table(chain_fits[0])
    ap, as_, aw = table(chain_fits[-1])
    return {
        "baseline_params": bp,
        "baseline_stderr": bs,
        "augmented_params": ap,
        "augmented_stderr": as_,
        "baseline_stderr_white": bw,
        "augmented_stderr_white": aw,
    }


# ----------------------------------------------------------------------------- corrected


@dataclass(frozen=True)
class CorrectedFit:
    """The whole chain fitted from the voltage with catalog mechanisms switched on.

    Attributes
    ----------
    trace_name
        The fitted trace.
    mechanisms
        The mechanism variants switched on (e.g. ``backlash``, ``sensor_delay[force_N]``).
    params, stderr
        Every fitted value (SI): the base parameters (a, b, c, mu, the motor, the gap
        polynomial, ``theta0_deg``) and each mechanism's as ``"variant.param"``; standard
        errors (``None`` where not identified), the larger of the white-residual and the
        serial-correlation-robust one (``stderr_white``, ``baseline_stderr_white``: the
        white ones).
    metrics, baseline_metrics
        Whole-chain metrics per recorded channel, corrected and baseline.
    baseline_params
        The baseline chain's values (no mechanism), for comparison.
    converged
        Whether the solver reported success.
    warnings
        Plain-language notes.
    fit, data
        The corrected least-squares fit and its data (the posterior starts from them).
    """

    trace_name: str
    mechanisms: tuple[str, ...]
    params: dict[str, float]
    stderr: dict[str, float | None]
    metrics: dict[str, dict[str, float | None]]
    baseline_params: dict[str, float]
    baseline_stderr: dict[str, float | None]
    baseline_metrics: dict[str, dict[str, float | None]]
    converged: bool
    delta_bic: float
    warnings: tuple[str, ...]
    predictions: dict[str, np.ndarray] = field(repr=False)
    fit: AugFit | None = field(default=None, repr=False)
    data: dict[str, Any] | None = field(default=None, repr=False)
    stderr_white: dict[str, float | None] = field(default_factory=dict)
    baseline_stderr_white: dict[str, float | None] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """A ``fit.json`` document (contract keys) for the corrected model."""
        return {
            "params": self.params,
            "stderr": self.stderr,
            "stderr_white": self.stderr_white,
            "metrics": metrics_json(self.metrics),
            "converged": self.converged,
            "stage": "chain",
            "mechanisms": list(self.mechanisms),
            "baseline": {
                "params": self.baseline_params,
                "stderr": self.baseline_stderr,
                "stderr_white": self.baseline_stderr_white,
                "metrics": metrics_json(self.baseline_metrics),
            },
            "evidence": {"delta_bic": self.delta_bic},
            "warnings": list(self.warnings),
        }


def mechanism_templates(names: Sequence[str]) -> list[AbstractMechanism]:
    """Mechanism instances for catalog ids or variants (``sensor_delay[force_N]``), each
    optionally in a flexible form after a colon (``backlash:spring``).

    Raises
    ------
    DiagnoseError
        An unknown name, or a sensor mechanism without its channel.
    """
    pool = {m.variant: m for m in variants()}
    out = []
    for name in names:
        name, _, form = name.strip().partition(":")
        if name in pool:
            try:
                out.append(pool[name].in_form(form))
            except ValueError as err:
                raise DiagnoseError(f"--with {name}:{form}: {err}") from None
            continue
        options = [v for v in pool if v.startswith(name + "[")]
        if options:
            raise DiagnoseError(
                f"--with {name}: say which channel it acts on, one of {', '.join(options)}"
            )
        raise DiagnoseError(
            f"--with {name}: not a catalog mechanism; choose from {', '.join(pool)}"
        )
    return out


@numerics
def fit_corrected(trace: Trace, mechanisms: Sequence[str]) -> CorrectedFit:
    """Fit the seed chain augmented by catalog mechanisms, from the voltage.

    Each mechanism is first fitted teacher-forced at its own stages (from its own
    starting points), then the whole chain is fitted from the logged voltage with every
    mechanism on, from the baseline chain and from the teacher-forced values.

    Parameters
    ----------
    trace
        One trace with ``voltage_V`` and ``theta_deg``.
    mechanisms
        Catalog ids or variants, e.g. ``["backlash", "sensor_delay[force_N]"]``.
    """
    templates = mechanism_templates(mechanisms)
    if not (trace.has("voltage_V") and trace.has("theta_deg")):
        raise DiagnoseError(
            f"{trace.label}: the corrected whole-chain fit needs voltage_V and theta_deg"
        )
    ses = Session(trace)
    ses.baseline()
    notes = list(ses.base_messages)
    for m in templates:
        if not ses.mechanism_stages(m):
            raise DiagnoseError(
                f"--with {m.variant}: its stages ({', '.join(m.stages)}) cannot be fitted "
                f"from the channels of {trace.label}"
            )
        reason = m.unsupported_reason(ses.cols, ses.ctx)
        if reason:
            raise DiagnoseError(f"--with {m.variant}: {reason}")
    stages = stage_order({s for m in templates for s in ses.mechanism_stages(m)})
    # A flexible form starts from its catalog form's fit, as in the diagnosis.
    f_tf = ses.fit(stages, [m.in_form("") for m in templates])
    if any(m.form for m in templates):
        flexible = [f.in_form(m.form) for f, m in zip(f_tf.mechanisms, templates, strict=True)]
        f_tf = ses.fit(stages, flexible, explore=[bool(m.form) for m in templates])
    tf = list(f_tf.mechanisms)
    data, chain_free, sigma, f0 = chain_baseline(ses, notes)
    f1 = fit_mechanisms(
        data,
        ("chain",),
        chain_free,
        tf,
        tuple(sigma),
        start={n: f0.values[n] for n in chain_free},
        ctx=ses.ctx,
        explore=[True] * len(tf),
        alt_starts=[{n: ses.values[n] for n in chain_free if n in ses.values}],
    )
    ev = bic_evidence(f1, f0, sigma)
    if not f1.converged:
        notes.append("the corrected whole-chain fit did not converge")
    if ev["delta_bic"] > -BIC_THRESHOLD:
        notes.append(
            f"the mechanisms do not improve the whole chain (dBIC {ev['delta_bic']:.1f} > "
            f"-{BIC_THRESHOLD:g}): this trace gives no evidence for them"
        )
    return corrected_record(trace, f0, f1, data, ev, notes)
