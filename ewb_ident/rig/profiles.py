"""Drive profiles of the synthetic rig: open-loop voltage steps and position-controlled
runs (the controller and its feed-forward)."""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ewb_ident.rig.params import (
    DEG,
    RigError,
    RigParams,
    check_finite,
    check_nonnegative,
    check_positive,
    theta_for_gap,
)

# --------------------------------------------------------------------------------------
# Input profiles
# --------------------------------------------------------------------------------------

NOMINAL = RigParams()
#: Velocity feedforward of the position controller (nominal motor), V per deg/s.
KFF_NOMINAL_V_S_PER_DEG = (NOMINAL.R * NOMINAL.v + NOMINAL.kT * NOMINAL.kb) / NOMINAL.kT / DEG
#: Acceleration feedforward of the position controller (nominal motor), V per deg/s^2.
KAFF_NOMINAL_V_S2_PER_DEG = NOMINAL.R * NOMINAL.M / NOMINAL.kT / DEG

CONTROLLER_DEFAULTS: dict[str, float] = {
    "kp_V_per_deg": 0.08,
    "ki_V_per_deg_s": 0.5,
    "kd_V_s_per_deg": 0.0,
    "kff_V_s_per_deg": KFF_NOMINAL_V_S_PER_DEG,
    "kaff_V_s2_per_deg": KAFF_NOMINAL_V_S2_PER_DEG,
    "v_max_V": 12.0,
}


#: Profiles under PI position control (the others are open-loop voltage).
CLOSED_LOOP = ("position", "through_c", "staircase")
#: Where the position profiles hold the piston, in bell half-widths ``a`` from ``c``:
#: ``position`` this far short of it, ``through_c`` this far past it.
THROUGH_C_PAST_A = 0.3


def _min_jerk(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10.0 - 15.0 * u + 6.0 * u**2)


def _ramps(t: np.ndarray, theta0: float, moves: Sequence[tuple[float, float, float]]) -> np.ndarray:
    """Reference angle: start at ``theta0``; each move ``(t0, t1, target)`` ramps smoothly."""
    ref = np.full_like(t, theta0)
    level = theta0
    for t0, t1, target in moves:
        ref = np.where(t >= t0, level + (target - level) * _min_jerk((t - t0) / (t1 - t0)), ref)
        level = target
    return ref


def _take(options: dict[str, Any], defaults: Mapping[str, Any], profile: str) -> dict[str, Any]:
    unknown = sorted(set(options) - set(defaults))
    if unknown:
        raise RigError(
            f"profile {profile!r}: unknown option(s) {unknown}; its options are {sorted(defaults)}"
        )
    merged = {**defaults, **options}
    # Plain floats for the JSON truth (NumPy scalars are numbers too).
    return {
        k: float(v) if isinstance(v, numbers.Real) and not isinstance(v, bool) else v
        for k, v in merged.items()
    }


def _check_fits(profile: str, end_s: float, duration_s: float) -> None:
    if end_s > duration_s + 1e-12:
        raise RigError(
            f"profile {profile!r}: the schedule ends at {end_s:.4g} s, after the trace "
            f"ends ({duration_s:.4g} s); make duration_s longer or the phases shorter"
        )


def drive_signal(
    profile: str,
    params: RigParams,
    t: np.ndarray,
    theta0_deg: float,
    options: dict[str, Any],
) -> tuple[np.ndarray, dict[str, Any]]:
    """Voltage (open loop) or reference angle (closed loop), and the resolved settings."""
    duration = float(t[-1])
    if profile == "steps":
        return _steps(t, options, duration)
    if profile in CLOSED_LOOP:
        if profile in ("position", "through_c"):
            o, moves = _position_moves(params, theta0_deg, options, duration, profile)
        else:
            o, moves = _staircase_moves(params, theta0_deg, options, duration)
        _check_controller(profile, o)
        return _ramps(t, theta0_deg, moves), {"kind": profile, **o}
    if profile == "voltage":
        o = _take(options, {"voltage_V": None}, profile)
        volts = np.asarray(o["voltage_V"], dtype=np.float64)
        return volts, {"kind": profile, "voltage_V": volts.tolist()}
    raise RigError(
        f"unknown profile {profile!r}; use 'steps', 'position', 'through_c', 'staircase' or "
        "'voltage' (with voltage_V=array)"
    )


def _steps(t: np.ndarray, options: dict[str, Any], duration: float):
    """Open-loop voltage steps: apply, hold at zero, release (the seed's experiment)."""
    profile = "steps"
    o = _take(
        options,
        {
            "v_apply_V": 4.0,
            "t_start_s": 0.1,
            "t_apply_s": 0.25,
            "t_hold_s": 1.5,
            "t_release_s": 0.25,
        },
        profile,
    )
    check_finite(f"profile {profile!r}", v_apply_V=o["v_apply_V"])
    for key in ("t_start_s", "t_apply_s", "t_hold_s", "t_release_s"):
        check_nonnegative(f"profile {profile!r}", **{key: o[key]})
    t1 = o["t_start_s"] + o["t_apply_s"]
    t2 = t1 + o["t_hold_s"]
    t3 = t2 + o["t_release_s"]
    _check_fits(profile, t3, duration)
    # A sample's voltage holds over [t_k, t_k+1): switch on the sample grid.
    volts = np.zeros_like(t)
    volts[(t >= o["t_start_s"] - 1e-12) & (t < t1 - 1e-12)] = o["v_apply_V"]
    volts[(t >= t2 - 1e-12) & (t < t3 - 1e-12)] = -o["v_apply_V"]
    return volts, {"kind": profile, **o}


def _position_moves(
    params: RigParams, theta0_deg: float, options: dict[str, Any], duration, profile: str
):
    """Apply, hold and release to a target angle (default: the piston 0.3 a short of c;
    ``through_c``: 0.3 a past it, through full clamping)."""
    o = _take(
        options,
        {
            "target_deg": None,
            "t_start_s": 0.1,
            "ramp_s": 0.5,
            "hold_s": 1.2,
            **CONTROLLER_DEFAULTS,
        },
        profile,
    )
    if o["target_deg"] is None:
        past = THROUGH_C_PAST_A if profile == "through_c" else -THROUGH_C_PAST_A
        o["target_deg"] = theta_for_gap(params, params.c + past * params.a)
    check_finite(f"profile {profile!r}", target_deg=o["target_deg"])
    check_positive(f"profile {profile!r}", ramp_s=o["ramp_s"])
    check_nonnegative(f"profile {profile!r}", t_start_s=o["t_start_s"], hold_s=o["hold_s"])
    t1 = o["t_start_s"] + o["ramp_s"]
    t2 = t1 + o["hold_s"]
    t3 = t2 + o["ramp_s"]
    _check_fits(profile, t3, duration)
    moves = [(o["t_start_s"], t1, o["target_deg"]), (t2, t3, theta0_deg)]
    return o, moves


def _staircase_moves(params: RigParams, theta0_deg: float, options: dict[str, Any], duration):
    """Up a staircase of angles (default: four force levels) and back down."""
    profile = "staircase"
    o = _take(
        options,
        {
            "levels_deg": None,
            "t_start_s": 0.1,
            "dwell_s": None,
            "peak_rate_deg_s": 1500.0,
            "min_ramp_s": 0.05,
            **CONTROLLER_DEFAULTS,
        },
        profile,
    )
    if o["levels_deg"] is None:
        o["levels_deg"] = [
            theta_for_gap(params, params.c + k * params.a) for k in (-1.6, -1.2, -0.9, -0.6)
        ]
    levels = [float(x) for x in o["levels_deg"]]
    if len(levels) < 1 or not all(math.isfinite(x) for x in levels):
        raise RigError(f"profile {profile!r}: levels_deg must be finite, got {levels}")
    if any(b <= a for a, b in zip(levels, levels[1:], strict=False)):
        raise RigError(f"profile {profile!r}: levels_deg must increase, got {levels}")
    o["levels_deg"] = levels
    check_positive(
        f"profile {profile!r}",
        peak_rate_deg_s=o["peak_rate_deg_s"],
        min_ramp_s=o["min_ramp_s"],
    )
    targets = levels + levels[-2::-1] + [theta0_deg]
    starts = [theta0_deg] + targets[:-1]
    ramps = [
        max(o["min_ramp_s"], 1.875 * abs(b - a) / o["peak_rate_deg_s"])
        for a, b in zip(starts, targets, strict=True)
    ]
    tail = 0.1
    if o["dwell_s"] is None:
        free = duration - o["t_start_s"] - sum(ramps) - tail
        o["dwell_s"] = free / len(targets)
        if o["dwell_s"] < 0.02:
            raise RigError(
                f"profile {profile!r}: {len(targets)} moves do not fit in "
                f"{duration:.4g} s; make duration_s longer or give fewer levels_deg"
            )
    check_nonnegative(f"profile {profile!r}", dwell_s=o["dwell_s"])
    moves = []
    t0 = o["t_start_s"]
    for ramp, target in zip(ramps, targets, strict=True):
        moves.append((t0, t0 + ramp, target))
        t0 += ramp + o["dwell_s"]
    _check_fits(profile, moves[-1][1], duration)
    return o, moves


def _check_controller(profile: str, o: dict[str, Any]) -> None:
    """The position controller's gains and voltage limit."""
    check_positive(f"profile {profile!r}", v_max_V=o["v_max_V"])
    check_nonnegative(
        f"profile {profile!r}",
        kp_V_per_deg=o["kp_V_per_deg"],
        ki_V_per_deg_s=o["ki_V_per_deg_s"],
        kd_V_s_per_deg=o["kd_V_s_per_deg"],
    )
    check_finite(
        f"profile {profile!r}",
        kff_V_s_per_deg=o["kff_V_s_per_deg"],
        kaff_V_s2_per_deg=o["kaff_V_s2_per_deg"],
    )
