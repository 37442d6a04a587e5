"""Uncertainty of a least-squares fit, and what the data do not pin down, in words.

Standard errors come from the Jacobian ``J`` of the weighted residuals at the optimum,
in the unconstrained coordinates ``u``: ``cov_u = s^2 (J^T J)^-1`` with ``s^2`` the
residual variance per degree of freedom, then mapped to SI units by the delta method
(``se_p = |dp/du| se_u``; the transforms act elementwise, so correlations carry over).

That formula holds when the residuals are white. When the model leaves something out,
or the noise is coloured, neighbouring residuals are correlated and it is too narrow:
a residual that runs for 100 samples carries the information of far fewer. So each
standard error is the larger of the white one and the serial-correlation-robust
(Newey-West) one, ``cov_u = A^-1 S A^-1`` with ``A = J^T J`` and ``S`` the long-run
covariance of the scores ``J_i r_i`` summed over the channels at each instant (Bartlett
kernel, bandwidth by Andrews' AR(1) plug-in rule). On white residuals the two agree to
within the estimator's own noise; the correlations reported are the white ones.

:func:`parameter_uncertainty` is the one function that computes them, for every
least-squares fit the tool makes (stage and chain fits, fits with mechanisms), with one
rule for the directions the data cannot determine (its docstring).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Above this condition number of the column-scaled Jacobian the fit is ill-conditioned.
ILL_CONDITIONED = 1.0e6
#: Above this |correlation| a pair of parameters is named as trading off.
STRONG_CORRELATION = 0.99
#: Above this standard error in the O(1) coordinate a parameter is poorly determined
#: (for log-scaled parameters: a relative standard error above 30 %).
POORLY_DETERMINED = 0.3
#: The scores' lag-one autocorrelation is clipped here before it sets the bandwidth (not
#: :data:`ewb_ident.data.metrics.RHO_MAX`, the diagnosis's clip of a residual's: another
#: estimate, with the value the standard errors were calibrated with).
SCORE_RHO_MAX = 0.99
#: A direction of the column-scaled Jacobian whose singular value is below this fraction
#: of the largest is one the data cannot determine; so is a column whose slope is below
#: this fraction of the steepest column's.
SINGULAR = 1.0e-12
#: A parameter loads on such a direction when its component in the direction's unit
#: vector exceeds this (the square root of the float64 epsilon: smaller components are
#: the decomposition's round-off).
LOADING = 1.5e-8


@dataclass(frozen=True)
class Uncertainty:
    """Linearised uncertainty at a least-squares optimum.

    Attributes
    ----------
    stderr
        Standard error of each parameter, SI units: the larger of the white-residual and
        the serial-correlation-robust one; None for a parameter the data cannot determine
        (:func:`parameter_uncertainty` says the rule).
    corr
        Correlation matrix of the parameters.
    condition_number
        Of the column-scaled Jacobian.
    sd_u
        Standard errors in the unconstrained O(1) coordinates (inf where undetermined).
    stderr_white
        The white-residual standard errors, SI units (None as in ``stderr``).
    """

    stderr: list[float | None]
    corr: np.ndarray
    condition_number: float
    sd_u: np.ndarray
    stderr_white: list[float | None]


def bandwidth(g: np.ndarray) -> int:
    """Bartlett-kernel bandwidth for the score series ``g`` (n, p): Andrews' (1991)
    plug-in rule with an AR(1) fitted to each column, ``1.1447 (alpha n)^(1/3)``."""
    n = g.shape[0]
    num = den = 0.0
    for x in g.T:
        v = float(x @ x)
        if not v > 0:
            continue
        rho = float(np.clip((x[1:] @ x[:-1]) / v, -SCORE_RHO_MAX, SCORE_RHO_MAX))
        s4 = ((1.0 - rho**2) * v / n) ** 2
        num += 4.0 * rho**2 * s4 / ((1.0 - rho) ** 6 * (1.0 + rho) ** 2)
        den += s4 / (1.0 - rho) ** 4
    alpha = num / den if den > 0 else 0.0
    return int(min(n - 1, np.ceil(1.1447 * (alpha * n) ** (1.0 / 3.0))))


def long_run_covariance(g: np.ndarray, lags: int | None = None) -> np.ndarray:
    """Newey-West estimate of ``sum_k E[g_t g_{t-k}^T]`` from the series ``g`` (n, p):
    ``Gamma_0 + sum_{k=1..L} (1 - k/(L+1)) (Gamma_k + Gamma_k^T)`` with
    ``Gamma_k = sum_t g_t g_{t-k}^T`` (a sum, not a mean) and ``L`` from
    :func:`bandwidth` unless given. Positive semi-definite."""
    n, p = g.shape
    lags = bandwidth(g) if lags is None else int(lags)
    if lags <= 0:
        return g.T @ g
    m = 1 << int(2 * n - 1).bit_length()
    G = np.fft.rfft(g, m, axis=0)
    # C[k, a, b] = sum_t g[t + k, a] g[t, b] (zero padding makes it linear, not circular).
    C = np.fft.irfft(G[:, :, None] * np.conj(G[:, None, :]), m, axis=0)[: lags + 1]
    w = 1.0 - np.arange(1, lags + 1) / (lags + 1.0)
    side = np.einsum("k,kab->ab", w, C[1:])
    return C[0] + side + side.T


def serial_variance(Js: np.ndarray, r: np.ndarray, inv: np.ndarray, segments) -> np.ndarray:
    """Diagonal of the sandwich ``inv S inv`` (the coordinates of ``Js``).

    ``segments``: ``(n_channels, n_time)`` per block of rows, in order: a trace's
    channels, each a time series of ``n_time`` samples. The scores are summed over the
    channels at each instant (errors of one instant may be correlated across channels)
    and ``S`` sums their :func:`long_run_covariance` over the blocks, each up to its
    last nonzero score (a padded trace's tail, weighted zero, is not part of it).
    """
    p = Js.shape[1]
    meat = np.zeros((p, p))
    row = 0
    for nch, nt in segments:
        size = int(nch) * int(nt)
        g = (Js[row : row + size] * r[row : row + size, None]).reshape(nch, nt, p).sum(axis=0)
        # A trace padded to a program's length ends in rows weighted zero: not samples.
        # Left in, they would lengthen the series that the bandwidth and the transform
        # see, and make the result depend on the padding.
        recorded = np.flatnonzero(np.any(g != 0.0, axis=1))
        if recorded.size:
            meat += long_run_covariance(g[: recorded[-1] + 1])
        row += size
    if row != Js.shape[0]:
        raise ValueError(f"segments cover {row} rows, the Jacobian has {Js.shape[0]}")
    return np.einsum("ij,jk,ki->i", inv, meat, inv)


def serial_sd(
    Js: np.ndarray, r: np.ndarray, inv: np.ndarray, segments, n: int, dof: int
) -> np.ndarray:
    """Serial-correlation-robust standard deviations in the coordinates of ``Js``
    (:func:`serial_variance`, with the white formula's small-sample factor ``n / dof``:
    ``n`` residuals that count, ``dof`` their degrees of freedom)."""
    var = serial_variance(Js, r, inv, segments) * n / dof
    return np.sqrt(np.clip(var, 0.0, None))


def parameter_uncertainty(
    J: np.ndarray, r: np.ndarray, u: np.ndarray, infos, segments=None, n: int | None = None
) -> Uncertainty:
    """Standard errors (SI), correlations and condition number from the Jacobian.

    The one computation of standard errors for every least-squares fit: the white one and
    the serial-correlation-robust one (with ``segments``), as the module docstring says.

    Singular directions, one rule: the columns of ``J`` are scaled to unit length and
    decomposed, ``J / scale = U diag(s) V^T``. A direction ``v`` (a row of ``V^T``) whose
    singular value is below :data:`SINGULAR` times the largest is one the data cannot
    determine, and so is a column whose slope (norm) is below :data:`SINGULAR` times the
    steepest column's (the direction of that parameter alone). A parameter that loads
    on such a direction (its component in ``v`` above :data:`LOADING`) has no standard
    error: ``None`` (and ``inf`` in ``sd_u``). The other parameters keep theirs, from the
    pseudo-inverse over the determined directions, which is their exact covariance
    since they do not move along the undetermined ones. A model that diverged (``J``
    or ``r`` not finite) gives no standard errors at all.

    Parameters
    ----------
    J
        Jacobian of the weighted residuals with respect to ``u``, shape (rows, p).
    r
        Weighted residuals at the optimum, shape (rows,).
    u
        The optimum in unconstrained coordinates, shape (p,).
    infos
        The :class:`~ewb_ident.model.params.ParamInfo` of each coordinate.
    segments
        How the rows are laid out in time (see :func:`serial_variance`); without it the
        standard errors are the white ones.
    n
        Residuals that count, for the degrees of freedom ``n - p`` (default: every row;
        fewer when the rows include padding weighted zero).
    """
    rows, p = J.shape
    n = rows if n is None else int(n)
    if p == 0:
        return Uncertainty([], np.zeros((0, 0)), 1.0, np.zeros(0), [])
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
        # A model that diverged (e.g. the seed's Heun integrator at a long step): no
        # standard errors, and no correlations to report.
        return Uncertainty([None] * p, np.eye(p), float("inf"), np.full(p, np.inf), [None] * p)
    scale = np.linalg.norm(J, axis=0)
    flat = ~(scale > SINGULAR * float(np.max(scale)))
    scale = np.where(flat, 1.0, scale)
    Js = J / scale
    Js[:, flat] = 0.0
    # SVD of the small triangular factor: the same singular values as Js, far cheaper.
    _, s, Vt = np.linalg.svd(np.linalg.qr(Js, mode="r"))
    s = np.concatenate([s, np.zeros(p - s.size)])  # fewer rows than columns
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    keep = s > s[0] * SINGULAR
    undetermined = flat | np.any(np.abs(Vt[~keep]) > LOADING, axis=0)
    inv = (Vt[keep].T / s[keep] ** 2) @ Vt[keep]
    dof = max(n - p, 1)
    cov_u = inv / np.outer(scale, scale) * float(r @ r) / dof
    sd_white = np.sqrt(np.clip(np.diag(cov_u), 0, None))
    safe = np.where(sd_white > 0, sd_white, 1.0)
    corr = cov_u / np.outer(safe, safe)
    sd_u = sd_white
    if segments is not None:
        sd_u = np.maximum(sd_white, serial_sd(Js, r, inv, segments, n, dof) / scale)
    stderr: list[float | None] = []
    white: list[float | None] = []
    for j, info in enumerate(infos):
        for out, sd in ((stderr, sd_u), (white, sd_white)):
            se = float(abs(info.dp_du(u[j])) * sd[j])
            out.append(se if np.isfinite(se) and not undetermined[j] else None)
    return Uncertainty(stderr, corr, cond, np.where(undetermined, np.inf, sd_u), white)


def identifiability_notes(names, unc: Uncertainty, stderr) -> list[str]:
    """Plain-language notes on what the data do not pin down.

    A parameter is *poorly determined* when its standard error in the O(1) coordinate
    exceeds :data:`POORLY_DETERMINED`. Pairs correlated beyond
    :data:`STRONG_CORRELATION` are named, since their single standard errors understate
    how they move together.
    """
    notes = []
    corr = unc.corr
    if unc.condition_number > ILL_CONDITIONED:
        notes.append(
            f"the fit is ill-conditioned (condition number {unc.condition_number:.3g}): some "
            "combination of the free parameters is not identified by this trace; fix a "
            "parameter or record a richer input"
        )
    poor = [n for n, s in zip(names, unc.sd_u, strict=True) if not s <= POORLY_DETERMINED]
    if poor:
        notes.append(
            f"poorly determined by this trace: {', '.join(poor)} (standard error beyond "
            f"{POORLY_DETERMINED:.0%} of its scale); treat their values as unreliable"
        )
    pairs = [
        f"{names[i]}-{names[j]} ({corr[i, j]:+.3f})"
        for i in range(len(names))
        for j in range(i + 1, len(names))
        if abs(corr[i, j]) > STRONG_CORRELATION
    ]
    if pairs:
        notes.append(
            "strongly correlated estimates (their errors move together, so single standard "
            f"errors understate joint uncertainty): {', '.join(pairs)}"
        )
    none = [n for n, s in stderr.items() if s is None]
    if none:
        notes.append(f"no standard error for {', '.join(none)}: the Jacobian is singular there")
    return notes


def saturation_notes(traces, preds, params, corr, names) -> list[str]:
    """Say plainly when the piston never passes the bell's centre c."""
    notes = []
    for t, pred, p in zip(traces, preds, params, strict=True):
        x = t["x_m"] if t.has("x_m") else pred.get("x_m")
        if x is None:
            continue
        c, a = float(p.c), float(p.a)
        if float(np.max(x)) < c:
            idx = {n: i for i, n in enumerate(names)}
            rho = [
                f"{m}-{n} {corr[idx[m], idx[n]]:+.2f}"
                for m, n in (("a", "b"), ("a", "c"), ("b", "c"))
                if m in idx and n in idx
            ]
            notes.append(
                f"{t.name}: the piston never passes the bell's centre c (max x = "
                f"{np.max(x) * 1e3:.3f} mm < c = {c * 1e3:.3f} mm, a = {a * 1e3:.3f} mm), so "
                "a, b and c are inferred from the rising flank alone and trade off"
                + (f" (correlations {', '.join(rho)})" if rho else "")
                + ": with more noise or a shorter apply, quite different (a, b, c) fit almost "
                "equally well. Their standard errors above include this; to pin them down, "
                "record an apply that drives the piston through full clamping"
                + (", or fix b." if "b" in idx else ".")
            )
    return notes
