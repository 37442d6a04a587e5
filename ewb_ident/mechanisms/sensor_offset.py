"""``sensor_offset``: an offset on the force or torque sensor (sensor stage).

The sensor reports ``y + offset``. Teacher-forced, the force offset shows in the force
stage (a reading while the pads are open) and, subtracted from the input, in the
torque stage. Flexible form (:meth:`SensorOffset.refinements`): a zero that drifts
linearly in time, ``y + offset + drift_per_s t`` (a strain-gauge bridge warming up; ``t``
from the trace's start).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
from jax.typing import ArrayLike

from ewb_ident.mechanisms.base import AbstractSensorMechanism, fmt_pm
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
_DRIFT = {
    "force_N": ParamInfo(
        "drift_per_s",
        "N/s",
        "affine",
        0.0,
        scale=10.0,
        lower=-1000.0,
        upper=1000.0,
        doc="drift of the force sensor's zero",
    ),
    "torque_Nm": ParamInfo(
        "drift_per_s",
        "N*m/s",
        "affine",
        0.0,
        scale=1.0,
        lower=-100.0,
        upper=100.0,
        doc="drift of the torque sensor's zero",
    ),
}
_STAGES = {"force_N": ("force", "torque"), "torque_Nm": ("torque",)}


class SensorOffset(AbstractSensorMechanism):
    """An offset on one sensor channel: constant, or drifting linearly (``drift``)."""

    id: ClassVar[str] = "sensor_offset"
    physics: ClassVar[str] = "a constant offset on the force or torque sensor"
    CHANNELS: ClassVar[tuple[str, ...]] = tuple(_INFO)

    FORM: ClassVar[str] = "drift"

    drift: bool = eqx.field(static=True, default=False)
    offset: ArrayLike = 0.0
    drift_per_s: ArrayLike = 0.0

    def param_info(self) -> tuple[ParamInfo, ...]:
        if self.drift:
            return (_INFO[self.channel], _DRIFT[self.channel])
        return (_INFO[self.channel],)

    @property
    def may_be_null(self) -> tuple[str, ...]:
        return ("offset",) if self.drift else ()

    @property
    def stage(self) -> str:
        return _STAGES[self.channel][0]

    @property
    def stages(self) -> tuple[str, ...]:
        return _STAGES[self.channel]

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        if self.drift:
            return [{"drift_per_s": 0.0}]
        return [{"offset": 0.0}]

    def form_start(self) -> dict[str, float]:
        return {"drift_per_s": 0.0}

    def _error(self, ctx):
        if self.drift:
            return self.offset + self.drift_per_s * ctx["t"]
        return self.offset

    def read(self, channel, y, ctx):
        return y + self._error(ctx) if channel == self.channel else y

    def unread(self, channel, y, ctx):
        return y - self._error(ctx) if channel == self.channel else y

    def observation(self, values, ctx) -> str:
        unit = _INFO[self.channel].unit
        what = "force" if self.channel == "force_N" else "torque"
        if self.drift:
            return (
                f"the {what} reading is {values['offset']:+.3g} {unit} off at the start, "
                f"and its zero drifts by {values['drift_per_s']:+.3g} {unit} per second"
            )
        return f"the {what} reading is {values['offset']:+.3g} {unit} off at every level"

    def describe(self, values, stderr, ctx) -> str:
        o, se = values["offset"], stderr.get("offset")
        unit = _INFO[self.channel].unit
        what = "force" if self.channel == "force_N" else "torque"
        if self.drift:
            d, sd = values["drift_per_s"], stderr.get("drift_per_s")
            return (
                f"an offset on the {what} sensor whose zero drifts, {fmt_pm(o, se)} {unit} "
                f"at the start and {fmt_pm(d, sd)} {unit}/s"
            )
        return f"a constant offset on the {what} sensor, {fmt_pm(o, se)} {unit}"
