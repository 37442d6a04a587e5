"""A learned term: a function of recorded and model signals plugged in at one place of
the chain, for physics outside the catalog (not itself a catalog mechanism).

The term is a linear combination of basis series, ``term[k] = sum_j c_j phi_j[k]``,
where each ``phi_j`` is a dimensionless function of the trace's signals (a column of
the basis built by :mod:`ewb_ident.diagnosis.discovery`, carried in the fit's data as
``data["learned"][place]``) and ``c_j`` is in the unit of the place. The *place* is
where in the model the term acts (:data:`PLACES`): an added voltage or load torque in
the motor, a shift of the piston or of the angle the gap curve sees, a shift of the
displacement the bell sees or an added force, a factor on the friction coefficient,
an added brake torque, or the reading of one sensor.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.stages import CHANNEL_INPUT_OF, CHANNEL_STAGE
from ewb_ident.data.trace import COLUMNS
from ewb_ident.mechanisms.base import AbstractMechanism
from ewb_ident.model.params import ParamInfo


class Place(NamedTuple):
    """One place of the chain a learned term can act at."""

    stage: str
    hook: str
    unit: str
    quantity: str  # the symbol of what the term adds, for equations
    words: str


#: Places a learned term can act at (``sensor.<channel>`` for each measured channel).
PLACES: dict[str, Place] = {
    "motor.electrical": Place(
        "motor", "voltage_series", "V", "ΔV", "a voltage added at the motor's terminals"
    ),
    "motor.mechanical": Place(
        "motor", "load_series", "N*m", "τ_load", "a load torque on the motor"
    ),
    "drive": Place("gap", "output", "m", "Δx", "a shift of the piston from the gap curve"),
    "gap": Place("gap", "wedge_angle", "deg", "Δθ", "a shift of the angle the gap curve sees"),
    "force.input": Place(
        "force", "force_input", "m", "Δx_bell", "a shift of the displacement the bell sees"
    ),
    "force.output": Place("force", "output", "N", "ΔF", "a force added to the bell's"),
    "friction": Place(
        "torque",
        "friction_coefficient",
        "1",
        "Δμ/μ",
        "a relative change of the friction coefficient",
    ),
    "torque.output": Place("torque", "output", "N*m", "ΔT", "a brake torque added"),
}
for _ch, _stage in CHANNEL_STAGE.items():
    PLACES[f"sensor.{_ch}"] = Place(
        _stage, "sensor", COLUMNS[_ch], f"Δ{_ch}", f"an error of the {_ch} sensor's reading"
    )


class LearnedTerm(AbstractMechanism):
    """A learned term at one place: coefficients of basis series (see module docstring).

    Attributes
    ----------
    place
        A key of :data:`PLACES`.
    names
        The basis series' names (their expressions, for the equation).
    scales
        Size of each coefficient, in the place's unit (one unit of the optimiser's
        coordinate).
    coef
        The coefficients, in the place's unit.
    """

    id: ClassVar[str] = "learned_term"
    physics: ClassVar[str] = "physics not in the catalog"

    place: str = eqx.field(static=True, default="force.output")
    names: tuple[str, ...] = eqx.field(static=True, default=())
    scales: tuple[float, ...] = eqx.field(static=True, default=())
    coef: Any = None

    def __check_init__(self):
        if self.place not in PLACES:
            raise ValueError(f"learned term: unknown place {self.place!r}; known: {sorted(PLACES)}")
        if len(self.scales) != len(self.names):
            raise ValueError("learned term: one scale per basis series")

    @property
    def stage(self) -> str:
        return PLACES[self.place].stage

    @property
    def hook(self) -> str:  # type: ignore[override]
        return PLACES[self.place].hook

    @property
    def variant(self) -> str:
        return f"learned[{self.place}]"

    @property
    def channel(self) -> str | None:
        """The sensor's channel for a sensor place."""
        return self.place.split(".", 1)[1] if self.place.startswith("sensor.") else None

    @property
    def stages(self) -> tuple[str, ...]:
        ch = self.channel
        if ch is None:
            return (self.stage,)
        inp = CHANNEL_INPUT_OF.get(ch)
        return (CHANNEL_STAGE[ch],) + ((inp,) if inp else ())

    @property
    def channels(self) -> tuple[str, ...]:
        ch = self.channel
        return (ch,) if ch else super().channels

    def param_info(self) -> tuple[ParamInfo, ...]:
        unit = PLACES[self.place].unit
        return tuple(
            ParamInfo(f"c{j}", unit, "affine", 0.0, scale=float(s))
            for j, s in enumerate(self.scales)
        )

    def _coef(self) -> jnp.ndarray:
        if self.coef is None:
            return jnp.zeros(len(self.names))
        return jnp.asarray(self.coef)

    def values(self) -> dict[str, float]:
        return {f"c{j}": v for j, v in enumerate(self.coefficients)}

    @property
    def coefficients(self) -> tuple[float, ...]:
        """The coefficients, in the place's unit per basis column."""
        return tuple(float(v) for v in np.asarray(self._coef(), dtype=float))

    def with_values(self, values: Mapping[str, Any]) -> LearnedTerm:
        cur = {f"c{j}": v for j, v in enumerate(list(self._coef()))}
        bad = sorted(set(values) - set(cur))
        if bad:
            raise ValueError(f"{self.variant}: unknown parameter(s) {bad}")
        cur |= dict(values)
        coef = (
            jnp.stack([jnp.asarray(cur[f"c{j}"], dtype=float) for j in range(len(self.names))])
            if self.names
            else jnp.zeros(0)
        )
        return LearnedTerm(place=self.place, names=self.names, scales=self.scales, coef=coef)

    def static_config(self) -> tuple[tuple[str, Any], ...]:
        return (("place", self.place), ("names", self.names), ("scales", self.scales))

    def starts(self, ctx) -> list[dict[str, float]]:
        # No term: a fit from there cannot end worse than the model without it.
        return [{f"c{j}": 0.0 for j in range(len(self.names))}]

    def implausible_reason(self, values, stderr) -> str:
        return ""

    # -- the term

    def term(self, ctx: Mapping[str, Any]) -> jnp.ndarray:
        """The term per sample, in the place's unit."""
        basis = ctx["learned"][self.place]
        return jnp.tensordot(basis, self._coef(), axes=1)

    def voltage_series(self, ctx):
        return self.term(ctx)

    def load_series(self, ctx):
        return self.term(ctx)

    def correction(self, signals):
        return self.term(signals)

    def wedge_angle(self, theta_deg, ctx):
        return theta_deg + self.term(ctx)

    def x_shift(self, ctx):
        return self.term(ctx)

    def mu_factor(self, ctx):
        return 1.0 + self.term(ctx)

    def read(self, channel, y, ctx):
        return y + self.term(ctx) if channel == self.channel else y

    def unread(self, channel, y, ctx):
        return y - self.term(ctx) if channel == self.channel else y


def term_at(mechanisms: Sequence[AbstractMechanism], place: str) -> LearnedTerm:
    """The learned term at ``place`` among fitted mechanisms."""
    return next(m for m in mechanisms if isinstance(m, LearnedTerm) and m.place == place)


def with_bases(data: Mapping[str, Any], bases: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """``data`` with learned terms' basis series by place (each (n, K), zero-padded to
    the data's length), which :meth:`LearnedTerm.term` reads."""
    n_pad = int(np.asarray(data["t"]).shape[0])
    learned = dict(data.get("learned", {}))
    for place, B in bases.items():
        padded = np.zeros((n_pad, B.shape[1]))
        padded[: B.shape[0]] = B
        learned[place] = jnp.asarray(padded)
    return dict(data) | {"learned": learned}
