"""``backlash``: play in the worm gear between pinion and wedge (gap stage).

The wedge side follows the pinion only once the pinion has crossed a dead band of
total width ``2 beta`` after a reversal: a play (backlash) operator,

    theta_w[k] = clip(theta_w[k-1], theta[k] - beta, theta[k] + beta),

and the gap polynomial sees ``theta_w``. Where the trace starts in the play is not known:
``theta_w[0] = theta[0] + side * beta`` with ``side`` in [-1, 1] fitted as a nuisance.

Flexible form (:meth:`Backlash.refinements`): play with a centring spring. Inside the
dead band the wedge side relaxes toward the pinion, ``d theta_w/dt = relax_per_s (theta
- theta_w)``, solved exactly for a pinion angle linear between samples and then held to
the play's limits; ``relax_per_s -> 0`` gives back the rigid play.
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
_SPRING = ParamInfo(
    "relax_per_s",
    "1/s",
    "log",
    10.0,
    lower=0.1,
    upper=1000.0,
    doc="rate at which a centring spring pulls the wedge side back inside the play",
)


class Backlash(AbstractMechanism):
    """Play operator between the measured pinion angle and the wedge-side angle, rigid or
    with a centring spring (``spring``)."""

    id: ClassVar[str] = "backlash"
    STAGE: ClassVar[str] = "gap"
    hook: ClassVar[str] = "wedge_angle"
    physics: ClassVar[str] = "play in the worm gear between pinion and wedge"
    NUISANCE: ClassVar[tuple[str, ...]] = ("side",)

    # A flexible form declared as every mechanism with one declares it (FORM, its static
    # flag, the parameter it adds; base.AbstractMechanism.refinements).
    FORM: ClassVar[str] = "spring"

    spring: bool = eqx.field(static=True, default=False)
    beta_deg: ArrayLike = 1.0
    side: ArrayLike = 0.9
    relax_per_s: ArrayLike = 0.1

    def param_info(self) -> tuple[ParamInfo, ...]:
        return (*_INFO, _SPRING) if self.spring else _INFO

    def form_start(self) -> dict[str, float]:
        return {"relax_per_s": _SPRING.lower}

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        if self.spring:
            return [{"relax_per_s": r} for r in (3.0, 10.0, 30.0)]
        return [{"beta_deg": b, "side": s} for b in (0.3, 1.0, 3.0, 8.0) for s in (0.9, -0.9, 0.0)]

    def wedge_angle(self, theta_deg: jnp.ndarray, ctx: Mapping[str, Any]) -> jnp.ndarray:
        beta = jnp.asarray(self.beta_deg)
        w0 = theta_deg[0] + self.side * beta
        if not self.spring:

            def step(w, th):
                w = jnp.clip(w, th - beta, th + beta)
                return w, w

            return jax.lax.scan(step, w0, theta_deg)[1]
        # Relaxation toward a pinion angle linear between samples, solved exactly over
        # each interval, then the play's limits.
        x = jnp.maximum(self.relax_per_s * ctx["dt"], 1e-300)
        a, c = jnp.exp(-x), -jnp.expm1(-x) / x

        def sprung(carry, th):
            w, prev = carry
            w = jnp.clip(th + a * (w - prev) - c * (th - prev), th - beta, th + beta)
            return (w, th), w

        rest = jax.lax.scan(sprung, (w0, theta_deg[0]), theta_deg[1:])[1]
        return jnp.concatenate([w0[None], rest])

    # The words, in the same shape as every mechanism's (observation, describe).
    def observation(self, values, ctx) -> str:
        return (
            f"the piston stands still for about {2 * values['beta_deg']:.1f} deg of pinion "
            "travel after each reversal"
        )

    def describe(self, values, stderr, ctx) -> str:
        b, se = values["beta_deg"], stderr.get("beta_deg")
        two = fmt_pm(2 * b, None if se is None else 2 * se)
        text = f"{self.physics}, total play 2 beta = {two} deg (beta = {fmt_pm(b, se)} deg)"
        if self.spring:
            rate = fmt_rate(values["relax_per_s"], stderr.get("relax_per_s"))
            text += f"; a spring pulls the wedge back inside the play ({rate})"
        return text
