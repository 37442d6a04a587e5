"""Error metrics between a simulated and a measured channel, and sensor-noise estimates.

Definitions (every report and JSON file uses these):

``rmse``
    Root-mean-square error, ``sqrt(mean((sim - meas)^2))``, in the channel's unit.
``nrmse_pct``
    RMSE over the measured channel's range, ``100 * rmse / (max(meas) - min(meas))``, %.
``percent_error``
    Relative L2 error, ``100 * ||sim - meas||_2 / ||meas||_2``, %. The seed paper
    reports "percent error" (3.3 % for force, 1.2 % for torque) without defining it; this
    is the most common reading of such a figure. It weighs errors by the signal's own
    size, so it is small for traces that dwell at high force: compare NRMSE across
    traces, and read the seed's figures as indicative only.

The sensor-noise estimate :func:`noise_sigma` uses second differences, which cancel a
smooth signal and leave the white sensor noise: for white noise of standard deviation
sigma, ``y[k+1] - 2 y[k] + y[k-1]`` has standard deviation ``sqrt(6) sigma``. A robust
scale (1.4826 * MAD) ignores the few samples where the signal itself bends sharply.
A quantised channel (an ADC, a potentiometer read at 12 bits) whose white noise is
smaller than its step has mostly zero second differences, so the MAD says "no noise";
its noise is then at least the rounding error, ``q / sqrt(12)`` for a step ``q``
(:func:`quantisation_step`). The MAD of values on a grid is itself on the grid: with
noise about one step, the MAD of the second differences is one step for any noise from
0.5 to 1.2 steps, and the estimate is off by up to -20 % or +20 % (a clean 12-bit
displacement at 1 kHz read 0.6 steps for 0.76, and its residual was taken for missing
physics). On a grid the scale is therefore the standard deviation of the second
differences within :data:`TRIM` robust scales of their median (the scale at least one
step), which is within 6 % of ``sqrt(sigma^2 + q^2 / 12)`` from a noise of 0.3 steps
upwards.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

#: The seed paper's reported percent errors, by channel.
SEED_PERCENT_ERROR: dict[str, float] = {"force_N": 3.3, "torque_Nm": 1.2}
#: The seed paper's acceptance: force and torque percent error below 10 %.
SEED_ACCEPTANCE_PCT = 10.0
#: Largest lag-1 autocorrelation of a residual that the diagnosis takes as measured, in
#: its effective number of residuals ``n (1 - rho) / (1 + rho)`` (a smooth misfit's
#: approaches 1). Not the clip of the standard errors' bandwidth
#: (:data:`ewb_ident.inference.uncertainty.SCORE_RHO_MAX`, another estimate).
RHO_MAX = 0.98
#: The probability of every interval the tool gives: the linearised intervals
#: (estimate ± :data:`Z90` standard errors) and the posterior's highest-density ones.
INTERVAL_PROB = 0.9
#: The standard normal quantile of a two-sided :data:`INTERVAL_PROB` interval,
#: ``ndtri(0.5 + INTERVAL_PROB / 2)``, written out to the last bit so that importing the
#: package does not import SciPy (``tests/test_fit.py`` checks it against
#: ``scipy.special.ndtri``); every linearised 90 % interval the tool gives.
Z90 = 1.6448536269514722


#: Second differences of a channel on a grid further than this many robust scales from
#: their median are left out of its noise estimate (:func:`noise_sigma`): the few samples
#: where the signal bends sharply; white noise loses 0.1 % of its variance.
TRIM = 4.0


def rmse(sim: ArrayLike, meas: ArrayLike) -> float:
    """Root-mean-square error, in the channel's unit."""
    r = np.asarray(sim, float) - np.asarray(meas, float)
    return float(np.sqrt(np.mean(r * r)))


def channel_metrics(sim: ArrayLike, meas: ArrayLike) -> dict[str, float | None]:
    """RMSE, NRMSE % and percent error of one channel (see module docstring).

    A metric that does not exist (a constant or all-zero measured channel, or a
    simulation that diverged) is ``None``.
    """
    sim = np.asarray(sim, float)
    meas = np.asarray(meas, float)
    with np.errstate(over="ignore", invalid="ignore"):
        e = rmse(sim, meas)
    if not (np.all(np.isfinite(sim)) and np.isfinite(e)):  # a diverged simulation
        return {"rmse": None, "nrmse_pct": None, "percent_error": None}
    span = float(np.max(meas) - np.min(meas))
    norm = float(np.linalg.norm(meas))
    return {
        "rmse": e,
        "nrmse_pct": 100.0 * e / span if span > 0 else None,
        "percent_error": 100.0 * float(np.linalg.norm(sim - meas)) / norm if norm > 0 else None,
    }


def noise_floor(y: ArrayLike) -> float:
    """Smallest noise level a channel is weighted with, in its unit: a noise-free channel
    would otherwise get an infinite weight (1e-6 of its range)."""
    y = np.asarray(y, float)
    return 1e-6 * float(np.max(y) - np.min(y)) + 1e-12


def noise_sigma(y: ArrayLike, step: float | None = None) -> float:
    """Standard deviation of white sensor noise on a sampled channel, robustly estimated.

    Parameters
    ----------
    y
        The measured channel (at least 5 samples), in its unit.
    step
        The grid step of the values (their :func:`quantisation_step`, found from ``y``
        when not given; 0 for none), in the channel's unit: given for a residual of a
        channel on a grid, which is near the grid but not on it.

    Returns
    -------
    Estimated noise standard deviation, in the channel's unit (0 for a noise-free one),
    at least the rounding error ``step / sqrt(12)``.
    """
    y = np.asarray(y, float)
    q = quantisation_step(y) if step is None else step
    d2 = np.diff(y, n=2)
    dev = np.abs(d2 - np.median(d2))
    scale = 1.4826 * float(np.median(dev))
    if q > 0:  # the MAD of values on a grid is on the grid (module docstring)
        keep = dev <= TRIM * max(scale, q)
        scale = float(np.sqrt(np.mean(dev[keep] ** 2)))
    return float(max(scale / np.sqrt(6.0), q / np.sqrt(12.0)))


def rounding_error(y: ArrayLike) -> float:
    """The standard deviation of a channel's rounding error, ``q / sqrt(12)`` for its
    :func:`quantisation_step` ``q`` (0 for a channel not on a grid), in its unit."""
    return quantisation_step(y) / np.sqrt(12.0)


def quantisation_step(y: ArrayLike) -> float:
    """The step of a channel recorded on a uniform grid (an ADC's least significant
    bit), in its unit; 0 when the values are not on one.

    The candidate step is the smallest change between consecutive samples; the channel
    is quantised when at least 99 % of all changes are whole multiples of it (to 1 % of
    the step) and there are at least 20 changes.
    """
    y = np.asarray(y, float)
    d = np.abs(np.diff(y))
    span = float(np.max(y) - np.min(y)) if y.size else 0.0
    d = d[d > 1e-9 * max(span, 1e-300)]
    if d.size < 20:
        return 0.0
    q = float(np.min(d))
    k = d / q
    on_grid = np.abs(k - np.round(k)) < 0.01
    return q if np.mean(on_grid) >= 0.99 else 0.0


def sensor_noise(y: ArrayLike) -> float:
    """The noise level a channel is judged against: :func:`noise_sigma`, floored at
    :func:`noise_floor` (in the channel's unit)."""
    return max(noise_sigma(y), noise_floor(y))


def smooth(y: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average over ``width`` samples (odd), ends held."""
    width = max(1, int(width) | 1)
    if width == 1:
        return np.asarray(y, float).copy()
    pad = width // 2
    yp = np.concatenate([np.full(pad, y[0]), y, np.full(pad, y[-1])])
    return np.convolve(yp, np.ones(width) / width, mode="valid")


def ar1_filter(x: ArrayLike, phi: ArrayLike, block: int = 64) -> np.ndarray:
    """``y[k] = x[k] + phi * y[k-1]`` from ``y[-1] = 0``, along the last axis (|phi| < 1).

    ``scipy.signal.lfilter([1], [1, -phi], x)``, without importing ``scipy.signal``
    (0.8 s of a command's start-up). Blocks of ``block`` samples are filtered at once
    by a matrix of powers of ``phi``, and the carry passed from block to block, so the
    Python loop runs over ``n / block`` blocks, not ``n`` samples. ``phi`` broadcasts
    against the leading axes of ``x`` (e.g. shape ``(m, 1)`` filters one signal with ``m``
    coefficients at once, giving shape ``(m, n)``).
    """
    x = np.asarray(x, float)
    phi = np.asarray(phi, float)
    n = x.shape[-1]
    nb = -(-n // block)
    lead = np.broadcast_shapes(x.shape[:-1], phi.shape[:-1] if phi.ndim else ())
    xb = np.zeros((*x.shape[:-1], nb * block))
    xb[..., :n] = x
    xb = xb.reshape(*x.shape[:-1], nb, block)
    i = np.arange(block)
    lag = i[:, None] - i[None, :]
    ph = (phi if phi.ndim else phi[None])[..., None, None]  # (..., 1, 1, 1)
    T = np.where(lag >= 0, ph ** np.maximum(lag, 0), 0.0)[..., 0, :, :]  # (..., B, B)
    local = np.einsum("...ij,...cj->...ci", T, xb)
    decay = (ph[..., 0, 0] ** (i + 1))  # (..., B)
    y = np.empty((*lead, nb, block))
    carry = np.zeros(lead)
    for c in range(nb):
        y[..., c, :] = local[..., c, :] + decay * carry[..., None]
        carry = y[..., c, -1]
    return y.reshape(*lead, nb * block)[..., :n]
