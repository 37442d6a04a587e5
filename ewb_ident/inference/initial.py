"""Start values from the data alone: closed forms and small grids, no seed values needed.

A local solver (Levenberg-Marquardt) finds the optimum of the valley it starts in. The
chain's cost has other valleys: the flat bell (``b -> 0``, force stuck at ``F_rt/2``)
catches a fit whose simulated angle is still far from the measured one, because
flattening the bell is the cheapest way to reduce a force error caused by timing. So
every link is first placed in its own valley from its measured input and output:

* the **motor** as a first-order lag plus integrator, ``theta = theta0 + K * (lag of V)``:
  for each time constant ``tau`` on a log grid the angle is linear in ``(theta0, K)``,
  so each grid point is a linear least-squares problem (exact zero-order-hold
  discretisation, no derivatives of noisy data). ``K`` (rad/s per V) and ``tau`` (s)
  then give ``M`` and ``v`` for the fixed ``R, kT, kb``; with current, ``R`` and ``kb``
  come from ``V = R i + kb omega`` first.
* the **bell** from ``log(F_rt / F - 1) = 2 b log|x - c| - 2 b log a``: for each
  candidate ``(F_rt, c)`` a straight-line fit gives ``b`` and ``a``; the candidate with
  the smallest force error wins. Candidates span the measured range, not the seed's.

These are starts, not answers: the least-squares fits refine them.
"""

from __future__ import annotations

import numpy as np

from ewb_ident.data.metrics import ar1_filter

DEG_PER_RAD = 180.0 / np.pi


def _lag_speed(V: np.ndarray, dt: float, tau) -> np.ndarray:
    """Speed at the sample times of a unit-gain first-order lag ``tau`` driven from rest
    by ``V`` under zero-order hold (exact): ``w[k+1] = q w[k] + (1 - q) V[k]``. Several
    ``tau`` (a 1-D array) give one row each."""
    q = np.exp(-dt / np.asarray(tau, float))[..., None]
    w = ar1_filter((1.0 - q) * np.asarray(V, float), q)
    return np.concatenate([np.zeros((*w.shape[:-1], 1)), w[..., :-1]], axis=-1)


def motor_lag(voltage_V: np.ndarray, theta_deg: np.ndarray, dt: float) -> dict[str, float]:
    """First-order-lag-plus-integrator fit of voltage -> angle.

    Model: ``d omega/dt = (K V - omega) / tau``, ``d theta/dt = omega``, from rest.

    Parameters
    ----------
    voltage_V
        Logged voltage (zero-order hold), V.
    theta_deg
        Measured pinion angle, degrees.
    dt
        Sample interval, s.

    Returns
    -------
    dict with ``K`` (rad/s per V), ``tau`` (s), ``theta0_deg`` and ``rms_deg`` (the
    residual of the best grid point).
    """
    V = np.asarray(voltage_V, float)
    th = np.asarray(theta_deg, float)
    best = None
    taus = np.geomspace(2e-3, 1.0, 48)
    speeds = _lag_speed(V, dt, taus)  # omega with K = 1, one row per tau
    for tau, w in zip(taus, speeds, strict=True):
        q = np.exp(-dt / tau)
        # theta increment over [t_k, t_k+1): tau (1 - q) w_k + (dt - tau (1 - q)) V_k
        inc = tau * (1.0 - q) * w + (dt - tau * (1.0 - q)) * V
        y = np.concatenate([[0.0], np.cumsum(inc[:-1])]) * DEG_PER_RAD
        A = np.stack([np.ones_like(y), y], axis=1)
        coef, *_ = np.linalg.lstsq(A, th, rcond=None)
        r = th - A @ coef
        sse = float(r @ r)
        if best is None or sse < best[0]:
            best = (sse, float(tau), float(coef[0]), float(coef[1]))
    sse, tau, theta0, K = best
    return {"K": K, "tau": tau, "theta0_deg": theta0, "rms_deg": float(np.sqrt(sse / th.size))}


def motor_start(
    voltage_V: np.ndarray,
    theta_deg: np.ndarray,
    dt: float,
    base: dict[str, float],
    current_A: np.ndarray | None = None,
) -> dict[str, float]:
    """Start values of the motor parameters from voltage, angle and (optional) current.

    ``kT`` is never changed (without a load-torque sensor only ratios to it are
    identified). Without current, ``R``, ``L`` and ``v`` keep their ``base`` values and
    ``kb``, ``M`` carry the two identified combinations.

    Returns
    -------
    dict of SI values for ``R``, ``kb``, ``M``, ``v`` and ``theta0_deg``.
    """
    lag = motor_lag(voltage_V, theta_deg, dt)
    K, tau = abs(lag["K"]), lag["tau"]
    K = max(K, 1e-6)
    R, kT, kb = base["R"], base["kT"], base["kb"]
    if current_A is not None:
        # V = R i + kb omega (+ L di/dt, small between switching instants): a linear fit
        # with omega from the lag model (smooth, unlike a derivative of the angle).
        omega = lag["K"] * _lag_speed(np.asarray(voltage_V, float), dt, tau)
        A = np.stack([np.asarray(current_A, float), omega], axis=1)
        coef, *_ = np.linalg.lstsq(A, np.asarray(voltage_V, float), rcond=None)
        if coef[0] > 0:
            R = float(coef[0])
        if coef[1] > 0:
            kb = float(coef[1])
    # Damping D = R v + kT kb = kT / K, inertia M = tau D / R. Without current, v is
    # held (base) and kb carries the rest of the damping; with current, kb was measured
    # and v carries the rest.
    damping = kT / K
    if current_A is None:
        v = base["v"]
        kb = max(damping - R * v, 0.05 * damping) / kT
    else:
        kb = min(kb, 0.9 * damping / kT)
        v = (damping - kT * kb) / R
    M = tau * damping / R
    return {"R": R, "kb": kb, "M": M, "v": v, "theta0_deg": lag["theta0_deg"]}


def bell_start(x_m: np.ndarray, force_N: np.ndarray) -> dict[str, float]:
    """Start values of the bell ``F = F_rt / (1 + |(x - c)/a|^(2b))`` from x and force.

    Parameters
    ----------
    x_m
        Piston displacement, m (measured, or from the measured angle).
    force_N
        Clamping force, N.

    Returns
    -------
    dict with ``F_rt`` (N), ``a`` (m), ``b`` (-), ``c`` (m).
    """
    x = np.asarray(x_m, float)
    F = np.asarray(force_N, float)
    f_top = float(np.percentile(F, 99.5))
    if not f_top > 0:
        raise ValueError("the force never rises above zero")
    x_top = float(np.median(x[F >= 0.98 * f_top]))
    flank = x[(F > 0.05 * f_top) & (F < 0.95 * f_top)]
    span = float(np.ptp(flank)) if flank.size > 2 else float(np.ptp(x)) / 4
    span = max(span, 1e-6)
    best = None
    cs = x_top + span * np.linspace(-0.3, 3.0, 34)
    for f_rt in f_top * np.array([1.0, 1.02, 1.06, 1.15, 1.3, 1.6, 2.0, 3.0]):
        use = (F > 0.03 * f_rt) & (F < 0.97 * f_rt)
        if use.sum() < 5:
            continue
        y = np.log(f_rt / F[use] - 1.0)
        # A straight line y = slope log|x - c| + icpt for every candidate c at once, by
        # least squares over the points not at c itself (one row per c).
        d = np.abs(x[use][None, :] - cs[:, None])
        ok = d > 1e-3 * span
        X = np.log(np.where(ok, d, 1.0))
        m = ok.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            xm = np.where(ok, X, 0.0).sum(axis=1) / m
            ym = np.where(ok, y[None, :], 0.0).sum(axis=1) / m
            dx = np.where(ok, X - xm[:, None], 0.0)
            slope = (dx * (y[None, :] - ym[:, None])).sum(axis=1) / (dx * dx).sum(axis=1)
        icpt = ym - slope * xm
        for j in np.flatnonzero((m >= 5) & (slope > 0.2)):
            b, a = slope[j] / 2.0, float(np.exp(-icpt[j] / slope[j]))
            pred = f_rt / (1.0 + np.abs((x - cs[j]) / a) ** (2 * b))
            sse = float(np.sum((pred - F) ** 2))
            if np.isfinite(sse) and (best is None or sse < best[0]):
                best = (sse, {"F_rt": float(f_rt), "a": a, "b": float(b), "c": float(cs[j])})
    if best is None:
        raise ValueError("no bell fits the force's rising flank")
    return best[1]
