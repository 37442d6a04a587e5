"""Independent EWB rig simulator with physics that is *not* in the identification tool's catalog.

Each case is one recording in the trace format v1 (``/work/shared/TRACE_FORMAT.md``) of a
varied rig unit with exactly one planted "uncatalogued" effect (14 families, two forms
each) or, for family ``"clean"``, none (optionally with a nuisance such as mains hum).
The module was written from the physics description only; it shares no code with the
identification package.

Base rig (clean model)
----------------------
* DC motor with a zero-order-hold voltage: ``V = L di/dt + R i + kb w``,
  ``M dw/dt + v w = kT i - tau`` (angle in rad inside the ODE).  The linear part is
  discretised exactly (matrix exponential); the planted nonlinear voltage / torque terms
  enter through an exponential-time-differencing predictor-corrector (ETD2) on sub-steps
  of at most ``H_MAX`` = 0.1 ms.  Without a motor effect the clean motor is stepped with
  the exact sample-interval transition.
* Gap ``x = p2 theta^2 + p1 theta + p0`` [m] (theta in deg); bell
  ``F = F_rt / (1 + |(x - c)/a|^(2 b))`` [N]; torque ``T = 2 mu F r_eff`` [N m].

Effect sizes
------------
Each family/form has a strength ``s`` to which the effect is (about) proportional.  It is
drawn log-uniformly in a range calibrated per loop class (open-loop steps vs closed
loop; ``_SIZE``) so that the *visibility* (max over the noisy recorded channels of
RMS(noise-free with effect - noise-free twin) / sigma) lands in about 4-15.  Rescale
rule (at most 12 runs): if the visibility is below 3.5, ``s`` is multiplied by
``4.5 / vis`` (at most 50); if the force or torque relative RMS change is 5 % or more,
``s`` is multiplied by ``4 / pct``; once both an invisible and an unconcealed strength are
known, the next ``s`` is their geometric mean (bisection, for threshold-like effects).
The drawn and final strengths and every attempt are in the truth (``rescales``).
For closed-loop drives the twin has the same reference and the same noise (the
controller reacts to the effect).

Command line
------------
``python -m validation_rigs.uncatalogued_rig --seed S --per-form N --out DIR [--check]``
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.linalg import expm
from scipy.signal import lfilter

NOMINAL: dict[str, float] = {
    "R": 1.0,  # ohm
    "L": 2.0e-3,  # H
    "kb": 0.10,  # V s/rad
    "kT": 0.10,  # N m/A
    "M": 3.0e-5,  # kg m^2
    "v": 1.0e-4,  # N m s/rad
    "p2": 3.8e-9,  # m/deg^2
    "p1": 1.5e-6,  # m/deg
    "p0": -8.4e-4,  # m
    "F_rt": 3500.0,  # N
    "a": 6.295e-4,  # m
    "c": 9.57e-4,  # m
    "b": 2.82,  # -
    "mu": 0.35,  # -
}
R_EFF_M: tuple[float, ...] = (0.10, 0.12, 0.15, 0.20, 0.25)
RATES_HZ: tuple[int, ...] = (100, 200, 500, 1000)
PROFILES: tuple[str, ...] = ("steps", "pi", "staircase")
NUISANCES: tuple[str, ...] = ("hum", "quantised", "pi_loop", "long", "slow_log")
COLUMNS: tuple[str, ...] = (
    "time_s", "voltage_V", "current_A", "theta_deg", "x_m", "force_N", "torque_Nm",
    "disc_speed_rad_s",
)
#: Base noise standard deviations (multiplied per case by a factor 0.5-2); torque scales
#: with r_eff / 0.15.  The disc speed gets a small noise of its own.
NOISE_BASE: dict[str, float] = {
    "theta_deg": 0.05, "x_m": 1e-6, "force_N": 5.0, "torque_Nm": 0.5, "current_A": 0.02,
    "disc_speed_rad_s": 0.05,
}
VIS_CHANNELS: tuple[str, ...] = ("current_A", "theta_deg", "x_m", "force_N", "torque_Nm")
H_MAX = 1.0e-4  # s, largest motor sub-step
V_SAT = 12.0  # V, closed-loop saturation
DEG = math.pi / 180.0
_K_NOM = NOMINAL["kT"] / (NOMINAL["kT"] * NOMINAL["kb"] + NOMINAL["R"] * NOMINAL["v"]) / DEG
_TAU_NOM = NOMINAL["R"] * NOMINAL["M"] / (NOMINAL["kT"] * NOMINAL["kb"]
                                         + NOMINAL["R"] * NOMINAL["v"])  # s, speed lag

_MOT = "motor"
FAMILIES: dict[str, dict] = {
    "magnetic_saturation": {
        "stage": _MOT, "place": "motor.mechanical",
        "depends_on": {"a": ["current"], "b": ["current"]},
        "words": "torque constant falls with |i|: a kT/(1+(i/i_s)^2), b kT(1-k|i|) >= 0.3 kT",
    },
    "armature_heating": {
        "stage": _MOT, "place": "motor.electrical",
        "depends_on": {"a": ["heat"], "b": ["heat"]},
        "words": "R = R0 (1 + h), tau_th dh/dt = g i^2 R - h (h <= 1); tau_th a 0.5 s, b 5 s",
    },
    "supply_sag": {
        "stage": _MOT, "place": "motor.electrical",
        "depends_on": {"a": ["current"], "b": ["current"]},
        "words": "a V - R_s i (source resistance); b sign(V) min(|V|, V_max - R_s i_load), "
        "i_load = max(sign(V) i, 0), V_max = max(|V| + q R_s i_load) of the no-effect "
        "run, q 0-0.3 (sags only under load)",
    },
    "brush_drop": {
        "stage": _MOT, "place": "motor.electrical",
        "depends_on": {"a": ["direction"], "b": ["direction", "current"]},
        "words": "brush voltage drop V_b against the current: a sharp (tanh(i/0.05 A)), "
        "b soft tanh(i/i0)",
    },
    "cogging": {
        "stage": _MOT, "place": "motor.mechanical",
        "depends_on": {"a": ["angle"], "b": ["angle", "force"]},
        "words": "periodic load torque A sin(2 pi theta/P + phi); a P 60 deg, "
        "b P 45 deg and A = A0 (1 + 3 F/F_rt)",
    },
    "quadratic_drag": {
        "stage": _MOT, "place": "motor.mechanical",
        "depends_on": {"a": ["speed"], "b": ["speed"]},
        "words": "speed-dependent load torque: a c w|w|, b c w^3",
    },
    "drive_compliance": {
        "stage": "gap", "place": "drive",
        "depends_on": {"a": ["force"], "b": ["force"]},
        "words": "piston lags the wedge by the drive compression: a F/k, "
        "b x0 ln(1 + F/F0) (stiffening); implicit x-F loop solved per sample",
    },
    "caliper_damping": {
        "stage": "force", "place": "force.output",
        "depends_on": {"a": ["x_rate"], "b": ["x_rate", "force"]},
        "words": "rate-dependent clamping force: a bell + c_d dx/dt (F >= 0), "
        "b bell (1 + beta dx/dt / xdot_ref)",
    },
    "pad_creep": {
        "stage": "force", "place": "force.output",
        "depends_on": {"a": ["force", "time"], "b": ["force", "time"]},
        "words": "viscoelastic pad relaxation F = bell - z, tau_c dz/dt = kappa bell - z "
        "(F >= 0); tau_c a 0.3 s, b 1.0 s",
    },
    "thermal_expansion": {
        "stage": "force", "place": "force.input",
        "depends_on": {"a": ["energy"], "b": ["time"]},
        "words": "piston grows by delta, F = bell(x + delta): a delta = alpha E "
        "(E = int T w_disc dt), b delta = beta t",
    },
    "mu_pressure": {
        "stage": "torque", "place": "friction",
        "depends_on": {"a": ["force"], "b": ["force"]},
        "words": "friction falls with pressure: a mu0 (1 - k F/F_rt), "
        "b mu0 (max(F, F_min)/F_ref)^-n",
    },
    "load_cell_nonlinearity": {
        "stage": "force", "place": "sensor.force_N",
        "depends_on": {"a": ["force"], "b": ["force"]},
        "words": "force reading F + k F^2/F_rt (a) or F + k F^3/F_rt^2 (b)",
    },
    "sensor_lowpass": {
        "stage": "torque", "place": "sensor.torque_Nm",
        "depends_on": {"a": ["force_rate"], "b": ["force_rate"]},
        "words": "torque reading low-passed (error ~ -tau dT/dt): a first order, "
        "b critically damped second order (two stages of tau/2)",
    },
    "lvdt_nonlinearity": {
        "stage": "gap", "place": "sensor.x_m",
        "depends_on": {"a": ["x"], "b": ["x"]},
        "words": "LVDT reading x + k (x - x_mid)^3 (a) or x (1 + g x/x_ref) (b)",
    },
}
for _f in FAMILIES.values():
    _f["forms"] = ("a", "b")

#: Strength ranges (lo, hi) per (family, form) for open-loop steps ("open") and closed
#: loop ("closed"), with the meaning of the strength.  Calibrated with pilot runs.
_SIZE: dict[tuple[str, str], dict] = {
    ("magnetic_saturation", "a"): {"open": (0.02, 0.048), "closed": (1.4, 3.4),
        "unit": "1/i_s^2 [1/A^2]"},
    ("magnetic_saturation", "b"): {"open": (0.045, 0.11), "closed": (0.67, 1.6),
        "unit": "k [1/A]"},
    ("armature_heating", "a"): {"open": (0.82, 2), "closed": (8.6, 21),
        "unit": "g [1/W]"},
    ("armature_heating", "b"): {"open": (3, 7.2), "closed": (82, 200),
        "unit": "g [1/W]"},
    ("supply_sag", "a"): {"open": (0.054, 0.13), "closed": (0.21, 0.51),
        "unit": "R_s [ohm]"},
    ("supply_sag", "b"): {"open": (0.051, 0.12), "closed": (42, 100),
        "unit": "R_s [ohm]"},
    ("brush_drop", "a"): {"open": (0.0053, 0.013), "closed": (0.036, 0.087),
        "unit": "V_b [V]"},
    ("brush_drop", "b"): {"open": (0.028, 0.068), "closed": (0.081, 0.19),
        "unit": "V_b [V]"},
    ("cogging", "a"): {"open": (0.00013, 0.00032), "closed": (0.0034, 0.0081),
        "unit": "A [N m]"},
    ("cogging", "b"): {"open": (5.4e-05, 0.00013), "closed": (0.0018, 0.0044),
        "unit": "A0 [N m]"},
    ("quadratic_drag", "a"): {"open": (0.0005, 0.0012), "closed": (0.0064, 0.015),
        "unit": "torque at 40 rad/s [N m]"},
    ("quadratic_drag", "b"): {"open": (0.00029, 0.00069), "closed": (0.0031, 0.0074),
        "unit": "torque at 40 rad/s [N m]"},
    ("drive_compliance", "a"): {"open": (7.6e-06, 1.8e-05), "closed": (8.1e-06, 1.9e-05),
        "unit": "F_rt/k [m]"},
    ("drive_compliance", "b"): {"open": (9e-06, 2.2e-05), "closed": (8.1e-06, 1.9e-05),
        "unit": "compression at F_rt [m]"},
    ("caliper_damping", "a"): {"open": (74, 180), "closed": (91, 220),
        "unit": "c_d * 0.01 m/s [N]"},
    ("caliper_damping", "b"): {"open": (0.055, 0.13), "closed": (0.077, 0.18),
        "unit": "beta [-]"},
    ("pad_creep", "a"): {"open": (0.031, 0.073), "closed": (0.028, 0.067),
        "unit": "kappa [-]"},
    ("pad_creep", "b"): {"open": (0.034, 0.082), "closed": (0.028, 0.066),
        "unit": "kappa [-]"},
    ("thermal_expansion", "a"): {"open": (1e-05, 2.5e-05), "closed": (1e-05, 2.4e-05),
        "unit": "alpha*1e4 J [m]"},
    ("thermal_expansion", "b"): {"open": (3.1e-06, 7.4e-06), "closed": (2.7e-06, 6.5e-06),
        "unit": "beta [m/s]"},
    ("mu_pressure", "a"): {"open": (0.021, 0.05), "closed": (0.018, 0.044),
        "unit": "k [-]"},
    ("mu_pressure", "b"): {"open": (0.036, 0.086), "closed": (0.038, 0.092),
        "unit": "n [-]"},
    ("load_cell_nonlinearity", "a"): {"open": (0.02, 0.048), "closed": (0.017, 0.042),
        "unit": "k [-]"},
    ("load_cell_nonlinearity", "b"): {"open": (0.03, 0.073), "closed": (0.031, 0.074),
        "unit": "k [-]"},
    ("sensor_lowpass", "a"): {"open": (0.002, 0.006), "closed": (0.002, 0.006),
        "unit": "tau [s]"},
    ("sensor_lowpass", "b"): {"open": (0.002, 0.006), "closed": (0.002, 0.006),
        "unit": "tau [s]"},
    ("lvdt_nonlinearity", "a"): {"open": (1.9e-05, 4.5e-05), "closed": (2.2e-05, 5.2e-05),
        "unit": "error at 1 mm [m]"},
    ("lvdt_nonlinearity", "b"): {"open": (1.5e-05, 3.7e-05), "closed": (1.7e-05, 4.1e-05),
        "unit": "error at 1 mm [m]"},
}


# ------------------------------------------------------------------------------------------
# Static chain
# ------------------------------------------------------------------------------------------


def gap_m(theta_deg, p: dict):
    """Piston gap ``x = p2 theta^2 + p1 theta + p0`` [m] from the pinion angle [deg]."""
    return p["p2"] * theta_deg**2 + p["p1"] * theta_deg + p["p0"]


def theta_for_gap(x_m, p: dict):
    """Pinion angle [deg] on the rising branch of the gap polynomial for a gap ``x_m`` [m]."""
    d = np.asarray(x_m, dtype=float) - p["p0"]
    return 2.0 * d / (p["p1"] + np.sqrt(np.maximum(p["p1"] ** 2 + 4.0 * p["p2"] * d, 0.0)))


def bell(x_m, p: dict):
    """Clamping force ``F_rt / (1 + |(x - c)/a|^(2b))`` [N] at the gap ``x_m`` [m]."""
    u = np.abs((np.asarray(x_m, dtype=float) - p["c"]) / p["a"])
    return p["F_rt"] / (1.0 + u ** (2.0 * p["b"]))


def dbell_dx(x_m, p: dict):
    """Derivative of ``bell`` with respect to the gap [N/m]."""
    u = (np.asarray(x_m, dtype=float) - p["c"]) / p["a"]
    n = 2.0 * p["b"]
    au = np.abs(u)
    return -p["F_rt"] * n * au ** (n - 1.0) * np.sign(u) / p["a"] / (1.0 + au**n) ** 2


def theta_for_force(frac: float, p: dict) -> float:
    """Pinion angle [deg] at which the bell gives ``frac * F_rt`` on the rising flank."""
    x = p["c"] - p["a"] * (1.0 / min(max(frac, 1e-9), 1.0) - 1.0) ** (0.5 / p["b"])
    return float(theta_for_gap(x, p))


def lag_foh(u: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """First-order lag ``tau dy/dt = u - y`` of a piecewise-linear input, exact per sample.

    Parameters
    ----------
    u : ndarray
        Input samples (any unit).
    tau, dt : float
        Time constant and sample interval [s].

    Returns
    -------
    ndarray
        Output samples (unit of ``u``), starting in steady state ``y[0] = u[0]``.
    """
    a = math.exp(-dt / tau)
    c = tau * (1.0 - a) / dt
    y, _ = lfilter([1.0 - c, c - a], [1.0, -a], u, zi=[u[0] * a])
    return y


# ------------------------------------------------------------------------------------------
# Motor
# ------------------------------------------------------------------------------------------


def motor_coeffs(p: dict, h: float) -> tuple[float, ...]:
    """ETD2 coefficients of the motor over a step ``h`` [s].

    The state is ``[i (A), w (rad/s), theta (rad)]`` and the inputs are the electrical
    voltage ``we`` [V] (into ``L di/dt``) and the mechanical torque ``wm`` [N m] (into
    ``M dw/dt``).  For inputs linear in time over the step, ``z(h) = Phi z + G0 w0 +
    G1 (w1 - w0)`` exactly.  Returns the 18 non-trivial entries
    ``(Phi[0:3, 0:2], G0, G1)`` flattened row by row.
    """
    m7 = np.zeros((7, 7))
    m7[:3, :3] = [
        [-p["R"] / p["L"], -p["kb"] / p["L"], 0.0],
        [p["kT"] / p["M"], -p["v"] / p["M"], 0.0],
        [0.0, 1.0, 0.0],
    ]
    m7[0, 3] = 1.0 / p["L"]
    m7[1, 4] = 1.0 / p["M"]
    m7[3, 5] = m7[4, 6] = 1.0 / h
    ex = expm(m7 * h)
    return tuple(float(v) for v in np.concatenate(
        [ex[:3, :2].ravel(), ex[:3, 3:5].ravel(), ex[:3, 5:7].ravel()]
    ))


class MotorEffect:
    """Nonlinear motor term of one family: ``f(i, w, th, V) -> (dV_removed [V], tau [N m])``.

    Parameters
    ----------
    family, form : str
        Family (one of the six motor families) and form ``"a"``/``"b"``.
    prm : dict
        Effect parameters (see ``effect_params``).
    p : dict
        Rig parameters.
    """

    def __init__(self, family: str, form: str, prm: dict, p: dict):
        self.h = 0.0  # heating state: fractional resistance rise [-]
        self.advance = None
        self.stiff = False  # voltage term solved implicitly in the current
        kT, r0 = p["kT"], p["R"]
        if family == "magnetic_saturation":
            if form == "a":
                s = prm["inv_is2"]
                self.f = lambda i, w, th, V: (0.0, kT * i * (1.0 - 1.0 / (1.0 + s * i * i)))
            else:
                k = prm["k"]
                self.f = lambda i, w, th, V: (0.0, kT * i * (1.0 - max(1.0 - k * abs(i), 0.3)))
        elif family == "armature_heating":
            g, e_tau = prm["g"], prm["tau_th"]

            def adv(i: float, hstep: float) -> None:
                target = g * i * i * r0 * (1.0 + self.h)
                self.h = min(target + (self.h - target) * math.exp(-hstep / e_tau), 1.0)

            self.advance = adv
            self.f = lambda i, w, th, V: (r0 * self.h * i, 0.0)
        elif family == "supply_sag":
            rs = prm["R_s"]
            if form == "a":
                self.f = lambda i, w, th, V: (rs * i, 0.0)
            else:  # ceiling sags with the current drawn from the supply
                vmax = prm["V_max"]
                self.stiff = True
                self.f = lambda i, w, th, V: (V - math.copysign(
                    min(abs(V), max(vmax - rs * max(math.copysign(i, V) if V else 0.0, 0.0),
                                    0.0)), V), 0.0)
        elif family == "brush_drop":
            vb, i0 = prm["V_b"], prm["i0"]
            self.f = lambda i, w, th, V: (vb * math.tanh(i / i0), 0.0)
        elif family == "cogging":
            amp, per, ph, gain = prm["A0"], prm["P_deg"], prm["phi"], prm["force_gain"]
            cc, aa, bb = p["c"], p["a"], 2.0 * p["b"]
            p2, p1, p0 = p["p2"], p["p1"], p["p0"]
            kk = 2.0 * math.pi / per / DEG  # per rad

            def cog(i, w, th, V):
                a_eff = amp
                if gain:
                    td = th / DEG
                    u = abs((p2 * td * td + p1 * td + p0 - cc) / aa)
                    a_eff = amp * (1.0 + gain / (1.0 + u**bb))
                return 0.0, a_eff * math.sin(kk * th + ph)

            self.f = cog
        elif family == "quadratic_drag":
            c = prm["c"]
            if form == "a":
                self.f = lambda i, w, th, V: (0.0, c * w * abs(w))
            else:
                self.f = lambda i, w, th, V: (0.0, c * w * w * w)
        else:
            raise ValueError(family)


def run_motor(p: dict, dt: float, n: int, theta0_deg: float, *, volts=None, ctrl=None,
              fx: MotorEffect | None = None, substeps: int | None = None) -> dict:
    """Simulate the motor (open loop or closed position loop) at the logged samples.

    Parameters
    ----------
    p : dict
        Rig parameters (SI).
    dt : float
        Sample interval [s].
    n : int
        Number of samples.
    theta0_deg : float
        Initial pinion angle [deg]; the motor starts at rest with zero current.
    volts : ndarray, optional
        Open-loop voltage held over each sample interval [V].
    ctrl : dict, optional
        Closed loop: ``ref`` [deg], ``ff`` [V] (feed-forward), ``kp`` [V/deg], ``ki``
        [V/(deg s)], ``noise`` [deg] (measurement noise the controller sees).
    fx : MotorEffect, optional
        Planted nonlinear motor term.
    substeps : int, optional
        Sub-steps per sample; default exact single step without ``fx`` and
        ``ceil(dt / H_MAX)`` with it.

    Returns
    -------
    dict
        ``V`` [V], ``i`` [A], ``w`` [rad/s], ``th`` [deg], ``dv`` (voltage removed) [V],
        ``tau`` (load torque) [N m], ``aux`` (heating state) [-] at the samples.
    """
    m = substeps or (1 if fx is None else max(1, math.ceil(dt / H_MAX - 1e-9)))
    h = dt / m
    a00, a01, a10, a11, a20, a21, g00, g01, g10, g11, g20, g21, \
        h00, h01, h10, h11, h20, h21 = motor_coeffs(p, h)
    f = fx.f if fx is not None else None
    adv = fx.advance if fx is not None else None
    out = {k: np.zeros(n) for k in ("V", "i", "w", "th", "dv", "tau", "aux")}
    o_v, o_i, o_w, o_th, o_dv, o_tq, o_aux = (out[k] for k in
                                              ("V", "i", "w", "th", "dv", "tau", "aux"))
    i = w = 0.0
    th = theta0_deg * DEG
    integ = 0.0
    if ctrl is not None:
        ref, ff, kp, ki, noise = ctrl["ref"], ctrl["ff"], ctrl["kp"], ctrl["ki"], ctrl["noise"]
    for k in range(n):
        if ctrl is None:
            volt = float(volts[k])
        else:
            e = float(ref[k]) - (th / DEG + float(noise[k]))
            integ_new = integ + ki * e * dt
            u = kp * e + integ_new + float(ff[k])
            volt = min(max(u, -V_SAT), V_SAT)
            if volt == u or (e > 0) != (u > 0):
                integ = integ_new  # conditional integration (anti-windup)
        o_v[k], o_i[k], o_w[k], o_th[k] = volt, i, w, th
        if f is None:
            for _ in range(m):
                i, w, th = (a00 * i + a01 * w + g00 * volt, a10 * i + a11 * w + g10 * volt,
                            th + a20 * i + a21 * w + g20 * volt)
            continue
        dv, tq = f(i, w, th, volt)
        o_dv[k], o_tq[k], o_aux[k] = dv, tq, fx.h
        for _ in range(m):
            we, wm = volt - dv, -tq
            ip = a00 * i + a01 * w + g00 * we + g01 * wm
            wp = a10 * i + a11 * w + g10 * we + g11 * wm
            tp = th + a20 * i + a21 * w + g20 * we + g21 * wm
            dv1, tq1 = f(ip, wp, tp, volt)
            if fx.stiff:  # implicit in i: x = ip + h00 (dv - dv(x)), Newton on a monotone r
                x = ip
                for _ in range(6):
                    d1 = f(x, wp, tp, volt)[0]
                    r = x - ip - h00 * (dv - d1)
                    slope = 1.0 + h00 * (f(x + 1e-6, wp, tp, volt)[0] - d1) / 1e-6
                    x -= r / slope
                    if abs(r) < 1e-12:
                        break
                dv1 = f(x, wp, tp, volt)[0]
            de, dm = dv - dv1, tq - tq1
            i, w, th = ip + h00 * de + h01 * dm, wp + h10 * de + h11 * dm, tp + h20 * de + h21 * dm
            if adv is not None:
                adv(i, h)
            dv, tq = f(i, w, th, volt)
    out["th"] = o_th / DEG
    return out


# ------------------------------------------------------------------------------------------
# Drive profiles
# ------------------------------------------------------------------------------------------


def _smooth(s: np.ndarray) -> np.ndarray:
    """Raised-cosine blend from 0 to 1 for ``s`` in [0, 1]."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(s, 0.0, 1.0))


class _Ref:
    """Sampled position reference [deg] built segment by segment."""

    def __init__(self, n: int, dt: float, start: float):
        self.n, self.dt, self.k, self.value = n, dt, 0, start
        self.ref = np.full(n, start)

    def hold(self, seconds: float) -> None:
        k1 = min(self.n, self.k + max(1, round(seconds / self.dt)))
        self.ref[self.k:k1] = self.value
        self.k = k1

    def ramp(self, seconds: float, target: float) -> None:
        m = min(self.n - self.k, max(2, round(seconds / self.dt)))
        s = np.arange(1, m + 1) / max(m, 1)
        self.ref[self.k:self.k + m] = self.value + (target - self.value) * _smooth(s)
        self.k += m
        self.value = target

    def fill(self) -> None:
        self.ref[self.k:] = self.value


def _split(rng: np.random.Generator, total: float, parts: int, minimum: float) -> np.ndarray:
    """Split ``total`` seconds into ``parts`` random durations of at least ``minimum`` [s]."""
    return minimum + max(total - parts * minimum, 0.0) * rng.dirichlet(np.full(parts, 2.0))


def _rest_angle(rng: np.random.Generator, p: dict) -> float:
    """Released pinion angle [deg]: gap between ``c - 3a`` and ``c - 2.2a``, at least 5 deg."""
    lo = max(float(theta_for_gap(p["c"] - 3.0 * p["a"], p)), 5.0)
    hi = max(float(theta_for_gap(p["c"] - 2.2 * p["a"], p)), lo + 1.0)
    return float(rng.uniform(lo, hi))


def _linear_end(co: tuple, z: tuple, segs: list, vx: float) -> tuple:
    """End state of the clean motor after segments ``[(V or None, samples), ...]``."""
    a00, a01, a10, a11, a20, a21, g00, _, g10, _, g20 = co[:11]
    i, w, th = z
    for volt, m in segs:
        vv = vx if volt is None else volt
        for _ in range(m):
            i, w, th = (a00 * i + a01 * w + g00 * vv, a10 * i + a11 * w + g10 * vv,
                        th + a20 * i + a21 * w + g20 * vv)
    return i, w, th


def _solve_v(co: tuple, z: tuple, segs: list, target_deg: float) -> float:
    """Voltage of the ``None`` segment so that the angle ends at ``target_deg`` (affine)."""
    e0, e1 = _linear_end(co, z, segs, 0.0)[2], _linear_end(co, z, segs, 1.0)[2]
    return (target_deg * DEG - e0) / (e1 - e0)


def plan_profile(profile: str, p: dict, rng: np.random.Generator, dt: float, n: int,
                 n_cyc: int, theta0: float) -> dict:
    """Draw a drive profile.

    Parameters
    ----------
    profile : str
        ``"steps"`` (open-loop voltage steps), ``"pi"`` (closed-loop PI on smooth
        apply/hold/release references) or ``"staircase"`` (closed-loop set-point steps).
    p : dict
        Rig parameters (SI).
    rng : numpy.random.Generator
        Randomness of the profile.
    dt : float
        Sample interval [s].
    n, n_cyc : int
        Number of samples and of apply cycles.
    theta0 : float
        Initial angle [deg].

    Returns
    -------
    dict
        ``volts`` [V] (open loop) or ``ctrl`` (see ``run_motor``), plus ``info`` (force
        fractions aimed at, voltages, gains).
    """
    fracs = list(rng.uniform(0.5, 0.95, n_cyc))
    fracs[int(rng.integers(n_cyc))] = float(rng.uniform(0.8, 0.95))
    k_rig = p["kT"] / (p["kT"] * p["kb"] + p["R"] * p["v"]) / DEG
    pre = float(rng.uniform(0.08, 0.25))
    share = (n * dt - pre) / n_cyc
    info: dict = {"target_force_fraction": [float(f) for f in fracs]}
    if profile == "steps":
        co = motor_coeffs(p, dt)
        volts = np.zeros(n)
        k = round(pre / dt)
        z = _linear_end(co, (0.0, 0.0, theta0 * DEG), [(0.0, k)], 0.0)
        info.update(apply_V=[], hold_V=[], release_V=[])
        for j in range(n_cyc):
            th_pk, rest = theta_for_force(fracs[j], p), _rest_angle(rng, p)
            va, vh, vr = rng.uniform(3.5, 5.0), rng.uniform(0.02, 0.1), -rng.uniform(3.0, 5.0)
            n_a = max(2, round((th_pk - z[2] / DEG) / (k_rig * va * dt)))
            n_r = max(2, round((th_pk - rest) / (k_rig * -vr * dt)))
            t_h, t_r = _split(rng, share - (n_a + n_r) * dt, 2, 0.12)
            n_h, n_rs = max(1, round(t_h / dt)), max(1, round(t_r / dt))
            if j == n_cyc - 1:
                n_rs = max(1, n - k - n_a - n_h - n_r)
            va = _solve_v(co, z, [(None, n_a), (vh, n_h)], th_pk)
            z = _linear_end(co, z, [(va, n_a), (vh, n_h)], 0.0)
            n_tail = min(n_rs, max(1, round(0.05 / dt)))
            vr = _solve_v(co, z, [(None, n_r), (0.0, n_tail)], rest)
            z = _linear_end(co, z, [(vr, n_r), (0.0, n_rs)], 0.0)
            seq = np.array([va] * n_a + [vh] * n_h + [vr] * n_r + [0.0] * n_rs)[: n - k]
            volts[k:k + len(seq)] = seq
            k += len(seq)
            for key, val in (("apply_V", va), ("hold_V", vh), ("release_V", vr)):
                info[key].append(float(val))
        return {"volts": volts, "info": info}
    tl = _Ref(n, dt, theta0)
    tl.hold(pre)
    t_min = 1.6 / (0.6 * _K_NOM * V_SAT)  # s per deg: raised-cosine peak speed pi/2 * mean
    for j in range(n_cyc):
        th_pk, rest = theta_for_force(fracs[j], p), _rest_angle(rng, p)
        t_dn = max(float(rng.uniform(0.12, 0.3)), t_min * (th_pk - rest))
        if profile == "pi":
            t_up = max(float(rng.uniform(0.15, 0.4)), t_min * (th_pk - tl.value))
            t_h, t_r = _split(rng, share - t_up - t_dn, 2, 0.12)
            tl.ramp(t_up, th_pk)
            tl.hold(t_h)
        else:
            n_lev = int(rng.integers(3, 6))
            levels = np.linspace(theta_for_force(0.12, p), th_pk, n_lev)
            t_first = max(0.08, t_min * (levels[0] - tl.value))
            steps = [max(float(rng.uniform(0.02, 0.05)), 2 * dt) for _ in levels[1:]]
            *holds, t_r = _split(rng, share - t_first - sum(steps) - t_dn, n_lev + 1, 0.08)
            tl.ramp(t_first, float(levels[0]))
            tl.hold(holds[0])
            for lev, st, hd in zip(levels[1:], steps, holds[1:], strict=True):
                tl.ramp(st, float(lev))
                tl.hold(hd)
        tl.ramp(t_dn, rest)
        tl.hold(t_r)
    tl.fill()
    kk = np.arange(n, dtype=float)
    shift = _TAU_NOM / dt + 0.5
    ff = (np.interp(kk + 1.0 + shift, kk, tl.ref) - np.interp(kk + shift, kk, tl.ref)) / dt / _K_NOM
    wc = min(2 * np.pi * float(rng.uniform(5.0, 10.0)), 2 * np.pi / dt / 12.0)
    kp = wc / _K_NOM
    ki = kp * wc / float(rng.uniform(4.0, 8.0))
    info.update(kp_V_per_deg=kp, ki_V_per_deg_s=ki, crossover_rad_s=wc)
    return {"ctrl": {"ref": tl.ref, "ff": ff, "kp": kp, "ki": ki}, "info": info}


# ------------------------------------------------------------------------------------------
# Effects
# ------------------------------------------------------------------------------------------


def draw_extras(family: str, form: str, rng: np.random.Generator, p: dict, twin: dict) -> dict:
    """Draw the effect parameters other than the strength (shapes, phases, references).

    ``twin`` is the motor run without the effect (``run_motor`` output); keys starting
    with ``_`` are working arrays, dropped from the parameters by ``effect_params``.
    """
    ex: dict = {}
    if family == "armature_heating":
        ex.update(tau_th=0.5 if form == "a" else 5.0, alpha_per_K=0.0039)
    elif family == "supply_sag" and form == "b":
        ex.update(sized_share=float(rng.uniform(0.0, 0.3)), _absV=np.abs(twin["V"]),
                  _absI=np.maximum(np.sign(twin["V"]) * twin["i"], 0.0))
    elif family == "brush_drop":
        ex["i0"] = 0.05 if form == "a" else float(rng.uniform(0.2, 0.6))
    elif family == "cogging":
        ex.update(P_deg=60.0 if form == "a" else 45.0, phi=float(rng.uniform(0, 2 * np.pi)),
                  force_gain=0.0 if form == "a" else 3.0)
    elif family == "quadratic_drag":
        ex["omega_ref"] = 40.0
    elif family == "drive_compliance" and form == "b":
        ex["F0"] = float(rng.uniform(0.2, 0.5)) * p["F_rt"]
    elif family == "caliper_damping":
        ex["xdot_ref"] = 0.01
    elif family == "pad_creep":
        ex["tau_c"] = 0.3 if form == "a" else 1.0
    elif family == "mu_pressure" and form == "b":
        ex.update(F_min=0.05 * p["F_rt"], F_ref=0.5 * p["F_rt"])
    elif family == "lvdt_nonlinearity":
        ex.update(x_mid=p["c"] - (1.5 + float(rng.uniform(-0.2, 0.2))) * p["a"], x_ref=1e-3)
    return ex


def effect_params(family: str, form: str, s: float, ex: dict, p: dict) -> dict:
    """Effect parameters (SI) from the strength ``s`` and the extras (see ``_SIZE``)."""
    prm = dict(ex)
    prm["strength"] = s
    if family == "magnetic_saturation":
        prm.update({"inv_is2": s, "i_s": s**-0.5} if form == "a" else {"k": s})
    elif family == "armature_heating":
        prm.update(g=s, K_th_K_per_W=s / ex["alpha_per_K"])
    elif family == "supply_sag":
        prm["R_s"] = s
        if form == "b":  # supply sized for a share of the sag at the worst sample of the twin
            prm["V_max"] = float(np.max(ex["_absV"] + ex["sized_share"] * s * ex["_absI"]))
    elif family == "brush_drop":
        prm["V_b"] = s
    elif family == "cogging":
        prm["A0"] = s
    elif family == "quadratic_drag":
        prm["c"] = s / ex["omega_ref"] ** (2 if form == "a" else 3)
    elif family == "drive_compliance":
        if form == "a":
            prm["k"] = p["F_rt"] / s
        else:
            prm["x0"] = s / math.log1p(p["F_rt"] / ex["F0"])
    elif family == "caliper_damping":
        prm.update({"c_d": s / ex["xdot_ref"]} if form == "a" else {"beta": s})
    elif family == "pad_creep":
        prm["kappa"] = s
    elif family == "thermal_expansion":
        prm.update({"alpha_m_per_J": s / 1e4} if form == "a" else {"beta_m_per_s": s})
    elif family in ("mu_pressure", "load_cell_nonlinearity"):
        prm["k" if form == "a" or family == "load_cell_nonlinearity" else "n"] = s
    elif family == "sensor_lowpass":
        prm["tau"] = s
    elif family == "lvdt_nonlinearity":
        prm.update({"k": s / 1e-9} if form == "a" else {"g": s / 1e-3})
    return {k: v for k, v in prm.items() if not k.startswith("_")}


_TERM_INPUT = {
    "magnetic_saturation": "current_A", "armature_heating": "temperature_rise_K",
    "supply_sag": "current_A", "brush_drop": "current_A", "cogging": "theta_deg",
    "quadratic_drag": "omega_rad_s", "drive_compliance": "force_N",
    "caliper_damping": "x_rate_m_s", "pad_creep": "force_N", "mu_pressure": "force_N",
    "load_cell_nonlinearity": "force_N", "sensor_lowpass": "torque_rate_Nm_s",
    "lvdt_nonlinearity": "x_m",
}


def chain(p: dict, mot: dict, dt: float, w_disc: float, family: str | None = None,
          form: str = "a", prm: dict | None = None) -> tuple[dict, np.ndarray, np.ndarray, str]:
    """Gap, force, torque and sensor readings (noise-free) from a motor run.

    Parameters
    ----------
    p : dict
        Rig parameters (SI).
    mot : dict
        Output of ``run_motor``.
    dt : float
        Sample interval [s].
    w_disc : float
        Disc speed [rad/s].
    family, form, prm : optional
        Planted effect (``None`` for the clean chain) and its parameters.

    Returns
    -------
    rec : dict
        Noise-free readings ``current_A``, ``theta_deg``, ``x_m``, ``force_N``,
        ``torque_Nm`` (SI).
    term : ndarray
        Planted term at its place per sample (unit per family, see ``FAMILIES``).
    term_input : ndarray
        Main signal the term depends on.
    term_input_name : str
        Name with unit of ``term_input``.
    """
    th, w, cur = mot["th"], mot["w"], mot["i"]
    n = len(th)
    t = np.arange(n) * dt
    x = gap_m(th, p)
    term = np.zeros(n)
    tin = np.zeros(n)
    prm = prm or {}
    name = _TERM_INPUT.get(family, "none")
    fam = family or ""
    if fam in ("magnetic_saturation", "supply_sag", "brush_drop"):
        term, tin = (mot["tau"] if fam == "magnetic_saturation" else mot["dv"]), cur
    elif fam == "armature_heating":
        term, tin = mot["dv"], mot["aux"] / prm["alpha_per_K"]
    elif fam in ("cogging", "quadratic_drag"):
        term, tin = mot["tau"], (th if fam == "cogging" else w)
    elif fam == "drive_compliance":
        g = x.copy()

        def comp(f):
            if form == "a":
                return f / prm["k"], 1.0 / prm["k"]
            return prm["x0"] * np.log1p(f / prm["F0"]), prm["x0"] / (prm["F0"] + f)

        for _ in range(12):  # Newton on r(x) = x - g + delta(bell(x))
            d, dd = comp(bell(x, p))
            x = x - (x - g + d) / (1.0 + dd * dbell_dx(x, p))
        term, tin = x - g, bell(x, p)
    xdot = (2.0 * p["p2"] * th + p["p1"]) * w / DEG  # m/s
    x_in = x
    mu = p["mu"]
    if fam == "thermal_expansion":
        if form == "a":
            e_j = np.zeros(n)
            for _ in range(5):  # fixed point on the braking energy
                pw = 2.0 * mu * p["r_eff"] * bell(x + prm["alpha_m_per_J"] * e_j, p) * w_disc
                e_j = np.concatenate([[0.0], np.cumsum(0.5 * (pw[1:] + pw[:-1]) * dt)])
            term, tin, name = prm["alpha_m_per_J"] * e_j, e_j, "energy_J"
        else:
            term, tin, name = prm["beta_m_per_s"] * t, t, "time_s"
        x_in = x + term
    fb = bell(x_in, p)
    force = fb
    if fam == "caliper_damping":
        if form == "a":
            force = np.maximum(fb + prm["c_d"] * xdot, 0.0)
        else:
            force = fb * np.maximum(1.0 + prm["beta"] * xdot / prm["xdot_ref"], 0.0)
        term, tin = force - fb, xdot
    elif fam == "pad_creep":
        z = lag_foh(prm["kappa"] * fb, prm["tau_c"], dt)
        force = np.maximum(fb - z, 0.0)
        term, tin = force - fb, fb
    fac = np.ones(n)
    if fam == "mu_pressure":
        if form == "a":
            fac = 1.0 - prm["k"] * force / p["F_rt"]
        else:
            fac = (np.maximum(force, prm["F_min"]) / prm["F_ref"]) ** -prm["n"]
        term, tin = fac - 1.0, force
    torque = 2.0 * mu * force * p["r_eff"] * fac
    rec = {"current_A": cur, "theta_deg": th, "x_m": x, "force_N": force, "torque_Nm": torque}
    if fam == "load_cell_nonlinearity":
        q = force / p["F_rt"]
        rec["force_N"] = force + prm["k"] * force * (q if form == "a" else q * q)
        term, tin = rec["force_N"] - force, force
    elif fam == "sensor_lowpass":
        if form == "a":
            rec["torque_Nm"] = lag_foh(torque, prm["tau"], dt)
        else:
            rec["torque_Nm"] = lag_foh(lag_foh(torque, prm["tau"] / 2, dt), prm["tau"] / 2, dt)
        term, tin = rec["torque_Nm"] - torque, np.gradient(torque, dt)
    elif fam == "lvdt_nonlinearity":
        if form == "a":
            rec["x_m"] = x + prm["k"] * (x - prm["x_mid"]) ** 3
        else:
            rec["x_m"] = x * (1.0 + prm["g"] * x / prm["x_ref"])
        term, tin = rec["x_m"] - x, x
    return rec, np.asarray(term, float), np.asarray(tin, float), name


def rescale(attempt, s: float, tries: int) -> tuple[Any, list[list[float]]]:
    """Bracket an effect's strength ``s`` until it is visible (>= 3.5x the noise on some
    channel) and concealed (force and torque < 5 % off the twin), in at most ``tries``
    simulations: ``attempt(s) -> (result, (visibility, force_pct, torque_pct))``.
    Returns the last result and every try's ``[s, visibility, force_pct, torque_pct]``."""
    hist: list[list[float]] = []
    s_lo, s_hi = 0.0, math.inf  # bracket: invisible below, not concealed above
    for _ in range(tries):
        result, (vis, pf, pt) = attempt(s)
        hist.append([s, vis, pf, pt])
        if vis < 3.5:
            s_lo = s
            s = math.sqrt(s * s_hi) if s_hi < math.inf else s * min(4.5 / max(vis, 1e-9), 50)
        elif max(pf, pt) >= 5.0:
            s_hi = s
            s = math.sqrt(s * s_lo) if s_lo > 0 else s * 4.0 / max(pf, pt)
        else:
            break
    return result, hist


def visibility(rec: dict, twin: dict, sig: dict, has_current: bool) -> tuple[float, float, float]:
    """Visibility and concealment of an effect.

    Returns
    -------
    tuple of float
        ``(vis, force_pct, torque_pct)``: max over the noisy recorded channels of
        RMS(rec - twin) / sigma [-], and the relative RMS change of force and torque [%].
    """
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    vis = max(rms(rec[c] - twin[c]) / sig[c] for c in VIS_CHANNELS
              if has_current or c != "current_A")
    pf = 100.0 * rms(rec["force_N"] - twin["force_N"]) / rms(twin["force_N"])
    pt = 100.0 * rms(rec["torque_Nm"] - twin["torque_Nm"]) / rms(twin["torque_Nm"])
    return vis, pf, pt


# ------------------------------------------------------------------------------------------
# Cases
# ------------------------------------------------------------------------------------------

_MOTOR_FAMILIES = {k for k, v in FAMILIES.items() if v["stage"] == _MOT}
_TERM_UNIT = {"motor.mechanical": "N m (load torque)", "motor.electrical": "V (voltage removed)",
              "drive": "m (x shift)", "force.input": "m (x shift)",
              "force.output": "N (force added)", "friction": "- (mu factor - 1)",
              "sensor.force_N": "N (reading - true)", "sensor.torque_Nm": "N m (reading - true)",
              "sensor.x_m": "m (reading - true)"}


@dataclass
class Case:
    """One simulated recording with its truth.

    Attributes
    ----------
    table : pandas.DataFrame
        The trace (trace-format columns, SI units).
    sidecar : dict
        ``r_eff_m`` [m], ``sample_rate_hz`` [Hz], ``disc_mode``, ``description``.
    truth : dict
        Family, form, parameters, stage, place, dependencies, profile, noise, visibility.
    term : numpy.ndarray
        Planted term at its place per sample (zeros for clean cases).
    term_input : numpy.ndarray
        Main signal the term depends on per sample.
    term_input_name : str
        Name (with unit) of ``term_input``.
    """

    table: pd.DataFrame
    sidecar: dict
    truth: dict
    term: np.ndarray
    term_input: np.ndarray
    term_input_name: str


def _code(name: str) -> int:
    """Small integer hash of a name (for the random seed)."""
    return zlib.crc32(name.encode()) & 0xFFFF


def _draw_rig(rng: np.random.Generator) -> dict:
    """Rig unit: every nominal parameter times ``1 + 0.05 N(0, 1)`` clipped to +-12 %."""
    p = {k: v * (1.0 + float(np.clip(0.05 * rng.standard_normal(), -0.12, 0.12)))
         for k, v in NOMINAL.items()}
    p["r_eff"] = float(rng.choice(R_EFF_M))
    return p


def _quantise(v: np.ndarray, lo: float, hi: float, bits: int = 12) -> np.ndarray:
    """``bits``-bit ADC over ``[lo, hi]`` (clipped at the ends)."""
    step = (hi - lo) / 2**bits
    return lo + np.clip(np.round((v - lo) / step), 0, 2**bits - 1) * step


def _table(rec: dict, volts: np.ndarray, t: np.ndarray, e: np.ndarray, sig: dict,
           has_current: bool, w_disc: float, nuisance: str | None, nu: dict,
           p: dict) -> pd.DataFrame:
    """Noisy trace table (columns in trace-format order) from noise-free readings."""
    cols = {"time_s": t, "voltage_V": volts}
    chans = ("theta_deg", "x_m", "force_N", "torque_Nm", "current_A")
    for j, c in enumerate(chans):
        if c != "current_A" or has_current:
            cols[c] = rec[c] + sig[c] * e[j]
    cols["disc_speed_rad_s"] = w_disc + sig["disc_speed_rad_s"] * e[5]
    if nuisance == "hum":
        cols["force_N"] = cols["force_N"] + nu["amplitude_N"] * np.sin(
            2 * np.pi * nu["freq_hz"] * t + nu["phase_rad"])
    if nuisance == "quantised":
        for c, (lo, hi) in nu["ranges"].items():
            if c in cols:
                cols[c] = _quantise(cols[c], lo, hi)
    return pd.DataFrame({c: cols[c] for c in COLUMNS if c in cols})


def _released(force: np.ndarray, f_rt: float) -> tuple[int, bool, float]:
    """Applies (force above 0.4 F_rt after a release below 0.05 F_rt) and end state.

    Returns
    -------
    tuple
        ``(applies, released, peak_fraction)``: number of applies, whether the force is
        released (below 0.05 F_rt) after the last one, and the peak force / F_rt.
    """
    applies, released = 0, bool(force[0] < 0.05 * f_rt)
    for f in force:
        if released and f > 0.4 * f_rt:
            applies, released = applies + 1, False
        elif not released and f < 0.05 * f_rt:
            released = True
    return applies, released, float(force.max() / f_rt)


def make_case(family: str, form: str, seed: int, index: int, *, nuisance: str | None = None,
              duration_s: float | None = None, rate_hz: float | None = None,
              profile: str | None = None, has_current: bool | None = None,
              substeps: int | None = None) -> Case:
    """Simulate one case.

    Parameters
    ----------
    family : str
        A key of ``FAMILIES`` or ``"clean"``.
    form : str
        ``"a"`` or ``"b"`` (ignored for ``"clean"``).
    seed, index : int
        Run seed and case index; the same call always gives the same case.
    nuisance : str, optional
        For ``"clean"``: one of ``NUISANCES``.
    duration_s, rate_hz, profile, has_current : optional
        Overrides of the drawn duration [s] (default 3 s), sample rate [Hz], drive profile
        (``"steps"``, ``"pi"``, ``"staircase"``) and presence of ``current_A``.
    substeps : int, optional
        Motor sub-steps per sample (default: exact without a motor effect, else
        ``ceil(dt / H_MAX)``); for convergence checks.

    Returns
    -------
    Case
    """
    if family != "clean" and (family not in FAMILIES or form not in ("a", "b")):
        raise ValueError(f"unknown family/form {family}/{form}")
    if nuisance is not None and (family != "clean" or nuisance not in NUISANCES):
        raise ValueError(f"nuisance {nuisance!r} needs family 'clean' and one of {NUISANCES}")
    form = form if family != "clean" else "-"
    ss = np.random.SeedSequence([seed, index, _code(family), _code(form), _code(nuisance or "-")])
    r_rig, r_plan, r_noise, r_eff = (np.random.default_rng(c) for c in ss.spawn(4))
    p = _draw_rig(r_rig)
    rate = int(r_plan.choice(RATES_HZ))
    prof = str(r_plan.choice(PROFILES))
    cur_on = bool(r_plan.random() < 0.5)
    factor = float(np.exp(r_plan.uniform(np.log(0.5), np.log(2.0))))
    w_disc = float(r_plan.uniform(20.0, 50.0))
    theta0 = float(r_plan.uniform(5.0, 40.0))
    dur = 3.0
    if nuisance == "pi_loop":
        prof = "pi"
    elif nuisance == "long":
        dur = 12.0
    elif nuisance == "slow_log":
        rate = 100
    rate = int(rate_hz) if rate_hz is not None else rate
    prof = profile or prof
    dur = float(duration_s) if duration_s is not None else dur
    cur_on = cur_on if has_current is None else bool(has_current)
    if nuisance == "long":
        n_cyc = 8
    elif dur <= 4.5:
        n_cyc = 2 if prof == "staircase" else int(r_plan.integers(2, 4))
    else:
        n_cyc = max(2, round(dur / (1.6 if prof == "staircase" else 1.2)))
    dt = 1.0 / rate
    n = round(dur * rate)
    plan = plan_profile(prof, p, r_plan, dt, n, n_cyc, theta0)
    e = r_noise.standard_normal((6, n))
    sig = {c: v * factor for c, v in NOISE_BASE.items()}
    sig["torque_Nm"] *= p["r_eff"] / 0.15
    ctrl = plan.get("ctrl")
    if ctrl is not None:
        ctrl["noise"] = sig["theta_deg"] * e[0]
    kw = {"volts": plan.get("volts"), "ctrl": ctrl, "substeps": substeps}
    mot0 = run_motor(p, dt, n, theta0, **kw)
    rec0, _, _, _ = chain(p, mot0, dt, w_disc)
    t = np.arange(n) * dt
    nu: dict = {}
    if nuisance == "hum":
        nu = {"freq_hz": float(r_eff.choice((50.0, 60.0))),
              "amplitude_N": float(r_eff.uniform(1.0, 3.0)) * sig["force_N"],
              "phase_rad": float(r_eff.uniform(0.0, 2 * np.pi))}
    elif nuisance == "quantised":
        nu = {"bits": 12, "ranges": {
            "theta_deg": (0.0, 1000.0), "x_m": (-1e-3, 2e-3), "force_N": (0.0, 4000.0),
            "torque_Nm": (0.0, 2 * 0.5 * 4000.0 * p["r_eff"]), "current_A": (-10.0, 10.0)}}
    elif nuisance is not None:
        nu = {"profile": prof, "rate_hz": rate, "duration_s": dur, "n_cycles": n_cyc}
    truth: dict = {"family": family, "form": form, "nuisance": nuisance, "nuisance_params": nu}
    if family == "clean":
        mot, rec, prm = mot0, rec0, {}
        term, tin, tname = np.zeros(n), np.zeros(n), "none"
        vis, pf, pt, s0, hist = 0.0, 0.0, 0.0, 0.0, []
        truth.update(stage=None, place=None, depends_on=[], words="no planted effect")
    else:
        info = FAMILIES[family]
        ex = draw_extras(family, form, r_eff, p, mot0)
        size = _SIZE[(family, form)]
        lo, hi = size["open" if prof == "steps" else "closed"]
        s0 = float(np.exp(r_eff.uniform(np.log(lo), np.log(hi))))

        def attempt(s):
            prm = effect_params(family, form, s, ex, p)
            mot = mot0
            if family in _MOTOR_FAMILIES:
                mot = run_motor(p, dt, n, theta0, fx=MotorEffect(family, form, prm, p), **kw)
            rec = chain(p, mot, dt, w_disc, family, form, prm)
            return (prm, mot, *rec), visibility(rec[0], rec0, sig, cur_on)

        (prm, mot, rec, term, tin, tname), hist = rescale(attempt, s0, 12)
        vis, pf, pt = hist[-1][1:]
        truth.update(stage=info["stage"], place=info["place"],
                     depends_on=list(info["depends_on"][form]), words=info["words"],
                     term_unit=_TERM_UNIT[info["place"]], strength_unit=size["unit"])
    n_app, rel_ok, pk = _released(rec0["force_N"], p["F_rt"])
    table = _table(rec, mot["V"], t, e, sig, cur_on, w_disc, nuisance, nu, p)
    truth.update(
        params={"effect": prm, "rig": p}, profile=prof, rate=rate, duration_s=dur,
        n_samples=n, n_cycles=n_cyc, theta0_deg=theta0, disc_speed_rad_s=w_disc,
        noise_factor=factor, noise_sigma=sig, has_current=cur_on, visibility=vis,
        concealed_force_pct=pf, concealed_torque_pct=pt, strength_drawn=s0,
        strength=hist[-1][0] if hist else 0.0,
        rescales=[dict(zip(("strength", "vis", "force_pct", "torque_pct"), h, strict=True))
                  for h in hist],
        term_input_name=tname, profile_info=plan["info"], applies_seen=n_app,
        released_between=rel_ok, peak_force_frac=pk,
    )
    desc = (f"uncatalogued rig: {family}/{form}" + (f" ({nuisance})" if nuisance else "")
            + f", profile {prof}, {rate} Hz; synthetic, see truth file")
    sidecar = {"r_eff_m": p["r_eff"], "sample_rate_hz": rate, "disc_mode": "drag",
               "hardware": "uncatalogued rig (independent simulator)", "description": desc}
    return Case(table, sidecar, truth, term, tin, tname)


def _jsonable(obj):
    """Convert numpy scalars / arrays inside dicts and lists to plain JSON types."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _atomic_write(path: Path, writer) -> None:
    """Write through a temporary file in the same directory, then rename."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        writer(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_case(case: Case, out_dir: Path, name: str) -> Path:
    """Write ``name.csv``, ``name.json`` (sidecar), ``name.truth.json`` and ``name.term.npz``.

    Returns
    -------
    pathlib.Path
        Path of the CSV table.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = out_dir / f"{name}.csv"

    def dump(obj):
        return lambda tmp: Path(tmp).write_text(json.dumps(_jsonable(obj), indent=2) + "\n")

    _atomic_write(out_dir / f"{name}.json", dump(case.sidecar))
    _atomic_write(out_dir / f"{name}.truth.json", dump(case.truth))

    def npz(tmp):
        with open(tmp, "wb") as fh:
            np.savez(fh, term=case.term, term_input=case.term_input,
                     term_input_name=np.array(case.term_input_name))

    _atomic_write(out_dir / f"{name}.term.npz", npz)
    _atomic_write(csv_path, lambda tmp: case.table.to_csv(tmp, index=False, float_format="%.10g"))
    return csv_path


# ------------------------------------------------------------------------------------------
# Checks and command line
# ------------------------------------------------------------------------------------------


def self_convergence(seed: int = 0) -> dict[str, float]:
    """Motor-integration self-convergence at 1 kHz.

    For a few configurations the case is made with ``substeps`` 10 (0.1 ms) and 20
    (0.05 ms), and for clean cases also with the exact single-step transition.

    Returns
    -------
    dict
        ``label -> max over noisy channels of max |difference| / sigma`` [-].
    """
    out = {}
    confs = [("clean", "-", "steps"), ("clean", "-", "pi"), ("clean", "-", "staircase"),
             ("magnetic_saturation", "a", "steps"), ("armature_heating", "a", "pi"),
             ("brush_drop", "a", "steps"), ("supply_sag", "b", "pi"), ("cogging", "b", "pi"),
             ("quadratic_drag", "b", "staircase")]
    for fam, form, prof in confs:
        kw = {"rate_hz": 1000, "profile": prof, "has_current": True}
        runs = [make_case(fam, form, seed, 0, substeps=m, **kw) for m in (10, 20)]
        if fam == "clean":
            runs.append(make_case(fam, form, seed, 0, **kw))
        sig = runs[0].truth["noise_sigma"]
        worst = 0.0
        for other in runs[1:]:
            for ch in VIS_CHANNELS:
                d = np.max(np.abs(runs[0].table[ch].to_numpy() - other.table[ch].to_numpy()))
                worst = max(worst, float(d / sig[ch]))
        out[f"{fam}/{form}/{prof}"] = worst
    return out


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0, help="run seed")
    ap.add_argument("--per-form", type=int, default=2, help="cases per family x form")
    ap.add_argument("--out", type=Path, required=True, help="output directory")
    ap.add_argument("--check", action="store_true", help="print the check table, exit 1 on fail")
    args = ap.parse_args(argv)
    rows, fails = [], []
    t_start = time.perf_counter()
    jobs = [(f, fo, None) for f in FAMILIES for fo in ("a", "b")]
    jobs += [("clean", "-", nu) for nu in NUISANCES]
    for fam, form, nu in jobs:
        cases, times = [], []
        for i in range(args.per_form if nu is None else 3):
            t0 = time.perf_counter()
            case = make_case(fam, form, args.seed, i, nuisance=nu)
            times.append(time.perf_counter() - t0)
            name = f"{fam}_{form}_{i:03d}" if nu is None else f"clean_{nu}_{i:03d}"
            write_case(case, args.out, name)
            cases.append(case)
            tr = case.truth
            if nu is None and tr["visibility"] < 3.0:
                fails.append(f"{name}: invisible (visibility {tr['visibility']:.2f})")
            if max(tr["concealed_force_pct"], tr["concealed_torque_pct"]) >= 10.0:
                fails.append(f"{name}: not concealed")
            if not (tr["released_between"] and tr["applies_seen"] >= 1
                    and tr["peak_force_frac"] >= 0.75):
                fails.append(f"{name}: drive (peak {tr['peak_force_frac']:.2f}, "
                             f"applies {tr['applies_seen']}, released {tr['released_between']})")
        vis = np.array([c.truth["visibility"] for c in cases])
        conc = [max(c.truth["concealed_force_pct"], c.truth["concealed_torque_pct"])
                for c in cases]
        resc = sum(len(c.truth["rescales"]) > 1 for c in cases)
        rows.append((fam if nu is None else f"clean:{nu}", form, len(cases), vis.min(),
                     float(np.median(vis)), max(conc), resc, max(times)))
    print(f"wrote {sum(r[2] for r in rows)} cases to {args.out} "
          f"in {time.perf_counter() - t_start:.1f} s")
    if not args.check:
        return 0
    print(f"{'family':24s} {'form':4s} {'n':>3s} {'vis_min':>7s} {'vis_med':>7s} "
          f"{'conc_max%':>9s} {'rescaled':>8s} {'t_max_s':>7s}")
    for fam, form, n, vmin, vmed, cmax, resc, tmax in rows:
        print(f"{fam:24s} {form:4s} {n:3d} {vmin:7.2f} {vmed:7.2f} {cmax:9.2f} {resc:8d} "
              f"{tmax:7.2f}")
    conv = self_convergence(args.seed)
    print("self-convergence at 1 kHz, max |diff| / sigma over channels "
          "(substeps 10 vs 20, clean also vs exact):")
    for k, v in conv.items():
        print(f"  {k:40s} {v:.2e}")
        if k.startswith("clean") and v >= 0.01:
            fails.append(f"self-convergence {k}: {v:.2e}")
    for msg in fails:
        print("FAIL:", msg)
    print("ALL CHECKS PASSED" if not fails else f"{len(fails)} CHECKS FAILED")
    return 0 if not fails else 1


if __name__ == "__main__":
    sys.exit(main())
