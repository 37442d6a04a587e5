"""Diagnosis: locate a mismatch between model and recording, name the missing physics,
add it to the model, refit, and show the fit improve.

Steps (:func:`diagnose`)
------------------------
1. **Baseline.** Each stage is fitted teacher-forced from its measured input
   (:func:`ewb_ident.inference.least_squares.fit`), and the whole chain from the voltage.
2. **Locate** (:mod:`ewb_ident.diagnosis.locate`). Each stage's residual is scored against its
   noise floor, phase by phase, with a whiteness test; a stage with a flagged cell is
   *located*. Nothing located: the verdict is ``none``.
3. **Explain.** Every catalog mechanism (:mod:`ewb_ident.mechanisms`) that acts on a
   located stage and that the trace's columns support is fitted teacher-forced at its
   stage(s), with that stage's own parameters refitted. Evidence is the change of the
   Bayesian information criterion against the same stages without it,
   ``dBIC = N_eff ln(RSS_1 / RSS_0) + dk ln N_eff`` (Gaussian likelihood with the noise
   scale profiled; ``RSS`` the sum of squared residuals over the noise floor). ``N_eff =
   N (1 - rho) / (1 + rho)`` is the effective number of the ``N`` residuals, with ``rho``
   the lag-1 autocorrelation of the residual *with* the mechanism (AR(1) errors): a
   mechanism that leaves the residual white gets the full evidence of ``N`` samples; one
   that only absorbs part of a smooth misfit (a fraction of a sample's delay, say) gets
   the evidence of the few independent stretches that misfit spans. Without this, a
   white-noise BIC over-counts correlated residuals and names noise-level structure.
   A mechanism is *supported* when

   - ``dBIC <= -BIC_THRESHOLD`` (10: "very strong" evidence on the scale of Kass and
     Raftery 1995, a Bayes factor above about 150),
   - every physical parameter lies inside its plausibility bounds and its 90 % interval
     excludes "no effect" (guard against reporting an unresolved value), and
   - it removes at least ``MIN_EXPLAINED`` (half) of the excess of the residual over the
     noise at its stages (guard against a catalog name absorbing part of some other
     physics), or at least ``CATALOG_SHARE`` of what the generic correction of step 4
     removes there (the excess can hold what no smooth term removes, e.g. noise on a
     measured input bent by a nonlinear stage).

   Forward selection: the supported mechanism with the lowest ``dBIC`` is added, the
   remaining candidates are refitted on top of it, and so on while a stage is still
   located (at most :data:`MAX_MECHANISMS`).
4. **Unknown physics.** A stage still located afterwards gets a sparse generic
   correction (:mod:`ewb_ident.diagnosis.correction`), reported as
   ``unexplained_<stage>`` with the terms it depends on. With no catalog finding the
   verdict is ``unexplained``.
5. **Show it.** The whole chain is refitted with the selected mechanisms, one added at a
   time, for metrics before and after each; words for each finding.

Thresholds are statistical (noise-relative scores, significance, information criterion)
and were set on rig settings other than those the accuracy study measures on.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import jax.numpy as jnp
import numpy as np
from scipy import stats

from ewb_ident.data.metrics import channel_metrics, noise_sigma, sensor_noise
from ewb_ident.data.trace import CHANNELS, STAGE_COLUMNS, Trace
from ewb_ident.diagnosis.correction import (
    FEATURES,
    GenericCorrection,
    available_features,
    forward_select,
    signals,
    with_signals,
)
from ewb_ident.diagnosis.locate import (
    FLOOR_SCALE,
    PHASES,
    STAGE_WORDS,
    Mismatch,
    StageCheck,
    describe_signature,
    phase_labels,
    score_check,
    signature,
    stage_excess,
    summary_text,
)
from ewb_ident.inference.augmented import (
    AugFit,
    AugProblem,
    clipped_to_u,
    fit_mechanisms,
    jacobian,
    make_data,
    residuals,
)
from ewb_ident.inference.least_squares import default_free
from ewb_ident.inference.least_squares import fit as fit_stage
from ewb_ident.mechanisms import AbstractMechanism, variants
from ewb_ident.mechanisms.base import fmt_pm
from ewb_ident.model.integrate import seed_motor_states
from ewb_ident.model.params import PARAMS, EWBParams
from ewb_ident.model.physics import clamp_force
from ewb_ident.model.predict import STAGE_OUTPUTS, n_substeps

#: A mechanism must lower the BIC by at least this much.
BIC_THRESHOLD = 10.0
#: ... and remove at least this fraction of the excess residual at its stages.
MIN_EXPLAINED = 0.5
#: ... unless it removes at least this share of what the generic correction removes.
CATALOG_SHARE = 0.8
#: Most catalog mechanisms selected for one trace.
MAX_MECHANISMS = 3
#: Averaging time of the displacement that drives a hysteresis state, s.
X_SMOOTH_S = 0.01
#: Most stages given a generic correction.
MAX_CORRECTIONS = 2

#: How to record a trace that separates two mechanisms a trace could not tell apart.
SEPARATE: defaultdict[frozenset[str], str] = defaultdict(
    str,
    {
        frozenset(("friction_speed", "friction_fade")): (
            "when the disc slows steadily while the pads heat up, speed and dissipated "
            "energy rise and fall together; disc-speed steps, or a cooled-down repeat, "
            "separate them"
        ),
    },
)

STAGE_ORDER: tuple[str, ...] = ("motor", "gap", "force", "torque")
MOTOR_PARAMS: tuple[str, ...] = ("R", "L", "kb", "kT", "M", "v")
MAIN_CHANNEL: dict[str, str] = {
    "motor": "theta_deg",
    "gap": "x_m",
    "force": "force_N",
    "torque": "torque_Nm",
}


class DiagnoseError(ValueError):
    """A trace that cannot be diagnosed (the message says why and what to do)."""


# ----------------------------------------------------------------------------- results


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

    def to_json(self) -> dict[str, Any]:
        return {
            "mechanism": self.variant,
            "effect": self.effect,
            "stages": list(self.stages),
            "round": self.round,
            "delta_bic": _num(self.delta_bic),
            "delta_chi2": _num(self.delta_chi2),
            "explained_fraction": _num(self.explained),
            "lr_p_value": _num(self.p_value),
            "params": self.params,
            "stderr": {k: _num(v) for k, v in self.stderr.items()},
            "selected": self.selected,
            "rejected_because": self.rejected or None,
        }


@dataclass(frozen=True)
class Finding:
    """One explanation of a mismatch: a catalog mechanism, or a generic correction."""

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
    catalog: bool = True
    alternatives: tuple[tuple[str, float], ...] = ()

    def to_json(self) -> dict[str, Any]:
        out = {
            "effect": self.effect,
            "stage": self.stage,
            "explanation": self.explanation,
            "params": self.params,
            "evidence": {k: _num(v) for k, v in self.evidence.items()},
            "metrics_before": _metrics_json(self.metrics_before),
            "metrics_after": _metrics_json(self.metrics_after),
            "stderr": {k: _num(v) for k, v in self.stderr.items()},
            "units": self.units,
            "mechanism": self.variant,
            "phases": list(self.phases),
            "catalog": self.catalog,
        }
        if self.depends_on:
            out["depends_on"] = list(self.depends_on)
        out["alternatives"] = [{"effect": e, "delta_bic": _num(d)} for e, d in self.alternatives]
        return out


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
        Explanations, best supported first (catalog ones, then generic corrections).
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
        The whole chain fitted with the catalog findings on (``None`` when nothing in
        the catalog was found or a generic correction is among them): where the
        corrected model's posterior starts.
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
    corrected: CorrectedFit | None = field(default=None, repr=False)

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
            "baseline": {
                "metrics": _metrics_json(self.baseline_metrics),
                "params": self.baseline_params,
                "stderr": self.baseline_stderr,
                "stage_metrics": {
                    s: _metrics_json(m) for s, m in self.stage_metrics_before.items()
                },
            },
            "augmented": {
                "metrics": _metrics_json(self.augmented_metrics),
                "stage_metrics": {s: _metrics_json(m) for s, m in self.stage_metrics_after.items()},
                "mechanisms": [f.effect for f in self.findings],
                "params": self.augmented_params,
                "stderr": self.augmented_stderr,
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
        for f in self.findings:
            tag = "" if f.catalog else " (not in the catalog)"
            lines.append(f"  {f.effect}{tag}: {f.explanation}")
        if self.verdict != "none":
            lines.append("  whole chain, NRMSE % before -> after:")
            for ch, m in self.baseline_metrics.items():
                a = self.augmented_metrics.get(ch, {})
                lines.append(f"   - {ch}: {_pct(m.get('nrmse_pct'))} -> {_pct(a.get('nrmse_pct'))}")
        for note in self.notes:
            lines.append(f"  note: {note}")
        return "\n".join(lines)


def _locate_const(name: str) -> float:
    from ewb_ident.diagnosis import locate

    return float(getattr(locate, name))


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def _num(v: Any) -> Any:
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) else None


def _metrics_json(m: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    return {ch: {k: _num(v) for k, v in mm.items()} for ch, mm in m.items()}


# ----------------------------------------------------------------------------- session


def _order(stages) -> tuple[str, ...]:
    if tuple(stages) == ("chain",):
        return ("chain",)
    return tuple(s for s in STAGE_ORDER if s in stages)


def _key(stages, mechs) -> tuple:
    return (_order(stages), tuple(m.variant + repr(m.static_config()) for m in mechs))


class _Session:
    """The trace, its noise floors and data, and a cache of fits."""

    def __init__(self, trace: Trace):
        self.trace = trace
        self.cols = tuple(c for c in trace.columns if c != "time_s")
        self.stages = tuple(s for s in STAGE_ORDER if all(trace.has(c) for c in STAGE_COLUMNS[s]))
        if not self.stages:
            raise DiagnoseError(
                f"{trace.label}: no stage of the chain can be checked: it needs at least "
                "one input-output pair (voltage_V and theta_deg, theta_deg and x_m, x_m and "
                "force_N, or force_N and torque_Nm); record these channels"
            )
        self.noise = {ch: sensor_noise(trace[ch]) for ch in CHANNELS if trace.has(ch)}
        self.labels = phase_labels(trace)
        self.cache: dict[tuple, AugFit] = {}
        self.ctx = self._facts()

    def _facts(self) -> dict[str, Any]:
        tr = self.trace
        ctx: dict[str, Any] = {"dt": tr.dt}
        if tr.has("voltage_V"):
            ctx["voltage_noise_V"] = noise_sigma(tr["voltage_V"])
        if tr.has("force_N"):
            ctx["force_max_N"] = float(np.max(tr["force_N"]))
        if tr.has("current_A"):
            ctx["current_peak_A"] = float(np.max(np.abs(tr["current_A"])))
        if tr.has("disc_speed_rad_s"):
            w = tr["disc_speed_rad_s"]
            contact = self.labels != "gapping"
            wc = w[contact] if np.sum(contact) > 2 else w
            ref = float(np.mean(wc))
            ctx["omega_ref"] = ref if abs(ref) > 1e-6 else 1.0
            ctx["disc_speed_range"] = (float(np.min(wc)), float(np.max(wc)))
            ctx["disc_speed_span"] = (
                float(np.max(wc) - np.min(wc)) / abs(ctx["omega_ref"]) if ref else 0.0
            )
            if tr.has("torque_Nm"):
                ctx["energy_total_J"] = float(np.sum(np.abs(tr["torque_Nm"] * w)) * tr.dt)
        return ctx

    # -- baseline

    def baseline(self) -> None:
        tr = self.trace
        vals = EWBParams().as_dict()
        vals["theta0_deg"] = float(np.median(tr["theta_deg"][:5])) if tr.has("theta_deg") else 0.0
        #: The start angle as recorded (a motor refit's second start).
        self.theta0_measured = vals["theta0_deg"]
        self.free: dict[str, tuple[str, ...]] = {}
        self.base_messages: list[str] = []
        for s in self.stages:
            free = default_free(s, [tr])
            self.free[s] = tuple(free)
            res = _safe_fit(tr, s, self.base_messages)
            if res is None:
                continue
            bad = []
            for name in free:
                v = float(res.values[name])
                info = PARAMS[name]
                if not np.isfinite(v) or (info.transform == "log" and v <= 1e-9 * info.ref):
                    bad.append(name)  # degenerate: start from the seed value instead
                    continue
                vals[name] = v
            if bad:
                self.base_messages.append(
                    f"the baseline {s}-stage fit returned degenerate values for "
                    f"{', '.join(bad)}; the diagnosis started them from the seed values"
                )
            if not res.converged:
                self.base_messages.append(f"the baseline {s}-stage fit: {res.message}")
        self.values = vals
        kT, R = vals["kT"], vals["R"]
        self.ctx |= {"kT": kT, "R": R}
        if tr.has("voltage_V") and R > 0:
            self.ctx["stall_torque_Nm"] = _stall_torque(tr, kT, R)
        self.sigma_tf = self._stage_sigma(vals)
        # The displacement that drives a hysteresis state: averaged over about 10 ms,
        # then through a play twice as wide as the averaged noise (sensor noise must not
        # drive a rate-independent friction state while the piston stands still).
        width = max(1, round(X_SMOOTH_S / tr.dt)) | 1
        xp = 2.0 * self.noise.get("x_m", 0.0) / np.sqrt(width)
        x_model = None
        if "motor" in self.stages and "gap" in self.stages:
            # Better still: the motor model's angle follows the logged voltage, so it
            # carries the actuator's small motions (controller dither in a hold) that
            # the displacement sensor's noise hides, and that a friction state feels.
            theta_model = self.base_fits_motor_theta(vals)
            x_model = vals["p2"] * theta_model**2 + vals["p1"] * theta_model + vals["p0"]
        data = make_data(
            tr,
            self.sigma_tf,
            vals,
            x_play_m=xp,
            omega_ref=self.ctx.get("omega_ref", 1.0),
            theta_noise=self.noise.get("theta_deg"),
            x_smooth=width,
            x_model=x_model,
        )
        self.data = with_signals(data, tr)
        self.base_fits = {s: self.fit((s,), ()) for s in self.stages}
        for s, f in self.base_fits.items():
            for name in self.free[s]:
                self.values[name] = f.values[name]

    def base_fits_motor_theta(self, v: Mapping[str, float]) -> np.ndarray:
        """The motor stage's angle (degrees) from the logged voltage, baseline values."""
        p = EWBParams(**{k: v[k] for k in EWBParams().as_dict()})
        states = seed_motor_states(
            p,
            jnp.asarray(self.trace["voltage_V"]),
            self.trace.dt,
            v["theta0_deg"],
            1,
            "exponential",
            None,
        )
        return np.asarray(states[:, 2]) * (180.0 / np.pi)

    def _stage_sigma(self, v: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Noise floor per sample of each teacher-forced stage's output."""
        tr, nz = self.trace, self.noise
        out: dict[str, np.ndarray] = {}
        n = tr.n
        for s in self.stages:
            if s == "motor":
                for ch in ("theta_deg", "current_A"):
                    if tr.has(ch):
                        out[ch] = np.full(n, nz[ch])
            elif s == "gap":
                th = tr["theta_deg"]
                g = 2 * v["p2"] * th + v["p1"]
                out["x_m"] = np.sqrt(nz["x_m"] ** 2 + (g * nz["theta_deg"]) ** 2)
            elif s == "force":
                x = tr["x_m"]
                hx = 1e-3 * abs(v["a"])
                f = lambda z: np.asarray(clamp_force(z, v["F_rt"], v["a"], v["b"], v["c"]))  # noqa: E731
                g = (f(x + hx) - f(x - hx)) / (2 * hx)
                out["force_N"] = np.sqrt(nz["force_N"] ** 2 + (g * nz["x_m"]) ** 2)
            elif s == "torque":
                g = 2 * v["mu"] * tr.r_eff_m
                out["torque_Nm"] = np.sqrt(nz["torque_Nm"] ** 2 + (g * nz["force_N"]) ** 2)
        return {ch: np.broadcast_to(np.asarray(v, float), (n,)).copy() for ch, v in out.items()}

    # -- fits

    def free_of(self, stages: Sequence[str]) -> tuple[str, ...]:
        out: list[str] = []
        for s in stages:
            out += [n for n in self.free[s] if n not in out]
        return tuple(out)

    def channels_of(self, stages: Sequence[str]) -> tuple[str, ...]:
        return tuple(c for s in stages for c in STAGE_OUTPUTS[s] if c in self.sigma_tf)

    def fit(
        self,
        stages: Sequence[str],
        mechs: Sequence[AbstractMechanism],
        explore: Sequence[bool] | None = None,
    ) -> AugFit:
        stages = _order(stages)
        key = _key(stages, mechs)
        if key not in self.cache:
            free = self.free_of(stages)
            alt = []
            if mechs and "motor" in stages:
                # A baseline motor fitted without the missing physics has compensated for
                # it (and a closed-loop trace lets such errors grow without bound): also
                # start from the nominal motor.
                nominal = EWBParams().as_dict() | {"theta0_deg": self.theta0_measured}
                alt.append(
                    {
                        n: nominal[n]
                        for n in free
                        if n in nominal and n in (*MOTOR_PARAMS, "theta0_deg")
                    }
                )
            self.cache[key] = fit_mechanisms(
                self.data,
                stages,
                free,
                tuple(mechs),
                self.channels_of(stages),
                start={n: self.values[n] for n in free},
                ctx=self.ctx,
                explore=explore,
                alt_starts=alt,
            )
        return self.cache[key]

    def check(self, stage: str, f: AugFit) -> list[StageCheck]:
        out = []
        for ch in STAGE_OUTPUTS[stage]:
            if ch in f.predictions and ch in self.sigma_tf:
                out.append(
                    StageCheck(stage, ch, self.trace[ch], f.predictions[ch], self.sigma_tf[ch])
                )
        return out

    def mechanism_stages(self, m: AbstractMechanism) -> tuple[str, ...]:
        return tuple(s for s in m.stages if s in self.stages)


def _chain_baseline(ses: _Session, messages: list[str]):
    """The whole chain from the voltage without mechanisms: its data, free parameters,
    per-channel noise levels and fit (started from the least-squares chain fit, or the
    stage values when that fails)."""
    trace = ses.trace
    base_chain = _safe_fit(trace, "chain", messages)
    start = ses.values if base_chain is None else base_chain.values
    free = tuple(default_free("chain", [trace]))
    sigma = {ch: ses.noise[ch] for ch in CHANNELS if trace.has(ch)}
    data = with_signals(
        make_data(trace, sigma, start, omega_ref=ses.ctx.get("omega_ref", 1.0)), trace
    )
    return data, free, sigma, fit_mechanisms(data, ("chain",), free, (), tuple(sigma))


def _chain_metrics(trace: Trace, f: AugFit) -> dict[str, dict[str, float | None]]:
    """Metrics of a fit's predictions for the channels the trace records."""
    return {ch: channel_metrics(p, trace[ch]) for ch, p in f.predictions.items() if trace.has(ch)}


def _safe_fit(trace: Trace, stage: str, messages: list[str]):
    """The baseline fit of one stage by :func:`ewb_ident.inference.least_squares.fit`, or
    ``None`` (and a
    message) when it fails numerically: the diagnosis then starts from the seed values."""
    try:
        return fit_stage(trace, stage=stage)
    except (np.linalg.LinAlgError, FloatingPointError, ArithmeticError) as err:
        messages.append(f"the baseline {stage} fit failed ({err}); started from seed values")
        return None


# ----------------------------------------------------------------------------- evidence


def _evidence(
    f1: AugFit,
    f0: AugFit,
    sigma: Mapping[str, np.ndarray],
    own: Sequence[str] | None = None,
) -> dict[str, float]:
    """Evidence for the mechanisms ``f1`` adds to ``f0`` (same stages and weights).

    ``explained_fraction`` is the share of the excess of ``f0``'s residual over the
    noise that ``f1`` removes; the noise expectation of the weighted residual sum of
    squares is ``sum_ch n c_ch^2`` with ``c_ch`` the residual's own white-noise level per
    channel (:func:`ewb_ident.diagnosis.locate.floor_scale`), so a noise floor that is off by some
    per cent does not distort it.
    """
    n = f0.n
    dk = f1.k - f0.k
    rss0, rss1 = max(f0.rss, 1e-300), max(f1.rss, 1e-300)
    rho = _lag1(f1, sigma)
    n_eff = n * (1.0 - rho) / (1.0 + rho)
    dbic = n_eff * float(np.log(rss1 / rss0)) + dk * float(np.log(n_eff))
    dchi2 = rss0 - rss1
    # The explained share is judged on the mechanism's own channels (``own``): a fit
    # that spans more stages (with an earlier finding) carries their residuals too.
    chans = [ch for ch in f0.residuals if own is None or ch in own] or list(f0.residuals)
    expected = ex0 = ex1 = 0.0
    for ch in chans:
        e = f0.residuals[ch] / sigma[ch]
        expected += e.size * float(np.clip(noise_sigma(e), *FLOOR_SCALE)) ** 2
        ex0 += float(f0.channel_rss[ch])
        ex1 += float(f1.channel_rss[ch])
    excess = ex0 - expected
    explained = (ex0 - ex1) / excess if excess > 0 else 0.0
    p = float(stats.chi2.sf(max(dchi2, 0.0), max(dk, 1)))
    return {
        "delta_bic": dbic,
        "delta_chi2": dchi2,
        "explained_fraction": explained,
        "lr_p_value": p,
        "score_before": float(np.sqrt(rss0 / n)),
        "score_after": float(np.sqrt(rss1 / n)),
        "n_residuals": float(n),
        "n_effective": float(n_eff),
        "residual_lag1_after": rho,
        "n_params_added": float(dk),
    }


#: Largest lag-1 autocorrelation used for the effective number of residuals.
RHO_MAX = 0.98


def _lag1(f: AugFit, sigma: Mapping[str, np.ndarray]) -> float:
    """Pooled lag-1 autocorrelation of ``f``'s weighted residuals, clipped to
    ``[0, RHO_MAX]``."""
    num = den = 0.0
    for ch, r in f.residuals.items():
        e = r / sigma[ch]
        e = e - np.mean(e)
        num += float(np.dot(e[1:], e[:-1]))
        den += float(np.dot(e, e))
    return float(np.clip(num / den, 0.0, RHO_MAX)) if den > 0 else 0.0


def _prefixed(ev: Mapping[str, float] | None) -> dict[str, float]:
    """The whole chain's evidence, keys prefixed ``chain_``."""
    keys = ("delta_bic", "delta_chi2", "lr_p_value")
    return {f"chain_{k}": ev[k] for k in keys} if ev else {}


def _fitted(f: AugFit, variant: str) -> AbstractMechanism:
    return next(m for m in f.mechanisms if m.variant == variant)


# ----------------------------------------------------------------------------- main


def diagnose(
    trace: Trace,
    *,
    bic_threshold: float = BIC_THRESHOLD,
    max_mechanisms: int = MAX_MECHANISMS,
    catalog: Sequence[str] | None = None,
    progress: Callable[[str], None] | None = None,
) -> DiagnosisResult:
    """Locate, explain and correct the mismatch between the model and one trace.

    Parameters
    ----------
    trace
        One rig trace (needs at least one input-output pair of a stage; the whole chain
        needs ``voltage_V``).
    bic_threshold
        Evidence a mechanism needs: ``dBIC <= -bic_threshold`` (default 10).
    max_mechanisms
        Most catalog mechanisms selected.
    catalog
        Catalog ids to consider (default: all).
    progress
        Called with a short description of each step as it starts (the CLI shows it on
        a terminal); the library itself never prints.

    Returns
    -------
    DiagnosisResult
        Its :meth:`~DiagnosisResult.to_json` is the ``diagnosis.json`` contract.

    Raises
    ------
    DiagnoseError
        The trace lacks the columns any stage needs, or ``catalog`` names unknown ids.

    Notes
    -----
    Each call compiles models for its trace's shape and the mechanisms it tries. A
    process that diagnoses many traces of different shapes should call
    ``jax.clear_caches()`` between them (``studies/diagnosis_accuracy.py`` does): the
    compiled code otherwise accumulates until the kernel's limit on memory maps.
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    pool = variants()
    if catalog is not None:
        known = {m.id for m in pool}
        bad = sorted(set(catalog) - known)
        if bad:
            raise DiagnoseError(f"unknown catalog id(s) {bad}; the catalog is {sorted(known)}")
        pool = [m for m in pool if m.id in set(catalog)]

    ses = _Session(trace)
    say = progress or (lambda text: None)
    say("baseline fits of every stage")
    ses.baseline()
    timings["baseline_stages"] = time.perf_counter() - t_start

    # 2. Locate.
    checks_before = {
        (c.stage, c.channel): c for s in ses.stages for c in ses.check(s, ses.base_fits[s])
    }
    cells = [m for c in checks_before.values() for m in score_check(c, ses.labels, trace.time_s)]
    cells = [_with_summary(m, checks_before, trace, ses.labels) for m in cells]
    flagged_cells = sorted((m for m in cells if m.flagged), key=lambda m: -m.score)
    located = {m.stage for m in flagged_cells}
    timings["locate"] = time.perf_counter() - t_start - sum(timings.values())

    # Chain baseline (from voltage).
    chain_ok = trace.has("voltage_V") and trace.has("theta_deg")
    chain_fits: list[AugFit] = []
    chain_free: tuple[str, ...] = ()
    if chain_ok:
        chain_data, chain_free, chain_sigma, f0 = _chain_baseline(ses, ses.base_messages)
        chain_fits.append(f0)
    timings["baseline_chain"] = time.perf_counter() - t_start - sum(timings.values())

    # 3. Explain: forward selection over the catalog.
    selected: list[AbstractMechanism] = []
    candidates: list[Candidate] = []
    evidence: dict[str, dict[str, float]] = {}
    current = dict(ses.base_fits)  # stage -> latest fit covering it
    still = set(located)
    last_round: list[tuple[Candidate, AugFit, dict[str, float], AbstractMechanism]] = []
    alternatives: dict[str, list[tuple[str, float]]] = {}
    for rnd in range(1, max_mechanisms + 1):
        if not still:
            break
        done = {m.variant for m in selected}
        results = []
        for tmpl in pool:
            if tmpl.variant in done:
                continue
            say(f"round {rnd}: trying {tmpl.variant}")
            mst = ses.mechanism_stages(tmpl)
            if not mst or not set(mst) & still:
                continue
            if tmpl.applicable(ses.cols, ses.ctx):
                continue
            T = _closure(mst, selected, ses)
            ms = [m for m in selected if set(ses.mechanism_stages(m)) & set(T)]
            f0 = ses.fit(T, ms, explore=[False] * len(ms))
            f1 = ses.fit(T, ms + [tmpl], explore=[False] * len(ms) + [True])
            own = [c for st in mst for c in STAGE_OUTPUTS[st]]
            ev = _evidence(f1, f0, ses.sigma_tf, own) | {"converged": float(f1.converged)}
            mech = _fitted(f1, tmpl.variant)
            se = f1.mechanism_stderr(mech)
            reason = mech.plausible(mech.values(), se)
            if not reason and ev["delta_bic"] > -bic_threshold:
                reason = f"dBIC {ev['delta_bic']:.1f} > -{bic_threshold:g}"
            if not reason and ev["explained_fraction"] < MIN_EXPLAINED:
                reason = (
                    f"explains only {100 * ev['explained_fraction']:.0f} % of the excess "
                    "residual at its stages"
                )
            cand = Candidate(
                variant=tmpl.variant,
                effect=tmpl.id,
                stages=T,
                round=rnd,
                delta_bic=ev["delta_bic"],
                delta_chi2=ev["delta_chi2"],
                explained=ev["explained_fraction"],
                p_value=ev["lr_p_value"],
                params=mech.values(),
                stderr=se,
                rejected=reason,
            )
            results.append((cand, f1, ev, mech))
        ok = [r for r in results if not r[0].rejected]
        best = min(ok, key=lambda r: r[0].delta_bic) if ok else None
        last_round = results if best is None else []
        for r in results:
            sel = best is not None and r[0] is best[0]
            candidates.append(Candidate(**{**r[0].__dict__, "selected": sel}) if sel else r[0])
        if best is None:
            break
        cand, f1, ev, mech = best
        selected.append(mech)
        evidence[mech.variant] = ev
        # Rivals the trace cannot tell apart from the choice: also supported, and within
        # the evidence threshold of it (a Bayes factor under about 150).
        alternatives[mech.variant] = [
            (r[0].effect, r[0].delta_bic)
            for r in ok
            if r is not best
            and r[0].effect != cand.effect
            and r[0].delta_bic - cand.delta_bic < bic_threshold
        ]
        for s in f1.stages:
            current[s] = f1
        for n in ses.free_of(f1.stages):
            ses.values[n] = f1.values[n]
        # The next round tries the stages located at first and any located now: a
        # weaker second effect may hide under the first one's residual (the targeted
        # evidence test is more sensitive than the location test).
        still = set(located) | _located(ses, current, structured=True)
    timings["explain"] = time.perf_counter() - t_start - sum(timings.values())

    say("looking for physics outside the catalog")
    # 4. Unknown physics at stages still located.
    corrections: list[tuple[str, AugFit, dict[str, float], Any]] = []
    notes_explain: list[str] = []
    # Only a residual clearly above the noise (not merely serially correlated) calls for
    # physics beyond the catalog once a mechanism has been added: what remains at the
    # noise level then is the approximation of the added physics.
    still = _located(ses, current, structured=not selected) if flagged_cells else set()
    remaining = _ranked_stages(ses, current, still)
    for s in remaining[:MAX_CORRECTIONS]:
        res = _generic(ses, s, selected, current, bic_threshold)
        if res is None:
            continue
        f_gen, ev, sel = res
        # A catalog mechanism that was held back only because it left part of the excess
        # unexplained, but removes as much as the flexible correction does, is the better
        # explanation: the rest is beyond any smooth term (e.g. noise on a measured input
        # bent by a nonlinear stage).
        rivals = [
            r
            for r in last_round
            if r[0].rejected.startswith("explains only")
            and r[1].stages == f_gen.stages
            and r[2]["delta_chi2"] >= CATALOG_SHARE * ev["delta_chi2"]
        ]
        if rivals:
            cand, f1, ev1, mech = min(rivals, key=lambda r: r[0].delta_bic)
            note = (
                f"explains {100 * cand.explained:.0f} % of the excess residual, "
                f"{100 * cand.delta_chi2 / ev['delta_chi2']:.0f} % of what a generic "
                "correction at its stage removes"
            )
            k = next(i for i, c in enumerate(candidates) if c is cand)
            candidates[k] = Candidate(**{**cand.__dict__, "selected": True, "rejected": ""})
            # One rival per stage set: a second located stage with the same stages must
            # not promote it again (it once did, and the candidate was no longer in the
            # list by identity) nor add another rival for the mismatch it explains.
            last_round = [r for r in last_round if r[1].stages != f1.stages]
            selected.append(mech)
            evidence[mech.variant] = ev1 | {"generic_delta_chi2": ev["delta_chi2"]}
            notes_explain.append(f"{mech.variant}: {note}")
            for st in f1.stages:
                current[st] = f1
            continue
        corrections.append((s, f_gen, ev, sel))
        for st in f_gen.stages:
            current[st] = f_gen
    timings["unknown"] = time.perf_counter() - t_start - sum(timings.values())

    say("confirming the findings on the whole chain")
    # 5. The whole chain with the findings added one at a time. The chain runs from the
    # logged voltage, which carries no sensor noise into the model: a finding must also
    # improve it (dBIC <= -threshold). That guards against explaining artefacts of a
    # teacher-forced stage (noise on its measured input bends a nonlinear stage's
    # output, a bias no mechanism should take the blame for).
    added: list[AbstractMechanism] = list(selected) + [
        _fitted(f, f"unexplained_{s}") for s, f, _, _ in corrections
    ]
    chain_ev: dict[str, dict[str, float]] = {}
    unconfirmed: list[tuple[AbstractMechanism, dict[str, float]]] = []
    if chain_ok:
        kept: list[AbstractMechanism] = []
        for m in added:
            prev = chain_fits[-1]
            mechs = [_mechanism_start(x, prev) for x in [*kept, m]]
            f = fit_mechanisms(
                chain_data,
                ("chain",),
                chain_free,
                mechs,
                tuple(chain_sigma),
                start={n: prev.values[n] for n in chain_free},
                explore=[False] * len(mechs),
                # ... and from the teacher-forced fits with the mechanisms
                alt_starts=[{n: ses.values[n] for n in chain_free if n in ses.values}],
            )
            ev = _evidence(f, prev, chain_sigma)
            if ev["delta_bic"] <= -bic_threshold:
                kept.append(m)
                chain_fits.append(f)
                chain_ev[m.variant] = ev
            else:
                unconfirmed.append((m, ev))
        added = kept
    timings["chain"] = time.perf_counter() - t_start - sum(timings.values())

    # Results.
    checks_after = {(c.stage, c.channel): c for s in ses.stages for c in ses.check(s, current[s])}

    stage_before = {
        s: {
            ch: channel_metrics(c.predicted, c.measured)
            for (st, ch), c in checks_before.items()
            if st == s
        }
        for s in ses.stages
    }
    stage_after = {
        s: {
            ch: channel_metrics(c.predicted, c.measured)
            for (st, ch), c in checks_after.items()
            if st == s
        }
        for s in ses.stages
    }
    findings: list[Finding] = []
    by_variant = {f"unexplained_{s}": (s, f, ev, sel) for s, f, ev, sel in corrections}
    for k, mech in enumerate(added):
        before = (
            _chain_metrics(trace, chain_fits[k]) if chain_ok else stage_before.get(mech.stage, {})
        )
        after = (
            _chain_metrics(trace, chain_fits[k + 1])
            if chain_ok
            else stage_after.get(mech.stage, {})
        )
        if isinstance(mech, GenericCorrection):
            s, f_gen, ev, sel = by_variant[mech.variant]
            ev = ev | _prefixed(chain_ev.get(mech.variant))
            findings.append(
                _generic_finding(ses, mech, f_gen, ev, sel, flagged_cells, before, after)
            )
        else:
            fit_m = current[mech.stage] if mech.stage in current else None
            se = _stderr_of(mech, fit_m, ses)
            ev = evidence[mech.variant] | _prefixed(chain_ev.get(mech.variant))
            alts = tuple(alternatives.get(mech.variant, ()))
            ctx = _refitted_ctx(ses, fit_m)
            findings.append(_finding(ses, mech, se, ev, flagged_cells, before, after, alts, ctx))

    notes = list(ses.base_messages) + notes_explain
    for m, ev in unconfirmed:
        notes.append(
            f"{m.variant} improved the {m.stage} stage fitted from its measured input, but "
            f"not the whole chain from the voltage (dBIC {ev['delta_bic']:.1f} > "
            f"-{bic_threshold:g}): not reported, as the mismatch it absorbed is within what "
            "noise on the stage's measured input produces"
        )
    if not flagged_cells:
        verdict = "none"
    elif any(f.catalog for f in findings):
        verdict = "found"
    else:  # located, not explained by the catalog: never "none"
        verdict = "unexplained"
    if flagged_cells and not findings:  # say where, when not even a correction helps
        notes.append(
            "a mismatch is located ("
            + ", ".join(f"{m.stage} stage, {m.phase}: {m.score:.1f}x" for m in flagged_cells[:3])
            + " the noise), but neither a catalog mechanism nor a generic correction "
            "explains it beyond the noise in the whole chain: unexplained"
        )
    timings["total"] = time.perf_counter() - t_start
    base_metrics = _chain_metrics(trace, chain_fits[0]) if chain_ok else {}
    aug_metrics = _chain_metrics(trace, chain_fits[-1]) if chain_ok else {}
    return DiagnosisResult(
        trace_name=trace.name,
        verdict=verdict,
        mismatches=tuple(flagged_cells),
        cells=tuple(cells),
        findings=tuple(findings),
        candidates=tuple(candidates),
        baseline_metrics=base_metrics,
        augmented_metrics=aug_metrics,
        stage_metrics_before=stage_before,
        stage_metrics_after=stage_after,
        noise=dict(ses.noise),
        checks_before=checks_before,
        checks_after=checks_after,
        chain_before=dict(chain_fits[0].predictions) if chain_ok else {},
        chain_after=dict(chain_fits[-1].predictions) if chain_ok else {},
        labels=ses.labels,
        trace=trace,
        timings=timings,
        notes=tuple(notes),
        corrected=_corrected_of(trace, chain_fits, chain_data, chain_sigma)
        if chain_ok and len(chain_fits) > 1
        else None,
        **_model_tables(chain_fits, chain_ok),
    )


def _corrected_of(trace: Trace, chain_fits, data, sigma) -> CorrectedFit | None:
    """The diagnosis's corrected whole chain as a :class:`CorrectedFit` (catalog
    mechanisms only: a generic correction has no physical parameters to sample)."""
    catalog = {m.variant for m in variants()}
    f0, f1 = chain_fits[0], chain_fits[-1]
    if not f1.mechanisms or any(m.variant not in catalog for m in f1.mechanisms):
        return None
    notes = () if f1.converged else ("the corrected whole-chain fit did not converge",)
    return _corrected_record(trace, f0, f1, data, _evidence(f1, f0, sigma), notes)


def _corrected_record(trace: Trace, f0, f1, data, ev, notes) -> CorrectedFit:
    """A :class:`CorrectedFit` from the baseline ``f0`` and corrected ``f1`` chain fits."""
    tables = _model_tables([f0, f1], True)
    return CorrectedFit(
        trace_name=trace.name,
        mechanisms=tuple(m.variant for m in f1.mechanisms),
        params=tables["augmented_params"],
        stderr=tables["augmented_stderr"],
        metrics=_chain_metrics(trace, f1),
        baseline_params=tables["baseline_params"],
        baseline_stderr=tables["baseline_stderr"],
        baseline_metrics=_chain_metrics(trace, f0),
        converged=bool(f1.converged),
        delta_bic=float(ev["delta_bic"]),
        warnings=tuple(notes),
        predictions={k: np.asarray(v) for k, v in f1.predictions.items()},
        fit=f1,
        data=data,
    )


def _model_tables(chain_fits: Sequence[AugFit], ok: bool) -> dict[str, dict]:
    """Parameter values and standard errors of the baseline and the corrected chain."""
    if not ok or not chain_fits:
        return {}

    def table(f: AugFit) -> tuple[dict[str, float], dict[str, float | None]]:
        values = {k: float(v) for k, v in f.values.items()}
        for m in f.mechanisms:
            values |= {f"{m.variant}.{k}": float(v) for k, v in m.values().items()}
        stderr = {k: f.stderr.get(k) for k in values}
        return values, stderr

    bp, bs = table(chain_fits[0])
    ap, as_ = table(chain_fits[-1])
    return {
        "baseline_params": bp,
        "baseline_stderr": bs,
        "augmented_params": ap,
        "augmented_stderr": as_,
    }


# ----------------------------------------------------------------------------- helpers


def _closure(stages, selected, ses) -> tuple[str, ...]:
    """``stages`` plus those of every selected mechanism that shares one with them."""
    T = set(stages)
    grew = True
    while grew:
        grew = False
        for m in selected:
            ms = set(ses.mechanism_stages(m))
            if ms & T and not ms <= T:
                T |= ms
                grew = True
    return _order(T)


def _located(ses: _Session, current, *, structured: bool) -> set[str]:
    """Stages whose current fit still shows a mismatch."""
    out = set()
    for s in ses.stages:
        for c in ses.check(s, current[s]):
            cells = score_check(c, ses.labels, ses.trace.time_s, structured=structured)
            if any(m.flagged for m in cells):
                out.add(s)
    return out


def _ranked_stages(ses: _Session, current, still) -> list[str]:
    excess = {}
    for s in still:
        excess[s] = sum(stage_excess(c) for c in ses.check(s, current[s]))
    return sorted(excess, key=lambda s: -excess[s])


def _mechanism_start(m: AbstractMechanism, prev: AugFit) -> AbstractMechanism:
    for pm in prev.mechanisms:
        if pm.variant == m.variant:
            return pm
    return m


def _stderr_of(mech: AbstractMechanism, f: AugFit | None, ses: _Session):
    for fit_ in [f, *ses.cache.values()]:
        if fit_ is None:
            continue
        for m in fit_.mechanisms:
            if m.variant == mech.variant and np.allclose(
                list(m.values().values()), list(mech.values().values())
            ):
                return fit_.mechanism_stderr(m)
    return {i.name: None for i in mech.param_info()}


def _with_summary(m: Mismatch, checks, trace, labels) -> Mismatch:
    if not m.flagged:
        return m
    c = checks[(m.stage, m.channel)]
    sig = signature(c, trace, labels)
    notes = describe_signature(c, sig, m.phase)
    return Mismatch(**{**m.__dict__, "summary": summary_text(m, notes), "signature": sig})


def _phases_of(stage: str, flagged: Sequence[Mismatch], stages: Sequence[str]) -> tuple[str, ...]:
    ph = {m.phase for m in flagged if m.stage in stages}
    return tuple(p for p in PHASES if p in ph)


def _and(items: Sequence[str]) -> str:
    items = list(items)
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _metric_words(ch: str, before, after) -> str:
    b = before.get(ch, {}).get("nrmse_pct")
    a = after.get(ch, {}).get("nrmse_pct")
    if b is None or a is None:
        return ""
    name = ch.split("_")[0]
    return f"{name} NRMSE {b:.2f} % → {a:.2f} %"


def _refitted_ctx(ses, fit_m: AugFit | None) -> dict[str, Any]:
    """The session's facts, with the motor's stall torque from the fit that holds the
    finding (the baseline motor may have bent to absorb the missing physics)."""
    ctx = dict(ses.ctx)
    if fit_m is None or not ses.trace.has("voltage_V"):
        return ctx
    kT, R = fit_m.values.get("kT", 0.0), fit_m.values.get("R", 0.0)
    if R > 0 and "R" in fit_m.stderr:
        ctx["stall_torque_Nm"] = _stall_torque(ses.trace, kT, R)
    return ctx


def _stall_torque(trace: Trace, kT: float, R: float) -> float:
    """The motor's stall torque at the trace's largest voltage, N*m."""
    return kT * float(np.max(np.abs(trace["voltage_V"]))) / R


def _finding(ses, mech, se, ev, flagged, before, after, alternatives=(), ctx=None) -> Finding:
    ctx = ses.ctx if ctx is None else ctx
    vals = mech.values()
    stages = ses.mechanism_stages(mech)
    phases = _phases_of(mech.stage, flagged, stages)
    where = f"{mech.stage} stage" + (f", {_and(phases)}" if phases else "")
    ch = mech.channels[0] if mech.hook == "sensor" else MAIN_CHANNEL[mech.stage]
    words = _metric_words(ch, before, after)
    text = (
        f"{mech.observation(vals, ctx)} ({where}): {mech.describe(vals, se, ctx)}"
        + (f"; {words}" if words else "")
        + f", ΔBIC {ev['delta_bic']:.0f}"
    )
    if alternatives:
        rivals = _and([f"{e} (ΔBIC {d:.0f})" for e, d in alternatives])
        text += f". But {rivals} explains it about as well: this trace cannot tell them apart"
        hints = [SEPARATE[frozenset((mech.id, e))] for e, _ in alternatives]
        text += "".join(f"; {h}" for h in hints if h)
    return Finding(
        effect=mech.id,
        variant=mech.variant,
        stage=mech.stage,
        explanation=text,
        params=vals,
        stderr=se,
        units={i.name: i.unit for i in mech.param_info()},
        evidence=ev,
        metrics_before=before,
        metrics_after=after,
        phases=phases,
        alternatives=tuple(alternatives),
    )


def _generic(ses: _Session, stage: str, selected, current, threshold):
    """Fit the sparse generic correction at ``stage``; ``None`` when no term helps."""
    sig = signals(ses.trace)
    feats = available_features(stage, sig)
    if not feats:
        return None
    T = _closure((stage,), selected, ses)
    ms = [m for m in selected if set(ses.mechanism_stages(m)) & set(T)]
    f_cur = ses.fit(T, ms, explore=[False] * len(ms))
    full = GenericCorrection(stage_name=stage, features=feats)
    mechs = [*f_cur.mechanisms, full]
    problem = AugProblem(
        stages=T,
        free=ses.free_of(T),
        specs=tuple((type(m), m.static_config()) for m in mechs),
        channels=ses.channels_of(T),
        n_sub=n_substeps(float(ses.data["dt"]), mechs),
    )
    u = [float(PARAMS[n].to_unconstrained(f_cur.values[n])) for n in problem.free]
    for m in mechs:
        vals = m.values()
        u += [clipped_to_u(i, vals[i.name]) for i in m.param_info()]
    u = jnp.asarray(np.asarray(u))
    r = np.asarray(residuals(problem, u, ses.data))
    J = np.asarray(jacobian(problem, u, ses.data))
    m_terms = len(feats)
    sel = forward_select(r, J[:, :-m_terms], J[:, -m_terms:], feats, threshold=threshold)
    if not sel.features:
        return None
    gc = GenericCorrection(stage_name=stage, features=sel.features)
    f_gen = ses.fit(T, [*f_cur.mechanisms, gc], explore=[False] * (len(ms) + 1))
    ev = _evidence(f_gen, f_cur, ses.sigma_tf)
    if ev["delta_bic"] > -threshold:
        return None
    return f_gen, ev, sel


def _generic_finding(ses, mech, f_gen, ev, sel, flagged, before, after) -> Finding:
    stage = mech.stage
    se = f_gen.mechanism_stderr(mech)
    vals = mech.values()
    words = FEATURES[stage]
    deps = []
    for f in mech.features:
        w = words[f]
        if w not in deps:
            deps.append(w)
    phases = _phases_of(stage, flagged, (stage,))
    where = f"{stage} stage" + (f", {_and(phases)}" if phases else "")
    ch = MAIN_CHANNEL[stage]
    mw = _metric_words(ch, before, after)
    terms = ", ".join(
        f"{f} {fmt_pm(vals[f'c_{f}'], se.get(f'c_{f}'))} {i.unit}"
        for f, i in zip(mech.features, mech.param_info(), strict=True)
    )
    kind = "load torque" if stage == "motor" else f"correction of {ch}"
    text = (
        f"the {STAGE_WORDS[stage]} misses something no catalog mechanism explains ({where}); "
        f"a generic {kind} depending on {'; '.join(deps)} improves the fit ({terms})"
        + (f"; {mw}" if mw else "")
        + f", ΔBIC {ev['delta_bic']:.0f}. Physics not in the catalog: inspect before "
        "modelling it."
    )
    return Finding(
        effect=f"unexplained_{stage}",
        variant=mech.variant,
        stage=stage,
        explanation=text,
        params=vals,
        stderr=se,
        units={i.name: i.unit for i in mech.param_info()},
        evidence=ev,
        metrics_before=before,
        metrics_after=after,
        phases=phases,
        depends_on=tuple(mech.features),
        catalog=False,
    )


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
        errors (``None`` where not identified).
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

    def to_json(self) -> dict[str, Any]:
        """A ``fit.json`` document (contract keys) for the corrected model."""
        return {
            "params": self.params,
            "stderr": self.stderr,
            "metrics": _metrics_json(self.metrics),
            "converged": self.converged,
            "stage": "chain",
            "mechanisms": list(self.mechanisms),
            "baseline": {
                "params": self.baseline_params,
                "stderr": self.baseline_stderr,
                "metrics": _metrics_json(self.baseline_metrics),
            },
            "evidence": {"delta_bic": self.delta_bic},
            "warnings": list(self.warnings),
        }


def mechanism_templates(names: Sequence[str]) -> list[AbstractMechanism]:
    """Mechanism instances for catalog ids or variants (``sensor_delay[force_N]``).

    Raises
    ------
    DiagnoseError
        An unknown name, or a sensor mechanism without its channel.
    """
    pool = {m.variant: m for m in variants()}
    out = []
    for name in names:
        name = name.strip()
        if name in pool:
            out.append(pool[name])
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
    ses = _Session(trace)
    ses.baseline()
    notes = list(ses.base_messages)
    for m in templates:
        if not ses.mechanism_stages(m):
            raise DiagnoseError(
                f"--with {m.variant}: its stages ({', '.join(m.stages)}) cannot be fitted "
                f"from the channels of {trace.label}"
            )
        reason = m.applicable(ses.cols, ses.ctx)
        if reason:
            raise DiagnoseError(f"--with {m.variant}: {reason}")
    stages = _order({s for m in templates for s in ses.mechanism_stages(m)})
    f_tf = ses.fit(stages, templates)
    tf = list(f_tf.mechanisms)
    data, chain_free, sigma, f0 = _chain_baseline(ses, notes)
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
    ev = _evidence(f1, f0, sigma)
    if not f1.converged:
        notes.append("the corrected whole-chain fit did not converge")
    if ev["delta_bic"] > -BIC_THRESHOLD:
        notes.append(
            f"the mechanisms do not improve the whole chain (dBIC {ev['delta_bic']:.1f} > "
            f"-{BIC_THRESHOLD:g}): this trace gives no evidence for them"
        )
    return _corrected_record(trace, f0, f1, data, ev, notes)
