"""What a diagnosis returns: candidates, findings and the result record (with its
JSON form)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ewb_ident.data.trace import Trace
from ewb_ident.diagnosis.artefacts import Artefact
from ewb_ident.diagnosis.corrected import CorrectedFit
from ewb_ident.diagnosis.locate import (
    Mismatch,
    StageCheck,
)
from ewb_ident.diagnosis.session import (
    BIC_THRESHOLD,
    MIN_EXPLAINED,
    json_number,
    metrics_json,
    pct_text,
)

# ----------------------------------------------------------------------------- results


# A frozen record of its fields, like the package's other results: alike in shape only.
@dataclass(frozen=True)
class Candidate:
    """One mechanism fitted as a candidate explanation, with its evidence."""

    variant: str
    effect: str
    stages: tuple[str, ...]
    round: int
    delta_bic: float
    delta_chi2: float
    explained: float
    p_value: float
    params: dict[str, float]
    stderr: dict[str, float | None]
    rejected: str
    selected: bool = False
    #: For a flexible form of a catalog mechanism: its dBIC against the catalog's form.
    form_gain_bic: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "mechanism": self.variant,
            "effect": self.effect,
            "stages": list(self.stages),
            "round": self.round,
            "delta_bic": json_number(self.delta_bic),
            "delta_chi2": json_number(self.delta_chi2),
            "explained_fraction": json_number(self.explained),
            "lr_p_value": json_number(self.p_value),
            "params": self.params,
            "stderr": {k: json_number(v) for k, v in self.stderr.items()},
            "selected": self.selected,
            "rejected_because": self.rejected or None,
            "form_delta_bic": json_number(self.form_gain_bic),
        }


@dataclass(frozen=True)
class Finding:
    """One explanation of a mismatch: a catalog mechanism, or a discovered term."""

    effect: str
    variant: str
    stage: str
    explanation: str
    params: dict[str, float]
    stderr: dict[str, float | None]
    units: dict[str, str]
    evidence: dict[str, float]
    metrics_before: dict[str, dict[str, float | None]]
    metrics_after: dict[str, dict[str, float | None]]
    phases: tuple[str, ...] = ()
    depends_on: tuple[str, ...] = ()
    #: Signals the trace cannot tell from those of ``depends_on`` (a learned term's).
    equivalents: tuple[str, ...] = ()
    catalog: bool = True
    alternatives: tuple[tuple[str, float], ...] = ()
    #: The mechanism's flexible form (``"drift"``, ``"spring"``, ...), ``""`` for the
    #: catalog's form.
    form: str = ""
    #: A discovered term (physics outside the catalog): where in the model it acts
    #: (:data:`ewb_ident.mechanisms.learned.PLACES`), its distilled equation (SI), its
    #: held-out improvement, its terms with 90 % intervals, and a physical reading.
    place: str = ""
    equation: str = ""
    heldout: dict[str, Any] = field(default_factory=dict)
    terms: tuple[dict[str, Any], ...] = ()
    reading: str = ""
    #: The discovered term as data (:meth:`ewb_ident.diagnosis.learned_spec.LearnedSpec.to_json`),
    #: to refit it on a trace (``fit --with-diagnosis``).
    basis: dict[str, Any] = field(default_factory=dict)
    #: The discovered term per sample, in the place's unit, and its main input with
    #: that input's label (for figures; not in JSON).
    term_series: np.ndarray | None = field(default=None, repr=False, compare=False)
    term_input: np.ndarray | None = field(default=None, repr=False, compare=False)
    term_input_label: str = ""

    def to_json(self) -> dict[str, Any]:
        out = {
            "effect": self.effect,
            "stage": self.stage,
            "explanation": self.explanation,
            "params": self.params,
            "evidence": {k: json_number(v) for k, v in self.evidence.items()},
            "metrics_before": metrics_json(self.metrics_before),
            "metrics_after": metrics_json(self.metrics_after),
            "stderr": {k: json_number(v) for k, v in self.stderr.items()},
            "units": self.units,
            "mechanism": self.variant,
            "phases": list(self.phases),
            "catalog": self.catalog,
        }
        if self.form:
            out["form"] = self.form
        if self.depends_on:
            out["depends_on"] = list(self.depends_on)
        out["alternatives"] = [
            {"effect": e, "delta_bic": json_number(d)} for e, d in self.alternatives
        ]
        if self.place:
            out["place"] = self.place
            out["equation"] = self.equation
            out["heldout"] = {
                k: (v if isinstance(v, str) else json_number(v)) for k, v in self.heldout.items()
            }
            out["terms"] = [
                {k: (v if isinstance(v, str) else json_number(v)) for k, v in t.items()}
                for t in self.terms
            ]
            out["reading"] = self.reading or None
            out["basis"] = self.basis
            out["depends_on_equivalent"] = list(self.equivalents)
        return out


# A frozen record of its fields, like the package's other results: alike in shape only.
@dataclass(frozen=True)
class DiagnosisResult:
    """The outcome of :func:`diagnose` (immutable).

    Attributes
    ----------
    trace_name
        The diagnosed trace.
    verdict
        ``"none"``, ``"found"`` or ``"unexplained"`` (see ``shared/CONTRACTS.md``).
    mismatches
        Flagged (stage, channel, phase) cells of the baseline, most severe first.
    cells
        Every scored cell of the baseline (flagged or not).
    findings
        Explanations, best supported first (catalog ones, then discovered terms).
    candidates
        Every mechanism fitted, with its evidence and why it was or was not selected.
    baseline_metrics, augmented_metrics
        Whole-chain metrics per channel, before and after the findings were added.
    stage_metrics_before, stage_metrics_after
        Teacher-forced metrics per stage and channel, before and after.
    noise
        Sensor-noise estimate per channel, in the channel's unit.
    checks_before, checks_after
        Residual checks per (stage, channel) before and after (for figures).
    chain_before, chain_after
        The whole chain's predictions before and after (for figures).
    labels
        Phase of each sample.
    timings
        Seconds spent per step.
    corrected
        The whole chain fitted with the findings on, catalog mechanisms and learned
        terms (``None`` when there is none): where the corrected model's posterior
        starts.
    """

    trace_name: str
    verdict: str
    mismatches: tuple[Mismatch, ...]
    cells: tuple[Mismatch, ...]
    findings: tuple[Finding, ...]
    candidates: tuple[Candidate, ...]
    baseline_metrics: dict[str, dict[str, float | None]]
    augmented_metrics: dict[str, dict[str, float | None]]
    stage_metrics_before: dict[str, dict[str, dict[str, float | None]]]
    stage_metrics_after: dict[str, dict[str, dict[str, float | None]]]
    noise: dict[str, float]
    checks_before: dict[tuple[str, str], StageCheck] = field(repr=False)
    checks_after: dict[tuple[str, str], StageCheck] = field(repr=False)
    chain_before: dict[str, np.ndarray] = field(repr=False)
    chain_after: dict[str, np.ndarray] = field(repr=False)
    labels: np.ndarray = field(repr=False)
    trace: Trace = field(repr=False)
    timings: dict[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    baseline_params: dict[str, float] = field(default_factory=dict)
    baseline_stderr: dict[str, float | None] = field(default_factory=dict)
    augmented_params: dict[str, float] = field(default_factory=dict)
    augmented_stderr: dict[str, float | None] = field(default_factory=dict)
    baseline_stderr_white: dict[str, float | None] = field(default_factory=dict)
    augmented_stderr_white: dict[str, float | None] = field(default_factory=dict)
    corrected: CorrectedFit | None = field(default=None, repr=False)
    #: Sensor artefacts recognised (not physics), :mod:`ewb_ident.diagnosis.artefacts`.
    artefacts: tuple[Artefact, ...] = ()

    def corrected_mechanisms(self) -> list[str]:
        """The catalog mechanism variants found: what ``fit --with-diagnosis`` and the
        corrected model switch on (empty when nothing in the catalog explains the data)."""
        return [
            f.variant
            for f in self.findings
            if f.catalog and not f.variant.startswith("unexplained_")
        ]

    def to_json(self) -> dict[str, Any]:
        """The contract ``diagnosis.json`` document (plain JSON, no NaN)."""
        return {
            "verdict": self.verdict,
            "mismatches": [m.to_json() for m in self.mismatches],
            "findings": [f.to_json() for f in self.findings],
            "artefacts": [a.to_json() for a in self.artefacts],
            "baseline": {
                "metrics": metrics_json(self.baseline_metrics),
                "params": self.baseline_params,
                "stderr": self.baseline_stderr,
                "stderr_white": self.baseline_stderr_white,
                "stage_metrics": {s: metrics_json(m) for s, m in self.stage_metrics_before.items()},
            },
            "augmented": {
                "metrics": metrics_json(self.augmented_metrics),
                "stage_metrics": {s: metrics_json(m) for s, m in self.stage_metrics_after.items()},
                "mechanisms": [f.effect for f in self.findings],
                "params": self.augmented_params,
                "stderr": self.augmented_stderr,
                "stderr_white": self.augmented_stderr_white,
                "params_note": (
                    "the whole chain refitted from the voltage with the findings on: the "
                    "corrected a, b, c, mu; mechanism parameters as 'variant.param'. Empty "
                    "when the whole-chain fit failed."
                ),
            },
            "trace": self.trace_name,
            "noise_sigma": self.noise,
            "candidates": [c.to_json() for c in self.candidates],
            "cells": [m.to_json() | {"flagged": m.flagged} for m in self.cells],
            "thresholds": {
                "score_min": _locate_const("SCORE_MIN"),
                "score_structured": _locate_const("SCORE_STRUCTURED"),
                "z_min": _locate_const("Z_MIN"),
                "bic_threshold": BIC_THRESHOLD,
                "min_explained_fraction": MIN_EXPLAINED,
                "rule": (
                    "a stage is located when a phase's residual RMS over the noise floor is "
                    ">= score_min with chi-square excess z >= z_min, or its lag-1 "
                    "autocorrelation is significant (rho sqrt(n) >= z_min) with score >= "
                    "score_structured; a mechanism is reported when dBIC <= -bic_threshold, "
                    "its parameters are plausible with a 90 % interval that excludes no effect, "
                    "and it removes >= min_explained_fraction of the excess residual"
                ),
            },
            "notes": list(self.notes),
            "timings_s": self.timings,
        }

    def summary(self) -> str:
        """A short plain-language summary (for the terminal)."""
        lines = [f"diagnosis of {self.trace_name}: {self.verdict}"]
        if not self.mismatches:
            lines.append("  every stage fits to the sensor noise; no missing physics is located.")
        elif self.verdict == "unexplained" and not self.findings:
            lines.append(
                "  a mismatch is located, but nothing explains it beyond the noise in the "
                "whole chain: unexplained (where: below)."
            )
        if self.mismatches:
            lines.append("  where the model misses (most severe first):")
            for m in self.mismatches[:5]:
                lines.append(
                    f"   - {m.stage} stage, {m.phase}, {m.channel}: {m.score:.1f}x the noise"
                )
        for a in self.artefacts:
            lines.append(f"  sensor artefact ({a.kind}): {a.summary}")
        for f in self.findings:
            tag = "" if f.catalog else " (not in the catalog)"
            lines.append(f"  {f.effect}{tag}: {f.explanation}")
        if self.verdict != "none":
            lines.append("  whole chain, NRMSE % before -> after:")
            for ch, m in self.baseline_metrics.items():
                a = self.augmented_metrics.get(ch, {})
                before, after = pct_text(m.get("nrmse_pct")), pct_text(a.get("nrmse_pct"))
                lines.append(f"   - {ch}: {before} -> {after}")
        for note in self.notes:
            lines.append(f"  note: {note}")
        return "\n".join(lines)


def _locate_const(name: str) -> float:
    from ewb_ident.diagnosis import locate

    return float(getattr(locate, name))
