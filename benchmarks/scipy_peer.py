"""The peer: the same whole-chain fit written the way a Python user writes it today.

SciPy ``solve_ivp`` (LSODA) integrates the motor with the logged voltage as a step
function; ``least_squares`` (trust-region reflective, 2-point finite differences) fits
the same free parameters, in the same log/affine coordinates, from the same start, with
the same per-channel weights as ewb-ident. Run as a script it fits one trace file and
prints the parameters (used by ``bench_fit.py`` for the cold, separate-process timing).

Integration settings: rtol 1e-8, atol 1e-10, ``max_step`` one sample interval (so the
solver does not step across a voltage change unseen). Looser tolerances make the
finite-difference Jacobian noise, and the fit stalls.
"""

from __future__ import annotations

import json
import sys

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

NOMINAL = dict(
    R=1.0,
    L=2.0e-3,
    kb=0.1,
    kT=0.1,
    M=2.0e-4,
    v=2.0e-3,
    p2=3.8e-9,
    p1=1.5e-6,
    p0=-8.4e-4,
    F_rt=3500.0,
    a=6.295e-4,
    b=2.82,
    c=9.57e-4,
    mu=0.35,
    theta0_deg=0.0,
)
LOG = {"R", "L", "kb", "kT", "M", "v", "F_rt", "a", "b"}
AFFINE_SCALE = {"p2": 1e-10, "p1": 1e-7, "p0": 1e-5, "c": 1e-4, "theta0_deg": 1.0}


#: The parameters ewb-ident varies by default on a trace with every channel recorded.
FREE = ["R", "L", "kb", "M", "v", "theta0_deg", "p2", "p1", "p0", "F_rt", "a", "b", "c", "mu"]


def to_physical(name, u):
    if name in LOG:
        return NOMINAL[name] * np.exp(u)
    if name == "mu":
        return 1.0 / (1.0 + np.exp(-u))
    return NOMINAL[name] + AFFINE_SCALE[name] * u


def to_u(name, p):
    if name in LOG:
        return np.log(p / NOMINAL[name])
    if name == "mu":
        return np.log(p) - np.log1p(-p)
    return (p - NOMINAL[name]) / AFFINE_SCALE[name]


def simulate(p, t, V, r_eff):
    """Whole chain from voltage: current, theta (deg), x, force, torque at times t."""
    dt = t[1] - t[0]

    def rhs(tt, s):
        k = min(int((tt - t[0]) / dt + 1e-9), len(V) - 1)
        i, w, _ = s
        di = (V[k] - p["R"] * i - p["kb"] * w) / p["L"]
        dw = (p["kT"] * i - p["v"] * w) / p["M"]
        return [di, dw, w]

    s0 = [0.0, 0.0, np.deg2rad(p["theta0_deg"])]
    sol = solve_ivp(
        rhs, (t[0], t[-1]), s0, method="LSODA", t_eval=t, rtol=1e-8, atol=1e-10, max_step=dt
    )
    theta = np.rad2deg(sol.y[2])
    x = p["p2"] * theta**2 + p["p1"] * theta + p["p0"]
    F = p["F_rt"] / (1.0 + np.abs((x - p["c"]) / p["a"]) ** (2 * p["b"]))
    return {
        "current_A": sol.y[0],
        "theta_deg": theta,
        "x_m": x,
        "force_N": F,
        "torque_Nm": 2 * p["mu"] * F * r_eff,
    }


def fit(t, V, measured, sigma, free, start, r_eff=0.15, fixed=None):
    """Weighted least squares of the whole chain; returns (params, scipy result)."""
    base = dict(NOMINAL) | dict(fixed or {})

    def params(u):
        return base | {n: to_physical(n, u[j]) for j, n in enumerate(free)}

    def residuals(u):
        sim = simulate(params(u), t, V, r_eff)
        return np.concatenate([(sim[c] - measured[c]) / sigma[c] for c in measured])

    u0 = np.array([to_u(n, start.get(n, base[n])) for n in free])
    res = least_squares(
        residuals,
        u0,
        method="trf",
        diff_step=1e-7,
        x_scale=1.0,
        xtol=1e-10,
        ftol=1e-10,
        gtol=1e-10,
        max_nfev=2000,
    )
    return params(res.x), res


def main(path: str, problem: str | None = None) -> None:
    """Fit the trace at ``path``. With ``problem`` (a JSON file: ``start``, ``sigma``,
    ``free``, ``fixed``, ``r_eff``), from those start values with those weights, as the
    benchmark's warm comparison does; without, every channel's noise from second
    differences and the seed values as the start."""
    import pandas as pd

    df = pd.read_csv(path)
    t = df["time_s"].to_numpy()
    chans = [c for c in ("theta_deg", "x_m", "force_N", "torque_Nm", "current_A") if c in df]
    measured = {c: df[c].to_numpy() for c in chans}
    if problem:
        spec = json.loads(open(problem).read())
        sigma, free, start = spec["sigma"], spec["free"], spec["start"]
        fixed, r_eff = spec["fixed"], spec["r_eff"]
    else:
        sigma = {c: np.std(np.diff(measured[c], 2)) / np.sqrt(6) for c in chans}
        free, start, fixed, r_eff = FREE, {"theta0_deg": float(measured["theta_deg"][0])}, {}, 0.15
    p, res = fit(t, df["voltage_V"].to_numpy(), measured, sigma, free, start, r_eff, fixed)
    print(json.dumps({"params": {n: p[n] for n in free}, "nfev": res.nfev, "status": res.status}))


if __name__ == "__main__":
    main(*sys.argv[1:3])
