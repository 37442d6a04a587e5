"""``force_hysteresis``: friction in caliper and wedge (force stage).

The force at a given displacement is higher on apply than on release. A Dahl-type
friction state ``z`` in [-1, 1] follows the displacement history,

    dz/dx = (sign(dx) - z) / delta     (exact over each sample's increment),

and ``F = F_bell(x) (1 + h z)``: ``z`` goes to +1 within about ``delta`` of apply travel
and to -1 within ``delta`` of release travel. Teacher-forced, the state is driven by the
measured displacement after a play filter as wide as twice its noise (so that sensor
noise does not drive the state during a hold); in the whole chain by the model's
displacement. The trace is assumed to start after a release (``z = -1``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import AbstractMechanism, fmt_pm
from ewb_ident.model.params import ParamInfo

# Parameters declared as every mechanism's are (ParamInfo): the same shape, their own values.
_INFO = (
    ParamInfo(
        "h",
        "1",
        "log",
        0.02,
        lower=1e-3,
        upper=0.5,
        doc="relative force excess on apply (deficit on release)",
    ),
    ParamInfo(
        "delta_m",
        "m",
        "log",
        2e-5,
        lower=2e-7,
        upper=1e-3,
        doc="displacement over which the friction state reverses",
    ),
)


# Declared as every catalog mechanism is (base.AbstractMechanism): the same shape, its own
# physics.
class ForceHysteresis(AbstractMechanism):
    """Multiplicative Dahl friction on the bell's clamping force."""

    id: ClassVar[str] = "force_hysteresis"
    STAGE: ClassVar[str] = "force"
    hook: ClassVar[str] = "clamp_force"
    physics: ClassVar[str] = "friction hysteresis in caliper and wedge"
    #: delta shapes the reversal; it is not tested against "no effect".
    NUISANCE: ClassVar[tuple[str, ...]] = ("delta_m",)

    h: ArrayLike = 0.02
    delta_m: ArrayLike = 2e-5

    def param_info(self) -> tuple[ParamInfo, ...]:
        return _INFO

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        return [{"h": h, "delta_m": d} for h in (0.01, 0.04) for d in (3e-6, 1.5e-5, 6e-5)]

    def clamp_force(self, x_drive, f_bell, ctx):
        dx = jnp.diff(x_drive, prepend=x_drive[:1])
        delta = jnp.asarray(self.delta_m)

        def step(z, d):
            s = jnp.sign(d)
            z = s - (s - z) * jnp.exp(-jnp.abs(d) / delta)
            return z, z

        z = jax.lax.scan(step, jnp.asarray(-1.0, f_bell.dtype), dx)[1]
        return f_bell * (1.0 + self.h * z)

    # The words, in the same shape as every mechanism's (observation, describe).
    def observation(self, values, ctx) -> str:
        h = values["h"]
        ratio = (1 + h) / (1 - h) - 1
        return (
            f"force is about {100 * ratio:.1f} % higher on apply than on release at the same "
            "displacement"
        )

    def describe(self, values, stderr, ctx) -> str:
        h, se = values["h"], stderr.get("h")
        fmax = float(ctx.get("force_max_N", 0.0))
        text = f"{self.physics}, h = {fmt_pm(h, se)}"
        if fmax > 0:
            H, seH = h * fmax, None if se is None else se * fmax
            text += f" (H = {fmt_pm(H, seH)} N at {fmax:.0f} N)"
        d, sd = values["delta_m"], stderr.get("delta_m")
        text += f", reversing over delta = {fmt_pm(d * 1e6, None if sd is None else sd * 1e6)} um"
        return text
