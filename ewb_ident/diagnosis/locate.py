"""Locating a mismatch between model and recording: where, when, and what it looks like.

Every link of the chain is checked teacher-forced from its measured input (motor:
voltage -> angle and current; gap: angle -> displacement; force: displacement -> force;
torque: force -> torque), and the whole chain from the voltage. Each residual
(measured minus model) is compared with its *noise floor*: the sensor noise of the
output channel, estimated from the data (second differences, see
:func:`ewb_ident.data.metrics.noise_sigma`), plus, for a teacher-forced stage, the input
channel's sensor noise carried through the stage (``|df/din| sigma_in``). Residuals are
split by the phase of the brake application (:func:`phase_labels`).

Score and test
--------------
For each stage, channel and phase the score is the residual RMS over the noise floor,
``S = sqrt(mean((r / sigma)^2))``: about 1 when the model fits to the noise. The floor
``sigma`` is rescaled, per stage, by the white-noise level of the residual itself
(:func:`floor_scale`: second differences cancel a smooth model error), so that a noise
estimate of the raw channel that is off by some per cent (signal curvature at low
sample rates, quantisation) neither hides nor invents a mismatch; a phase of at least
:data:`PHASE_SCALE_MIN_SAMPLES` samples has a floor at least its own residual's white
level (:func:`phase_floor_scale`). A phase is flagged as a mismatch when

- ``S >= SCORE_MIN`` (the residual is clearly larger than the noise: the floor itself
  is estimated to a few per cent), and ``z = (sum (r/sigma)^2 - n) / sqrt(2 n_eff)`` is
  at least ``Z_MIN`` (chi-square excess; ``n_eff`` discounts the serial correlation of
  the residual), or
- the residual has structure: its lag-1 autocorrelation ``rho`` is significant,
  ``rho sqrt(n) >= Z_MIN``, with ``S >= SCORE_STRUCTURED`` (white noise has ``rho ~ 0``
  whatever its level).

Signatures (:func:`signature`) describe the residual of a stage for the explanation:
dependence on the direction of motion, on speed (a lag, by regression on the rate of
the model's output), on force level, on elapsed time, on disc speed, an offset while the
pads are open, and periodic content at the disc rotation frequency.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ewb_ident.data.metrics import noise_sigma, quantisation_step, rounding_error, smooth
from ewb_ident.data.stages import STAGE_WORDS
from ewb_ident.data.trace import Trace

PHASES: tuple[str, ...] = ("gapping", "clamping", "saturation", "release")

#: Smallest residual RMS over the noise floor that is flagged (with a significant z).
SCORE_MIN = 1.25
#: Smallest score of a flagged *structured* (serially correlated) residual.
SCORE_STRUCTURED = 1.1
#: Significance (in standard deviations) of a flagged mismatch.
Z_MIN = 5.0
#: Fewest samples of a phase that is scored.
MIN_SAMPLES = 12

UNITS: dict[str, str] = {
    "theta_deg": "deg",
    "x_m": "m",
    "force_N": "N",
    "torque_Nm": "N*m",
    "current_A": "A",
}


# ----------------------------------------------------------------------------- phases


def motion_rate(trace: Trace) -> np.ndarray:
    """Smoothed rate of the piston displacement (or of the pinion angle without it),
    in the channel's unit per second."""
    ch = "x_m" if trace.has("x_m") else "theta_deg"
    width = max(3, round(0.02 / trace.dt))
    return np.gradient(smooth(trace[ch], width), trace.dt)


def phase_labels(trace: Trace) -> np.ndarray:
    """Phase of the brake application at each sample (strings of :data:`PHASES`).

    ``gapping``: the pads are open (no clamping force above its open-pad level);
    ``clamping``: in contact and applying; ``release``: in contact and retracting;
    ``saturation``: in contact and holding still. Contact is a smoothed force more than
    ``max(3 % of its range, 5 sigma)`` above its open-pad level; motion is a smoothed
    displacement (or angle) rate beyond 3 % of its largest magnitude.
    """
    n = trace.n
    v = motion_rate(trace)
    v_thr = 0.03 * float(np.max(np.abs(v))) if np.any(v) else 0.0
    if trace.has("force_N"):
        width = max(3, round(0.02 / trace.dt))
        F = smooth(trace["force_N"], width)
        lo = float(np.percentile(F, 2))
        thr = max(0.03 * (float(np.max(F)) - lo), 5.0 * noise_sigma(trace["force_N"]))
        contact = F - lo > thr
    else:
        contact = np.zeros(n, bool)
    labels = np.full(n, "saturation", dtype=object)
    labels[contact & (v > v_thr)] = "clamping"
    labels[contact & (v < -v_thr)] = "release"
    labels[~contact] = "gapping"
    return labels.astype(str)


# ----------------------------------------------------------------------------- checks


@dataclass(frozen=True)
class StageCheck:
    """The residual of one channel of one stage (or the chain) against its noise floor.

    Attributes
    ----------
    stage, channel
        Where (``chain`` for the whole chain) and which output channel.
    measured, predicted
        The recorded channel and the model's prediction, in the channel's unit.
    sigma
        Noise floor per sample (sensor noise, plus carried input noise), same unit.
    rounded
        The output, or the stage's measured input, is recorded on a grid coarse against
        its noise (:func:`coarsely_rounded`): its rounding error is serially correlated
        wherever the signal moves by less than a step per sample, so serial correlation
        alone is no evidence of missing physics in this check.
    """

    stage: str
    channel: str
    measured: np.ndarray
    predicted: np.ndarray
    sigma: np.ndarray
    rounded: bool = False

    @property
    def residual(self) -> np.ndarray:
        """Measured minus model, in the channel's unit."""
        return self.measured - self.predicted

    @property
    def normalized(self) -> np.ndarray:
        """Residual over the noise floor."""
        return self.residual / self.sigma

    @functools.cached_property
    def step(self) -> float:
        """The measured channel's grid step (0 when not on a grid), its unit: its
        rounding error is ``step / sqrt(12)``."""
        return quantisation_step(self.measured)


@dataclass(frozen=True)
class Mismatch:
    """One scored (stage, channel, phase) cell.

    Attributes
    ----------
    score
        Residual RMS over the noise floor (1 when the model fits to the noise).
    z
        Significance of the excess over the noise, in standard deviations.
    rho
        Lag-1 autocorrelation of the normalised residual (0 for white noise).
    flagged
        Whether the cell is a mismatch (see module docstring).
    """

    stage: str
    channel: str
    phase: str
    t_start_s: float
    t_end_s: float
    n: int
    score: float
    z: float
    rho: float
    rms: float
    noise: float
    mean: float
    flagged: bool
    summary: str = ""
    signature: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The contract's mismatch entry (plus the test statistics)."""
        # The document's keys spelled out, each from its attribute: alike in shape to the
        # other to_json documents, each the contract of its own.
        return {
            "stage": self.stage,
            "phase": self.phase,
            "channel": self.channel,
            "t_start_s": self.t_start_s,
            "t_end_s": self.t_end_s,
            "score": self.score,
            "summary": self.summary,
            "z": self.z,
            "lag1_autocorrelation": self.rho,
            "residual_rms": self.rms,
            "noise_floor": self.noise,
            "residual_mean": self.mean,
            "n_samples": self.n,
        }


def _lag1(e: np.ndarray, idx: np.ndarray) -> float:
    """Lag-1 autocorrelation over consecutive sample pairs within ``idx``."""
    if idx.size < 3:
        return 0.0
    pairs = idx[:-1][np.diff(idx) == 1]
    if pairs.size < 2:
        return 0.0
    a, b = e[pairs], e[pairs + 1]
    den = float(np.sqrt(np.sum(a * a) * np.sum(b * b)))
    return float(np.sum(a * b) / den) if den > 0 else 0.0


def _worst_run(mask: np.ndarray, excess: np.ndarray) -> tuple[int, int]:
    """First and last index of the contiguous run of ``mask`` with the largest excess."""
    best, best_val, start = (0, 0), -np.inf, None
    for k in range(mask.size + 1):
        inside = k < mask.size and mask[k]
        if inside and start is None:
            start = k
        elif not inside and start is not None:
            val = float(np.sum(excess[start:k]))
            if val > best_val:
                best, best_val = (start, k - 1), val
            start = None
    return best


#: Bounds of the data-driven rescaling of a stage's noise floor.
FLOOR_SCALE = (0.5, 2.0)


def floor_scale(check: StageCheck) -> float:
    """How much the residual's own white-noise level differs from the modelled floor.

    The second differences of the residual over the floor (robust scale, see
    :func:`ewb_ident.data.metrics.noise_sigma`) cancel any smooth model error and keep the
    white noise, sensor and carried input noise alike; clipped to :data:`FLOOR_SCALE`.
    A quantised channel's level is at least its rounding error (:func:`white_level`).
    """
    return float(np.clip(white_level(check), *FLOOR_SCALE))


def coarsely_rounded(y: np.ndarray, residual: np.ndarray | None = None) -> bool:
    """Whether a channel's rounding error (:func:`ewb_ident.data.metrics.rounding_error`)
    is at least half of its noise (:func:`ewb_ident.data.metrics.noise_sigma`): of
    ``residual``, the channel less a model of it, when given (at a low sample rate the
    channel's own motion inflates its second differences: a clean 12-bit angle at 100 Hz
    read 4x its true noise and was not taken as rounded), else of the channel."""
    e = rounding_error(y)
    return e > 0 and e >= 0.5 * noise_sigma(y if residual is None else residual)


def white_level(check: StageCheck, idx: np.ndarray | None = None) -> float:
    """The white-noise level of the normalised residual (over samples ``idx``, default
    all), at least the measured channel's rounding error over the floor.

    A channel recorded on a coarse grid (a 12-bit angle) has mostly zero second
    differences, so the robust scale of its residual says "no noise" and would halve its
    floor; its residual holds at least the rounding error ``q / sqrt(12)`` of its step
    ``q`` (:func:`ewb_ident.data.metrics.quantisation_step`). (Found on a clean 1 kHz trace
    of the third rig with a quantised angle, reported ``unexplained`` at the motor stage
    with 2.2x the halved floor.) The residual is near a grid of that step over the floor,
    so its scale is taken as on a grid (:func:`ewb_ident.data.metrics.noise_sigma`).
    """
    r = check.normalized if idx is None else check.normalized[idx]
    s = check.sigma if idx is None else check.sigma[idx]
    return noise_sigma(r, step=check.step / float(np.median(s)))


#: Fewest samples of a phase whose own white-noise level may raise its floor (the robust
#: scale of n samples is uncertain by about 1.2/sqrt(n): 17 % at 50).
PHASE_SCALE_MIN_SAMPLES = 50


def phase_floor_scale(check: StageCheck, idx: np.ndarray) -> float:
    """The white-noise level of the normalised residual within one phase (samples
    ``idx``), as :func:`floor_scale` but over the phase alone; 0 for a phase shorter than
    :data:`PHASE_SCALE_MIN_SAMPLES`.

    The floor of a teacher-forced stage has two parts, the output's sensor noise and the
    input's carried through the stage, each estimated from the data and each off by its
    own factor (signal curvature at low rates inflates one more than the other). One
    scale per stage then fits the phases where one part dominates and not the others: a
    clean 100 Hz staircase of another rig had its force residual in the gapping phase at
    1.4x the stage-scaled floor, white (lag-1 autocorrelation -0.08) and equal to the
    sensor's true noise. A phase's floor is therefore at least its own residual's white
    level; second differences cancel a smooth model error, so a structured mismatch is
    not hidden by this.
    """
    if idx.size < PHASE_SCALE_MIN_SAMPLES:
        return 0.0
    level = white_level(check, idx)
    if check.rounded and check.step > 0:
        # Where a channel on a coarse grid holds one value, its rounding error is one offset of
        # up to half a step for the whole hold, not white noise of q/sqrt(12) (the holds
        # of a clean 12-bit angle in saturation scored 1.37x).
        m = check.measured
        same = np.diff(m) == 0
        held = np.r_[False, same] | np.r_[same, False]
        bound = np.where(held[idx], 0.5 * check.step, check.step / np.sqrt(12.0))
        level = max(level, float(np.sqrt(np.mean(bound**2)) / np.median(check.sigma[idx])))
    return float(np.clip(level, *FLOOR_SCALE))


def score_check(
    check: StageCheck, labels: np.ndarray, time_s: np.ndarray, *, structured: bool = True
) -> list[Mismatch]:
    """Score one stage check phase by phase (see module docstring).

    With ``structured=False`` only a residual clearly above the noise (``S >=
    SCORE_MIN``) is flagged, not a merely serially correlated one: used after a
    mechanism has been added, when what remains at noise level is the approximation of
    the added physics rather than more missing physics.
    """
    c_stage = floor_scale(check)
    r = check.residual
    out = []
    for phase in PHASES:
        mask = labels == phase
        idx = np.flatnonzero(mask)
        n = idx.size
        if n < MIN_SAMPLES:
            continue
        c = max(c_stage, phase_floor_scale(check, idx))
        e = check.normalized / c
        q = float(np.sum(e[idx] ** 2))
        score = float(np.sqrt(q / n))
        rho = _lag1(e, idx)
        # Serial correlation of the residual shrinks the effective sample size.
        n_eff = n * (1 - max(rho, 0.0)) / (1 + max(rho, 0.0))
        z = (q - n) / np.sqrt(2.0 * max(n_eff, 1.0))
        z_rho = rho * np.sqrt(n)
        flagged = (score >= SCORE_MIN and z >= Z_MIN) or (
            structured and not check.rounded and z_rho >= Z_MIN and score >= SCORE_STRUCTURED
        )
        i0, i1 = _worst_run(mask, e**2 - 1.0)
        out.append(
            Mismatch(
                stage=check.stage,
                channel=check.channel,
                phase=phase,
                t_start_s=float(time_s[i0]),
                t_end_s=float(time_s[i1]),
                n=int(n),
                score=score,
                z=float(z),
                rho=float(rho),
                rms=float(np.sqrt(np.mean(r[idx] ** 2))),
                noise=float(c * np.sqrt(np.mean(check.sigma[idx] ** 2))),
                mean=float(np.mean(r[idx])),
                flagged=bool(flagged),
            )
        )
    return out


def stage_excess(check: StageCheck) -> float:
    """Excess of the weighted residual sum of squares over its noise expectation."""
    e = check.normalized
    return float(np.sum(e * e) - e.size)


# ----------------------------------------------------------------------------- signature


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


def disc_angle(trace: Trace) -> np.ndarray | None:
    """Disc rotation angle from the disc speed, rad (``None`` without that column)."""
    if not trace.has("disc_speed_rad_s"):
        return None
    w = trace["disc_speed_rad_s"]
    return np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * trace.dt)])


def signature(check: StageCheck, trace: Trace, labels: np.ndarray) -> dict[str, Any]:
    """What the residual of one stage depends on (see module docstring).

    Returns a dict with, where they apply: ``apply_minus_release`` (mean residual while
    applying minus while releasing, in the channel's unit, and ``..._pct`` of the mean
    channel level in contact), ``lag_s`` and ``lag_se_s`` (the output lags the model by
    this much: ``r ~ -lag * d(model)/dt``), ``corr_force``, ``corr_time``,
    ``corr_disc_speed``, ``open_offset`` (mean residual with the pads open) and
    ``open_offset_z``, ``disc_periodic`` (amplitude of the residual once per disc
    revolution over its median amplitude at nearby orders).
    """
    r = check.residual
    sig = check.sigma
    dt = trace.dt
    t = trace.time_s - trace.time_s[0]
    contact = labels != "gapping"
    out: dict[str, Any] = {}
    v = motion_rate(trace)
    app, rel = contact & (v > 0), contact & (v < 0)
    if np.sum(app) >= MIN_SAMPLES and np.sum(rel) >= MIN_SAMPLES:
        diff = float(np.mean(r[app]) - np.mean(r[rel]))
        level = float(np.mean(np.abs(check.measured[contact]))) if np.any(contact) else 0.0
        out["apply_minus_release"] = diff
        out["apply_minus_release_pct"] = 100.0 * diff / level if level > 0 else 0.0
    rate = np.gradient(check.predicted, dt)
    w = 1.0 / sig**2
    den = float(np.sum(w * rate * rate))
    if den > 0:
        lag = -float(np.sum(w * rate * r)) / den
        res = r + lag * rate
        s2 = float(np.sum(w * res * res)) / max(r.size - 1, 1)
        out["lag_s"] = lag
        out["lag_se_s"] = float(np.sqrt(s2 / den))
    if np.sum(contact) >= MIN_SAMPLES:
        rc = r[contact]
        if trace.has("force_N"):
            out["corr_force"] = _corr(rc, trace["force_N"][contact])
        out["corr_time"] = _corr(rc, t[contact])
        if trace.has("disc_speed_rad_s"):
            out["corr_disc_speed"] = _corr(rc, trace["disc_speed_rad_s"][contact])
    gapping = ~contact
    if np.sum(gapping) >= MIN_SAMPLES and check.channel in ("force_N", "torque_Nm"):
        m = float(np.mean(r[gapping]))
        out["open_offset"] = m
        out["open_offset_z"] = m / float(np.sqrt(np.mean(sig[gapping] ** 2) / np.sum(gapping)))
    phi = disc_angle(trace)
    if phi is not None and np.sum(contact) >= 4 * MIN_SAMPLES:
        out["disc_periodic"] = _periodic_ratio((r / sig)[contact], phi[contact])
    return out


def _periodic_ratio(e: np.ndarray, phi: np.ndarray) -> float:
    """Amplitude of ``e`` once per revolution of ``phi`` over its median amplitude at
    nearby non-integer orders (0.55 to 1.45 revolutions; integer orders excluded): about
    1 for noise or for a slow trend, large for a once-per-revolution variation."""

    def amp(order: float) -> float:
        c, s = np.cos(order * phi), np.sin(order * phi)
        return float(np.hypot(np.sum(e * c), np.sum(e * s)) / np.sqrt(e.size))

    ref = [amp(o) for o in np.linspace(0.55, 1.45, 10) if abs(o - 1.0) > 0.2]
    den = float(np.median(ref))
    return amp(1.0) / den if den > 0 else 0.0


def describe_signature(check: StageCheck, sig: Mapping[str, Any], phase_sel: str) -> list[str]:
    """Plain-language notes on the signature's salient features."""
    notes = []
    unit = UNITS.get(check.channel, "")
    if abs(sig.get("apply_minus_release_pct", 0.0)) >= 1.0:
        pct = sig["apply_minus_release_pct"]
        more = "higher" if pct > 0 else "lower"
        notes.append(
            f"{check.channel} is {abs(pct):.1f} % {more} than the model on apply than on release"
        )
    lag, se = sig.get("lag_s"), sig.get("lag_se_s")
    if lag is not None and se and abs(lag) > 4 * se and abs(lag) > 1e-4:
        word = "lags" if lag > 0 else "leads"
        notes.append(f"the measured {check.channel} {word} the model by {abs(lag) * 1e3:.1f} ms")
    if abs(sig.get("open_offset_z", 0.0)) > 5:
        notes.append(
            f"it reads {sig['open_offset']:.3g} {unit} off the model while the pads are open"
        )
    for key, words in (
        ("corr_force", "force level"),
        ("corr_time", "elapsed time"),
        ("corr_disc_speed", "disc speed"),
    ):
        c = sig.get(key, 0.0)
        if abs(c) >= 0.5:
            notes.append(f"the residual follows {words} (correlation {c:+.2f})")
    if sig.get("disc_periodic", 0.0) >= 4.0:
        notes.append("it varies once per disc revolution")
    return notes


def summary_text(m: Mismatch, notes: list[str]) -> str:
    """The one-paragraph summary of a mismatch."""
    unit = UNITS.get(m.channel, "")
    text = (
        f"{STAGE_WORDS.get(m.stage, m.stage)}, {m.phase}: {m.channel} residual RMS "
        f"{m.rms:.3g} {unit} is {m.score:.1f}x the noise floor ({m.noise:.3g} {unit})"
    )
    if m.rho > 0.3:
        text += f"; not white (lag-1 autocorrelation {m.rho:.2f})"
    if notes:
        text += "; " + "; ".join(notes)
    return text
