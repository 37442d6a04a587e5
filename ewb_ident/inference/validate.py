"""Validation on another trace: simulate fitted parameters where they were not fitted.

The first thing a system-identification user does with a model is run it on a recording
it has not seen (MATLAB's ``compare``). :func:`validate` simulates the whole chain from
the new trace's voltage with the parameters of an earlier fit (``fit.json``), and scores
every recorded channel:

* against the seed paper's acceptance: force and torque percent error within 10 %;
* against the trace's own noise floor: the residual RMS of each channel over its sensor
  noise (estimated from the data, :func:`ewb_ident.data.metrics.noise_sigma`). Within
  :data:`NOISE_RATIO` the model explains the recording down to its noise.

Only the start angle is taken from the new trace (the pinion rests where the recording
starts); every other parameter comes from the fit, and the pad radius from the new
trace (its sidecar, or the stated default).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ewb_ident.data.metrics import SEED_ACCEPTANCE_PCT, channel_metrics, sensor_noise
from ewb_ident.data.stages import CHANNELS
from ewb_ident.data.trace import InputError, Trace, TraceError
from ewb_ident.data.validation import check_trace
from ewb_ident.model.numerics import numerics
from ewb_ident.model.params import MODEL_PARAMS, PARAMS, EWBParams
from ewb_ident.model.predict import simulate_chain

#: Residual RMS up to this many times the sensor noise counts as "at the noise floor".
NOISE_RATIO = 1.5


class ValidateError(InputError):
    """Parameters that cannot be validated (unreadable or incomplete ``fit.json``)."""


def load_document(path: str | Path) -> dict[str, Any]:
    """A ``fit.json`` document.

    Raises
    ------
    ValidateError
        Unreadable file, or not a JSON object.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValidateError(f"{path}: cannot read it as fit.json ({err}); give a fit.json") from err
    if not isinstance(doc, dict):
        raise ValidateError(f"{path}: not a JSON object; give the fit.json that `fit` wrote")
    return doc


def load_params(path: str | Path) -> EWBParams:
    """The model parameters of a ``fit.json`` (``params``; per-trace values averaged).

    Raises
    ------
    ValidateError
        Unreadable file, or a parameter missing, not a finite number or outside its
        bounds (:data:`~ewb_ident.model.params.PARAMS`): the one rule for every
        parameters file (``validate --params``, ``simulate --params``).
    """
    path = Path(path)
    doc = load_document(path)
    params = doc.get("params")
    if not isinstance(params, dict):
        raise ValidateError(f"{path}: no 'params' object; give the fit.json that `fit` wrote")
    return checked_params(params, str(path), "give a complete fit.json")


def checked_params(params: Mapping[str, Any], where: str, fix: str) -> EWBParams:
    """Model parameters from ``params``: each of :data:`MODEL_PARAMS` a finite number
    inside its bounds (:data:`~ewb_ident.model.params.PARAMS`), the one rule for every
    parameters file and the Python API's ``validate``.

    Raises
    ------
    ValidateError
        Naming ``where``, the parameter and its value.
    """
    values = {}
    for name in MODEL_PARAMS:
        v = params.get(name)
        if not isinstance(v, int | float) or isinstance(v, bool) or not np.isfinite(v):
            raise ValidateError(f"{where}: params.{name} is {v!r}, not a finite number; {fix}")
        info = PARAMS[name]
        if info.transform != "affine" and not info.inside(float(v)):
            raise ValidateError(
                f"{where}: params.{name} is {v!r}, outside its bounds ({info.lower:g} < {name}"
                f" < {info.upper:g} {info.unit}); give the parameters of a fit that converged"
            )
        values[name] = float(v)
    return EWBParams(**values)


# A frozen record of its fields, like the package's other results: alike in shape only.
@dataclass(frozen=True)
class ValidationResult:
    """Scores of fitted parameters on a trace they were not fitted to.

    Attributes
    ----------
    trace_name
        The validation trace.
    metrics
        Per recorded channel: ``rmse`` (channel unit), ``nrmse_pct``, ``percent_error``,
        ``noise_sigma`` (sensor noise, channel unit) and ``noise_ratio`` (RMSE over it).
    passes_seed
        Force and torque percent errors within the seed's 10 % (where recorded).
    at_noise_floor
        Every channel's ``noise_ratio`` within :data:`NOISE_RATIO`.
    verdict
        ``"at_noise_floor"``, ``"passes_seed_acceptance"`` or ``"mismatch"``.
    words
        The verdict in a sentence, naming the worst channel.
    """

    trace_name: str
    params: EWBParams
    theta0_deg: float
    r_eff_m: float
    metrics: dict[str, dict[str, float | None]]
    passes_seed: bool
    at_noise_floor: bool
    verdict: str
    words: str
    simulated: dict[str, np.ndarray] = field(repr=False)
    #: The corrected model's mechanisms and learned terms (empty: the seed chain).
    mechanisms: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        """The ``validate.json`` document."""
        # The document's keys spelled out, each from its attribute: alike in shape to the
        # other to_json documents, each the contract of its own.
        return {
            "trace": self.trace_name,
            "verdict": self.verdict,
            "summary": self.words,
            "passes_seed_acceptance": self.passes_seed,
            "at_noise_floor": self.at_noise_floor,
            "metrics": self.metrics,
            "params": self.params.as_dict(),
            "mechanisms": list(self.mechanisms),
            "theta0_deg": self.theta0_deg,
            "r_eff_m": self.r_eff_m,
            "thresholds": {
                "seed_percent_error": SEED_ACCEPTANCE_PCT,
                "noise_ratio": NOISE_RATIO,
            },
        }


@numerics
def validate(
    trace: Trace, params: EWBParams | Mapping[str, float], model: Any = None
) -> ValidationResult:
    """Simulate ``params`` on ``trace`` from its voltage and score every recorded channel.

    Parameters
    ----------
    trace
        A trace with ``voltage_V`` and ``theta_deg`` (the start angle) and any outputs.
    params
        Model parameters (SI), e.g. from :func:`load_params`.
    model
        A corrected model (:class:`ewb_ident.diagnosis.corrected.CorrectedModel`: the
        mechanisms and learned terms of a ``fit --with``/``--with-diagnosis`` fit),
        simulated instead of the seed chain; ``None``: the seed chain.
    """
    trace = check_trace(trace)
    if isinstance(params, Mapping):
        params = checked_params(params, "params", "give every model parameter as a number")
    for col in ("voltage_V", "theta_deg"):
        if not trace.has(col):
            raise TraceError(
                f"{trace.label}: column '{col}', row -: validation simulates from the voltage "
                "and starts at the recorded angle; record this channel"
            )
    theta0 = float(np.median(trace["theta_deg"][:5]))
    if model is None:
        sim = simulate_chain(params, trace["voltage_V"], trace.dt, theta0, trace.r_eff_m)
    else:
        sim = model.simulate(trace, params.as_dict() | {"theta0_deg": theta0})
    sim = {k: np.asarray(v) for k, v in sim.items()}
    metrics: dict[str, dict[str, float | None]] = {}
    for ch in CHANNELS:
        if not trace.has(ch):
            continue
        m = channel_metrics(sim[ch], trace[ch])
        sd = sensor_noise(trace[ch])
        ratio = None if m["rmse"] is None else m["rmse"] / sd
        metrics[ch] = m | {"noise_sigma": sd, "noise_ratio": ratio}
    finite = all(m["rmse"] is not None for m in metrics.values())
    pes = [
        metrics[ch]["percent_error"]
        for ch in ("force_N", "torque_Nm")
        if ch in metrics and metrics[ch]["percent_error"] is not None
    ]
    passes = finite and all(pe <= SEED_ACCEPTANCE_PCT for pe in pes)
    at_floor = finite and all(m["noise_ratio"] <= NOISE_RATIO for m in metrics.values())
    worst = max(metrics, key=lambda ch: metrics[ch]["noise_ratio"]) if metrics and finite else None
    if not finite:
        verdict, words = "mismatch", "the simulation diverged on this trace"
    elif at_floor:
        verdict = "at_noise_floor"
        words = (
            f"the fitted model reproduces {trace.name} to its sensor noise (every channel "
            f"within {NOISE_RATIO:g}x)"
        )
    else:
        m = metrics[worst]
        verdict = "passes_seed_acceptance" if passes else "mismatch"
        words = (
            f"{worst} misses by {m['noise_ratio']:.1f}x its sensor noise (RMSE {m['rmse']:.3g}"
            + (f", NRMSE {m['nrmse_pct']:.2f} %)" if m["nrmse_pct"] is not None else ")")
            + (
                "; force and torque still within the seed's 10 % acceptance"
                if passes
                else "; outside the seed's 10 % acceptance"
            )
            + ": this trace differs from the one the model was fitted to (another unit, "
            "a hardware change, or physics the model leaves out)"
        )
    # One keyword per field: alike in shape to other constructors' calls (problem.Setup).
    return ValidationResult(
        trace_name=trace.name,
        params=params,
        theta0_deg=theta0,
        r_eff_m=float(trace.r_eff_m),
        metrics=metrics,
        passes_seed=passes,
        at_noise_floor=at_floor,
        verdict=verdict,
        words=words,
        simulated=sim,
        mechanisms=() if model is None else tuple(model.names),
    )
