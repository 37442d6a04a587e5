"""Filters of a series that discovery uses: two of :mod:`scipy.signal`'s and
:func:`scipy.stats.rankdata`, computed as SciPy computes them, without importing
``scipy.signal`` or ``scipy.stats``, and a counter of the motion's reversals
(:func:`reversals`).

Importing ``scipy.signal`` imports ``scipy.stats``, ``scipy.optimize``,
``scipy.interpolate`` and ``scipy.spatial`` with it, and ``scipy.stats`` alone takes
about 1 s: processor time at every ``ewb-ident diagnose``, which uses none of them.
Each function here does the same floating-point operations in the same order as its
SciPy counterpart, so its results are SciPy's (bit for bit with SciPy 1.17;
``tests/test_discovery.py`` checks them against the installed SciPy's). And the
leave-one-out averages that take a recorded channel's noise at a sample out of its level
there (:func:`leave_one_out`, :func:`denoised`).
"""

from __future__ import annotations

import numpy as np


def first_order_lowpass(x: np.ndarray, b0: float, a1: float, z0: float) -> np.ndarray:
    """``scipy.signal.lfilter([b0], [1.0, -a1], x, zi=[z0])[0]`` for a 1-D float ``x``.

    SciPy's filter (transposed direct form II, its ``b`` padded with a zero to the
    length of ``a``) computes, per sample, ``y = z + b0 * x`` and then
    ``z = x * 0.0 - y * (-a1)``; this loop computes exactly that, in Python floats
    (IEEE doubles, as SciPy's C loop). The loop costs some 0.1 us a sample.

    Parameters
    ----------
    x : numpy.ndarray
        The signal (1-D, float64).
    b0 : float
        The feed-forward coefficient.
    a1 : float
        The feedback coefficient (``y[k] = b0 x[k] + a1 y[k-1]``).
    z0 : float
        The filter's initial state (SciPy's ``zi``).

    Returns
    -------
    numpy.ndarray
        The filtered signal, float64, of ``x``'s length.
    """
    na1 = -a1
    z = float(z0)
    out = []
    for xk in np.asarray(x, dtype=np.float64).tolist():
        yk = z + b0 * xk
        out.append(yk)
        z = xk * 0.0 - yk * na1
    return np.array(out, dtype=np.float64)


def fft_convolve_columns(h: np.ndarray, U: np.ndarray) -> np.ndarray:
    """``scipy.signal.fftconvolve(h[:, None], U, axes=0)``: the full convolution of the
    1-D ``h`` with each column of ``U`` (shape ``(len(h) + len(U) - 1, K)``).

    As SciPy: both real inputs padded to the next fast length of the full convolution,
    transformed with :func:`scipy.fft.rfftn` along the first axis, multiplied, and
    transformed back with :func:`scipy.fft.irfftn`; the full length kept, as a copy.

    Parameters
    ----------
    h : numpy.ndarray
        The impulse response (1-D, real, at least 2 samples).
    U : numpy.ndarray
        The signals (2-D, real, at least 2 rows), one per column.

    Returns
    -------
    numpy.ndarray
        The convolutions, one per column of ``U``.
    """
    in1, in2 = np.asarray(h)[:, None], np.asarray(U)
    if in1.shape[0] < 2 or in2.ndim != 2 or in2.shape[0] < 2 or in2.size == 0:
        from scipy.signal import fftconvolve  # a case SciPy handles otherwise

        return fftconvolve(in1, in2, axes=0)
    from scipy import fft as sp_fft

    full = in1.shape[0] + in2.shape[0] - 1
    fshape = [sp_fft.next_fast_len(full, True)]
    sp1 = sp_fft.rfftn(in1, fshape, axes=[0])
    sp2 = sp_fft.rfftn(in2, fshape, axes=[0])
    ret = sp_fft.irfftn(sp1 * sp2, fshape, axes=[0])
    return np.array(ret[(slice(full), slice(max(in1.shape[1], in2.shape[1])))])


def reversals(y: np.ndarray, share: float) -> tuple[np.ndarray, np.ndarray]:
    """The reversals of a motion so far, and the travel since the last one.

    A reversal is an extreme of ``y`` from which it comes back by more than ``share`` of
    its range (a Schmitt trigger: the dither of a closed loop at rest is none); it counts
    from the sample after the extreme. The first departure from the start sets the
    direction and is not counted.

    Parameters
    ----------
    y : numpy.ndarray
        The position (1-D), e.g. the pinion angle in degrees.
    share : float
        The hysteresis, as a share of ``y``'s range.

    Returns
    -------
    count : numpy.ndarray
        The number of reversals before each sample.
    travel : numpy.ndarray
        ``y`` less its value at the last reversal (before the first: at the start), in
        ``y``'s unit.
    """
    y = np.asarray(y, dtype=np.float64)
    vals = y.tolist()
    h = share * float(np.ptp(y)) if y.size else 0.0
    events: list[int] = []
    direction, ext = 0, 0
    for k, v in enumerate(vals):
        if direction == 0:
            if abs(v - vals[0]) > h:
                direction, ext = (1 if v > vals[0] else -1), k
        elif (v - vals[ext]) * direction > 0:
            ext = k
        elif (vals[ext] - v) * direction > h:
            events.append(ext)
            direction, ext = -direction, k
    anchors = np.array([0, *events], dtype=int)  # the start, then each reversal's extreme
    count = np.searchsorted(anchors[1:], np.arange(y.size), side="left")
    return count.astype(np.float64), y - y[anchors[count]]


def leave_one_out(y: np.ndarray, half: int) -> np.ndarray:
    """Centred moving average over ``2 half`` neighbours, the sample itself left out
    (ends: the neighbours there are). A recorded channel's noise at a sample is then
    not in the input at that sample, so a term cannot fit the residual's noise through
    its input; the central differences of the result hold no noise of their own sample
    either (it enters both neighbours equally)."""
    y = np.asarray(y, float)
    n = y.size
    c = np.concatenate([[0.0], np.cumsum(y)])
    k = np.arange(n)
    lo, hi = np.maximum(k - half, 0), np.minimum(k + half + 1, n)
    count = hi - lo - 1
    return (c[hi] - c[lo] - y) / np.maximum(count, 1)


#: Longest half-window of a channel's leave-one-out average, s.
MAX_HALF_S = 0.05


def denoised(y: np.ndarray, dt: float) -> np.ndarray:
    """A recorded channel's level without its noise at each sample: the
    :func:`leave_one_out` average whose half-width (1 sample to :data:`MAX_HALF_S`)
    predicts the channel's samples best. For white noise that prediction's error is the
    noise plus the average's own error, so the best predictor is the best estimate of
    the level: a wide window where the noise is large against how fast the channel
    moves (a load cell's noise, which otherwise blurs a term that depends on the force
    into one on the quieter angle), a narrow one where it moves fast."""
    y = np.asarray(y, float)
    top = max(1, int(MAX_HALF_S / dt))
    halves = sorted({max(1, round(h)) for h in np.geomspace(1, top, 8)})
    fits = [leave_one_out(y, h) for h in halves]
    return fits[int(np.argmin([np.mean((y - f) ** 2) for f in fits]))]


def average_ranks(v: np.ndarray) -> np.ndarray:
    """Ranks of ``v`` from 1, ties given the mean of their ranks
    (``scipy.stats.rankdata(v)``, method ``"average"``)."""
    v = np.asarray(v, dtype=float).reshape(-1)
    order = np.argsort(v, kind="mergesort")
    s = v[order]
    new = np.r_[True, s[1:] != s[:-1]]
    starts = np.flatnonzero(new)
    counts = np.diff(np.r_[starts, s.size])
    out = np.empty(v.size)
    out[order] = (starts + 0.5 * (counts + 1))[np.cumsum(new) - 1]
    return out
