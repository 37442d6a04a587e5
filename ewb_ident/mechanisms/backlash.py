"""``backlash``: play in the worm gear between pinion and wedge (gap stage).

The wedge side follows the pinion only once the pinion has crossed a dead band of
total width ``2 beta`` after a reversal: a play (backlash) operator,

    theta_w[k] = clip(theta_w[k-1], theta[k] - beta, theta[k] + beta),

and the gap polynomial sees ``theta_w``. Where the trace starts in the play is not known:
``theta_w[0] = theta[0] + side * beta`` with ``side`` in [-1, 1] fitted as a nuisance.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import AbstractMechanism, fmt_pm
from ewb_ident.model.params import ParamInfo

_INFO = (
    ParamInfo(
        "beta_deg",
        "deg",
        "log",
        1.0,
        lower=0.05,
        upper=30.0,
        doc="half width of the play, pinion degrees",
    ),
    ParamInfo(
        "side",
        "1",
        "logit",
        0.0,
        lower=-1.0,
        upper=1.0,
        doc="where the trace starts in the play: +1 release side, -1 apply side",
    ),
)


class Backlash(AbstractMechanism):
    """Play operator between the measured pinion angle and the wedge-side angle."""

    id: ClassVar[str] = "backlash"
    STAGE: ClassVar[str] = "gap"
    hook: ClassVar[str] = "wedge_angle"
    physics: ClassVar[str] = "play in the worm gear between pinion and wedge"
    NUISANCE: ClassVar[tuple[str, ...]] = ("side",)

    beta_deg: ArrayLike = 1.0
    side: ArrayLike = 0.9

    def param_info(self) -> tuple[ParamInfo, ...]:
        return _INFO

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        return [{"beta_deg": b, "side": s} for b in (0.3, 1.0, 3.0, 8.0) for s in (0.9, -0.9, 0.0)]

    def wedge_angle(self, theta_deg: jnp.ndarray, ctx: Mapping[str, Any]) -> jnp.ndarray:
        beta = jnp.asarray(self.beta_deg)

        def step(w, th):
            w = jnp.clip(w, th - beta, th + beta)
            return w, w

        return jax.lax.scan(step, theta_deg[0] + self.side * beta, theta_deg)[1]

    def observation(self, values, ctx) -> str:
        return (
            f"the piston stands still for about {2 * values['beta_deg']:.1f} deg of pinion "
            "travel after each reversal"
        )

    def describe(self, values, stderr, ctx) -> str:
        b, se = values["beta_deg"], stderr.get("beta_deg")
        two = fmt_pm(2 * b, None if se is None else 2 * se)
        return f"{self.physics}, total play 2 beta = {two} deg (beta = {fmt_pm(b, se)} deg)"
