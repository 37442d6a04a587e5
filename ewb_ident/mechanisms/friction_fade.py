"""``friction_fade``: the pad friction coefficient falls as braking energy heats the
pads (torque stage).

``mu = mu0 (1 - phi E)`` with ``E(t) = int T omega_d dt`` the energy dissipated in the
pads since the trace started (J) and ``phi`` the loss of mu per joule (the pad
temperature coefficient over the heat capacity, ``phi_per_K / C``). Pad cooling is
neglected: it is slow (tens of seconds) against a trace of a few seconds. Needs the
``disc_speed_rad_s`` column.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import AbstractMechanism, fmt_pm
from ewb_ident.model.params import ParamInfo

_INFO = (
    ParamInfo(
        "phi_per_J",
        "1/J",
        "log",
        1e-6,
        lower=1e-10,
        upper=1e-3,
        doc="relative loss of mu per joule dissipated in the pads",
    ),
)


class FrictionFade(AbstractMechanism):
    """Energy-driven fade of mu."""

    id: ClassVar[str] = "friction_fade"
    STAGE: ClassVar[str] = "torque"
    hook: ClassVar[str] = "friction_coefficient"
    physics: ClassVar[str] = "the pad friction coefficient falls as braking energy heats the pads"
    NEEDS: ClassVar[tuple[str, ...]] = ("disc_speed_rad_s",)
    SCREENED: ClassVar[bool] = True
    #: The factor uses the dissipated energy (computed from the other factors first).
    USES_ENERGY: ClassVar[bool] = True

    phi_per_J: ArrayLike = 1e-6

    def param_info(self) -> tuple[ParamInfo, ...]:
        return _INFO

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        e = float(ctx.get("energy_total_J", 0.0))
        if e <= 0:
            return [{"phi_per_J": 1e-6}]
        return [{"phi_per_J": f / e} for f in (0.003, 0.02, 0.1)]

    def mu_factor(self, ctx):
        return 1.0 - self.phi_per_J * ctx["energy_J"]

    def observation(self, values, ctx) -> str:
        e = float(ctx.get("energy_total_J", 0.0))
        return (
            f"the friction coefficient falls by {100 * values['phi_per_J'] * e:.1f} % over the "
            f"trace as {e / 1e3:.1f} kJ are dissipated"
        )

    def describe(self, values, stderr, ctx) -> str:
        phi, se = values["phi_per_J"], stderr.get("phi_per_J")
        return (
            f"{self.physics}, mu falls by "
            f"{fmt_pm(phi * 1e5, None if se is None else se * 1e5)} % per kJ dissipated"
        )
