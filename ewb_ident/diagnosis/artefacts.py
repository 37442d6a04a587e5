"""Structured sensor noise that is not brake physics: recognised, named and removed.

A disturbance that does not depend on the brake's state is a property of the
instrumentation, not of the brake, and must not raise an alarm about missing physics:

* **Periodic interference** (:func:`periodic_interference`): a sinusoid of fixed
  frequency in a channel's residual (mains hum at 50 or 60 Hz or a harmonic, or its
  alias at the logging rate; a switching regulator's ripple) is recognised when it is
  (1) a clear line in the residual's spectrum (above its neighbourhood with a
  false-alarm probability under 1e-3 over the whole band), (2) stationary: the same
  amplitude and phase in each quarter of the trace, and (3) indifferent to the brake:
  about as strong with the pads open as in contact, and not at a harmonic of the disc's
  rotation. It is then subtracted from the channel before the diagnosis.
* **Quantisation** (:func:`ewb_ident.data.metrics.quantisation_step`): a channel on a
  grid coarse against its noise is named; its rounding error is treated as noise.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ewb_ident.data.metrics import quantisation_step
from ewb_ident.data.stages import STAGE_COLUMNS

#: False-alarm probability of a spectral line over the searched band.
LINE_ALPHA = 1e-3
#: Lowest frequency searched, Hz (slower structure is the brake's).
F_MIN_HZ = 2.0
#: Each quarter's amplitude is at least this share of the whole trace's.
MIN_BLOCK_SHARE = 0.5
#: Open-pad and contact amplitudes agree within this factor.
STATE_RATIO = 2.0
#: Most lines removed per channel.
MAX_LINES = 3


@dataclass(frozen=True)
class Artefact:
    """A recognised sensor artefact (the ``artefacts`` entries of ``diagnosis.json``)."""

    channel: str
    kind: str
    summary: str
    frequency_hz: float | None = None
    amplitude: float | None = None

    def to_json(self) -> dict[str, Any]:
        """The entry: every field, under its own name."""
        return asdict(self)


def _fit_line(e: np.ndarray, t: np.ndarray, f: float, idx=None) -> tuple[complex, np.ndarray]:
    """Least-squares sinusoid at ``f`` (with a constant) over ``idx``: its complex
    amplitude ``a + i b`` (``a cos + b sin``) and the sinusoid over the whole trace."""
    sel = slice(None) if idx is None else idx
    X = np.stack([np.cos(2 * np.pi * f * t), np.sin(2 * np.pi * f * t), np.ones_like(t)], 1)
    coef = np.linalg.lstsq(X[sel], e[sel], rcond=None)[0]
    return complex(coef[0], coef[1]), X[:, :2] @ coef[:2]


def _disc_frequencies(disc_speed: np.ndarray | None) -> list[float]:
    if disc_speed is None:
        return []
    f0 = abs(float(np.mean(disc_speed))) / (2 * np.pi)
    return [k * f0 for k in range(1, 5)] if f0 > 0 else []


def _aliased(f: float, fs: float) -> float:
    """The frequency ``f`` appears at when sampled at ``fs``."""
    r = f % fs
    return min(r, fs - r)


def _name(f: float, fs: float) -> str:
    for mains in (50.0, 60.0):
        for k in range(1, 6):
            if abs(_aliased(k * mains, fs) - f) < 0.3:
                shown = f"{k * mains:g} Hz" + (
                    "" if abs(k * mains - f) < 0.3 else f", seen at {f:.1f} Hz"
                )
                return f"mains interference ({shown})"  # fmt: skip
    return f"periodic interference at {f:.2f} Hz"


def periodic_interference(
    e: np.ndarray,
    dt: float,
    open_pads: np.ndarray | None = None,
    disc_speed: np.ndarray | None = None,
) -> list[tuple[float, float, np.ndarray]]:
    """Fixed-frequency lines in the residual ``e`` that do not depend on the brake's
    state: ``(frequency Hz, amplitude, the sinusoid per sample)``, strongest first."""
    e = np.asarray(e, float) - float(np.mean(e))
    n = e.size
    if n < 64:
        return []
    t = np.arange(n) * dt
    out = []
    resid = e.copy()
    for _ in range(MAX_LINES):
        win = np.hanning(n)
        P = np.abs(np.fft.rfft(resid * win)) ** 2
        freqs = np.fft.rfftfreq(n, dt)
        band = np.flatnonzero(freqs >= F_MIN_HZ)
        if band.size < 20:
            break
        half = 25
        local = np.array(
            [np.median(P[max(0, k - half) : k + half + 1]) / np.log(2) for k in range(P.size)]
        )
        ratio = P[band] / np.maximum(local[band], 1e-300)
        k = int(band[np.argmax(ratio)])
        # Exponential ordinates: P(ratio > x) = exp(-x) per bin, over the band.
        if float(np.max(ratio)) < np.log(band.size / LINE_ALPHA):
            break
        f = float(freqs[k])
        if 0 < k < P.size - 1:  # refine between bins (log-parabola)
            a, b, c = np.log(P[k - 1 : k + 2] + 1e-300)
            den = a - 2 * b + c
            if den < 0:
                f += 0.5 * (a - c) / den * (freqs[1] - freqs[0])
        if any(abs(f - fd) < 2.0 / (n * dt) for fd in _disc_frequencies(disc_speed)):
            break  # a line at the disc's rotation is the brake's
        amp, line = _fit_line(resid, t, f)
        blocks = np.array_split(np.arange(n), 4)
        each = [_fit_line(resid, t, f, b)[0] for b in blocks]
        steady = min(abs(c) for c in each) >= MIN_BLOCK_SHARE * abs(amp) and abs(
            np.mean(each)
        ) >= 0.7 * np.mean([abs(c) for c in each])
        if not steady:
            break
        if open_pads is not None and 0.1 * n <= int(np.sum(open_pads)) <= 0.9 * n:
            a_open = abs(_fit_line(resid, t, f, open_pads)[0])
            a_contact = abs(_fit_line(resid, t, f, ~open_pads)[0])
            if not (1 / STATE_RATIO <= a_open / max(a_contact, 1e-300) <= STATE_RATIO):
                break
        out.append((f, float(np.sqrt(2.0 * np.mean(line**2))), line))
        resid = resid - line
    return out


def find_artefacts(checks, trace, labels) -> tuple[list[Artefact], dict[str, np.ndarray]]:
    """Sensor artefacts in the residuals of the stage checks, and the recorded channels
    with the periodic ones removed (only those changed).

    Parameters
    ----------
    checks
        ``{(stage, channel): StageCheck}`` of the baseline.
    trace
        The trace.
    labels
        The phase of each sample (``gapping``: pads open).
    """
    arts: list[Artefact] = []
    cleaned: dict[str, np.ndarray] = {}
    disc = trace["disc_speed_rad_s"] if trace.has("disc_speed_rad_s") else None
    open_pads = np.asarray(labels) == "gapping"
    fs = 1.0 / trace.dt
    found: dict[str, list[float]] = {}
    for (stage, ch), c in checks.items():
        if ch in found:
            continue
        lines = periodic_interference(c.measured - c.predicted, trace.dt, open_pads, disc)
        # A line of the stage's measured input shows in its output's residual too.
        upstream = found.get(STAGE_COLUMNS.get(stage, ("",))[0], [])
        lines = [x for x in lines if all(abs(x[0] - f) > 0.5 for f in upstream)]
        found[ch] = [f for f, _, _ in lines]
        if lines:
            total = sum(line for _, _, line in lines)
            cleaned[ch] = np.asarray(trace[ch], float) - total
            for f, amp, _ in lines:
                noise = float(np.median(c.sigma))
                arts.append(
                    Artefact(
                        ch,
                        "periodic_interference",
                        f"{_name(f, fs)} on {ch}: a steady {f:.2f} Hz sinusoid of amplitude "
                        f"{amp:.3g} ({amp / noise:.1f}x the noise), the same with the pads "
                        "open and in contact: not brake physics; removed before the diagnosis",
                        f,
                        amp,
                    )
                )
    for ch in trace.channels:
        if ch in ("time_s", "voltage_V"):
            continue
        q = quantisation_step(trace[ch])
        if q > 0:
            arts.append(
                Artefact(
                    ch,
                    "quantised",
                    f"{ch} is recorded on a grid of {q:.3g}: its rounding error is treated as "
                    "sensor noise",
                    None,
                    q,
                )
            )
    return arts, cleaned
