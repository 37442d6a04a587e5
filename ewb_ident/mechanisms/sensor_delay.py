"""``sensor_delay``: one channel lags the others by a fixed time (sensor stage).

The sensor of ``channel`` reports ``y(t - delay)`` (linear interpolation between
samples, so the delay is fitted as a continuous number). Teacher-forced, the channel
is the output of one stage (the model is delayed) and the input of the next (the
reading is advanced by the delay before it drives the model).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import jax.numpy as jnp
from jax.typing import ArrayLike

from ewb_ident.data.stages import CHANNEL_INPUT_OF, CHANNEL_STAGE
from ewb_ident.mechanisms.base import AbstractSensorMechanism, fmt_pm
from ewb_ident.model.params import ParamInfo

_INFO = (ParamInfo("delay_s", "s", "log", 0.01, lower=1e-4, upper=0.25, doc="sensor delay"),)


def shift(y: jnp.ndarray, samples: jnp.ndarray) -> jnp.ndarray:
    """``y`` delayed by a (fractional) number of samples; held at the ends."""
    k = jnp.arange(y.shape[0], dtype=y.dtype)
    return jnp.interp(k - samples, k, y)


class SensorDelay(AbstractSensorMechanism):
    """A fixed delay on one sensor channel."""

    id: ClassVar[str] = "sensor_delay"
    physics: ClassVar[str] = "one channel lags the others by a fixed time"
    CHANNELS: ClassVar[tuple[str, ...]] = tuple(CHANNEL_STAGE)

    delay_s: ArrayLike = 0.01

    def param_info(self) -> tuple[ParamInfo, ...]:
        return _INFO

    @property
    def stage(self) -> str:
        return CHANNEL_STAGE[self.channel]

    @property
    def stages(self) -> tuple[str, ...]:
        tail = (CHANNEL_INPUT_OF[self.channel],) if self.channel in CHANNEL_INPUT_OF else ()
        return (CHANNEL_STAGE[self.channel], *tail)

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        dt = float(ctx.get("dt", 0.005))
        return [{"delay_s": f * dt} for f in (0.3, 1.0, 3.0, 8.0)]

    def read(self, channel, y, ctx):
        if channel != self.channel:
            return y
        return shift(y, self.delay_s / ctx["dt"])

    def unread(self, channel, y, ctx):
        if channel != self.channel:
            return y
        return shift(y, -self.delay_s / ctx["dt"])

    def observation(self, values, ctx) -> str:
        return f"{self.channel} lags the other channels by about {values['delay_s'] * 1e3:.1f} ms"

    def describe(self, values, stderr, ctx) -> str:
        d, se = values["delay_s"], stderr.get("delay_s")
        dt = float(ctx.get("dt", 0.0))
        text = (
            f"a delay in the {self.channel} sensor or its logging, "
            f"{fmt_pm(d * 1e3, None if se is None else se * 1e3)} ms"
        )
        if dt > 0:
            text += f" ({d / dt:.1f} samples)"
        return text
