"""``sensor_offset``: a constant offset on the force or torque sensor (sensor stage).

The sensor reports ``y + offset``. Teacher-forced, the force offset shows in the force
stage (a reading while the pads are open) and, subtracted from the input, in the
torque stage.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import AbstractMechanism, fmt_pm
from ewb_ident.model.params import ParamInfo

_INFO = {
    "force_N": ParamInfo(
        "offset",
        "N",
        "affine",
        0.0,
        scale=10.0,
        lower=-1000.0,
        upper=1000.0,
        doc="offset of the force sensor",
    ),
    "torque_Nm": ParamInfo(
        "offset",
        "N*m",
        "affine",
        0.0,
        scale=1.0,
        lower=-100.0,
        upper=100.0,
        doc="offset of the torque sensor",
    ),
}
_STAGES = {"force_N": ("force", "torque"), "torque_Nm": ("torque",)}


class SensorOffset(AbstractMechanism):
    """A constant offset on one sensor channel."""

    id: ClassVar[str] = "sensor_offset"
    hook: ClassVar[str] = "sensor"
    physics: ClassVar[str] = "a constant offset on the force or torque sensor"

    channel: str = eqx.field(static=True, default="force_N")
    offset: ArrayLike = 0.0

    def __check_init__(self):
        if self.channel not in _INFO:
            raise ValueError(
                f"sensor_offset: channel must be one of {tuple(_INFO)}, got {self.channel!r}"
            )

    def param_info(self) -> tuple[ParamInfo, ...]:
        return (_INFO[self.channel],)

    @property
    def stage(self) -> str:
        return _STAGES[self.channel][0]

    @property
    def variant(self) -> str:
        return f"sensor_offset[{self.channel}]"

    @property
    def stages(self) -> tuple[str, ...]:
        return _STAGES[self.channel]

    @property
    def channels(self) -> tuple[str, ...]:
        return (self.channel,)

    def unsupported_reason(self, channels, ctx) -> str | None:
        if self.channel not in channels:
            return f"the trace has no {self.channel}"
        return None

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        return [{"offset": 0.0}]

    def read(self, channel, y, ctx):
        return y + self.offset if channel == self.channel else y

    def unread(self, channel, y, ctx):
        return y - self.offset if channel == self.channel else y

    def observation(self, values, ctx) -> str:
        unit = _INFO[self.channel].unit
        what = "force" if self.channel == "force_N" else "torque"
        return f"the {what} reading is {values['offset']:+.3g} {unit} off at every level"

    def describe(self, values, stderr, ctx) -> str:
        o, se = values["offset"], stderr.get("offset")
        unit = _INFO[self.channel].unit
        what = "force" if self.channel == "force_N" else "torque"
        return f"a constant offset on the {what} sensor, {fmt_pm(o, se)} {unit}"
