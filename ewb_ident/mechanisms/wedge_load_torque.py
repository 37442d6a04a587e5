"""``wedge_load_torque``: the clamping force reacts on the actuator (motor stage).

The self-locking worm gear passes part of the clamping force back to the pinion as a
torque that opposes motion in either direction, ``tau = k_w F tanh(omega / omega0)``,
and holds the actuator when it stops (``omega0``, a small speed, is fitted as a
nuisance). It is integrated implicitly as a friction-like torque
(:func:`ewb_ident.mechanisms.model.motor_states`); ``F`` is the model's clamping force
at the state's pinion angle.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import jax.numpy as jnp
from jax.typing import ArrayLike

from ..params import EWBParams, ParamInfo
from .base import AbstractMechanism, fmt_pm

_INFO = (
    ParamInfo(
        "k_w",
        "N*m/N",
        "log",
        3e-5,
        lower=1e-7,
        upper=1e-3,
        doc="load torque at the pinion per newton of clamping force",
    ),
    ParamInfo(
        "omega0_rad_s",
        "rad/s",
        "log",
        0.5,
        lower=0.01,
        upper=20.0,
        doc="motor speed over which the load torque reverses with the motion",
    ),
)


class WedgeLoadTorque(AbstractMechanism):
    """Load torque on the motor proportional to the clamping force."""

    id: ClassVar[str] = "wedge_load_torque"
    STAGE: ClassVar[str] = "motor"
    hook: ClassVar[str] = "motor_friction"
    physics: ClassVar[str] = (
        "the clamping force reacts on the actuator as a load torque that opposes motion "
        "(self-locking worm gear)"
    )
    NEEDS: ClassVar[tuple[str, ...]] = ("force_N",)
    NUISANCE: ClassVar[tuple[str, ...]] = ("omega0_rad_s",)

    k_w: ArrayLike = 3e-5
    omega0_rad_s: ArrayLike = 0.5

    def param_info(self) -> tuple[ParamInfo, ...]:
        return _INFO

    @property
    def channels(self) -> tuple[str, ...]:
        return ("theta_deg", "current_A")

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        return [{"k_w": k, "omega0_rad_s": w} for k in (3e-6, 1e-5, 3e-5, 1e-4) for w in (0.1, 1.0)]

    def motor_friction(self, s: jnp.ndarray, p: EWBParams, force: jnp.ndarray):
        tau = self.k_w * jnp.maximum(force, 0.0)
        return tau, jnp.asarray(self.omega0_rad_s) + 0.0 * tau

    def observation(self, values, ctx) -> str:
        return "the motor turns slower than the model while the clamping force builds"

    def describe(self, values, stderr, ctx) -> str:
        k, se = values["k_w"], stderr.get("k_w")
        fmax = float(ctx.get("force_max_N", 0.0))
        stall = float(ctx.get("stall_torque_Nm", 0.0))
        text = (
            f"{self.physics}, k_w = {fmt_pm(k * 1e6, None if se is None else se * 1e6)} "
            "uN*m per N of clamping force"
        )
        if fmax > 0:
            text += f", i.e. {k * fmax * 1e3:.0f} mN*m at the peak force of {fmax:.0f} N"
            if stall > 0:
                text += f" ({100 * k * fmax / stall:.0f} % of the motor's stall torque)"
        return text
