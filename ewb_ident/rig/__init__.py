"""Synthetic brake rig: traces of the EWB test rig with documented truth.

This module is the *truth generator* for tests, datasets and studies. Its physics and
its integrator are written here, independently of the fitting model (it imports only
:mod:`ewb_ident.data.trace`), so that a test that fits a generated trace checks the model
against something it does not share code with.

The rig
-------
A DC motor driven by the applied voltage ``V`` (zero-order hold over each logging
interval) turns the worm pinion (angle ``theta``, rad internally, degrees in traces)::

    L di/dt = V - R i - kb omega
    M domega/dt = kT i - v omega - tau_load - tau_friction
    dtheta/dt = omega

The wedge-side angle ``theta_w`` (degrees; equal to the pinion angle unless there is
``backlash``) sets the piston displacement and the clamping force (generalized bell)::

    x = p2 theta_w**2 + p1 theta_w + p0
    F = F_rt / (1 + |(x - c) / a|**(2 b))
    T = 2 mu F r_eff                      (brake torque at the disc)

The disc is either held at a prescribed speed by a dynamometer (``drag``: constant or a
linear ramp) or coasts on a flywheel (``coast``: ``J domega_d/dt = -T``). The sliding
friction needs sliding: ``T`` is scaled by ``clip(omega_d / 0.1 rad/s, -1, 1)``, which is
1 unless the disc is (nearly) stopped.

Integration: ``jax.lax.scan`` over the logging samples with a fixed-step classical RK4
inner loop (an integer number of sub-steps per sample, at most ``fine_step_s``, default
20 us), jit-compiled in float64 and cached by the static settings (which effects are
switched on, the number of sub-steps, ...), so that many traces with different
parameter values reuse one compiled function.

Catalog effects (:data:`EFFECTS`, ids as in CONTRACTS.md) can be switched on, alone or
together; each is a frozen dataclass holding its physical parameters.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, overload

import jax
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.trace import Trace

__all__ = [
    "EFFECTS",
    "Backlash",
    "CleanRun",
    "CurrentLimit",
    "ForceHysteresis",
    "FrictionFade",
    "FrictionSpeed",
    "RigEffect",
    "RigError",
    "RigParams",
    "SensorDelay",
    "SensorNoise",
    "SensorOffset",
    "Stiction",
    "WedgeLoadTorque",
    "simulate_rig",
    "theta_for_gap",
    "vary",
]

DEG = 180.0 / math.pi  # degrees per radian
#: Disc speed below which the sliding friction fades out, rad/s.
DISC_SLIP_RAD_S = 0.1
#: Relaxation time of the stick phase of the stiction model, s (numerical, not physics).
STICK_RELAX_S = 1e-4
#: Channels with a sensor (noise, quantisation) in the order the noise is drawn.
SENSOR_CHANNELS: tuple[str, ...] = (
    "theta_deg",
    "x_m",
    "force_N",
    "torque_Nm",
    "current_A",
    "disc_speed_rad_s",
)


class RigError(ValueError):
    """Settings of the synthetic rig that cannot be simulated (the message says why)."""


def _check_finite(owner: str, **values: float) -> None:
    for key, value in values.items():
        if (
            isinstance(value, bool)
            or not isinstance(value, numbers.Real)
            or not math.isfinite(value)
        ):
            raise RigError(f"{owner}: {key} must be a finite number, got {value!r}")


def _check_positive(owner: str, **values: float) -> None:
    _check_finite(owner, **values)
    for key, value in values.items():
        if value <= 0:
            raise RigError(f"{owner}: {key} must be > 0, got {value!r}")


def _check_nonnegative(owner: str, **values: float) -> None:
    _check_finite(owner, **values)
    for key, value in values.items():
        if value < 0:
            raise RigError(f"{owner}: {key} must be >= 0, got {value!r}")


# --------------------------------------------------------------------------------------
# Rig parameters and sensors
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RigParams:
    """Physical parameters of the synthetic rig (SI units; angles of the gap in degrees).

    Parameters
    ----------
    R, L, kb, kT, M, v
        Motor resistance (ohm), inductance (H), back-EMF constant (V s/rad), torque
        constant (N m/A), rotor + gear inertia at the pinion (kg m^2), viscous friction
        (N m s/rad).
    p2, p1, p0
        Gap polynomial ``x = p2 theta**2 + p1 theta + p0`` (theta in degrees, x in m).
    F_rt, a, c, b
        Generalized bell of the clamping force: saturation force (N), half width (m),
        centre (m), exponent (dimensionless; the power is ``2 b``).
    mu
        Pad friction coefficient.
    r_eff_m
        Effective pad radius, m.
    disc_mode
        ``"drag"``: the dynamometer holds the disc speed (``disc_speed_rad_s``, ramped
        linearly to ``disc_speed_end_rad_s`` over the trace when that is given);
        ``"coast"``: the disc starts at ``disc_speed_rad_s`` and decelerates by
        ``-T / disc_inertia_kg_m2``.
    disc_speed_rad_s, disc_speed_end_rad_s, disc_inertia_kg_m2
        Disc speed at the start (rad/s), at the end of a drag ramp (rad/s, ``None`` for
        constant speed), disc + flywheel inertia (kg m^2, used in ``coast``).
    """

    R: float = 1.0
    L: float = 2.0e-3
    kb: float = 0.1
    kT: float = 0.1
    M: float = 2.0e-4
    v: float = 2.0e-3
    p2: float = 3.8e-9
    p1: float = 1.5e-6
    p0: float = -8.4e-4
    F_rt: float = 3500.0
    a: float = 6.295e-4
    c: float = 9.57e-4
    b: float = 2.82
    mu: float = 0.35
    r_eff_m: float = 0.15
    disc_mode: Literal["drag", "coast"] = "drag"
    disc_speed_rad_s: float = 50.0
    disc_speed_end_rad_s: float | None = None
    disc_inertia_kg_m2: float = 20.0

    def __post_init__(self) -> None:
        owner = "RigParams"
        _check_positive(
            owner,
            R=self.R,
            L=self.L,
            kT=self.kT,
            M=self.M,
            F_rt=self.F_rt,
            a=self.a,
            b=self.b,
            r_eff_m=self.r_eff_m,
            disc_inertia_kg_m2=self.disc_inertia_kg_m2,
        )
        _check_nonnegative(owner, kb=self.kb, v=self.v, mu=self.mu)
        _check_finite(
            owner, p2=self.p2, p1=self.p1, p0=self.p0, c=self.c, disc=self.disc_speed_rad_s
        )
        if self.disc_mode not in ("drag", "coast"):
            raise RigError(f"{owner}: disc_mode must be 'drag' or 'coast', got {self.disc_mode!r}")
        if self.disc_speed_end_rad_s is not None:
            _check_finite(owner, disc_speed_end_rad_s=self.disc_speed_end_rad_s)
            if self.disc_mode == "coast":
                raise RigError(
                    f"{owner}: disc_speed_end_rad_s={self.disc_speed_end_rad_s!r} is a drag "
                    "ramp; a coasting disc's speed follows from the torque (set it to None)"
                )

    @property
    def disc_varies(self) -> bool:
        """Whether the disc speed changes during a trace (a drag ramp or a coast)."""
        return self.disc_mode == "coast" or (
            self.disc_speed_end_rad_s is not None
            and self.disc_speed_end_rad_s != self.disc_speed_rad_s
        )


#: Fields of :class:`RigParams` that :func:`vary` perturbs (physics of the hardware;
#: pad radius and disc settings are known geometry and operating conditions).
VARIED_PARAMS: tuple[str, ...] = (
    "R",
    "L",
    "kb",
    "kT",
    "M",
    "v",
    "p2",
    "p1",
    "p0",
    "F_rt",
    "a",
    "c",
    "b",
    "mu",
)


def vary(params: RigParams, rng: np.random.Generator, rel: float = 0.05) -> RigParams:
    """A copy of ``params`` perturbed like another unit of the same hardware.

    Each parameter of :data:`VARIED_PARAMS` is multiplied by ``exp(rel * N(0, 1))`` (a
    log-normal factor with relative spread ``rel``; signs are kept), drawn from ``rng``
    in the order of :data:`VARIED_PARAMS`.

    Parameters
    ----------
    params
        The parameters to perturb.
    rng
        ``numpy.random.Generator``, e.g. ``numpy.random.default_rng(seed)``.
    rel
        Relative spread (dimensionless, >= 0).
    """
    _check_nonnegative("vary", rel=rel)
    factors = np.exp(rel * rng.standard_normal(len(VARIED_PARAMS)))
    changes = {
        key: float(getattr(params, key) * f) for key, f in zip(VARIED_PARAMS, factors, strict=True)
    }
    return dataclasses.replace(params, **changes)


def theta_for_gap(params: RigParams, x_m: float) -> float:
    """Wedge-side angle (degrees) at which the gap polynomial reaches ``x_m``.

    The root on the rising branch of ``p2 theta**2 + p1 theta + p0`` (the one reached
    by applying the brake from rest).
    """
    p2, p1, p0 = params.p2, params.p1, params.p0 - x_m
    if p2 == 0.0:
        if p1 == 0.0:
            raise RigError("theta_for_gap: the gap polynomial is constant (p2 = p1 = 0)")
        return -p0 / p1
    disc = p1 * p1 - 4.0 * p2 * p0
    if disc < 0:
        raise RigError(f"theta_for_gap: the gap polynomial never reaches x = {x_m!r} m")
    return (-p1 + math.sqrt(disc)) / (2.0 * p2)


@dataclass(frozen=True)
class SensorNoise:
    """Sensor noise: Gaussian white noise standard deviations and quantisation steps.

    A standard deviation or quantum of 0 switches it off. The noise of all channels is
    drawn in one fixed order from ``numpy.random.default_rng(seed)``, so switching one
    channel off leaves the noise of the others unchanged. ``voltage_V`` is logged exact.

    Parameters
    ----------
    theta_deg, x_m, force_N, torque_Nm, current_A, disc_speed_rad_s
        Standard deviations in the unit of the channel.
    q_theta_deg, q_x_m, q_force_N, q_torque_Nm, q_current_A, q_disc_speed_rad_s
        Quantisation steps (``q * round(value / q)``), in the unit of the channel.
    """

    theta_deg: float = 0.2
    x_m: float = 2e-6
    force_N: float = 10.0
    torque_Nm: float = 1.0
    current_A: float = 0.02
    disc_speed_rad_s: float = 0.0
    q_theta_deg: float = 0.0
    q_x_m: float = 0.0
    q_force_N: float = 0.0
    q_torque_Nm: float = 0.0
    q_current_A: float = 0.0
    q_disc_speed_rad_s: float = 0.0

    def __post_init__(self) -> None:
        _check_nonnegative("SensorNoise", **dataclasses.asdict(self))

    @classmethod
    def none(cls) -> SensorNoise:
        """No noise and no quantisation on any channel."""
        return cls(**{f.name: 0.0 for f in dataclasses.fields(cls)})

    def sigma(self, channel: str) -> float:
        """Noise standard deviation of ``channel``."""
        return float(getattr(self, channel))

    def quantum(self, channel: str) -> float:
        """Quantisation step of ``channel``."""
        return float(getattr(self, "q_" + channel))


# --------------------------------------------------------------------------------------
# Catalog effects
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RigEffect:
    """Base of the switchable catalog effects; ``id`` is the CONTRACTS.md catalog id."""

    id: ClassVar[str] = ""

    def to_dict(self) -> dict[str, Any]:
        """The effect's parameters as plain JSON values."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class Backlash(RigEffect):
    """Play between worm pinion and wedge (a play operator of total width ``2 beta``).

    ``theta_w = clip(theta_w, theta - beta, theta + beta)`` along the path: the wedge
    side follows the pinion only once the pinion has crossed the dead band after a
    reversal. The gap uses ``theta_w``; the angle sensor reads the pinion.

    Parameters
    ----------
    beta_deg
        Half width of the dead band, degrees.
    initial_side
        Where the pinion starts in the play: ``"release"`` (``theta_w = theta0 + beta``,
        as after a release: the first apply crosses the whole band), ``"apply"``
        (``theta_w = theta0 - beta``) or ``"centre"`` (``theta_w = theta0``).
    """

    id: ClassVar[str] = "backlash"
    beta_deg: float = 3.0
    initial_side: Literal["release", "apply", "centre"] = "release"

    def __post_init__(self) -> None:
        _check_nonnegative("Backlash", beta_deg=self.beta_deg)
        if self.initial_side not in ("release", "apply", "centre"):
            raise RigError(
                "Backlash: initial_side must be 'release', 'apply' or 'centre', "
                f"got {self.initial_side!r}"
            )


@dataclass(frozen=True)
class WedgeLoadTorque(RigEffect):
    """Clamping force reacting on the motor:
    ``tau = k_w F tanh(omega_w / omega0) + k_r F``.

    Two forms of the same physics, alone or together: a self-locking worm gear
    (``k_w``: a friction-like torque that opposes motion in both directions and holds the
    actuator when it stops) and a wedge that is not self-locking (``k_r``: a reaction
    torque of one direction that drives the pinion back toward release, so holding the
    force takes current). ``omega_w`` is the wedge-side speed (the pinion speed unless the
    pinion is inside a backlash dead band).

    Parameters
    ----------
    k_w
        Friction-like load torque per clamping force, N m/N (>= 0).
    omega0_rad_s
        Speed scale of the direction switch, rad/s.
    k_r
        Reaction torque per clamping force, N m/N; positive drives the pinion toward
        release.
    """

    id: ClassVar[str] = "wedge_load_torque"
    k_w: float = 3e-5
    omega0_rad_s: float = 0.5
    k_r: float = 0.0

    def __post_init__(self) -> None:
        _check_nonnegative("WedgeLoadTorque", k_w=self.k_w)
        _check_positive("WedgeLoadTorque", omega0_rad_s=self.omega0_rad_s)
        _check_finite("WedgeLoadTorque", k_r=self.k_r)


@dataclass(frozen=True)
class ForceHysteresis(RigEffect):
    """Dahl-type friction in caliper and wedge: ``F = F_bell(x) (1 + h z)``.

    ``dz/dt = (xdot - |xdot| z) / delta_m``, i.e. ``dz/dx = (1 - z sign(xdot)) / delta``:
    ``z`` tends to +1 while the piston advances and to -1 while it retracts, over a
    characteristic displacement ``delta_m``. ``z`` starts at -1 (after a release).

    Parameters
    ----------
    h
        Relative force excess on apply (deficit on release), dimensionless.
    delta_m
        Characteristic displacement, m.
    """

    id: ClassVar[str] = "force_hysteresis"
    h: float = 0.03
    delta_m: float = 2e-5

    def __post_init__(self) -> None:
        _check_nonnegative("ForceHysteresis", h=self.h)
        _check_positive("ForceHysteresis", delta_m=self.delta_m)
        if self.h >= 1:
            raise RigError(f"ForceHysteresis: h must be < 1, got {self.h!r}")


#: Channels whose sensor can lag (sensor_delay).
DELAYABLE: tuple[str, ...] = ("theta_deg", "x_m", "force_N", "torque_Nm", "current_A")


@dataclass(frozen=True)
class SensorDelay(RigEffect):
    """One channel's sensor lags by ``delay_s``: it reads the value at ``t - delay_s``.

    Fractional delays interpolate linearly in the fine-step history; before the start
    the sensor reads the initial value. A delayed ``theta_deg`` is also what the
    position controller sees.

    Parameters
    ----------
    channel
        One of :data:`DELAYABLE`.
    delay_s
        Delay, s.
    """

    id: ClassVar[str] = "sensor_delay"
    channel: str = "force_N"
    delay_s: float = 0.015

    def __post_init__(self) -> None:
        _check_nonnegative("SensorDelay", delay_s=self.delay_s)
        if self.channel not in DELAYABLE:
            raise RigError(f"SensorDelay: channel must be one of {DELAYABLE}, got {self.channel!r}")


@dataclass(frozen=True)
class FrictionSpeed(RigEffect):
    """Speed-dependent pad friction: ``mu = mu0 (1 + kappa (omega_d - omega_ref) / omega_ref)``.

    Needs a disc speed that varies (a drag ramp or ``coast``).

    Parameters
    ----------
    kappa
        Relative change of mu per relative change of disc speed, dimensionless.
    omega_ref_rad_s
        Disc speed at which ``mu = mu0``, rad/s.
    """

    id: ClassVar[str] = "friction_speed"
    kappa: float = -0.15
    omega_ref_rad_s: float = 50.0

    def __post_init__(self) -> None:
        _check_finite("FrictionSpeed", kappa=self.kappa)
        _check_positive("FrictionSpeed", omega_ref_rad_s=self.omega_ref_rad_s)


@dataclass(frozen=True)
class FrictionFade(RigEffect):
    """Fade: pad temperature rise ``dTheta`` lowers friction, ``mu = mu0 (1 - phi dTheta)``.

    ``d(dTheta)/dt = T omega_d / C - dTheta / tau_th`` (``dTheta`` = Theta - Theta0, K;
    starts at 0). The defaults give about 7 % less mu at the end of a 3 s position or
    steps trace at the default drag speed (about 20 K).

    Parameters
    ----------
    phi_per_K
        Relative loss of mu per kelvin, 1/K.
    heat_capacity_J_per_K
        Heat capacity of the pad surface layer, J/K.
    tau_thermal_s
        Cooling time constant, s.
    """

    id: ClassVar[str] = "friction_fade"
    phi_per_K: float = 3.5e-3
    heat_capacity_J_per_K: float = 1500.0
    tau_thermal_s: float = 60.0

    def __post_init__(self) -> None:
        _check_nonnegative("FrictionFade", phi_per_K=self.phi_per_K)
        _check_positive(
            "FrictionFade",
            heat_capacity_J_per_K=self.heat_capacity_J_per_K,
            tau_thermal_s=self.tau_thermal_s,
        )


@dataclass(frozen=True)
class SensorOffset(RigEffect):
    """A constant offset on the force or torque sensor (in the channel's unit).

    Parameters
    ----------
    channel
        ``"force_N"`` or ``"torque_Nm"``.
    offset
        Offset, N or N m.
    """

    id: ClassVar[str] = "sensor_offset"
    channel: Literal["force_N", "torque_Nm"] = "force_N"
    offset: float = 40.0

    def __post_init__(self) -> None:
        _check_finite("SensorOffset", offset=self.offset)
        if self.channel not in ("force_N", "torque_Nm"):
            raise RigError(
                f"SensorOffset: channel must be 'force_N' or 'torque_Nm', got {self.channel!r}"
            )


@dataclass(frozen=True)
class CurrentLimit(RigEffect):
    """The driver limits the motor current to ``+-i_max_A``.

    Applied voltage ``V_app = clip(V_cmd, kb omega - R i_max, kb omega + R i_max)``
    (with ``|i| <= i_max`` this keeps it there); ``voltage_V`` logs ``V_cmd``.

    Parameters
    ----------
    i_max_A
        Current limit, A.
    """

    id: ClassVar[str] = "current_limit"
    i_max_A: float = 2.0

    def __post_init__(self) -> None:
        _check_positive("CurrentLimit", i_max_A=self.i_max_A)


@dataclass(frozen=True)
class Stiction(RigEffect):
    """Coulomb friction with static breakaway in motor and gears (Karnopp stick band).

    Outside the band ``|omega| >= band``: ``tau_f = tau_c sign(omega)``. Inside it the
    friction holds the actuator up to ``tau_s``:
    ``tau_f = clip(tau_ext + M omega / t_stick, -tau_s, tau_s)`` with ``tau_ext = kT i -
    tau_load`` and ``t_stick`` = :data:`STICK_RELAX_S`, so a stuck actuator has
    ``omega = 0`` exactly until ``|tau_ext| > tau_s``.

    Parameters
    ----------
    tau_c_Nm
        Coulomb (sliding) friction torque, N m.
    tau_s_Nm
        Static (breakaway) friction torque, N m (>= tau_c).
    band_rad_s
        Half width of the stick band, rad/s.
    """

    id: ClassVar[str] = "stiction"
    tau_c_Nm: float = 0.02
    tau_s_Nm: float = 0.03
    band_rad_s: float = 0.01

    def __post_init__(self) -> None:
        _check_nonnegative("Stiction", tau_c_Nm=self.tau_c_Nm, tau_s_Nm=self.tau_s_Nm)
        _check_positive("Stiction", band_rad_s=self.band_rad_s)
        if self.tau_s_Nm < self.tau_c_Nm:
            raise RigError(
                f"Stiction: tau_s_Nm={self.tau_s_Nm!r} must be >= tau_c_Nm={self.tau_c_Nm!r}"
            )


#: The catalog effects by id.
EFFECTS: dict[str, type[RigEffect]] = {
    cls.id: cls
    for cls in (
        Backlash,
        WedgeLoadTorque,
        ForceHysteresis,
        SensorDelay,
        FrictionSpeed,
        FrictionFade,
        SensorOffset,
        CurrentLimit,
        Stiction,
    )
}


def _resolve_effects(effects: Iterable[RigEffect | str]) -> dict[str, RigEffect]:
    if isinstance(effects, str | RigEffect):
        effects = (effects,)
    out: dict[str, RigEffect] = {}
    for eff in effects:
        if isinstance(eff, str):
            if eff not in EFFECTS:
                raise RigError(f"unknown effect {eff!r}; the catalog ids are {sorted(EFFECTS)}")
            eff = EFFECTS[eff]()
        if not isinstance(eff, RigEffect) or eff.id not in EFFECTS:
            raise RigError(f"effects must be catalog ids or RigEffect instances, got {eff!r}")
        if eff.id in out:
            raise RigError(f"effect {eff.id!r} given twice; give each effect at most once")
        out[eff.id] = eff
    return out


# --------------------------------------------------------------------------------------
# Input profiles
# --------------------------------------------------------------------------------------

_NOMINAL = RigParams()
#: Velocity feedforward of the position controller (nominal motor), V per deg/s.
KFF_NOMINAL_V_S_PER_DEG = (_NOMINAL.R * _NOMINAL.v + _NOMINAL.kT * _NOMINAL.kb) / _NOMINAL.kT / DEG
#: Acceleration feedforward of the position controller (nominal motor), V per deg/s^2.
KAFF_NOMINAL_V_S2_PER_DEG = _NOMINAL.R * _NOMINAL.M / _NOMINAL.kT / DEG

_CONTROLLER_DEFAULTS: dict[str, float] = {
    "kp_V_per_deg": 0.08,
    "ki_V_per_deg_s": 0.5,
    "kd_V_s_per_deg": 0.0,
    "kff_V_s_per_deg": KFF_NOMINAL_V_S_PER_DEG,
    "kaff_V_s2_per_deg": KAFF_NOMINAL_V_S2_PER_DEG,
    "v_max_V": 12.0,
}


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


def _profile(
    profile: str,
    params: RigParams,
    t: np.ndarray,
    theta0_deg: float,
    options: dict[str, Any],
) -> tuple[np.ndarray, dict[str, Any]]:
    """Voltage (open loop) or reference angle (closed loop), and the resolved settings."""
    duration = float(t[-1])
    if profile == "steps":
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
        _check_finite(f"profile {profile!r}", v_apply_V=o["v_apply_V"])
        for key in ("t_start_s", "t_apply_s", "t_hold_s", "t_release_s"):
            _check_nonnegative(f"profile {profile!r}", **{key: o[key]})
        t1 = o["t_start_s"] + o["t_apply_s"]
        t2 = t1 + o["t_hold_s"]
        t3 = t2 + o["t_release_s"]
        _check_fits(profile, t3, duration)
        # A sample's voltage holds over [t_k, t_k+1): switch on the sample grid.
        volts = np.zeros_like(t)
        volts[(t >= o["t_start_s"] - 1e-12) & (t < t1 - 1e-12)] = o["v_apply_V"]
        volts[(t >= t2 - 1e-12) & (t < t3 - 1e-12)] = -o["v_apply_V"]
        return volts, {"kind": profile, **o}

    if profile in ("position", "staircase"):
        if profile == "position":
            o = _take(
                options,
                {
                    "target_deg": None,
                    "t_start_s": 0.1,
                    "ramp_s": 0.5,
                    "hold_s": 1.2,
                    **_CONTROLLER_DEFAULTS,
                },
                profile,
            )
            if o["target_deg"] is None:
                o["target_deg"] = theta_for_gap(params, params.c - 0.3 * params.a)
            _check_finite(f"profile {profile!r}", target_deg=o["target_deg"])
            _check_positive(f"profile {profile!r}", ramp_s=o["ramp_s"])
            _check_nonnegative(f"profile {profile!r}", t_start_s=o["t_start_s"], hold_s=o["hold_s"])
            t1 = o["t_start_s"] + o["ramp_s"]
            t2 = t1 + o["hold_s"]
            t3 = t2 + o["ramp_s"]
            _check_fits(profile, t3, duration)
            moves = [(o["t_start_s"], t1, o["target_deg"]), (t2, t3, theta0_deg)]
        else:
            o = _take(
                options,
                {
                    "levels_deg": None,
                    "t_start_s": 0.1,
                    "dwell_s": None,
                    "peak_rate_deg_s": 1500.0,
                    "min_ramp_s": 0.05,
                    **_CONTROLLER_DEFAULTS,
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
            _check_positive(
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
            _check_nonnegative(f"profile {profile!r}", dwell_s=o["dwell_s"])
            moves = []
            t0 = o["t_start_s"]
            for ramp, target in zip(ramps, targets, strict=True):
                moves.append((t0, t0 + ramp, target))
                t0 += ramp + o["dwell_s"]
            _check_fits(profile, moves[-1][1], duration)
        _check_positive(f"profile {profile!r}", v_max_V=o["v_max_V"])
        _check_nonnegative(
            f"profile {profile!r}",
            kp_V_per_deg=o["kp_V_per_deg"],
            ki_V_per_deg_s=o["ki_V_per_deg_s"],
            kd_V_s_per_deg=o["kd_V_s_per_deg"],
        )
        _check_finite(
            f"profile {profile!r}",
            kff_V_s_per_deg=o["kff_V_s_per_deg"],
            kaff_V_s2_per_deg=o["kaff_V_s2_per_deg"],
        )
        return _ramps(t, theta0_deg, moves), {"kind": profile, **o}

    if profile == "voltage":
        o = _take(options, {"voltage_V": None}, profile)
        volts = np.asarray(o["voltage_V"], dtype=np.float64)
        return volts, {"kind": profile, "voltage_V": volts.tolist()}

    raise RigError(
        f"unknown profile {profile!r}; use 'steps', 'position', 'staircase' or 'voltage' "
        "(with voltage_V=array)"
    )


# --------------------------------------------------------------------------------------
# The compiled simulator
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Static:
    """Settings that change the compiled program (the cache key)."""

    n_sub: int
    closed_loop: bool
    backlash: bool
    wedge_load: bool
    hysteresis: bool
    friction_speed: bool
    fade: bool
    current_limit: bool
    stiction: bool
    coast: bool
    delay_channel: str | None
    delay_buffer: int


# State vector indices.
_I, _W, _TH, _Z, _HEAT, _WD = range(6)


@functools.lru_cache(maxsize=64)
def _compiled(st: _Static):
    """Build and jit the simulator for one set of static settings."""

    def wedge(y, thw_old, p):
        """Wedge-side angle (deg) and speed (rad/s) given the play state before the step."""
        th_deg = y[_TH] * DEG
        if not st.backlash:
            return th_deg, y[_W]
        beta = p["beta_deg"]
        thw = jnp.clip(thw_old, th_deg - beta, th_deg + beta)
        pushing = ((thw_old <= th_deg - beta) & (y[_W] > 0)) | (
            (thw_old >= th_deg + beta) & (y[_W] < 0)
        )
        return thw, jnp.where(pushing, y[_W], 0.0)

    def observe(y, thw_old, p):
        thw, ww = wedge(y, thw_old, p)
        x = p["p2"] * thw**2 + p["p1"] * thw + p["p0"]
        f_bell = p["F_rt"] / (1.0 + jnp.abs((x - p["c"]) / p["a"]) ** (2.0 * p["b"]))
        force = f_bell * (1.0 + p["hyst_h"] * y[_Z]) if st.hysteresis else f_bell
        mu = p["mu"]
        if st.friction_speed:
            mu = mu * (1.0 + p["kappa"] * (y[_WD] - p["omega_ref"]) / p["omega_ref"])
        if st.fade:
            mu = mu * (1.0 - p["phi"] * y[_HEAT])
        sliding = jnp.clip(y[_WD] / DISC_SLIP_RAD_S, -1.0, 1.0)
        torque = 2.0 * mu * force * p["r_eff"] * sliding
        return {"thw": thw, "ww": ww, "x": x, "force": force, "mu": mu, "torque": torque}

    def rhs(y, volts, thw_old, p):
        o = observe(y, thw_old, p)
        i, w = y[_I], y[_W]
        if st.current_limit:
            lim = p["R"] * p["i_max"]
            volts = jnp.clip(volts, p["kb"] * w - lim, p["kb"] * w + lim)
        di = (volts - p["R"] * i - p["kb"] * w) / p["L"]
        tau_ext = p["kT"] * i
        if st.wedge_load:
            tau_ext = tau_ext - p["k_w"] * o["force"] * jnp.tanh(o["ww"] / p["omega0"])
            tau_ext = tau_ext - p["k_r"] * o["force"]
        if st.stiction:
            stick = jnp.clip(tau_ext + p["M"] * w / STICK_RELAX_S, -p["tau_s"], p["tau_s"])
            tau_f = jnp.where(jnp.abs(w) < p["band"], stick, p["tau_c"] * jnp.sign(w))
        else:
            tau_f = 0.0
        dw = (tau_ext - p["v"] * w - tau_f) / p["M"]
        if st.hysteresis:
            xdot = (2.0 * p["p2"] * o["thw"] + p["p1"]) * o["ww"] * DEG
            dz = (xdot - jnp.abs(xdot) * y[_Z]) / p["delta"]
        else:
            dz = 0.0
        if st.fade:
            dheat = o["torque"] * y[_WD] / p["heat_cap"] - y[_HEAT] / p["tau_th"]
        else:
            dheat = 0.0
        dwd = -o["torque"] / p["J"] if st.coast else p["disc_slope"]
        return jnp.stack([di, dw, w, jnp.asarray(dz, y.dtype), jnp.asarray(dheat, y.dtype), dwd])

    def advance(y, thw, volts, p):
        """One classical RK4 step of size h; then the play operator."""
        h = p["h"]
        k1 = rhs(y, volts, thw, p)
        k2 = rhs(y + 0.5 * h * k1, volts, thw, p)
        k3 = rhs(y + 0.5 * h * k2, volts, thw, p)
        k4 = rhs(y + h * k3, volts, thw, p)
        y = y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        if st.backlash:
            th_deg = y[_TH] * DEG
            thw = jnp.clip(thw, th_deg - p["beta_deg"], th_deg + p["beta_deg"])
        return y, thw

    def channel(y, thw, p, name):
        if name == "theta_deg":
            return y[_TH] * DEG
        if name == "current_A":
            return y[_I]
        o = observe(y, thw, p)
        return {"x_m": o["x"], "force_N": o["force"], "torque_Nm": o["torque"]}[name]

    nb = st.delay_buffer

    def run(p, y0, thw0, xs):
        buf0 = jnp.full((max(nb, 1),), channel(y0, thw0, p, st.delay_channel or "theta_deg"))
        carry0 = (y0, thw0, buf0, jnp.asarray(0, jnp.int64), jnp.zeros_like(y0[0]), y0[_TH] * DEG)

        def sample(carry, x):
            y, thw, buf, j, integ, meas_prev = carry
            o = observe(y, thw, p)
            th_true = y[_TH] * DEG
            out = {
                "theta_deg": th_true,
                "theta_w_deg": o["thw"],
                "x_m": o["x"],
                "force_N": o["force"],
                "torque_Nm": o["torque"],
                "current_A": y[_I],
                "disc_speed_rad_s": y[_WD],
                "mu": o["mu"],
                "hysteresis_z": y[_Z],
                "pad_temperature_rise_K": y[_HEAT],
            }
            th_sensor = th_true
            if st.delay_channel is not None:
                m, frac = p["delay_m"], p["delay_frac"]
                y_a = buf[jnp.mod(j - m, nb)]
                y_b = buf[jnp.mod(j - m - 1, nb)]
                delayed = (1.0 - frac) * y_a + frac * y_b
                out["delayed"] = delayed
                if st.delay_channel == "theta_deg":
                    th_sensor = delayed
            q = p["q_theta"]
            raw = th_sensor + p["sigma_theta"] * x["noise_theta"]
            meas = jnp.where(q > 0, q * jnp.round(raw / jnp.where(q > 0, q, 1.0)), raw)
            out["theta_meas_deg"] = meas
            if st.closed_loop:
                err = x["ref"] - meas
                deriv = -(meas - meas_prev) / p["dt"]
                base = (
                    p["kff"] * x["ref_rate"]
                    + p["kaff"] * x["ref_acc"]
                    + p["kp"] * err
                    + p["kd"] * deriv
                )
                integ_new = integ + err * p["dt"]
                trial = base + p["ki"] * integ_new
                # Anti-windup: stop integrating when saturated and the error pushes further.
                windup = (jnp.abs(trial) > p["v_max"]) & (jnp.sign(trial) == jnp.sign(err))
                integ = jnp.where(windup, integ, integ_new)
                volts = jnp.clip(base + p["ki"] * integ, -p["v_max"], p["v_max"])
            else:
                volts = x["volts"]
            out["voltage_V"] = volts

            def sub(_, c):
                y, thw, buf, j = c
                y, thw = advance(y, thw, volts, p)
                j = j + 1
                if st.delay_channel is not None:
                    buf = buf.at[jnp.mod(j, nb)].set(channel(y, thw, p, st.delay_channel))
                return y, thw, buf, j

            y, thw, buf, j = jax.lax.fori_loop(0, st.n_sub, sub, (y, thw, buf, j))
            return (y, thw, buf, j, integ, meas), out

        _, outs = jax.lax.scan(sample, carry0, xs)
        return outs

    return jax.jit(run)


# --------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CleanRun:
    """The noise-free side of a simulated trace (for tests and studies).

    Parameters
    ----------
    trace
        What the sensors would read without noise and quantisation (sensor effects
        such as ``sensor_delay`` and ``sensor_offset`` included), same columns as the
        noisy trace.
    states
        True physical quantities at the sample times, float64 arrays:
        ``theta_deg`` (pinion), ``theta_w_deg`` (wedge side), ``x_m``, ``force_N``,
        ``torque_Nm``, ``current_A``, ``disc_speed_rad_s``, ``mu``, ``hysteresis_z``,
        ``pad_temperature_rise_K`` and ``theta_ref_deg`` (closed-loop profiles only).
    """

    trace: Trace
    states: Mapping[str, np.ndarray]


@overload
def simulate_rig(
    params: RigParams = ...,
    *,
    profile: str = ...,
    sample_rate_hz: float = ...,
    duration_s: float | None = ...,
    theta0_deg: float = ...,
    effects: Iterable[RigEffect | str] = ...,
    noise: SensorNoise = ...,
    seed: int = ...,
    name: str = ...,
    fine_step_s: float = ...,
    return_clean: Literal[False] = ...,
    **profile_options: Any,
) -> tuple[Trace, dict[str, Any]]: ...


@overload
def simulate_rig(
    params: RigParams = ...,
    *,
    profile: str = ...,
    sample_rate_hz: float = ...,
    duration_s: float | None = ...,
    theta0_deg: float = ...,
    effects: Iterable[RigEffect | str] = ...,
    noise: SensorNoise = ...,
    seed: int = ...,
    name: str = ...,
    fine_step_s: float = ...,
    return_clean: Literal[True],
    **profile_options: Any,
) -> tuple[Trace, dict[str, Any], CleanRun]: ...


def simulate_rig(
    params: RigParams = RigParams(),  # noqa: B008 - frozen, immutable default
    *,
    profile: str = "steps",
    sample_rate_hz: float = 200.0,
    duration_s: float | None = None,
    theta0_deg: float = 0.0,
    effects: Iterable[RigEffect | str] = (),
    noise: SensorNoise = SensorNoise(),  # noqa: B008 - frozen, immutable default
    seed: int = 0,
    name: str = "synthetic",
    fine_step_s: float = 2e-5,
    return_clean: bool = False,
    **profile_options: Any,
):
    """Simulate one recording of the synthetic rig.

    Parameters
    ----------
    params
        Rig parameters (truth).
    profile
        ``"steps"`` (open-loop voltage steps; options ``v_apply_V``, ``t_start_s``,
        ``t_apply_s``, ``t_hold_s``, ``t_release_s``), ``"position"`` (PI position
        control of an apply-hold-release reference; options ``target_deg`` (default: the
        angle where ``x = c - 0.3 a``), ``t_start_s``, ``ramp_s``, ``hold_s``),
        ``"staircase"`` (the same controller through increasing levels and back;
        options ``levels_deg``, ``t_start_s``, ``dwell_s``, ``peak_rate_deg_s``,
        ``min_ramp_s``) or ``"voltage"`` (``voltage_V=array``, one value per sample).
        The controller options are ``kp_V_per_deg``, ``ki_V_per_deg_s``,
        ``kd_V_s_per_deg``, ``kff_V_s_per_deg`` (velocity feedforward, tuned to the
        nominal motor) and ``v_max_V`` (saturation, 12 V); it runs at the logging rate on
        the measured (noisy) angle, and ``voltage_V`` logs its command.
    sample_rate_hz
        Logging rate, Hz (100 to 1000).
    duration_s
        Trace length, s (default 3 s; for ``"voltage"`` it follows from the array).
    theta0_deg
        Initial pinion angle, degrees.
    effects
        Catalog effects: :class:`RigEffect` instances or catalog ids (defaults).
    noise
        Sensor noise; :meth:`SensorNoise.none` for none.
    seed
        Seed of ``numpy.random.default_rng`` for the sensor noise.
    name
        Name of the trace.
    fine_step_s
        Largest RK4 step, s; the step is ``1 / (sample_rate_hz * n)`` for the smallest
        integer ``n`` that keeps it at or below this.
    return_clean
        Also return a :class:`CleanRun` with the noise-free readings and true states.
    **profile_options
        Options of the profile (above).

    Returns
    -------
    trace
        The noisy trace (columns ``time_s``, ``voltage_V``, ``current_A``,
        ``theta_deg``, ``x_m``, ``force_N``, ``torque_Nm``, ``disc_speed_rad_s``).
    truth
        JSON-serialisable truth: rig parameters, effects and their parameters, noise,
        resolved profile settings, seed, sampling and integration settings.
    clean
        Only with ``return_clean=True``.
    """
    if not isinstance(params, RigParams):
        raise RigError(f"params must be a RigParams, got {type(params).__name__}")
    if not isinstance(noise, SensorNoise):
        raise RigError(f"noise must be a SensorNoise, got {type(noise).__name__}")
    _check_finite("simulate_rig", sample_rate_hz=sample_rate_hz, theta0_deg=theta0_deg)
    if not 100.0 <= sample_rate_hz <= 1000.0:
        raise RigError(f"sample_rate_hz must be within 100 to 1000 Hz, got {sample_rate_hz!r}")
    _check_positive("simulate_rig", fine_step_s=fine_step_s)
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise RigError(f"seed must be a non-negative integer, got {seed!r}")
    eff = _resolve_effects(effects)
    dt = 1.0 / sample_rate_hz

    if profile == "voltage":
        volts_in = profile_options.get("voltage_V")
        if volts_in is None:
            raise RigError("profile 'voltage' needs voltage_V=array (one value per sample, V)")
        volts_in = np.asarray(volts_in, dtype=np.float64)
        if volts_in.ndim != 1 or volts_in.size < 2 or not np.all(np.isfinite(volts_in)):
            raise RigError(
                "voltage_V must be a 1-D array of at least 2 finite values, got shape "
                f"{volts_in.shape}"
            )
        n = volts_in.size
        if duration_s is not None and abs((n - 1) * dt - duration_s) > 0.5 * dt:
            raise RigError(
                f"voltage_V has {n} samples = {(n - 1) * dt:.6g} s at {sample_rate_hz} Hz, "
                f"but duration_s={duration_s!r}; leave duration_s out or make them agree"
            )
    else:
        duration_s = 3.0 if duration_s is None else duration_s
        _check_positive("simulate_rig", duration_s=duration_s)
        n = int(round(duration_s * sample_rate_hz)) + 1
    t = np.arange(n) * dt
    duration = float(t[-1])

    signal, resolved = _profile(profile, params, t, theta0_deg, dict(profile_options))
    closed_loop = profile in ("position", "staircase")

    if FrictionSpeed.id in eff and not params.disc_varies:
        raise RigError(
            "effect 'friction_speed' needs a disc speed that varies: set "
            "RigParams(disc_speed_end_rad_s=...) for a drag ramp or disc_mode='coast'"
        )

    n_sub = max(1, math.ceil(dt / fine_step_s * (1.0 - 1e-12)))
    h = dt / n_sub
    if Stiction.id in eff and h > STICK_RELAX_S / 2:
        raise RigError(
            f"effect 'stiction' needs fine_step_s <= {STICK_RELAX_S / 2:g} s, got a step of {h:g} s"
        )

    # Sensor noise: one fixed draw order, independent of which sigmas are zero.
    rng = np.random.default_rng(seed)
    unit_noise = {ch: rng.standard_normal(n) for ch in SENSOR_CHANNELS}

    p: dict[str, float] = {
        key: float(getattr(params, key))
        for key in ("R", "L", "kb", "kT", "M", "v", "p2", "p1", "p0", "F_rt", "a", "c", "b", "mu")
    }
    p.update(
        r_eff=params.r_eff_m,
        J=params.disc_inertia_kg_m2,
        h=h,
        dt=dt,
        sigma_theta=noise.theta_deg,
        q_theta=noise.q_theta_deg,
        disc_slope=0.0,
    )
    if params.disc_mode == "drag" and params.disc_speed_end_rad_s is not None:
        p["disc_slope"] = (params.disc_speed_end_rad_s - params.disc_speed_rad_s) / duration
    thw0 = theta0_deg
    z0 = 0.0
    delay_channel, delay_buffer = None, 0
    if Backlash.id in eff:
        bl = eff[Backlash.id]
        p["beta_deg"] = bl.beta_deg
        thw0 = theta0_deg + {"release": 1.0, "apply": -1.0, "centre": 0.0}[bl.initial_side] * (
            bl.beta_deg
        )
    if WedgeLoadTorque.id in eff:
        e = eff[WedgeLoadTorque.id]
        p.update(k_w=e.k_w, omega0=e.omega0_rad_s, k_r=e.k_r)
    if ForceHysteresis.id in eff:
        e = eff[ForceHysteresis.id]
        p.update(hyst_h=e.h, delta=e.delta_m)
        z0 = -1.0
    if SensorDelay.id in eff:
        e = eff[SensorDelay.id]
        steps = e.delay_s / h
        m = int(math.floor(steps + 1e-9))
        p.update(delay_m=m, delay_frac=max(0.0, steps - m))
        delay_channel = e.channel
        delay_buffer = 1 << max(1, (m + 2 - 1).bit_length())  # power of two >= m + 2
    if FrictionSpeed.id in eff:
        e = eff[FrictionSpeed.id]
        p.update(kappa=e.kappa, omega_ref=e.omega_ref_rad_s)
    if FrictionFade.id in eff:
        e = eff[FrictionFade.id]
        p.update(phi=e.phi_per_K, heat_cap=e.heat_capacity_J_per_K, tau_th=e.tau_thermal_s)
    if CurrentLimit.id in eff:
        p["i_max"] = eff[CurrentLimit.id].i_max_A
    if Stiction.id in eff:
        e = eff[Stiction.id]
        p.update(tau_c=e.tau_c_Nm, tau_s=e.tau_s_Nm, band=e.band_rad_s)
    if closed_loop:
        p.update(
            kp=resolved["kp_V_per_deg"],
            ki=resolved["ki_V_per_deg_s"],
            kd=resolved["kd_V_s_per_deg"],
            kff=resolved["kff_V_s_per_deg"],
            kaff=resolved["kaff_V_s2_per_deg"],
            v_max=resolved["v_max_V"],
        )

    static = _Static(
        n_sub=n_sub,
        closed_loop=closed_loop,
        backlash=Backlash.id in eff,
        wedge_load=WedgeLoadTorque.id in eff,
        hysteresis=ForceHysteresis.id in eff,
        friction_speed=FrictionSpeed.id in eff,
        fade=FrictionFade.id in eff,
        current_limit=CurrentLimit.id in eff,
        stiction=Stiction.id in eff,
        coast=params.disc_mode == "coast",
        delay_channel=delay_channel,
        delay_buffer=delay_buffer,
    )
    if closed_loop:
        # Feedforward from the reference's mean rate and acceleration over each interval.
        ref = signal
        rate = np.diff(ref, append=ref[-1]) / dt
        xs = {
            "noise_theta": unit_noise["theta_deg"],
            "ref": ref,
            "ref_rate": rate,
            "ref_acc": np.diff(rate, prepend=0.0) / dt,
        }
    else:
        xs = {"noise_theta": unit_noise["theta_deg"], "volts": signal}

    y0 = np.array([0.0, 0.0, theta0_deg / DEG, z0, 0.0, params.disc_speed_rad_s])
    with jax.enable_x64(True):
        fn = _compiled(static)
        jp = {
            k: jnp.asarray(val, jnp.int64 if k == "delay_m" else jnp.float64)
            for k, val in p.items()
        }
        outs = fn(
            jp,
            jnp.asarray(y0, jnp.float64),
            jnp.asarray(thw0, jnp.float64),
            {k: jnp.asarray(val, jnp.float64) for k, val in xs.items()},
        )
        outs = {k: np.asarray(val, dtype=np.float64) for k, val in outs.items()}

    # Sensor readings without noise (sensor effects included).
    clean = {
        "voltage_V": outs["voltage_V"],
        "current_A": outs["current_A"].copy(),
        "theta_deg": outs["theta_deg"].copy(),
        "x_m": outs["x_m"].copy(),
        "force_N": outs["force_N"].copy(),
        "torque_Nm": outs["torque_Nm"].copy(),
        "disc_speed_rad_s": outs["disc_speed_rad_s"].copy(),
    }
    if delay_channel is not None:
        clean[delay_channel] = outs["delayed"]
    if SensorOffset.id in eff:
        e = eff[SensorOffset.id]
        clean[e.channel] = clean[e.channel] + e.offset

    measured = dict(clean)
    for ch in SENSOR_CHANNELS:
        if ch == "theta_deg":
            measured[ch] = outs["theta_meas_deg"]  # what the controller saw
            continue
        value = clean[ch] + noise.sigma(ch) * unit_noise[ch]
        q = noise.quantum(ch)
        measured[ch] = q * np.round(value / q) if q > 0 else value

    sidecar: dict[str, Any] = {
        "r_eff_m": params.r_eff_m,
        "sample_rate_hz": float(sample_rate_hz),
        "disc_mode": params.disc_mode,
        "hardware": "synthetic EWB rig (ewb_ident.rig)",
        "description": f"synthetic trace, {profile} profile, seed {seed}",
    }
    if params.disc_mode == "coast":
        sidecar["disc_inertia_kg_m2"] = params.disc_inertia_kg_m2
    trace = Trace(name=name, time_s=t.copy(), channels=measured, sidecar=dict(sidecar))

    truth: dict[str, Any] = {
        "generator": "ewb_ident.rig",
        "name": name,
        "params": dataclasses.asdict(params),
        "effects": {k: e.to_dict() for k, e in eff.items()},
        "noise": dataclasses.asdict(noise),
        "profile": resolved,
        "seed": int(seed),
        "sample_rate_hz": float(sample_rate_hz),
        "duration_s": duration,
        "n_samples": int(n),
        "theta0_deg": float(theta0_deg),
        "fine_step_s": h,
        "n_substeps": n_sub,
    }
    if not return_clean:
        return trace, truth
    states = {
        k: outs[k]
        for k in (
            "theta_deg",
            "theta_w_deg",
            "x_m",
            "force_N",
            "torque_Nm",
            "current_A",
            "disc_speed_rad_s",
            "mu",
            "hysteresis_z",
            "pad_temperature_rise_K",
        )
    }
    if closed_loop:
        states["theta_ref_deg"] = signal.copy()
    clean_trace = Trace(name=name, time_s=t.copy(), channels=clean, sidecar=dict(sidecar))
    return trace, truth, CleanRun(trace=clean_trace, states=states)
