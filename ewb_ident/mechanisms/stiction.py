"""``stiction``: Coulomb friction in motor and gears (motor stage).

A friction torque of constant size ``tau_c`` opposes motion and holds the actuator
still until the motor torque exceeds it: a dead band before the actuator moves, and a
speed deficit in every move. Integrated implicitly (time-stepping with set-valued
friction), so a stuck actuator stays exactly still.

Flexible form (:meth:`Stiction.refinements`): Stribeck friction, higher near standstill,
``tau_c + excess exp(-(omega / stribeck_rad_s)^2)`` (omega the motor speed at the start
of each integration sub-step): a breakaway torque ``tau_c + excess`` that falls to the
Coulomb level once the actuator runs; with ``stribeck_rad_s -> 0`` the classic static
plus Coulomb friction. The Stribeck speed is a shape, not checked for plausibility.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import AbstractMechanism, fmt_pm
from ewb_ident.model.params import EWBParams, ParamInfo

_INFO = (
    ParamInfo(
        "tau_c_Nm",
        "N*m",
        "log",
        0.01,
        lower=1e-5,
        upper=1.0,
        doc="Coulomb (and breakaway) friction torque at the pinion",
    ),
)
_STRIBECK = (
    ParamInfo(
        "excess_Nm",
        "N*m",
        "log",
        0.01,
        lower=1e-6,
        upper=1.0,
        doc="breakaway friction torque above the Coulomb level (Stribeck)",
    ),
    ParamInfo(
        "stribeck_rad_s",
        "rad/s",
        "log",
        3.0,
        lower=0.01,
        upper=1000.0,
        doc="motor speed over which the friction falls to the Coulomb level",
    ),
)


#: Switching speed of the Coulomb friction, rad/s: small enough to hold the actuator
#: still (numerical regularisation of the sign function, not a physical parameter).
STICK_SPEED_RAD_S = 1e-3
#: A Stribeck speed below this (rad/s) is reported as static friction: the excess acts
#: only on an actuator held still.
STATIC_ONLY_RAD_S = 0.05
#: A dead band (in volts at standstill) narrower than this many times the logged
#: voltage's white noise could be that noise absorbed, not friction.
INPUT_NOISE_RATIO = 3.0


class Stiction(AbstractMechanism):
    """Coulomb friction torque with sticking: constant, or falling with speed from a
    higher breakaway level (``stribeck``)."""

    id: ClassVar[str] = "stiction"
    STAGE: ClassVar[str] = "motor"
    hook: ClassVar[str] = "motor_friction"
    physics: ClassVar[str] = (
        "Coulomb friction in motor and gears: a dead band before the actuator moves"
    )

    NUISANCE: ClassVar[tuple[str, ...]] = ("stribeck_rad_s",)

    FORM: ClassVar[str] = "stribeck"

    stribeck: bool = eqx.field(static=True, default=False)
    tau_c_Nm: ArrayLike = 0.01
    excess_Nm: ArrayLike = 0.0
    stribeck_rad_s: ArrayLike = 3.0

    def param_info(self) -> tuple[ParamInfo, ...]:
        return (*_INFO, *_STRIBECK) if self.stribeck else _INFO

    def form_start(self) -> dict[str, float]:
        return {"excess_Nm": 0.3 * float(self.values()["tau_c_Nm"])}

    @property
    def channels(self) -> tuple[str, ...]:
        return ("theta_deg", "current_A")

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        if self.stribeck:
            tau = float(self.values()["tau_c_Nm"])
            # The catalog form's level is a mean of breakaway and running friction: the
            # running level lies below it.
            return [
                {"tau_c_Nm": (1.0 - 0.5 * f) * tau, "excess_Nm": f * tau, "stribeck_rad_s": w}
                for f in (0.3, 0.6, 1.0)
                for w in (0.3, 3.0, 30.0)
            ]
        return [{"tau_c_Nm": t} for t in (0.002, 0.01, 0.03, 0.1)]

    def motor_friction(
        self, s: jnp.ndarray, p: EWBParams, force: jnp.ndarray, start: jnp.ndarray | None = None
    ):
        tau = jnp.asarray(self.tau_c_Nm) + 0.0 * s[1]
        if self.stribeck:
            # The level from the speed at the sub-step's start: an actuator held still
            # (omega exactly 0) breaks away only above tau_c + excess.
            w = (s if start is None else start)[1]
            tau = tau + self.excess_Nm * jnp.exp(-jnp.square(w / self.stribeck_rad_s))
        return tau, jnp.full_like(tau, STICK_SPEED_RAD_S)

    def observation(self, values, ctx) -> str:
        return "the actuator starts late and runs slower than the model in every move"

    def describe(self, values, stderr, ctx) -> str:
        """The finding in words; a dead band no wider than a few times the logged
        voltage's noise is named as possibly that noise (a rival this trace cannot rule
        out: see :data:`INPUT_NOISE_RATIO`)."""
        t, se = values["tau_c_Nm"], stderr.get("tau_c_Nm")
        text = f"{self.physics}, tau_c = {fmt_pm(t * 1e3, None if se is None else se * 1e3)} mN*m"
        if self.stribeck:
            e, sx = values["excess_Nm"], stderr.get("excess_Nm")
            ws = values["stribeck_rad_s"]
            fall = (
                f"Stribeck friction, falling off over about {ws:.2g} rad/s of motor speed"
                if ws >= STATIC_ONLY_RAD_S
                else "static friction: the excess holds only while the actuator is still"
            )
            text += (
                f", and {fmt_pm(e * 1e3, None if sx is None else sx * 1e3)} mN*m more to break "
                f"away ({fall})"
            )
        kT, R = ctx.get("kT"), ctx.get("R")
        brk = t + (values["excess_Nm"] if self.stribeck else 0.0)
        if kT and R:
            text += (
                f"; the motor does not move until the current exceeds {brk / kT:.2f} A "
                f"(about {brk / kT * R:.2f} V at standstill)"
            )
            noise = ctx.get("voltage_noise_V", 0.0)
            if brk / kT * R < INPUT_NOISE_RATIO * noise:
                text += (
                    f". Caution: that dead band is within {INPUT_NOISE_RATIO:g}x the logged "
                    f"voltage's own noise ({noise:.2g} V); if that noise is the logger's and "
                    "not the driver's, the model integrates voltage the motor never saw and a "
                    "dead band absorbs it just as well: check with the driver's commanded "
                    "voltage or larger moves"
                )
        return text
