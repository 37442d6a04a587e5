"""Independent simulator of a third electronic-wedge-brake (EWB) test rig.

This module writes synthetic rig recordings in the trace format v1
(``/work/shared/TRACE_FORMAT.md``) so that a system-identification tool can be
tested on a rig it was not developed against.  It was written from the physics
description only and shares no code with the identification package.

Physics (clean seed model, no extra effects)
--------------------------------------------
* DC motor, voltage held constant over each logged sample interval (zero-order hold)::

      V = L di/dt + R i + kb dtheta/dt                      [V]
      M d2theta/dt2 + v dtheta/dt = kT i                    [N m]   (theta in rad)

  The model is linear, so it is discretised exactly (matrix exponential of the
  augmented system) for each sample interval.
* Piston gap from the pinion angle in degrees: ``x = p2 theta^2 + p1 theta + p0`` [m].
* Clamping force (generalised bell): ``F = F_rt / (1 + |(x - c)/a|^(2 b))`` [N].
* Brake torque: ``T = 2 mu F r_eff`` [N m].

Note that the bell is a *bump* with its maximum ``F_rt`` at ``x = c``: a piston that
"passes c" sees the force rise to ``F_rt`` and fall again beyond ``c``.  With the
nominal gap polynomial ``x = 0`` at about 313 deg and ``x = c`` at about 518 deg.

Command line
------------
``python -m validation_rigs.third_rig --seed S --n N --out DIR`` writes ``DIR/case_000.csv``,
``DIR/case_000.json`` (sidecar), ``DIR/case_000.truth.json`` and ``DIR/cases.csv``.
``--check`` additionally verifies the written cases (finite traces, force range,
peak-force fractions, tracking errors, agreement with a fine-tolerance ``solve_ivp``
re-run) and prints a summary table.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
from scipy.linalg import expm

# --------------------------------------------------------------------------------------
# Nominal rig
# --------------------------------------------------------------------------------------

#: Nominal parameters in SI units (p2 in m/deg^2, p1 in m/deg, p0 in m).  The motor
#: constants are referred to the worm pinion (motor plus a small gearhead), which is why
#: kb = kT = 0.1 V s/rad and M = 3e-5 kg m^2: with them a 12 V step turns the pinion at
#: about 6800 deg/s and an apply stroke (about 500 deg) takes 0.08-0.2 s at 6-12 V.
NOMINAL: dict[str, float] = {
    "R": 1.0,  # ohm
    "L": 2.0e-3,  # H
    "kb": 0.10,  # V s/rad
    "kT": 0.10,  # N m/A
    "M": 3.0e-5,  # kg m^2
    "v": 1.0e-4,  # N m s/rad
    "a": 6.295e-4,  # m
    "c": 9.57e-4,  # m
    "b": 2.82,  # -
    "F_rt": 3500.0,  # N
    "mu": 0.35,  # -
    "r_eff": 0.15,  # m
    "p2": 3.8e-9,  # m/deg^2
    "p1": 1.5e-6,  # m/deg
    "p0": -8.4e-4,  # m
}

#: Profile codes (a..e of the brief) and their draw probabilities.
PROFILES: tuple[str, ...] = ("steps", "pid_position", "staircase", "force_pi", "chirp")
PROFILE_PROBS: tuple[float, ...] = (0.24, 0.24, 0.18, 0.16, 0.18)

#: Column order of the trace format.
COLUMNS: tuple[str, ...] = (
    "time_s",
    "voltage_V",
    "current_A",
    "theta_deg",
    "x_m",
    "force_N",
    "torque_Nm",
    "disc_speed_rad_s",
)

RATES_HZ: tuple[int, ...] = (100, 200, 250, 500, 1000)
DEG = math.pi / 180.0


# --------------------------------------------------------------------------------------
# Static maps
# --------------------------------------------------------------------------------------


def gap_m(theta_deg, p: dict):
    """Piston gap from the pinion angle.

    Parameters
    ----------
    theta_deg : float or ndarray
        Pinion angle [deg].
    p : dict
        Parameters with ``p2`` [m/deg^2], ``p1`` [m/deg], ``p0`` [m].

    Returns
    -------
    float or ndarray
        Piston displacement ``x`` [m].
    """
    return p["p2"] * theta_deg**2 + p["p1"] * theta_deg + p["p0"]


def theta_for_gap(x_m, p: dict):
    """Invert the gap polynomial on its rising branch.

    Parameters
    ----------
    x_m : float or ndarray
        Piston displacement [m].
    p : dict
        Parameters with ``p2`` [m/deg^2], ``p1`` [m/deg], ``p0`` [m].

    Returns
    -------
    float or ndarray
        Pinion angle [deg] with ``gap_m(theta) == x_m`` and ``dx/dtheta > 0``.
    """
    d = np.asarray(x_m, dtype=float) - p["p0"]
    disc = np.maximum(p["p1"] ** 2 + 4.0 * p["p2"] * d, 0.0)
    return 2.0 * d / (p["p1"] + np.sqrt(disc))


def bell_force(x_m, p: dict):
    """Clamping force of the generalised bell.

    Parameters
    ----------
    x_m : float or ndarray
        Piston displacement [m].
    p : dict
        Parameters with ``F_rt`` [N], ``a`` [m], ``c`` [m], ``b`` [-].

    Returns
    -------
    float or ndarray
        Clamping force [N], in ``(0, F_rt]``.
    """
    u = np.abs((np.asarray(x_m, dtype=float) - p["c"]) / p["a"])
    return p["F_rt"] / (1.0 + u ** (2.0 * p["b"]))


def gap_for_force_fraction(frac: float, side: int, p: dict) -> float:
    """Piston displacement at which the bell gives ``frac * F_rt``.

    Parameters
    ----------
    frac : float
        Force fraction of ``F_rt`` in (0, 1] [-].
    side : int
        -1 for the rising flank (``x < c``), +1 for the far flank (``x > c``).
    p : dict
        Parameters with ``a`` [m], ``c`` [m], ``b`` [-].

    Returns
    -------
    float
        Piston displacement [m].
    """
    frac = min(max(frac, 1e-9), 1.0)
    return p["c"] + side * p["a"] * (1.0 / frac - 1.0) ** (1.0 / (2.0 * p["b"]))


def theta_for_force_fraction(frac: float, side: int, p: dict) -> float:
    """Pinion angle [deg] at which the chain gives ``frac * F_rt``.

    See ``gap_for_force_fraction`` for the parameters; returns the angle [deg].
    """
    return float(theta_for_gap(gap_for_force_fraction(frac, side, p), p))


def force_slope_n_per_deg(theta_deg: float, p: dict) -> float:
    """Derivative dF/dtheta of the static chain.

    Parameters
    ----------
    theta_deg : float
        Pinion angle [deg].
    p : dict
        Chain parameters.

    Returns
    -------
    float
        dF/dtheta [N/deg] (positive on the rising flank).
    """
    x = gap_m(theta_deg, p)
    u = (x - p["c"]) / p["a"]
    au = abs(u)
    n = 2.0 * p["b"]
    dfdx = -p["F_rt"] * n * au ** (n - 1.0) * math.copysign(1.0, u) / p["a"] / (1.0 + au**n) ** 2
    return dfdx * (2.0 * p["p2"] * theta_deg + p["p1"])


def brake_torque(force_n, p: dict):
    """Brake torque ``T = 2 mu F r_eff``.

    Parameters
    ----------
    force_n : float or ndarray
        Clamping force [N].
    p : dict
        Parameters with ``mu`` [-] and ``r_eff`` [m].

    Returns
    -------
    float or ndarray
        Brake torque [N m].
    """
    return 2.0 * p["mu"] * np.asarray(force_n) * p["r_eff"]


def motor_speed_gain_deg(p: dict) -> float:
    """Steady-state no-load pinion speed per volt, ``kT / (kT kb + R v)`` [deg/s/V]."""
    return p["kT"] / (p["kT"] * p["kb"] + p["R"] * p["v"]) / DEG


# --------------------------------------------------------------------------------------
# Motor simulation
# --------------------------------------------------------------------------------------


def _motor_matrices(p: dict) -> tuple[np.ndarray, np.ndarray]:
    """Continuous state-space matrices of the motor, state ``[i (A), omega (rad/s), theta (rad)]``.

    Returns ``(A, B)`` with ``dz/dt = A z + B V``.
    """
    a_mat = np.array(
        [
            [-p["R"] / p["L"], -p["kb"] / p["L"], 0.0],
            [p["kT"] / p["M"], -p["v"] / p["M"], 0.0],
            [0.0, 1.0, 0.0],
        ]
    )
    b_vec = np.array([1.0 / p["L"], 0.0, 0.0])
    return a_mat, b_vec


class MotorStepper:
    """Exact zero-order-hold discretisation of the motor over one sample interval.

    Parameters
    ----------
    p : dict
        Motor parameters ``R`` [ohm], ``L`` [H], ``kb`` [V s/rad], ``kT`` [N m/A],
        ``M`` [kg m^2], ``v`` [N m s/rad].
    dt : float
        Sample interval [s].

    Notes
    -----
    The state is ``z = [i (A), omega (rad/s), theta (rad)]``; ``step(z, V)`` returns the
    state one interval later with the voltage ``V`` [V] held constant.
    """

    def __init__(self, p: dict, dt: float):
        a_mat, b_vec = _motor_matrices(p)
        aug = np.zeros((4, 4))
        aug[:3, :3] = a_mat
        aug[:3, 3] = b_vec
        e = expm(aug * dt)
        self.phi = e[:3, :3].copy()
        self.gam = e[:3, 3].copy()
        self.dt = dt

    def step(self, z: np.ndarray, volt: float) -> np.ndarray:
        """Advance the state by one interval [state units as in the class notes]."""
        return self.phi @ z + self.gam * volt

    def run(self, z0: np.ndarray, volts: np.ndarray) -> np.ndarray:
        """Simulate a voltage sequence.

        Parameters
        ----------
        z0 : ndarray, shape (3,)
            Initial state ``[A, rad/s, rad]``.
        volts : ndarray, shape (n,)
            Voltage held over each interval [V].

        Returns
        -------
        ndarray, shape (n + 1, 3)
            States at the sample instants, starting with ``z0``.
        """
        out = np.empty((len(volts) + 1, 3))
        out[0] = z0
        z = np.asarray(z0, dtype=float)
        for k, volt in enumerate(volts):
            z = self.phi @ z + self.gam * volt
            out[k + 1] = z
        return out


def simulate_motor(p: dict, volts: np.ndarray, dt: float, theta0_deg: float) -> np.ndarray:
    """Open-loop motor response to a logged (zero-order-hold) voltage sequence.

    Parameters
    ----------
    p : dict
        Motor parameters (see ``MotorStepper``).
    volts : ndarray, shape (n,)
        Voltage applied over the interval starting at each sample [V].
    dt : float
        Sample interval [s].
    theta0_deg : float
        Initial pinion angle [deg]; the motor starts at rest with zero current.

    Returns
    -------
    ndarray, shape (n, 3)
        Current [A], speed [rad/s] and angle [deg] at the sample instants ``k dt``.
    """
    st = MotorStepper(p, dt)
    zs = st.run(np.array([0.0, 0.0, theta0_deg * DEG]), np.asarray(volts, dtype=float)[:-1])
    zs[:, 2] /= DEG
    return zs


def simulate_motor_ivp(
    p: dict, volts: np.ndarray, dt: float, theta0_deg: float, rtol: float = 1e-10
) -> np.ndarray:
    """Reference re-run of ``simulate_motor`` with ``solve_ivp`` (Radau), interval by interval.

    Parameters
    ----------
    p : dict
        Motor parameters.
    volts : ndarray, shape (n,)
        Voltage over each interval [V].
    dt : float
        Sample interval [s].
    theta0_deg : float
        Initial angle [deg].
    rtol : float
        Relative tolerance [-]; absolute tolerances are 1e-3 * rtol in SI units.

    Returns
    -------
    ndarray, shape (n, 3)
        Current [A], speed [rad/s] and angle [deg] at the samples.
    """
    a_mat, b_vec = _motor_matrices(p)
    z = np.array([0.0, 0.0, theta0_deg * DEG])
    out = np.empty((len(volts), 3))
    out[0] = z
    atol = np.full(3, 1e-3 * rtol)
    for k in range(len(volts) - 1):
        volt = float(volts[k])
        sol = solve_ivp(
            lambda _t, y, volt=volt: a_mat @ y + b_vec * volt,
            (0.0, dt),
            z,
            method="Radau",
            rtol=rtol,
            atol=atol,
            jac=lambda _t, _y: a_mat,
        )
        z = sol.y[:, -1]
        out[k + 1] = z
    out[:, 2] /= DEG
    return out


# --------------------------------------------------------------------------------------
# Case drawing
# --------------------------------------------------------------------------------------


def draw_case(rng: np.random.Generator) -> dict:
    """Draw one rig / recording configuration.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness (one child generator per case).

    Returns
    -------
    dict
        JSON-serialisable case description: true parameters (SI; p2 in m/deg^2,
        p1 in m/deg), profile code, sample rate [Hz], duration [s], time offset [s],
        initial angle [deg], noise standard deviations, quantisation, channel subset,
        and ``sim_seed`` (seed of the generator ``make_trace`` uses for the profile
        details and the noise).
    """
    n = NOMINAL
    p: dict[str, float] = {}
    for k in ("R", "L", "kb", "M", "v"):
        p[k] = n[k] * rng.uniform(0.6, 1.6)
    kb_equals_kt = bool(rng.random() < 0.5)
    p["kT"] = p["kb"] if kb_equals_kt else n["kT"] * rng.uniform(0.6, 1.6)
    p["a"] = n["a"] * rng.uniform(0.8, 1.25)
    p["c"] = n["c"] * rng.uniform(0.85, 1.15)
    p["b"] = rng.uniform(2.0, 3.8)
    p["F_rt"] = rng.uniform(2500.0, 5000.0)
    p["mu"] = rng.uniform(0.25, 0.5)
    p["r_eff"] = rng.uniform(0.10, 0.25)
    p["p2"] = n["p2"] * rng.uniform(0.7, 1.3)
    p["p1"] = n["p1"] * rng.uniform(0.85, 1.15)
    p["p0"] = n["p0"] + rng.uniform(-50e-6, 50e-6)

    profile = str(rng.choice(PROFILES, p=PROFILE_PROBS))
    rate = int(rng.choice(RATES_HZ))
    duration = float(rng.uniform(2.0, 6.0))
    t0 = round(float(rng.uniform(0.0, 10.0)), 3) if rng.random() < 0.3 else 0.0
    theta0 = float(rng.uniform(-20.0, 60.0))
    low = bool(rng.random() < 0.15)

    noise = {
        "theta_deg": float(rng.uniform(0.02, 0.3)),
        "x_m": float(rng.uniform(0.5e-6, 5e-6)),
        "force_N": float(rng.uniform(2.0, 15.0)),
        "torque_Nm": float(rng.uniform(0.2, 3.0)),
        "current_A": float(rng.uniform(0.005, 0.05)),
        "disc_speed_rad_s": float(rng.uniform(0.1, 1.0)),
        "voltage_V": float(rng.uniform(0.01, 0.05)) if rng.random() < 0.2 else 0.0,
    }
    theta_bits = int(rng.choice((12, 16))) if rng.random() < 0.5 else 0
    force_step = 1.0 if rng.random() < 0.3 else 0.0

    channels = ["time_s", "voltage_V", "current_A", "theta_deg", "x_m", "force_N"]
    channels += ["torque_Nm", "disc_speed_rad_s"]
    if rng.random() < 0.5:
        channels.remove("current_A")
    if rng.random() < 0.3:
        channels.remove("disc_speed_rad_s")
    if rng.random() < 0.1:
        channels.remove("force_N")  # torque is then always kept
    elif rng.random() < 0.15:
        channels.remove("torque_Nm")

    return {
        "params": {k: float(val) for k, val in p.items()},
        "kb_equals_kT": kb_equals_kt,
        "profile": profile,
        "rate_hz": rate,
        "duration_s": duration,
        "t0_s": t0,
        "theta0_deg": theta0,
        "intended_low": low,
        "v_sat_V": 24.0 if rng.random() < 0.3 else 12.0,
        "disc_speed_rad_s": float(rng.uniform(20.0, 100.0)),
        "noise_std": noise,
        "theta_quant_bits": theta_bits,
        "theta_pot_range_deg": [-360.0, 3240.0],
        "force_quant_N": force_step,
        "channels": channels,
        "sim_seed": int(rng.integers(0, 2**63 - 1)),
    }


# --------------------------------------------------------------------------------------
# Profiles
# --------------------------------------------------------------------------------------


def _smooth(s: np.ndarray) -> np.ndarray:
    """Raised-cosine blend from 0 to 1 for ``s`` in [0, 1]."""
    s = np.clip(s, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * s)


class _Timeline:
    """Builds a sampled reference (position [deg] or force [N]) segment by segment."""

    def __init__(self, n: int, dt: float, start: float):
        self.n, self.dt = n, dt
        self.ref = np.full(n, np.nan)
        self.kind = np.zeros(n, dtype=int)  # 0 position hold, 1 position ramp, 2 force
        self.k = 0
        self.value = start

    def _span(self, seconds: float) -> slice:
        m = max(1, int(round(seconds / self.dt)))
        k1 = min(self.n, self.k + m)
        sl = slice(self.k, k1)
        self.k = k1
        return sl

    def hold(self, seconds: float, value: float | None = None, kind: int = 0) -> None:
        if value is not None:
            self.value = value
        sl = self._span(seconds)
        self.ref[sl] = self.value
        self.kind[sl] = kind

    def ramp(self, seconds: float, target: float, kind: int = 1) -> None:
        sl = self._span(seconds)
        m = sl.stop - sl.start
        if m > 0:
            s = np.arange(1, m + 1) / m
            self.ref[sl] = self.value + (target - self.value) * _smooth(s)
            self.kind[sl] = kind
        self.value = target

    def fill(self, kind: int = 0) -> None:
        self.ref[self.k :] = self.value
        self.kind[self.k :] = kind
        self.k = self.n

    def remaining(self) -> float:
        return (self.n - self.k) * self.dt


def _split(rng: np.random.Generator, total: float, parts: int, minimum: float) -> np.ndarray:
    """Split ``total`` seconds into ``parts`` random durations, each at least ``minimum``."""
    spare = max(total - parts * minimum, 0.0)
    return minimum + spare * rng.dirichlet(np.full(parts, 2.0))


def _apply_level(rng: np.random.Generator, low: bool, p: dict) -> tuple[float, float, int]:
    """Target angle of one apply.

    Returns
    -------
    tuple
        ``(theta_deg, force_fraction, side)``: for a low apply the rising-flank angle of
        a fraction 0.22-0.42 (never reaching ``c``); otherwise the far-flank angle (the
        piston passes ``c``) at a fraction 0.6-0.95.
    """
    if low:
        f = float(rng.uniform(0.22, 0.42))
        return theta_for_force_fraction(f, -1, p), f, -1
    f = float(rng.uniform(0.6, 0.95))
    return theta_for_force_fraction(f, +1, p), f, +1


def _ramp_time(rng: np.random.Generator, dtheta: float, k_deg: float, v_sat: float) -> float:
    """Ramp duration [s] in 0.1-0.5 s, lengthened so the peak reference speed stays feasible."""
    t = float(rng.uniform(0.1, 0.5))
    t_min = 1.6 * abs(dtheta) / (0.7 * k_deg * v_sat)  # raised cosine peak speed pi/2 * mean
    return max(t, t_min)


def _plan_position(case: dict, rng: np.random.Generator, n: int, dt: float) -> dict:
    """Reference for the closed-loop position profiles (pid_position, staircase, chirp)."""
    p = case["params"]
    k_deg = motor_speed_gain_deg(p)
    vs = case["v_sat_V"]
    low = case["intended_low"]
    tl = _Timeline(n, dt, case["theta0_deg"])
    info: dict = {}
    tl.hold(float(rng.uniform(0.05, 0.3)))
    total = tl.remaining()
    prof = case["profile"]
    if prof == "pid_position":
        n_cyc = 2 if (rng.random() < 0.5 and total > 2.0) else 1
        levels, fracs = [], []
        for _ in range(n_cyc):
            th, f, _side = _apply_level(rng, low, p)
            levels.append(th)
            fracs.append(f)
        info["target_force_fraction"] = fracs
        rest_angles = [float(rng.uniform(-10.0, 60.0)) for _ in range(n_cyc)]
        ramps = []
        prev = case["theta0_deg"]
        for th, rest in zip(levels, rest_angles, strict=True):
            ramps += [_ramp_time(rng, th - prev, k_deg, vs), _ramp_time(rng, th - rest, k_deg, vs)]
            prev = rest
        holds = _split(rng, total - sum(ramps), 2 * n_cyc, 0.1)
        for j in range(n_cyc):
            tl.ramp(ramps[2 * j], levels[j])
            tl.hold(holds[2 * j])
            tl.ramp(ramps[2 * j + 1], rest_angles[j])
            tl.hold(holds[2 * j + 1])
    elif prof == "staircase":
        n_lev = int(rng.integers(3, 6))
        th_top, f_top, _side = _apply_level(rng, low, p)
        th_bot = theta_for_force_fraction(0.08, -1, p)
        if low:
            th_bot = theta_for_force_fraction(0.03, -1, p)
        levels = list(np.linspace(th_bot, th_top, n_lev))
        seq = levels + levels[-2::-1]
        info["target_force_fraction"] = [f_top]
        info["levels_deg"] = [float(v) for v in levels]
        rest = float(rng.uniform(-10.0, 60.0))
        t_step = [float(rng.uniform(0.02, 0.08)) for _ in seq]
        t_first = _ramp_time(rng, th_bot - case["theta0_deg"], k_deg, vs)
        t_last = _ramp_time(rng, th_bot - rest, k_deg, vs)
        holds = _split(rng, total - sum(t_step) - t_first - t_last, len(seq) + 1, 0.08)
        tl.ramp(t_first, seq[0])
        tl.hold(holds[0])
        for j, lev in enumerate(seq[1:], start=1):
            tl.ramp(max(t_step[j], 2 * dt), lev)
            tl.hold(holds[j])
        tl.ramp(t_last, rest)
    else:  # chirp
        a = p["a"]
        if low:
            f_hi = float(rng.uniform(0.22, 0.42))
            x_hi = gap_for_force_fraction(f_hi, -1, p)
            x_lo = x_hi - float(rng.uniform(0.3, 0.8)) * a
            info["target_force_fraction"] = [f_hi]
        else:
            x_op = p["c"] + float(rng.uniform(-0.4, 0.2)) * a
            dx = float(rng.uniform(0.5, 1.0)) * a
            x_lo, x_hi = x_op - dx, x_op + dx
            info["target_force_fraction"] = [1.0]
        th_lo, th_hi = float(theta_for_gap(x_lo, p)), float(theta_for_gap(x_hi, p))
        th_op, amp = 0.5 * (th_lo + th_hi), 0.5 * (th_hi - th_lo)
        rest = float(rng.uniform(-10.0, 60.0))
        t_in = _ramp_time(rng, th_op - case["theta0_deg"], k_deg, vs)
        t_out = _ramp_time(rng, th_op - rest, k_deg, vs)
        t_settle, t_rest = float(rng.uniform(0.1, 0.3)), float(rng.uniform(0.1, 0.4))
        t_ch = max(total - t_in - t_out - t_settle - t_rest, 0.5)
        fs = 1.0 / dt
        f_cap = min(fs / 40.0, 8.0)
        chirp = rng.random() < 0.6
        if chirp:
            f0 = float(rng.uniform(0.3, 1.0))
            f1 = float(min(rng.uniform(3.0, 10.0), f_cap))
        else:
            f0 = f1 = float(min(rng.uniform(0.5, 4.0), f_cap))
        # keep the reference speed feasible for the motor
        vmax = 2 * np.pi * f1 * amp
        if vmax > 0.5 * k_deg * vs:
            f1 = max(0.5 * k_deg * vs / (2 * np.pi * amp), 0.2)
            f0 = min(f0, f1)
        info.update(sine_f0_hz=f0, sine_f1_hz=f1, sine_amp_deg=amp, sine_center_deg=th_op)
        tl.ramp(t_in, th_op)
        tl.hold(t_settle)
        sl = tl._span(t_ch)
        m = sl.stop - sl.start
        tt = np.arange(m) * dt
        t_len = max(m * dt, dt)
        phase = 2 * np.pi * (f0 * tt + 0.5 * (f1 - f0) * tt**2 / t_len)
        taper = np.minimum(1.0, np.minimum(tt, t_len - tt) / 0.25)
        tl.ref[sl] = th_op + amp * np.clip(taper, 0.0, 1.0) * np.sin(phase)
        tl.kind[sl] = 1
        tl.value = th_op
        tl.ramp(t_out, rest)
    tl.fill()
    return {"theta_ref": tl.ref, "kind": tl.kind, "info": info}


def _controller_model(p: dict, rng: np.random.Generator) -> dict:
    """Rig's own (commissioning) model of the chain: true values with a few per cent error."""
    q = dict(p)
    for k in ("a", "c", "F_rt", "p1", "p2"):
        q[k] = p[k] * (1.0 + 0.03 * rng.uniform(-1.0, 1.0))
    q["b"] = p["b"] * (1.0 + 0.05 * rng.uniform(-1.0, 1.0))
    return q


def _plan_force(case: dict, rng: np.random.Generator, n: int, dt: float, q: dict) -> dict:
    """References for the force-control profile.

    Returns a position base reference [deg] (controller-model feed-forward), a force
    reference [N] (NaN outside force phases), the fade weight of the force-loop angle
    correction, and info.
    """
    p = case["params"]
    k_deg = motor_speed_gain_deg(p)
    vs = case["v_sat_V"]
    low = case["intended_low"]
    f_rt = p["F_rt"]
    f_min_frac = 0.05
    tl = _Timeline(n, dt, case["theta0_deg"])
    fref = np.full(n, np.nan)
    info: dict = {}
    tl.hold(float(rng.uniform(0.05, 0.3)))
    stroke = (not low) and rng.random() < 0.7
    info["position_stroke"] = bool(stroke)
    if stroke:  # position-controlled stroke past c before the force phases
        th, f, _side = _apply_level(rng, False, p)
        rest = float(rng.uniform(-10.0, 60.0))
        tl.ramp(_ramp_time(rng, th - tl.value, k_deg, vs), th)
        tl.hold(float(rng.uniform(0.1, 0.3)))
        tl.ramp(_ramp_time(rng, th - rest, k_deg, vs), rest)
        tl.hold(float(rng.uniform(0.1, 0.3)))
        info["stroke_force_fraction"] = f
    total = tl.remaining()
    n_cyc = 2 if (rng.random() < 0.4 and total > 3.0) else 1
    fracs = []
    for j in range(n_cyc):
        frac = float(rng.uniform(0.22, 0.42) if low else rng.uniform(0.6, 0.9))
        fracs.append(frac)
        f_set = frac * f_rt
        th_c = theta_for_force_fraction(min(f_min_frac * f_rt / q["F_rt"], 0.97), -1, q)
        rest = float(rng.uniform(-10.0, 60.0))
        t_app = _ramp_time(rng, th_c - tl.value, k_deg, vs)
        t_up, t_dn = float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.2, 0.8))
        t_rel = _ramp_time(rng, th_c - rest, k_deg, vs)
        budget = total / n_cyc - t_app - t_up - t_dn - t_rel
        t_hold, t_rest = _split(rng, budget, 2, 0.1)
        tl.ramp(t_app, th_c)
        # force phase: ramp up, hold, ramp down (force reference in N)
        for seg_t, f_a, f_b in (
            (t_up, f_min_frac * f_rt, f_set),
            (t_hold, f_set, f_set),
            (t_dn, f_set, f_min_frac * f_rt),
        ):
            sl = tl._span(seg_t)
            m = sl.stop - sl.start
            s = np.arange(1, m + 1) / max(m, 1)
            fref[sl] = f_a + (f_b - f_a) * _smooth(s)
            tl.kind[sl] = 2
        tl.value = th_c
        tl.ramp(t_rel, rest)
        if j == n_cyc - 1:
            tl.fill()
        else:
            tl.hold(t_rest)
    tl.fill()
    info["target_force_fraction"] = fracs
    # feed-forward angle from the controller model on the rising flank
    base = tl.ref.copy()
    is_f = tl.kind == 2
    ff = np.clip(fref[is_f] / q["F_rt"], 1e-3, 0.97)
    base[is_f] = [theta_for_force_fraction(float(f), -1, q) for f in ff]
    # fade weight of the integral correction: 1 in force phases, ramps to 0 afterwards
    weight = np.zeros(n)
    weight[is_f] = 1.0
    k = 0
    while k < n:
        if is_f[k] and (k + 1 == n or not is_f[k + 1]):
            j = k + 1
            while j < n and tl.kind[j] == 1:
                j += 1
            m = j - (k + 1)
            if m > 0:
                weight[k + 1 : j] = 1.0 - _smooth(np.arange(1, m + 1) / m)
            k = j
        else:
            k += 1
    return {"theta_ref": base, "force_ref": fref, "weight": weight, "kind": tl.kind, "info": info}


def _solve_voltage(
    st: MotorStepper, z: np.ndarray, segs: list[tuple[float | None, int]], target_deg: float
) -> float:
    """Voltage of the single unknown segment (``None``) so the angle ends at ``target_deg``.

    The motor is linear, so the end angle is affine in that voltage; two evaluations
    give the exact solution.
    """

    def end_theta(volt: float) -> float:
        zz = z.copy()
        for v, m in segs:
            vv = volt if v is None else v
            for _ in range(m):
                zz = st.step(zz, vv)
        return zz[2] / DEG

    e0, e1 = end_theta(0.0), end_theta(1.0)
    return (target_deg - e0) / (e1 - e0)


def _plan_steps(case: dict, rng: np.random.Generator, n: int, dt: float) -> dict:
    """Open-loop voltage steps: apply, hold (0 V or small V), release (negative V), rest."""
    p = case["params"]
    st = MotorStepper(p, dt)
    k_deg = motor_speed_gain_deg(p)
    low = case["intended_low"]
    volts = np.zeros(n)
    z = np.array([0.0, 0.0, case["theta0_deg"] * DEG])
    k = max(1, int(round(rng.uniform(0.05, 0.3) / dt)))
    for _ in range(k):
        z = st.step(z, 0.0)
    total = (n - k) * dt
    n_cyc = 2 if (rng.random() < 0.5 and total > 2.0) else 1
    info: dict = {"target_force_fraction": [], "apply_V": [], "hold_V": [], "release_V": []}
    theta = case["theta0_deg"]
    for j in range(n_cyc):
        th_pk, f, _side = _apply_level(rng, low, p)
        rest = float(rng.uniform(-10.0, 60.0))
        va0, vr0 = float(rng.uniform(6.0, 12.0)), float(rng.uniform(4.0, 12.0))
        n_a = max(2, int(round((th_pk - theta) / (k_deg * va0 * dt))))
        n_r = max(2, int(round((th_pk - rest) / (k_deg * vr0 * dt))))
        share = total / n_cyc - (n_a + n_r) * dt
        t_hold, t_rest = _split(rng, share, 2, 0.1)
        n_h, n_rest = max(1, int(round(t_hold / dt))), max(1, int(round(t_rest / dt)))
        if j == n_cyc - 1:
            n_rest = max(1, n - k - n_a - n_h - n_r)
        if rng.random() < 0.5:
            v_h = 0.0
        else:  # small holding voltage, drifting the pinion by a few degrees
            v_h = float(rng.uniform(2.0, 15.0)) / (k_deg * n_h * dt)
        v_a = _solve_voltage(st, z, [(None, n_a), (v_h, n_h)], th_pk)
        for _ in range(n_a):
            z = st.step(z, v_a)
        for _ in range(n_h):
            z = st.step(z, v_h)
        n_tail = min(n_rest, max(1, int(round(0.05 / dt))))
        v_r = _solve_voltage(st, z, [(None, n_r), (0.0, n_tail)], rest)
        for _ in range(n_r):
            z = st.step(z, v_r)
        for _ in range(n_rest):
            z = st.step(z, 0.0)
        seq = [v_a] * n_a + [v_h] * n_h + [v_r] * n_r + [0.0] * n_rest
        seq = seq[: n - k]
        volts[k : k + len(seq)] = seq
        k += len(seq)
        theta = rest
        info["target_force_fraction"].append(f)
        info["apply_V"].append(v_a)
        info["hold_V"].append(v_h)
        info["release_V"].append(v_r)
        if k >= n:
            break
    return {"volts": volts, "info": info}


# --------------------------------------------------------------------------------------
# Trace generation
# --------------------------------------------------------------------------------------


def _quantise(val: float, step: float, lo: float = 0.0) -> float:
    return lo + round((val - lo) / step) * step if step > 0 else val


def make_trace(case: dict) -> tuple[dict, dict, dict]:
    """Simulate one recording.

    Parameters
    ----------
    case : dict
        Output of ``draw_case``.

    Returns
    -------
    columns : dict of str to ndarray
        Logged channels in trace-format order (``time_s`` [s], ``voltage_V`` [V],
        ``current_A`` [A], ``theta_deg`` [deg], ``x_m`` [m], ``force_N`` [N],
        ``torque_Nm`` [N m], ``disc_speed_rad_s`` [rad/s]; absent channels omitted).
    sidecar : dict
        ``r_eff_m`` [m], ``sample_rate_hz`` [Hz], ``disc_mode``, ``hardware``,
        ``description``.
    truth : dict
        True parameters (SI; ``p2`` in m/deg^2, ``p1`` in m/deg), profile, rate,
        channels, ``passes_c``, noise standard deviations and summary numbers.  The key
        ``_signals`` holds noise-free arrays (applied voltage, current, speed, angle,
        gap, force, references) and is not meant for JSON output.
    """
    p = case["params"]
    rng = np.random.default_rng(case["sim_seed"])
    fs = case["rate_hz"]
    dt = 1.0 / fs
    n = int(round(case["duration_s"] * fs))
    prof = case["profile"]
    v_sat = case["v_sat_V"]
    k_true = motor_speed_gain_deg(p)

    # controller design (from the rig's own, slightly wrong, estimate of the motor gain)
    k_hat = k_true * float(rng.uniform(0.9, 1.1))
    # ramp lag of the motor speed behind the voltage, (L v + R M) / (R v + kT kb) [s]
    tau_true = (p["L"] * p["v"] + p["R"] * p["M"]) / (p["R"] * p["v"] + p["kT"] * p["kb"])
    tau_hat = tau_true * float(rng.uniform(0.8, 1.2))
    wc = min(2 * np.pi * fs / float(rng.uniform(10.0, 16.0)), 2 * np.pi * float(rng.uniform(6, 14)))
    kp = wc / k_hat  # V/deg
    ki = kp * wc / float(rng.uniform(8.0, 15.0))  # V/(deg s)
    kd = kp * float(rng.uniform(0.0, 0.3)) / wc  # V s/deg
    tau_d = 2.0 * dt
    q = _controller_model(p, rng)
    ki_f = wc / float(rng.uniform(6.0, 10.0))  # 1/s, outer force loop (angle units)
    kp_f = float(rng.uniform(0.0, 0.3))  # -, proportional share of the outer loop

    plan: dict
    closed = prof != "steps"
    if prof == "steps":
        plan = _plan_steps(case, rng, n, dt)
    elif prof == "force_pi":
        plan = _plan_force(case, rng, n, dt, q)
    else:
        plan = _plan_position(case, rng, n, dt)

    ns = case["noise_std"]
    e_th = rng.normal(0.0, ns["theta_deg"], n)
    e_f = rng.normal(0.0, ns["force_N"], n)
    bits = case["theta_quant_bits"]
    pot_lo, pot_hi = case["theta_pot_range_deg"]
    q_th = (pot_hi - pot_lo) / 2**bits if bits else 0.0
    q_f = case["force_quant_N"]

    st = MotorStepper(p, dt)
    z = np.array([0.0, 0.0, case["theta0_deg"] * DEG])
    states = np.empty((n, 3))
    volts = np.zeros(n)
    th_meas = np.empty(n)
    f_meas = np.empty(n)
    th_ref = np.full(n, np.nan)
    integ = 0.0
    dfilt = 0.0
    e_prev = None
    dtheta_f = 0.0  # force-loop angle correction [deg]
    if closed:
        base = plan["theta_ref"]
        weight = plan.get("weight", np.zeros(n))
        fref = plan.get("force_ref", np.full(n, np.nan))
        th_lim, g_pk = np.inf, 1.0
        if prof == "force_pi":
            th_lim = theta_for_force_fraction(0.97, -1, q)
            g_pk = max(
                force_slope_n_per_deg(t, q)
                for t in np.linspace(theta_for_force_fraction(0.02, -1, q), th_lim, 200)
            )
        # velocity feed-forward with preview of the motor lag (plus half a sample of ZOH)
        kk = np.arange(n, dtype=float)
        shift = tau_hat / dt + 0.5
        base_ahead = np.interp(kk + shift, kk, base)
        base_ahead1 = np.interp(kk + 1.0 + shift, kk, base)
        u_ffs = (base_ahead1 - base_ahead) / dt / k_hat
    for k in range(n):
        states[k] = z
        theta_true = z[2] / DEG
        y = _quantise(theta_true + e_th[k], q_th, pot_lo)
        force_true = float(bell_force(gap_m(theta_true, p), p))
        fm = _quantise(force_true + e_f[k], q_f)
        th_meas[k], f_meas[k] = y, fm
        if not closed:
            volt = plan["volts"][k]
        else:
            r_base = base[k]
            if not np.isnan(fref[k]):  # outer force loop, scheduled by the model slope
                g = min(max(force_slope_n_per_deg(r_base + dtheta_f, q), g_pk / 30.0), g_pk)
                e_ang = (fref[k] - fm) / g
                dtheta_f = float(np.clip(dtheta_f + ki_f * dt * e_ang, -80.0, 80.0))
                r = min(r_base + dtheta_f + kp_f * e_ang, th_lim)
            else:
                r = r_base + weight[k] * dtheta_f
                if weight[k] == 0.0:
                    dtheta_f = 0.0
            th_ref[k] = r
            e = r - y
            de = 0.0 if e_prev is None else (e - e_prev) / dt
            dfilt += (dt / (tau_d + dt)) * (de - dfilt)  # filtered derivative of the error
            e_prev = e
            u_ff = u_ffs[k]
            integ_new = integ + ki * e * dt
            u = kp * e + integ_new + kd * dfilt + u_ff
            volt = float(np.clip(u, -v_sat, v_sat))
            if volt == u or np.sign(e) != np.sign(u):
                integ = integ_new  # conditional integration (anti-windup)
        volts[k] = volt
        z = st.step(z, volt)

    cur, omega, theta = states[:, 0], states[:, 1], states[:, 2] / DEG
    x = gap_m(theta, p)
    force = bell_force(x, p)
    torque = brake_torque(force, p)

    t = case["t0_s"] + np.arange(n) * dt
    cols_all = {
        "time_s": t,
        "voltage_V": volts + rng.normal(0.0, 1.0, n) * ns["voltage_V"],
        "current_A": cur + rng.normal(0.0, ns["current_A"], n),
        "theta_deg": th_meas,
        "x_m": x + rng.normal(0.0, ns["x_m"], n),
        "force_N": f_meas,
        "torque_Nm": torque + rng.normal(0.0, ns["torque_Nm"], n),
        "disc_speed_rad_s": case["disc_speed_rad_s"] + rng.normal(0.0, ns["disc_speed_rad_s"], n),
    }
    columns = {c: cols_all[c] for c in COLUMNS if c in case["channels"]}

    sidecar = {
        "r_eff_m": p["r_eff"],
        "sample_rate_hz": fs,
        "disc_mode": "drag",
        "hardware": "third rig (independent simulator, clean seed model)",
        "description": f"profile {prof}; synthetic, see truth file",
    }

    tracking = {}
    if closed:
        ok = ~np.isnan(th_ref)
        tracking["theta_rmse_deg"] = float(np.sqrt(np.mean((theta[ok] - th_ref[ok]) ** 2)))
        hold = plan["kind"] == 0
        if hold.any():
            tracking["theta_rmse_hold_deg"] = float(
                np.sqrt(np.mean((theta[hold] - th_ref[hold]) ** 2))
            )
        if prof == "force_pi":
            fp = ~np.isnan(plan["force_ref"])
            tracking["force_rmse_N"] = float(
                np.sqrt(np.mean((force[fp] - plan["force_ref"][fp]) ** 2))
            )
            tracking["force_rmse_frac"] = tracking["force_rmse_N"] / p["F_rt"]

    truth = {k: float(val) for k, val in p.items()}
    truth.update(
        {
            "units": {
                "a": "m",
                "b": "-",
                "c": "m",
                "mu": "-",
                "F_rt": "N",
                "p2": "m/deg^2",
                "p1": "m/deg",
                "p0": "m",
                "R": "ohm",
                "L": "H",
                "kb": "V s/rad",
                "kT": "N m/A",
                "M": "kg m^2",
                "v": "N m s/rad",
                "r_eff": "m",
            },
            "kb_equals_kT": case["kb_equals_kT"],
            "profile": prof,
            "rate": fs,
            "n_samples": n,
            "duration_s": n * dt,
            "t0_s": case["t0_s"],
            "theta0_deg": case["theta0_deg"],
            "channels": [c for c in COLUMNS if c in case["channels"]],
            "passes_c": bool(np.max(x) > p["c"]),
            "intended_low": case["intended_low"],
            "peak_force_frac": float(np.max(force) / p["F_rt"]),
            "peak_force_N": float(np.max(force)),
            "theta_range_deg": [float(theta.min()), float(theta.max())],
            "x_range_m": [float(x.min()), float(x.max())],
            "noise_std": ns,
            "theta_quant_bits": bits,
            "theta_quant_step_deg": q_th,
            "theta_pot_range_deg": [pot_lo, pot_hi],
            "force_quant_N": q_f,
            "voltage_log_noise_V": ns["voltage_V"],
            "v_sat_V": v_sat if closed else None,
            "disc_speed_rad_s": case["disc_speed_rad_s"],
            "disc_mode": "drag",
            "tau_load_Nm": 0.0,
            "closed_loop": closed,
            "controller": (
                {
                    "kp_V_per_deg": kp,
                    "ki_V_per_deg_s": ki,
                    "kd_V_s_per_deg": kd,
                    "motor_gain_estimate_deg_per_s_V": k_hat,
                    "outer_force_ki_per_s": ki_f,
                    "outer_force_kp": kp_f,
                }
                if closed
                else None
            ),
            "motor_gain_deg_per_s_V": k_true,
            "tracking": tracking,
            "profile_info": plan["info"],
            "_signals": {
                "voltage_applied_V": volts,
                "current_A": cur,
                "omega_rad_s": omega,
                "theta_deg": theta,
                "x_m": x,
                "force_N": force,
                "torque_Nm": torque,
                "theta_ref_deg": th_ref,
                "force_ref_N": plan.get("force_ref", np.full(n, np.nan)),
            },
        }
    )
    return columns, sidecar, truth


# --------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------


def case_rng(seed: int, index: int) -> np.random.Generator:
    """Generator for case ``index`` of run ``seed``; independent of the number of cases."""
    return np.random.default_rng(np.random.SeedSequence(entropy=seed, spawn_key=(index,)))


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items() if not str(k).startswith("_")}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return obj


def write_case(out: Path, name: str, columns: dict, sidecar: dict, truth: dict) -> None:
    """Write ``NAME.csv``, ``NAME.json`` (sidecar) and ``NAME.truth.json`` into ``out``."""
    names = list(columns)
    data = np.column_stack([columns[c] for c in names])
    np.savetxt(
        out / f"{name}.csv", data, fmt="%.10g", delimiter=",", header=",".join(names), comments=""
    )
    (out / f"{name}.json").write_text(json.dumps(_jsonable(sidecar), indent=2) + "\n")
    (out / f"{name}.truth.json").write_text(json.dumps(_jsonable(truth), indent=2) + "\n")


SUMMARY_FIELDS = (
    "case",
    "profile",
    "rate_hz",
    "n_samples",
    "t0_s",
    "channels",
    "passes_c",
    "intended_low",
    "peak_force_frac",
    "theta_max_deg",
    "theta_rmse_deg",
    "force_rmse_frac",
    "r_eff",
    "F_rt",
)


def generate(seed: int, n_cases: int, out: Path) -> list[tuple[dict, dict, dict, dict]]:
    """Generate and write ``n_cases`` cases; return ``(case, columns, sidecar, truth)`` tuples."""
    out.mkdir(parents=True, exist_ok=True)
    results, rows = [], []
    for i in range(n_cases):
        case = draw_case(case_rng(seed, i))
        cols, side, truth = make_trace(case)
        name = f"case_{i:03d}"
        write_case(out, name, cols, side, truth)
        results.append((case, cols, side, truth))
        rows.append(
            {
                "case": name,
                "profile": truth["profile"],
                "rate_hz": truth["rate"],
                "n_samples": truth["n_samples"],
                "t0_s": f"{truth['t0_s']:.6g}",
                "channels": " ".join(truth["channels"]),
                "passes_c": truth["passes_c"],
                "intended_low": truth["intended_low"],
                "peak_force_frac": f"{truth['peak_force_frac']:.4f}",
                "theta_max_deg": f"{truth['theta_range_deg'][1]:.2f}",
                "theta_rmse_deg": f"{truth['tracking'].get('theta_rmse_deg', float('nan')):.4g}",
                "force_rmse_frac": f"{truth['tracking'].get('force_rmse_frac', float('nan')):.4g}",
                "r_eff": f"{truth['r_eff']:.6g}",
                "F_rt": f"{truth['F_rt']:.6g}",
            }
        )
    with open(out / "cases.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=SUMMARY_FIELDS)
        w.writeheader()
        w.writerows(rows)
    return results


# --------------------------------------------------------------------------------------
# Self-check
# --------------------------------------------------------------------------------------


def check(results: list, out: Path, ivp: bool = True) -> bool:
    """Verify generated cases and print a summary table.

    Checks: all written columns finite and re-read equal to the arrays; true force within
    ``[0, F_rt]``; peak-force fraction consistent with the intent (low: 0.15-0.5 and never
    past ``c``; high: past ``c``, except force control without a stroke); position and
    force tracking RMSE; angle of the exact-discretisation simulation versus a Radau
    ``solve_ivp`` re-run at rtol 1e-10 (< 1e-4 deg).

    Returns
    -------
    bool
        True if every check passed.
    """
    ok_all = True
    hdr = (
        f"{'case':8s} {'profile':12s} {'Hz':>5s} {'n':>5s} {'low':>4s} {'passC':>5s} "
        f"{'pkF/Frt':>7s} {'thmax':>6s} {'rmse_th':>8s} {'rmse_F%':>7s} {'ivp_dth':>8s} channels"
    )
    print(hdr)
    for i, (case, cols, _side, truth) in enumerate(results):
        name = f"case_{i:03d}"
        sig = truth["_signals"]
        p = case["params"]
        msgs = []
        back = np.loadtxt(out / f"{name}.csv", delimiter=",", skiprows=1)
        if not np.all(np.isfinite(back)):
            msgs.append("non-finite")
        if not np.allclose(back, np.column_stack(list(cols.values())), rtol=1e-8, atol=1e-12):
            msgs.append("csv round trip")
        if np.any(np.diff(cols["time_s"]) <= 0):
            msgs.append("time not increasing")
        f = sig["force_N"]
        if f.min() < 0 or f.max() > p["F_rt"] * (1 + 1e-12):
            msgs.append("force range")
        pk = truth["peak_force_frac"]
        if truth["intended_low"]:
            if not (0.15 <= pk <= 0.5) or truth["passes_c"]:
                msgs.append("low intent")
        elif truth["profile"] != "force_pi" or truth["profile_info"].get("position_stroke"):
            if not truth["passes_c"] or pk < 0.97:
                msgs.append("pass-c intent")
        else:
            tgt = max(truth["profile_info"]["target_force_fraction"])
            if abs(pk - tgt) > 0.08 or truth["passes_c"]:
                msgs.append("force-ctrl peak")
        if truth["theta_range_deg"][0] < -60 or truth["theta_range_deg"][1] > 1400:
            msgs.append("theta range")
        dth = float("nan")
        if ivp:
            ref = simulate_motor_ivp(
                p, sig["voltage_applied_V"], 1.0 / truth["rate"], truth["theta0_deg"]
            )
            dth = float(np.max(np.abs(ref[:, 2] - sig["theta_deg"])))
            if dth > 1e-4:
                msgs.append("ivp mismatch")
        tr = truth["tracking"]
        print(
            f"{name:8s} {truth['profile']:12s} {truth['rate']:5d} {truth['n_samples']:5d} "
            f"{str(truth['intended_low'])[0]:>4s} {str(truth['passes_c'])[0]:>5s} {pk:7.3f} "
            f"{truth['theta_range_deg'][1]:6.1f} {tr.get('theta_rmse_deg', float('nan')):8.3f} "
            f"{100 * tr.get('force_rmse_frac', float('nan')):7.2f} {dth:8.1e} "
            f"{','.join(c.split('_')[0] for c in truth['channels'][1:])}"
            + (f"  FAIL: {'; '.join(msgs)}" if msgs else "")
        )
        ok_all &= not msgs
    print("ALL CHECKS PASSED" if ok_all else "SOME CHECKS FAILED")
    return ok_all


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0, help="run seed")
    ap.add_argument("--n", type=int, default=20, help="number of cases")
    ap.add_argument("--out", type=Path, required=True, help="output directory")
    ap.add_argument("--check", action="store_true", help="verify the cases and print a table")
    ap.add_argument("--no-ivp", action="store_true", help="skip the solve_ivp re-run in --check")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    results = generate(args.seed, args.n, args.out)
    print(f"wrote {args.n} cases to {args.out} in {time.perf_counter() - t0:.1f} s")
    if args.check:
        return 0 if check(results, args.out, ivp=not args.no_ivp) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
