"""``friction_speed``: the pad friction coefficient depends on the disc sliding speed
(torque stage).

``mu = mu0 (1 + kappa (omega_d - omega_ref) / omega_ref)``, with ``omega_ref`` the mean
disc speed while the pads are clamped (so ``mu0`` is the friction coefficient there).
Needs the ``disc_speed_rad_s`` column and a disc speed that varies while clamped.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import AbstractMechanism, fmt_pm
from ewb_ident.model.params import ParamInfo

_INFO = (
    ParamInfo(
        "kappa",
        "1",
        "affine",
        0.0,
        scale=0.1,
        lower=-1.0,
        upper=1.0,
        doc="relative change of mu per relative change of disc speed",
    ),
)
#: Smallest relative span of the disc speed (while clamped) at which kappa is fitted.
MIN_SPEED_SPAN = 0.05


class FrictionSpeed(AbstractMechanism):
    """A linear dependence of mu on the disc speed."""

    id: ClassVar[str] = "friction_speed"
    STAGE: ClassVar[str] = "torque"
    hook: ClassVar[str] = "friction_coefficient"
    physics: ClassVar[str] = "the pad friction coefficient depends on the disc sliding speed"
    NEEDS: ClassVar[tuple[str, ...]] = ("disc_speed_rad_s",)
    SCREENED: ClassVar[bool] = True

    kappa: ArrayLike = 0.0

    def param_info(self) -> tuple[ParamInfo, ...]:
        return _INFO

    def unsupported_reason(self, channels, ctx) -> str | None:
        reason = super().unsupported_reason(channels, ctx)
        if reason:
            return reason
        if float(ctx.get("disc_speed_span", 0.0)) < MIN_SPEED_SPAN:
            return "the disc speed hardly varies while the pads are clamped"
        return None

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        return [{"kappa": 0.0}]

    def mu_factor(self, ctx):
        w_ref = ctx["omega_ref"]
        return 1.0 + self.kappa * (ctx["disc_speed"] - w_ref) / w_ref

    def observation(self, values, ctx) -> str:
        k = values["kappa"]
        w_ref = float(ctx.get("omega_ref", 0.0))
        lo, hi = ctx.get("disc_speed_range", (0.0, 0.0))
        change = 100 * k * (hi - lo) / w_ref if w_ref > 0 else 0.0
        trend = "higher" if k > 0 else "lower"
        return (
            f"the friction coefficient is {abs(change):.1f} % {trend} at {hi:.0f} rad/s "
            f"disc speed than at {lo:.0f} rad/s"
        )

    def describe(self, values, stderr, ctx) -> str:
        k, se = values["kappa"], stderr.get("kappa")
        w_ref = float(ctx.get("omega_ref", 0.0))
        return (
            f"{self.physics}, kappa = {fmt_pm(k, se)} (relative change of mu per relative "
            f"change of speed, about {w_ref:.1f} rad/s)"
        )
