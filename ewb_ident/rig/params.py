"""The synthetic rig's true parameters, their unit-to-unit spread, and its sensor noise."""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ewb_ident.data.trace import InputError

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


class RigError(InputError):
    """Settings of the synthetic rig that cannot be simulated (the message says why)."""


def check_finite(owner: str, **values: float) -> None:
    for key, value in values.items():
        if (
            isinstance(value, bool)
            or not isinstance(value, numbers.Real)
            or not math.isfinite(value)
        ):
            raise RigError(f"{owner}: {key} must be a finite number, got {value!r}")


def check_positive(owner: str, **values: float) -> None:
    check_finite(owner, **values)
    for key, value in values.items():
        if value <= 0:
            raise RigError(f"{owner}: {key} must be > 0, got {value!r}")


def check_nonnegative(owner: str, **values: float) -> None:
    check_finite(owner, **values)
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

    # The seed model's parameters (model.params.EWBParams, same names and values),
    # deliberately separate: the rig is the truth the tool is tested against and imports
    # nothing of the tool's (only data).
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
        check_positive(
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
        check_nonnegative(owner, kb=self.kb, v=self.v, mu=self.mu)
        check_finite(
            owner, p2=self.p2, p1=self.p1, p0=self.p0, c=self.c, disc=self.disc_speed_rad_s
        )
        if self.disc_mode not in ("drag", "coast"):
            raise RigError(f"{owner}: disc_mode must be 'drag' or 'coast', got {self.disc_mode!r}")
        if self.disc_speed_end_rad_s is not None:
            check_finite(owner, disc_speed_end_rad_s=self.disc_speed_end_rad_s)
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
    check_nonnegative("vary", rel=rel)
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
        check_nonnegative("SensorNoise", **dataclasses.asdict(self))

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
