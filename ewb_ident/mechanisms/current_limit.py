"""``current_limit``: the motor driver limits the current (motor stage).

The driver clips the armature voltage so that the current stays within ``+-i_max``:
``V_eff = clip(V, kb omega - R i_max, kb omega + R i_max)``. The logged ``voltage_V``
is the command, so the seed model over-predicts the current, and the acceleration,
whenever the command asks for more.

Flexible form (:meth:`CurrentLimit.refinements`): a limit that sets in gradually,
``V_eff = kb omega + R i_max sat_k((V - kb omega) / (R i_max))`` with
``sat_k(u) = u / (1 + |u|^(1/k))^k``: the sharp clip at ``k -> 0``, ``u / (1 + |u|)`` at
``k = 1``; a ``tanh`` limiter is within 2 % of the limit of ``k = 0.36``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import AbstractMechanism, fmt_pm
from ewb_ident.model.params import EWBParams, ParamInfo

_INFO = (
    ParamInfo(
        "i_max_A",
        "A",
        "log",
        2.0,
        lower=0.05,
        upper=200.0,
        doc="current limit of the motor driver",
    ),
)
_SOFTNESS = ParamInfo(
    "softness",
    "1",
    "logit",
    0.3,
    lower=0.0,
    upper=2.0,
    doc="how gradually the limit sets in (0: a sharp clip)",
)


def soft_saturation(u: jnp.ndarray, k: jnp.ndarray) -> jnp.ndarray:
    """``u / (1 + |u|^(1/k))^k``, written so that it neither overflows nor loses its
    slope for small ``k`` or ``u`` (dimensionless)."""
    au = jnp.maximum(jnp.abs(u), 1e-12)
    return u * jnp.exp(-k * jax.nn.softplus(jnp.log(au) / k))


class CurrentLimit(AbstractMechanism):
    """A current-limiting driver: a state-dependent clip of the armature voltage, sharp
    or gradual (``soft``)."""

    id: ClassVar[str] = "current_limit"
    STAGE: ClassVar[str] = "motor"
    hook: ClassVar[str] = "voltage"
    physics: ClassVar[str] = "the motor driver limits the current, so motor torque saturates"

    FORM: ClassVar[str] = "soft"

    soft: bool = eqx.field(static=True, default=False)
    i_max_A: ArrayLike = 2.0
    softness: ArrayLike = 0.0

    def param_info(self) -> tuple[ParamInfo, ...]:
        return (*_INFO, _SOFTNESS) if self.soft else _INFO

    def form_start(self) -> dict[str, float]:
        return {"softness": 0.3}

    @property
    def channels(self) -> tuple[str, ...]:
        return ("theta_deg", "current_A")

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        if self.soft:
            return [{"softness": k} for k in (0.15, 0.4, 0.8)]
        peak = float(ctx.get("current_peak_A", 0.0))
        if peak > 0:
            return [{"i_max_A": f * peak} for f in (0.4, 0.6, 0.8, 0.95)]
        # No current sensor: the current the voltage asks for at the recorded speed. It
        # bounds the limit from above, loosely (a limit holds the speed down, and a fit
        # of the motor without the limit has compensated), so the starts span 30x below.
        demand = float(ctx.get("current_demand_A", 0.0)) or 4.0
        return [{"i_max_A": f * demand} for f in (0.03, 0.06, 0.12, 0.25, 0.5, 0.8)]

    def voltage(self, V: jnp.ndarray, s: jnp.ndarray, p: EWBParams) -> jnp.ndarray:
        lim = p.R * self.i_max_A
        emf = p.kb * s[1]
        if self.soft:
            return emf + lim * soft_saturation((V - emf) / lim, self.softness)
        return jnp.clip(V, emf - lim, emf + lim)

    def observation(self, values, ctx) -> str:
        return (
            f"the motor current levels off at about {values['i_max_A']:.2f} A where the model "
            "asks for more, and the motor accelerates more slowly"
        )

    def describe(self, values, stderr, ctx) -> str:
        i, se = values["i_max_A"], stderr.get("i_max_A")
        peak = float(ctx.get("current_peak_A", 0.0))
        text = f"{self.physics}, i_max = {fmt_pm(i, se)} A"
        if self.soft:
            k, sk = values["softness"], stderr.get("softness")
            text += f", setting in gradually (softness {fmt_pm(k, sk)}; 0 is a sharp clip)"
        if peak > 0:
            text += f" (the largest recorded current is {peak:.2f} A)"
        return text
