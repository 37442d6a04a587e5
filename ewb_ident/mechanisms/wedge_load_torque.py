"""``wedge_load_torque``: the clamping force reacts on the actuator (motor stage).

The wedge passes part of the clamping force back to the pinion, in either of two forms
or both: ``tau = k_w F tanh(omega / omega0) + k_r F``. A self-locking worm gear gives
the first, a torque that opposes motion in either direction and holds the actuator when
it stops (``omega0``, a small speed, is fitted as a nuisance); a wedge that is not
self-locking gives the second, a reaction of one direction that drives the pinion back
toward release (``k_r > 0``), so that holding the force takes current. The first is
integrated implicitly as a friction-like torque, the second explicitly as a load torque
(:func:`ewb_ident.model.predict.motor_states`); ``F`` is the model's clamping force
at the state's pinion angle.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import RESOLVED_Z, AbstractMechanism, fmt_pm
from ewb_ident.model.params import EWBParams, ParamInfo

# Parameters declared as every mechanism's are (ParamInfo): the same shape, their own values.
_INFO = (
    ParamInfo(
        "k_w",
        "N*m/N",
        "log",
        3e-5,
        lower=1e-8,
        upper=1e-3,
        doc="friction-like load torque at the pinion per newton of clamping force",
    ),
    ParamInfo(
        "omega0_rad_s",
        "rad/s",
        "logit",
        0.5,
        lower=0.01,
        upper=20.0,
        doc="motor speed over which the load torque reverses with the motion",
    ),
    ParamInfo(
        "k_r",
        "N*m/N",
        "affine",
        0.0,
        scale=1e-5,
        lower=-1e-3,
        upper=1e-3,
        doc="reaction torque at the pinion per newton of clamping force, toward release",
    ),
)

#: The reaction form is named in words when k_r exceeds this share of k_w.
REACTION_SHARE = 0.1
#: A resolved part under this share of the other is left out of the words.
NEGLIGIBLE = 0.01


class WedgeLoadTorque(AbstractMechanism):
    """Load torque on the motor proportional to the clamping force."""

    id: ClassVar[str] = "wedge_load_torque"
    STAGE: ClassVar[str] = "motor"
    hook: ClassVar[str] = "motor_friction"
    EXTRA_HOOKS: ClassVar[tuple[str, ...]] = ("load_torque",)
    physics: ClassVar[str] = (
        "the clamping force reacts on the actuator as a load torque (opposing motion: a "
        "self-locking worm gear; toward release: a wedge that is not self-locking)"
    )
    NEEDS: ClassVar[tuple[str, ...]] = ("force_N",)
    NUISANCE: ClassVar[tuple[str, ...]] = ("omega0_rad_s",)

    k_w: ArrayLike = 3e-5
    omega0_rad_s: ArrayLike = 0.5
    k_r: ArrayLike = 0.0

    def param_info(self) -> tuple[ParamInfo, ...]:
        return _INFO

    @property
    def channels(self) -> tuple[str, ...]:
        return ("theta_deg", "current_A")

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        friction = [
            {"k_w": k, "omega0_rad_s": w, "k_r": 0.0}
            for k in (3e-6, 1e-5, 3e-5, 1e-4)
            for w in (0.1, 1.0)
        ]
        reaction = [{"k_w": 1e-7, "omega0_rad_s": 1.0, "k_r": k} for k in (-1e-5, 1e-5, 3e-5)]
        both = [
            {"k_w": k, "omega0_rad_s": 1.0, "k_r": r} for k in (1e-5, 3e-5) for r in (1e-5, 3e-5)
        ]
        return friction + reaction + both

    def implausible_reason(self, values, stderr) -> str:
        """Neither part too large, and at least one resolved. A part at no effect is
        absent, not implausible: a trace of one form drives the other to zero (``k_w``
        below its lower bound, where its log coordinate has run off)."""
        unresolved = []
        for info in _INFO:
            if info.name in self.NUISANCE:
                continue
            v, se = float(values[info.name]), stderr.get(info.name)
            if abs(v) >= info.upper:
                return (
                    f"{info.name} = {v:.3g} {info.unit} is outside the plausible range "
                    f"({info.lower:.3g}, {info.upper:.3g}) {info.unit}"
                )
            absent = info.transform == "log" and v <= info.lower
            if absent or se is None or not np.isfinite(se) or abs(v) < RESOLVED_Z * se:
                shown = (
                    "no standard error"
                    if se is None or absent
                    else f"{v:.3g} ± {se:.2g} {info.unit}"
                )
                unresolved.append(f"{info.name} ({shown})")
        if len(unresolved) == 2:
            return "neither part is resolved: " + ", ".join(unresolved)
        return ""

    def load_torque(self, s: jnp.ndarray, p: EWBParams, force: jnp.ndarray) -> jnp.ndarray:
        return self.k_r * jnp.maximum(force, 0.0) + 0.0 * s[1]

    def motor_friction(
        self, s: jnp.ndarray, p: EWBParams, force: jnp.ndarray, start: jnp.ndarray | None = None
    ):
        tau = self.k_w * jnp.maximum(force, 0.0)
        return tau, jnp.asarray(self.omega0_rad_s) + 0.0 * tau

    def observation(self, values, ctx) -> str:
        text = "the motor turns slower than the model while the clamping force builds"
        if values["k_r"] > REACTION_SHARE * values["k_w"]:
            text += ", and the force drives it back toward release (holding takes current)"
        return text

    def describe(self, values, stderr, ctx) -> str:
        fmax = float(ctx.get("force_max_N", 0.0))
        stall = float(ctx.get("stall_torque_Nm", 0.0))
        parts = []

        def resolved(name):
            se = stderr.get(name)
            return se is not None and abs(values[name]) >= RESOLVED_Z * se

        largest = max(abs(values["k_w"]), abs(values["k_r"]))
        shown = [
            n for n in ("k_w", "k_r") if resolved(n) and abs(values[n]) >= NEGLIGIBLE * largest
        ] or ["k_w", "k_r"]
        for name, words in (("k_w", "opposing motion"), ("k_r", "toward release")):
            if name not in shown:
                continue  # this form is not in the trace
            k, se = values[name], stderr.get(name)
            text = (
                f"{name} = {fmt_pm(k * 1e6, None if se is None else se * 1e6)} uN*m per N "
                f"of clamping force ({words})"
            )
            if fmax > 0:
                text += f", i.e. {k * fmax * 1e3:.0f} mN*m at the peak force of {fmax:.0f} N"
                if stall > 0:
                    text += f" ({100 * abs(k) * fmax / stall:.0f} % of the motor's stall torque)"
            parts.append(text)
        return f"{self.physics}, " + "; ".join(parts)
