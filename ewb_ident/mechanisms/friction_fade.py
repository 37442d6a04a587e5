"""``friction_fade``: the pad friction coefficient falls as braking energy heats the
pads (torque stage).

``mu = mu0 (1 - phi E)`` with ``E(t) = int T omega_d dt`` the energy dissipated in the
pads since the trace started (J) and ``phi`` the loss of mu per joule (the pad
temperature coefficient over the heat capacity, ``phi_per_K / C``). Pad cooling is
neglected: it is slow (tens of seconds) against a trace of a few seconds. Needs the
``disc_speed_rad_s`` column.

Flexible form (:meth:`FrictionFade.refinements`): fade driven by a temperature that also
cools, ``mu = mu0 (1 - phi E_c)`` with ``dE_c/dt = P - cool_per_s E_c`` (``P = T
omega_d`` the braking power): the heat held by a thin surface layer that the pad body
draws away within ``1 / cool_per_s`` seconds, so mu recovers between applications.
``cool_per_s -> 0`` gives back the energy form.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import AbstractMechanism, fmt_pm, fmt_rate
from ewb_ident.model.params import ParamInfo

# Parameters declared as every mechanism's are (ParamInfo): the same shape, their own values.
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
_COOLING = ParamInfo(
    "cool_per_s",
    "1/s",
    "log",
    1.0,
    lower=1e-3,
    upper=100.0,
    doc="rate at which the pad surface loses the heat that fades it",
)


def retained_energy(power: jnp.ndarray, dt: jnp.ndarray, rate: jnp.ndarray) -> jnp.ndarray:
    """Energy held at each sample when it leaks away at ``rate`` (1/s), J: the exact
    solution of ``dE/dt = P - rate E`` for a power ``P`` (W) held over each interval
    ``dt`` (s), from ``E = 0``."""
    a = jnp.exp(-rate * dt)
    g = -jnp.expm1(-rate * dt) / rate

    def step(e, pk):
        e = a * e + g * pk
        return e, e

    rest = jax.lax.scan(step, jnp.zeros((), power.dtype), power[:-1])[1]
    return jnp.concatenate([jnp.zeros(1, power.dtype), rest])


# Declared as every catalog mechanism is (base.AbstractMechanism): the same shape, its own
# physics.
class FrictionFade(AbstractMechanism):
    """Energy-driven fade of mu; with ``cooling``, the energy leaks away."""

    id: ClassVar[str] = "friction_fade"
    STAGE: ClassVar[str] = "torque"
    hook: ClassVar[str] = "friction_coefficient"
    physics: ClassVar[str] = "the pad friction coefficient falls as braking energy heats the pads"
    NEEDS: ClassVar[tuple[str, ...]] = ("disc_speed_rad_s",)
    SCREENED: ClassVar[bool] = True
    #: The factor uses the dissipated energy (computed from the other factors first).
    USES_ENERGY: ClassVar[bool] = True

    FORM: ClassVar[str] = "cooling"

    cooling: bool = eqx.field(static=True, default=False)
    phi_per_J: ArrayLike = 1e-6
    cool_per_s: ArrayLike = 1.0

    def param_info(self) -> tuple[ParamInfo, ...]:
        return (*_INFO, _COOLING) if self.cooling else _INFO

    def form_start(self) -> dict[str, float]:
        return {"cool_per_s": _COOLING.lower}

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        if self.cooling:
            # A surface that cools within the trace holds a fraction ~ 1 / (rate * T) of
            # the energy: phi grows by as much for the same fade.
            phi = float(self.values()["phi_per_J"])
            span = float(ctx.get("duration_s", 3.0))
            return [
                {"cool_per_s": r, "phi_per_J": phi * max(1.0, 0.5 * r * span)}
                for r in (0.3, 1.0, 3.0)
            ]
        e = float(ctx.get("energy_total_J", 0.0))
        if e <= 0:
            return [{"phi_per_J": 1e-6}]
        return [{"phi_per_J": f / e} for f in (0.003, 0.02, 0.1)]

    def mu_factor(self, ctx):
        if self.cooling:
            return 1.0 - self.phi_per_J * retained_energy(
                ctx["power_W"], ctx["dt"], self.cool_per_s
            )
        return 1.0 - self.phi_per_J * ctx["energy_J"]

    def observation(self, values, ctx) -> str:
        e = float(ctx.get("energy_total_J", 0.0))
        if self.cooling:
            return (
                "the friction coefficient falls while the brake dissipates power and "
                f"recovers within about {1.0 / values['cool_per_s']:.2g} s once it stops"
            )
        return (
            f"the friction coefficient falls by {100 * values['phi_per_J'] * e:.1f} % over the "
            f"trace as {e / 1e3:.1f} kJ are dissipated"
        )

    def describe(self, values, stderr, ctx) -> str:
        phi, se = values["phi_per_J"], stderr.get("phi_per_J")
        text = (
            f"{self.physics}, mu falls by "
            f"{fmt_pm(phi * 1e5, None if se is None else se * 1e5)} % per kJ dissipated"
        )
        if self.cooling:
            rate = fmt_rate(values["cool_per_s"], stderr.get("cool_per_s"))
            text += f" and recovers as the pad surface cools ({rate})"
        return text
