"""``stiction``: Coulomb friction in motor and gears (motor stage).

A friction torque of constant size ``tau_c`` opposes motion and holds the actuator
still until the motor torque exceeds it: a dead band before the actuator moves, and a
speed deficit in every move. Integrated implicitly (time-stepping with set-valued
friction), so a stuck actuator stays exactly still.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

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


#: Switching speed of the Coulomb friction, rad/s: small enough to hold the actuator
#: still (numerical regularisation of the sign function, not a physical parameter).
STICK_SPEED_RAD_S = 1e-3
#: A dead band (in volts at standstill) narrower than this many times the logged
#: voltage's white noise could be that noise absorbed, not friction.
INPUT_NOISE_RATIO = 3.0


class Stiction(AbstractMechanism):
    """Constant Coulomb friction torque with sticking."""

    id: ClassVar[str] = "stiction"
    STAGE: ClassVar[str] = "motor"
    hook: ClassVar[str] = "motor_friction"
    physics: ClassVar[str] = (
        "Coulomb friction in motor and gears: a dead band before the actuator moves"
    )

    tau_c_Nm: ArrayLike = 0.01

    def param_info(self) -> tuple[ParamInfo, ...]:
        return _INFO

    @property
    def channels(self) -> tuple[str, ...]:
        return ("theta_deg", "current_A")

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        return [{"tau_c_Nm": t} for t in (0.002, 0.01, 0.03, 0.1)]

    def motor_friction(self, s: jnp.ndarray, p: EWBParams, force: jnp.ndarray):
        tau = jnp.asarray(self.tau_c_Nm) + 0.0 * s[1]
        return tau, jnp.full_like(tau, STICK_SPEED_RAD_S)

    def observation(self, values, ctx) -> str:
        return "the actuator starts late and runs slower than the model in every move"

    def describe(self, values, stderr, ctx) -> str:
        """The finding in words; a dead band no wider than a few times the logged
        voltage's noise is named as possibly that noise (a rival this trace cannot rule
        out: see :data:`INPUT_NOISE_RATIO`)."""
        t, se = values["tau_c_Nm"], stderr.get("tau_c_Nm")
        text = f"{self.physics}, tau_c = {fmt_pm(t * 1e3, None if se is None else se * 1e3)} mN*m"
        kT, R = ctx.get("kT"), ctx.get("R")
        if kT and R:
            text += (
                f"; the motor does not move until the current exceeds {t / kT:.2f} A "
                f"(about {t / kT * R:.2f} V at standstill)"
            )
            noise = ctx.get("voltage_noise_V", 0.0)
            if t / kT * R < INPUT_NOISE_RATIO * noise:
                text += (
                    f". Caution: that dead band is within {INPUT_NOISE_RATIO:g}x the logged "
                    f"voltage's own noise ({noise:.2g} V); if that noise is the logger's and "
                    "not the driver's, the model integrates voltage the motor never saw and a "
                    "dead band absorbs it just as well: check with the driver's commanded "
                    "voltage or larger moves"
                )
        return text
