"""Physics the seed model leaves out, as the synthetic rig simulates it (one class
per catalog effect)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

from ewb_ident.rig.params import RigError, check_finite, check_nonnegative, check_positive

# --------------------------------------------------------------------------------------
# Catalog effects
# --------------------------------------------------------------------------------------


# Each effect is a frozen dataclass of its parameters whose __post_init__ checks them: the
# classes are alike in shape, their physics is not.
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
    spring_tau_s
        Second form, play with a spring: inside the dead band a centring spring (against
        the wedge side's damping) pulls the wedge side back toward the pinion,
        ``d theta_w/dt = (theta - theta_w) / spring_tau_s``, s. ``0`` (default): a rigid
        play, the wedge side stays where the pinion left it.
    """

    id: ClassVar[str] = "backlash"
    beta_deg: float = 3.0
    initial_side: Literal["release", "apply", "centre"] = "release"
    spring_tau_s: float = 0.0

    def __post_init__(self) -> None:
        check_nonnegative("Backlash", beta_deg=self.beta_deg, spring_tau_s=self.spring_tau_s)
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
    # Fields and checks alike in shape to the other effects' (see RigEffect), not in physics.
    k_w: float = 3e-5
    omega0_rad_s: float = 0.5
    k_r: float = 0.0

    def __post_init__(self) -> None:
        check_nonnegative("WedgeLoadTorque", k_w=self.k_w)
        check_positive("WedgeLoadTorque", omega0_rad_s=self.omega0_rad_s)
        check_finite("WedgeLoadTorque", k_r=self.k_r)


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
        check_nonnegative("ForceHysteresis", h=self.h)
        check_positive("ForceHysteresis", delta_m=self.delta_m)
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
        Delay (``kind="transport"``) or time constant (``kind="lag"``), s.
    kind
        ``"transport"``: a pure delay (a late time stamp, a buffered bus). ``"lag"``: a
        first-order low-pass of time constant ``delay_s`` (an amplifier's or
        anti-alias filter's bandwidth), applied to the channel's samples assuming the
        signal is linear between them. Not for ``theta_deg`` (the controller reads it).
    """

    id: ClassVar[str] = "sensor_delay"
    channel: str = "force_N"
    delay_s: float = 0.015
    kind: Literal["transport", "lag"] = "transport"

    def __post_init__(self) -> None:
        check_nonnegative("SensorDelay", delay_s=self.delay_s)
        if self.channel not in DELAYABLE:
            raise RigError(f"SensorDelay: channel must be one of {DELAYABLE}, got {self.channel!r}")
        if self.kind not in ("transport", "lag"):
            raise RigError(f"SensorDelay: kind must be 'transport' or 'lag', got {self.kind!r}")
        if self.kind == "lag" and self.channel == "theta_deg":
            raise RigError("SensorDelay: kind 'lag' is not simulated on theta_deg")


@dataclass(frozen=True)
class FrictionSpeed(RigEffect):
    """Speed-dependent pad friction, with ``s = (omega_d - omega_ref) / omega_ref``:
    ``mu = mu0 (1 + kappa s)`` (``law="linear"``) or
    ``mu = mu0 (1 + kappa (1 - exp(-s)))`` (``law="exponential"``: the same slope at
    ``omega_ref``, curving toward a plateau above it and steepening below).

    Needs a disc speed that varies (a drag ramp or ``coast``).

    Parameters
    ----------
    kappa
        Relative change of mu per relative change of disc speed at ``omega_ref``,
        dimensionless.
    omega_ref_rad_s
        Disc speed at which ``mu = mu0``, rad/s.
    law
        ``"linear"`` or ``"exponential"``.
    """

    id: ClassVar[str] = "friction_speed"
    kappa: float = -0.15
    omega_ref_rad_s: float = 50.0
    law: Literal["linear", "exponential"] = "linear"

    def __post_init__(self) -> None:
        check_finite("FrictionSpeed", kappa=self.kappa)
        check_positive("FrictionSpeed", omega_ref_rad_s=self.omega_ref_rad_s)
        if self.law not in ("linear", "exponential"):
            raise RigError(
                f"FrictionSpeed: law must be 'linear' or 'exponential', got {self.law!r}"
            )


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
        check_nonnegative("FrictionFade", phi_per_K=self.phi_per_K)
        check_positive(
            "FrictionFade",
            heat_capacity_J_per_K=self.heat_capacity_J_per_K,
            tau_thermal_s=self.tau_thermal_s,
        )


@dataclass(frozen=True)
class SensorOffset(RigEffect):
    """An offset on the force or torque sensor (in the channel's unit):
    ``offset + drift_per_s t`` (t from the trace's start).

    Parameters
    ----------
    channel
        ``"force_N"`` or ``"torque_Nm"``.
    offset
        Offset at the start, N or N m.
    drift_per_s
        Second form, a drifting zero (a strain-gauge bridge warming up): the offset's
        rate, N/s or N m/s. ``0`` (default): a constant offset.
    """

    id: ClassVar[str] = "sensor_offset"
    channel: Literal["force_N", "torque_Nm"] = "force_N"
    offset: float = 40.0
    drift_per_s: float = 0.0

    def __post_init__(self) -> None:
        check_finite("SensorOffset", offset=self.offset, drift_per_s=self.drift_per_s)
        if self.channel not in ("force_N", "torque_Nm"):
            raise RigError(
                f"SensorOffset: channel must be 'force_N' or 'torque_Nm', got {self.channel!r}"
            )


@dataclass(frozen=True)
class CurrentLimit(RigEffect):
    """The driver limits the motor current to ``+-i_max_A``.

    ``kind="clip"``: applied voltage ``V_app = clip(V_cmd, kb omega - R i_max, kb omega +
    R i_max)`` (with ``|i| <= i_max`` this keeps it there). ``kind="soft"``: a driver
    whose limit sets in gradually, ``V_app = kb omega + R i_max tanh((V_cmd - kb omega) /
    (R i_max))``. ``voltage_V`` logs ``V_cmd``.

    Parameters
    ----------
    i_max_A
        Current limit, A.
    kind
        ``"clip"`` or ``"soft"``.
    """

    id: ClassVar[str] = "current_limit"
    i_max_A: float = 2.0
    kind: Literal["clip", "soft"] = "clip"

    def __post_init__(self) -> None:
        check_positive("CurrentLimit", i_max_A=self.i_max_A)
        if self.kind not in ("clip", "soft"):
            raise RigError(f"CurrentLimit: kind must be 'clip' or 'soft', got {self.kind!r}")


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
    stribeck_rad_s
        Second form, Stribeck friction: sliding friction that falls from ``tau_s`` to
        ``tau_c`` with speed, ``tau_c + (tau_s - tau_c) exp(-(omega / stribeck_rad_s)^2)``,
        rad/s. ``0`` (default): it drops to ``tau_c`` at once.
    """

    id: ClassVar[str] = "stiction"
    tau_c_Nm: float = 0.02
    tau_s_Nm: float = 0.03
    band_rad_s: float = 0.01
    stribeck_rad_s: float = 0.0

    def __post_init__(self) -> None:
        check_nonnegative(
            "Stiction",
            tau_c_Nm=self.tau_c_Nm,
            tau_s_Nm=self.tau_s_Nm,
            stribeck_rad_s=self.stribeck_rad_s,
        )
        check_positive("Stiction", band_rad_s=self.band_rad_s)
        if self.tau_s_Nm < self.tau_c_Nm:
            raise RigError(
                f"Stiction: tau_s_Nm={self.tau_s_Nm!r} must be >= tau_c_Nm={self.tau_c_Nm!r}"
            )


#: The catalog effects by id.
# The same ids in the same order as mechanisms.CATALOG, deliberately separate: the rig is
# the truth the tool is tested against and imports nothing of the tool's (only data).
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


def resolve_effects(effects: Iterable[RigEffect | str]) -> dict[str, RigEffect]:
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
