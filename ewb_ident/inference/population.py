"""A campaign's parameters as a population: the random-effects combination of per-trace
estimates, and the change of a parameter between two groups of traces.

Each trace ``i`` gives an estimate ``y_i`` with a standard error ``s_i`` (the fit's
robust one). The traces of a campaign are of several rig units, days and temperatures,
so their true values differ: ``y_i = theta + u_i + e_i`` with ``u_i ~ N(0, tau^2)`` the
trace-to-trace (unit-to-unit) spread and ``e_i ~ N(0, s_i^2)`` the measurement error.

* ``tau^2`` by Paule and Mandel's estimator: the ``tau^2`` at which the generalised Q
  statistic equals its expectation ``k - 1`` (so it always lies inside the Q-profile
  interval below; DerSimonian and Laird's moment estimator, used before, need not: on a
  campaign of traces at 100 Hz to 1 kHz, whose standard errors differ a
  hundredfold, it fell outside for 9 of 26 groups x parameters), ``theta`` as the mean
  weighted by ``1 / (s_i^2 + tau^2)``;
* the 90 % interval of ``theta`` by Hartung-Knapp-Sidik-Jonkman: a t interval with
  ``k - 1`` degrees of freedom on the weighted residual variance (never narrower than the
  plain standard error ``1 / sqrt(sum of the weights)``), which keeps its level with few
  traces where the plain normal interval does not;
* the 90 % interval of ``tau`` by the Q-profile (Viechtbauer 2007): the values of
  ``tau^2`` at which the generalised Q statistic equals the 95 % and 5 % quantiles of
  chi-square with ``k - 1`` degrees of freedom.

When the traces come from rig units with several traces each, :func:`two_level` separates
the unit-to-unit spread from the trace-to-trace spread within a unit: a pooled
Paule-Mandel estimate of the within-unit spread first, then the units' means combined as
above (the population mean's interval then has ``units - 1`` degrees of freedom, not
``traces - 1``: repeated traces of one unit are not independent draws of the population).

A group change is the difference of two groups' means, each combined as above, with a
Welch-Satterthwaite t interval; whether it changed is decided as
:func:`ewb_ident.inference.compare.compare` decides it for two traces (the probability
that the change exceeds the practical tolerance is above 0.95).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import optimize, stats

from ewb_ident.data.metrics import Z90
from ewb_ident.inference.compare import ParameterChange, practical_tolerance

#: Probability of every interval here (two-sided).
LEVEL = 0.90


@dataclass(frozen=True)
class Combined:
    """The random-effects combination of one parameter's per-trace estimates (SI).

    Attributes
    ----------
    n
        Traces combined (those with a finite estimate and standard error).
    mean, stderr, low90, high90
        The population mean, its standard error (Hartung-Knapp) and 90 % interval.
    df
        Degrees of freedom of the mean's t interval (``n - 1``; ``inf``: one trace,
        a normal interval on its own standard error).
    tau, tau_low90, tau_high90
        The spread between traces beyond their measurement errors (Paule-Mandel), and
        its 90 % Q-profile interval; ``None`` with fewer than two traces.
    q
        Cochran's Q (heterogeneity statistic), ``None`` with fewer than two traces.
    """

    n: int
    mean: float
    stderr: float
    low90: float
    high90: float
    df: float
    tau: float | None
    tau_low90: float | None
    tau_high90: float | None
    q: float | None


def _generalised_q(tau2: float, y: np.ndarray, v: np.ndarray) -> float:
    w = 1.0 / (v + tau2)
    mu = float(np.sum(w * y) / np.sum(w))
    return float(np.sum(w * (y - mu) ** 2))


def _q_profile(y: np.ndarray, v: np.ndarray, target: float, q=None) -> float:
    """The ``tau^2 >= 0`` at which the generalised Q (``q(tau2, y, v)``, default
    :func:`_generalised_q`) equals ``target`` (0 when even ``tau^2 = 0`` gives less). Q
    falls monotonically in ``tau^2``."""
    q = q or _generalised_q
    if q(0.0, y, v) <= target:
        return 0.0
    hi = max(float(np.var(y)), float(np.max(v)))
    while q(hi, y, v) > target:
        hi *= 10.0
    # (a tolerance relative to the bracket: tau^2 of the gap polynomial's p2 is ~1e-19,
    # far below brentq's default absolute tolerance of 2e-12)
    return float(optimize.brentq(lambda t2: q(t2, y, v) - target, 0.0, hi, xtol=hi * 1e-14))


def random_effects(estimates: Sequence[float], stderrs: Sequence[float]) -> Combined | None:
    """Combine per-trace estimates of one parameter (see the module docstring).

    Parameters
    ----------
    estimates, stderrs
        Per trace, the estimate and its standard error, in the parameter's SI unit;
        pairs with a missing, non-finite or non-positive standard error are left out.

    Returns
    -------
    Combined or None
        ``None`` when no trace is usable.
    """
    y = np.asarray(estimates, dtype=float)
    s = np.asarray([np.nan if e is None else e for e in stderrs], dtype=float)
    keep = np.isfinite(y) & np.isfinite(s) & (s > 0)
    y, v = y[keep], s[keep] ** 2
    k = int(y.size)
    if k == 0:
        return None
    if k == 1:
        se = math.sqrt(float(v[0]))
        m = float(y[0])
        return Combined(1, m, se, m - Z90 * se, m + Z90 * se, math.inf, None, None, None, None)
    w = 1.0 / v
    mu_fixed = float(np.sum(w * y) / np.sum(w))
    q = float(np.sum(w * (y - mu_fixed) ** 2))
    tau2 = _q_profile(y, v, float(k - 1))  # Paule-Mandel
    ws = 1.0 / (v + tau2)
    mu = float(np.sum(ws * y) / np.sum(ws))
    q_hk = float(np.sum(ws * (y - mu) ** 2)) / (k - 1)
    se = math.sqrt(max(1.0, q_hk) / float(np.sum(ws)))
    t = float(stats.t.ppf(0.5 + LEVEL / 2, k - 1))
    upper_q = float(stats.chi2.ppf(0.5 + LEVEL / 2, k - 1))
    lower_q = float(stats.chi2.ppf(0.5 - LEVEL / 2, k - 1))
    tau_lo = math.sqrt(_q_profile(y, v, upper_q))
    tau_hi = math.sqrt(_q_profile(y, v, lower_q))
    return Combined(
        k, mu, se, mu - t * se, mu + t * se, float(k - 1), math.sqrt(tau2), tau_lo, tau_hi, q
    )


@dataclass(frozen=True)
class TwoLevel:
    """The combination of one parameter's per-trace estimates when several traces come
    from each rig unit: ``y_ij = theta + u_i + v_ij + e_ij`` (unit ``i``, trace ``j``),
    ``u_i ~ N(0, tau_unit^2)`` the unit-to-unit spread, ``v_ij ~ N(0, tau_trace^2)`` the
    trace-to-trace spread within a unit, ``e_ij ~ N(0, s_ij^2)`` the measurement error
    (see :func:`two_level`).

    Attributes
    ----------
    units
        The random-effects combination of the unit means (:func:`random_effects`): its
        ``n`` is the number of units, ``tau`` (with its Q-profile interval) the
        unit-to-unit spread, ``mean`` and its interval (``n_units - 1`` degrees of
        freedom) the population mean.
    n_traces
        Traces used.
    repeated
        Units with two traces or more (those that say anything about ``tau_trace``).
    tau_trace, tau_trace_low90, tau_trace_high90
        The trace-to-trace spread within a unit (pooled Paule-Mandel) and its 90 %
        Q-profile interval; ``None`` when no unit has two traces.
    """

    units: Combined
    n_traces: int
    repeated: int
    tau_trace: float | None
    tau_trace_low90: float | None
    tau_trace_high90: float | None

    # The population's mean, as :class:`Combined` has it (for :func:`group_change`): one
    # property per attribute, alike in shape.
    @property
    def n(self) -> int:
        return self.n_traces

    @property
    def mean(self) -> float:
        return self.units.mean

    @property
    def stderr(self) -> float:
        return self.units.stderr

    @property
    def df(self) -> float:
        return self.units.df

    @property
    def low90(self) -> float:
        return self.units.low90

    @property
    def high90(self) -> float:
        return self.units.high90


def _within_q(tau2: float, y: np.ndarray, v: np.ndarray, groups: np.ndarray) -> float:
    """The generalised Q of every trace about its own unit's weighted mean, summed."""
    w = 1.0 / (v + tau2)
    sw = np.bincount(groups, weights=w)
    means = np.bincount(groups, weights=w * y) / sw
    return float(np.sum(w * (y - means[groups]) ** 2))


def two_level(
    estimates: Sequence[float],
    stderrs: Sequence[float],
    units: Sequence[object],
) -> TwoLevel | None:
    """Combine per-trace estimates of one parameter from several traces per rig unit
    (see :class:`TwoLevel`), in two steps:

    1. ``tau_trace^2``, pooled over the units: the Paule-Mandel value at which the
       generalised Q of the traces about their own unit's weighted mean, summed over the
       units, equals its expectation ``sum (n_i - 1)``; its 90 % interval by the
       Q-profile on chi-square with ``sum (n_i - 1)`` degrees of freedom. (0, and
       ``None`` reported, when no unit has two traces.)
    2. Each unit's mean, weighted by ``1 / (s_ij^2 + tau_trace^2)``, with the variance
       ``1 / sum of the weights``; the unit means combined by :func:`random_effects`
       (Paule-Mandel ``tau_unit``, Hartung-Knapp mean interval on ``n_units - 1``
       degrees of freedom, Q-profile ``tau_unit`` interval).

    A trace with no unit (``None``) is a unit of its own. The uncertainty of
    ``tau_trace`` is not carried into step 2 (as in two-stage meta-analysis).

    Returns
    -------
    TwoLevel or None
        ``None`` when no trace is usable (a missing, non-finite or non-positive
        standard error leaves a trace out).
    """
    y = np.asarray(estimates, dtype=float)
    s = np.asarray([np.nan if e is None else e for e in stderrs], dtype=float)
    labels = [f"trace:{k}" if u is None or u != u else f"unit:{u}" for k, u in enumerate(units)]
    keep = np.isfinite(y) & np.isfinite(s) & (s > 0)
    y, v = y[keep], s[keep] ** 2
    if y.size == 0:
        return None
    _, groups = np.unique(np.asarray(labels)[keep], return_inverse=True)
    sizes = np.bincount(groups)
    df_within = int(np.sum(sizes - 1))
    if df_within > 0:

        def q(t2, yy, vv):
            return _within_q(t2, yy, vv, groups)

        tau2 = _q_profile(y, v, float(df_within), q)
        bounds = [math.sqrt(_q_profile(y, v, float(stats.chi2.ppf(0.5 + side * LEVEL / 2,
                                                                  df_within)), q))
                  for side in (1, -1)]
        tau_t = (math.sqrt(tau2), *bounds)
    else:
        tau2, tau_t = 0.0, (None, None, None)
    w = 1.0 / (v + tau2)
    sw = np.bincount(groups, weights=w)
    means = np.bincount(groups, weights=w * y) / sw
    units_comb = random_effects(means, np.sqrt(1.0 / sw))
    return TwoLevel(units_comb, int(y.size), int(np.sum(sizes > 1)), *tau_t)


def group_change(
    name: str,
    before: Combined | TwoLevel,
    after: Combined | TwoLevel,
    tolerance: Mapping[str, float] | None = None,
) -> ParameterChange:
    """The change of a parameter's population mean from one group of traces to another.

    Parameters
    ----------
    name
        The parameter (its default tolerance follows :func:`practical_tolerance`).
    before, after
        The two groups' combinations (:func:`random_effects` or :func:`two_level`).
    tolerance
        Practical tolerance per parameter, SI units (default: 1 % of the ``before``
        mean, as ``compare`` uses).

    Returns
    -------
    ParameterChange
        ``delta = after.mean - before.mean``, its standard error, 90 % Welch-Satterthwaite
        t interval and ``P(|delta| > tolerance)``.
    """
    d = after.mean - before.mean
    va, vb = before.stderr**2, after.stderr**2
    se = math.sqrt(va + vb)
    terms = sum(var**2 / g.df for var, g in ((va, before), (vb, after)) if math.isfinite(g.df))
    df = (va + vb) ** 2 / terms if terms > 0 else math.inf
    dist = stats.norm if not math.isfinite(df) else stats.t(df)
    tol = practical_tolerance(name, before.mean, tolerance)
    if se > 0:
        half = float(dist.ppf(0.5 + LEVEL / 2)) * se
        p = float(dist.cdf((d - tol) / se) + dist.cdf((-d - tol) / se))
        lo, hi, sd = d - half, d + half, se
    else:
        p, lo, hi, sd = None, None, None, None
    return ParameterChange(name, before.mean, after.mean, d, sd, lo, hi, tol, p)


@dataclass(frozen=True)
class Trend:
    """A parameter's linear trend against a covariate (time, cycle number ...), from
    per-trace estimates: the random-effects meta-regression ``y_i = beta0 + beta1 x_i +
    u_i + e_i`` (``u_i ~ N(0, tau^2)`` the scatter about the line beyond the measurement
    errors, ``e_i ~ N(0, s_i^2)``).

    Attributes
    ----------
    n
        Traces used.
    slope, slope_low90, slope_high90
        ``beta1`` (parameter unit per covariate unit) and its 90 % interval (Knapp-Hartung
        t interval with ``n - 2`` degrees of freedom).
    x_first, x_last
        The covariate's range.
    change
        The drift over that range, ``beta1 (x_last - x_first)``, as a change from the
        line's value at ``x_first`` to its value at ``x_last``, with its 90 % interval,
        practical tolerance and ``P(|drift| > tolerance)`` (:class:`ParameterChange`;
        ``changed``: a trend, decided as ``compare`` decides a change).
    tau
        The scatter about the line beyond the measurement errors (method of moments).
    """

    n: int
    slope: float
    slope_stderr: float
    slope_low90: float
    slope_high90: float
    df: float
    x_first: float
    x_last: float
    change: ParameterChange
    tau: float


def trend(
    name: str,
    x: Sequence[float],
    estimates: Sequence[float],
    stderrs: Sequence[float],
    tolerance: Mapping[str, float] | None = None,
) -> Trend | None:
    """Fit a parameter's linear trend against ``x`` (see :class:`Trend`).

    ``tau^2`` by the method of moments of the meta-regression's residual Q (the
    DerSimonian-Laird estimator with a covariate); the coefficients by weighted least
    squares with weights ``1 / (s_i^2 + tau^2)``; their covariance scaled by the
    Knapp-Hartung factor ``max(1, Q* / (k - 2))`` with a t interval on ``k - 2`` degrees
    of freedom. Pairs with a missing or non-positive standard error are left out;
    ``None`` with fewer than three usable traces or a single value of ``x``.
    """
    xs = np.asarray(x, dtype=float)
    y = np.asarray(estimates, dtype=float)
    s = np.asarray([np.nan if e is None else e for e in stderrs], dtype=float)
    keep = np.isfinite(xs) & np.isfinite(y) & np.isfinite(s) & (s > 0)
    xs, y, v = xs[keep], y[keep], s[keep] ** 2
    k = int(y.size)
    if k < 3 or np.ptp(xs) == 0:
        return None
    x0 = float(np.min(xs))
    X = np.column_stack([np.ones(k), xs - x0])

    def wls(w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        cov = np.linalg.inv(X.T @ (w[:, None] * X))
        beta = cov @ (X.T @ (w * y))
        return beta, cov, float(np.sum(w * (y - X @ beta) ** 2))

    w = 1.0 / v
    _, cov_fixed, q = wls(w)
    # trace(P), P = W - W X (X'WX)^-1 X'W
    trace_p = float(np.sum(w) - np.trace(cov_fixed @ (X.T @ (w[:, None] ** 2 * X))))
    tau2 = max(0.0, (q - (k - 2)) / trace_p) if trace_p > 0 else 0.0
    beta, cov, q_star = wls(1.0 / (v + tau2))
    cov = cov * max(1.0, q_star / (k - 2))
    df = float(k - 2)
    t = float(stats.t.ppf(0.5 + LEVEL / 2, df))
    slope, se = float(beta[1]), math.sqrt(float(cov[1, 1]))
    x1 = float(np.max(xs))
    span = x1 - x0
    start = float(beta[0])
    drift, drift_se = slope * span, se * span
    tol = practical_tolerance(name, start, tolerance)
    dist = stats.t(df)
    p = float(dist.cdf((drift - tol) / drift_se) + dist.cdf((-drift - tol) / drift_se))
    change = ParameterChange(name, start, start + drift, drift, drift_se, drift - t * drift_se,
                             drift + t * drift_se, tol, p)
    return Trend(k, slope, se, slope - t * se, slope + t * se, df, x0, x1, change,
                 math.sqrt(tau2))
