"""A second, independent rig simulator: "somebody else's rig" for the tests and studies.

``ewb_ident/rig/`` is one rig: its parameters sit within ~5 % of the seed's, and it was
written by the same hands as the fitted model. This module is written separately, with
other tools and other habits, so that the fit is checked against traces it was not
tuned to:

* parameters drawn over wide ranges (motor gain and time constant, armature L/R 1-5 ms,
  gap polynomial, bell width, exponent and centre, rated force, pad radius 0.10-0.25 m,
  friction 0.25-0.5), not within a few percent of the seed;
* the motor propagated sample by sample with SciPy's ``expm`` of the augmented
  (zero-order-hold) matrix: an exact discretisation, independent of the JAX model;
* profiles: open-loop apply-hold-release voltage steps (once or twice), a PID position
  controller closed at the logging rate on the *measured* (noisy, quantised) angle with
  actuator saturation, and a staircase through the same controller;
* sensors with white noise and quantisation; any optional channel can be left out.

It models the seed chain exactly (no catalog effect): a clean recording of a rig whose
physics the model contains, so a fit must recover its truth.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.linalg import expm

from ewb_ident.data.trace import Trace

OPTIONAL = ("current_A", "torque_Nm", "disc_speed_rad_s")


@dataclass(frozen=True)
class OtherRig:
    """Truth of one unit of the other rig (SI units; gap angle in degrees)."""

    R: float
    L: float
    kb: float
    kT: float
    M: float
    v: float
    p2: float
    p1: float
    p0: float
    F_rt: float
    a: float
    b: float
    c: float
    mu: float
    r_eff_m: float


def draw_rig(rng: np.random.Generator) -> OtherRig:
    """A rig unit drawn over wide, physically sensible ranges."""
    R = rng.uniform(0.4, 2.5)
    L = R * rng.uniform(1e-3, 5e-3)
    kT = rng.uniform(0.04, 0.15)
    kb = kT * rng.uniform(0.9, 1.1)  # SI: back-EMF and torque constants nearly equal
    gain = rng.uniform(6.0, 20.0)  # no-load speed per volt, rad/s/V
    tau_m = rng.uniform(0.01, 0.06)  # mechanical time constant, s
    damping = kT / (R * gain)  # R v + kT kb = kT / gain  ->  v
    v = max(damping - kT * kb / R, 0.0) + rng.uniform(1e-4, 1e-3)
    M = tau_m * (v + kT * kb / R)
    p1 = rng.uniform(0.8e-6, 2.5e-6)
    p2 = rng.uniform(0.0, 6e-9)
    p0 = -rng.uniform(0.4e-3, 1.0e-3)
    return OtherRig(
        R=R, L=L, kb=kb, kT=kT, M=M, v=v, p2=p2, p1=p1, p0=p0,
        F_rt=rng.uniform(2500.0, 6000.0),
        a=rng.uniform(0.45e-3, 0.9e-3),
        b=rng.uniform(1.8, 4.0),
        c=rng.uniform(0.7e-3, 1.3e-3),
        mu=rng.uniform(0.25, 0.5),
        r_eff_m=float(rng.choice([0.10, 0.12, 0.15, 0.2, 0.25])),
    )  # fmt: skip


def angle_at_gap(rig: OtherRig, x_m: float) -> float:
    """Pinion angle (deg) on the rising branch where the gap polynomial equals ``x_m``."""
    if rig.p2 < 1e-15:
        return (x_m - rig.p0) / rig.p1
    disc = rig.p1**2 + 4 * rig.p2 * (x_m - rig.p0)
    return (-rig.p1 + math.sqrt(disc)) / (2 * rig.p2)


def _zoh(rig: OtherRig, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretisation of the motor: state (i, w, theta_rad), input V."""
    A = np.array(
        [
            [-rig.R / rig.L, -rig.kb / rig.L, 0.0],
            [rig.kT / rig.M, -rig.v / rig.M, 0.0],
            [0.0, 1.0, 0.0],
        ]
    )
    big = np.zeros((4, 4))
    big[:3, :3] = A * h
    big[0, 3] = h / rig.L
    E = expm(big)
    return E[:3, :3], E[:3, 3]


@dataclass(frozen=True)
class Sensors:
    """White-noise standard deviations and quantisation steps (0: none)."""

    theta_deg: float = 0.15
    x_m: float = 1.5e-6
    force_N: float = 8.0
    torque_Nm: float = 0.8
    current_A: float = 0.015
    disc_speed_rad_s: float = 0.05
    q_theta_deg: float = 360.0 / 4096  # a 12-bit absolute encoder
    q_force_N: float = 1.0


def record(
    rig: OtherRig,
    *,
    profile: str,
    rate_hz: float,
    duration_s: float = 3.0,
    seed: int = 0,
    drop: tuple[str, ...] = (),
    sensors: Sensors | None = None,
    theta0_deg: float = 0.0,
    name: str = "other_rig",
) -> tuple[Trace, dict]:
    """One recording of ``rig``.

    ``profile``: ``"steps"`` (apply-hold-release open loop), ``"steps2"`` (twice),
    ``"position"`` (PID apply-hold-release, closed at the logging rate) or
    ``"staircase"`` (the PID through rising levels and back).
    """
    sensors = sensors or Sensors()
    rng = np.random.default_rng(seed)
    h = 1.0 / rate_hz
    n = int(round(duration_s * rate_hz)) + 1
    t = np.arange(n) * h
    Ad, Bd = _zoh(rig, h)
    # Targets: through the clamping flank, sometimes past the bell's centre.
    top = angle_at_gap(rig, rig.c + rng.uniform(-0.35, 0.15) * rig.a)
    v_max = 12.0

    def measure_theta(th_deg: float) -> float:
        val = th_deg + sensors.theta_deg * rng.standard_normal()
        q = sensors.q_theta_deg
        return q * round(val / q) if q else val

    s = np.array([0.0, 0.0, math.radians(theta0_deg)])
    states = np.zeros((n, 3))
    volts = np.zeros(n)
    theta_meas = np.zeros(n)
    if profile in ("position", "staircase"):
        if profile == "position":
            levels = [top]
        else:
            levels = [theta0_deg + f * (top - theta0_deg) for f in (0.55, 0.75, 0.9, 1.0)]
        seq = levels + levels[-2::-1] + [theta0_deg]
        t_move = (duration_s - 0.3) / len(seq)
        ramp = min(0.35, 0.6 * t_move)

        def reference(tk: float) -> float:
            k = int((tk - 0.1) // t_move) if tk >= 0.1 else -1
            if k < 0:
                return theta0_deg
            k = min(k, len(seq) - 1)
            start = theta0_deg if k == 0 else seq[k - 1]
            u = min(max((tk - 0.1 - k * t_move) / ramp, 0.0), 1.0)
            return start + (seq[k] - start) * (3 * u * u - 2 * u**3)

        kp, ki, kd = rng.uniform(0.05, 0.15), rng.uniform(0.2, 1.0), rng.uniform(0.0, 4e-4)
        integ, prev_e = 0.0, 0.0
        for k in range(n):
            states[k] = s
            theta_meas[k] = measure_theta(math.degrees(s[2]))
            e = reference(t[k]) - theta_meas[k]
            u = kp * e + ki * integ + kd * (e - prev_e) / h
            u_sat = min(max(u, -v_max), v_max)
            if u == u_sat:  # anti-windup: integrate only when not saturated
                integ += e * h
            prev_e = e
            volts[k] = u_sat
            s = Ad @ s + Bd * u_sat
    elif profile in ("steps", "steps2"):
        v_apply = rng.uniform(3.0, 8.0)
        reps = 2 if profile == "steps2" else 1
        window = (duration_s - 0.2) / reps
        k_start = [int(round((0.1 + r * window) / h)) for r in range(reps)]
        phase, k_on, k_hold_end, rep = "idle", 0, 0, -1
        for k in range(n):
            states[k] = s
            theta_meas[k] = measure_theta(math.degrees(s[2]))
            if rep + 1 < reps and k == k_start[rep + 1]:
                rep, phase, k_on = rep + 1, "apply", k
            if phase == "apply" and math.degrees(s[2]) >= top:
                n_apply = k - k_on
                phase, k_hold_end = "hold", k + int(round(0.35 * window / h))
            if phase == "hold" and k >= k_hold_end:
                phase, k_off = "release", k + n_apply
            if phase == "release" and k >= k_off:
                phase = "idle"
            volts[k] = {"apply": v_apply, "release": -v_apply}.get(phase, 0.0)
            s = Ad @ s + Bd * volts[k]
    else:
        raise ValueError(f"unknown profile {profile!r}")

    theta_deg = np.degrees(states[:, 2])
    x = (rig.p2 * theta_deg + rig.p1) * theta_deg + rig.p0
    force = rig.F_rt / (1.0 + np.abs((x - rig.c) / rig.a) ** (2 * rig.b))
    torque = 2 * rig.mu * force * rig.r_eff_m
    disc = np.full(n, 40.0)

    def noisy(values: np.ndarray, sd: float, q: float = 0.0) -> np.ndarray:
        out = values + sd * rng.standard_normal(n)
        return q * np.round(out / q) if q else out

    channels = {
        "voltage_V": volts,
        "theta_deg": theta_meas,
        "x_m": noisy(x, sensors.x_m),
        "force_N": noisy(force, sensors.force_N, sensors.q_force_N),
        "torque_Nm": noisy(torque, sensors.torque_Nm),
        "current_A": noisy(states[:, 0], sensors.current_A),
        "disc_speed_rad_s": noisy(disc, sensors.disc_speed_rad_s),
    }
    for col in drop:
        channels.pop(col)
    sidecar = {"r_eff_m": rig.r_eff_m, "sample_rate_hz": rate_hz, "disc_mode": "drag"}
    trace = Trace(name=name, time_s=t, channels=channels, sidecar=sidecar)
    truth = asdict(rig) | {"profile": profile, "seed": seed, "sensors": asdict(sensors)}
    return trace, truth
