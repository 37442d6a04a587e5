"""The one interface every catalog mechanism implements.

A *mechanism* is a piece of brake physics the seed model leaves out, written as a
differentiable augmentation of one link of the chain. It declares

- ``id`` (the catalog id of ``shared/CONTRACTS.md``) and the ``stage`` it acts on;
- the ``hook`` it plugs into (:data:`HOOKS`): where in the chain its function is called;
- its parameters as :class:`ewb_ident.model.params.ParamInfo` (SI units, a transform to an
  unconstrained O(1) coordinate for the optimiser, and *plausibility bounds*: a fitted
  value outside them, or at them, is not reported as a finding);
- the teacher-forced ``stages`` whose residuals it changes (a sensor mechanism on
  ``force_N`` changes the force stage, where the channel is the output, and the torque
  stage, where it is the input).

Mechanisms are immutable :class:`equinox.Module` pytrees: the parameter values are
(possibly traced) array fields named as in :meth:`AbstractMechanism.param_info`; static
configuration (which channel a sensor mechanism acts on) is a static field. The hooks
are pure JAX functions; the default of each is the identity, so a mechanism overrides
only the hook it declares.

Hooks
-----
``voltage``               ``V_eff = voltage(V, s, p)``: the voltage the armature sees
                          (motor stage; ``s`` = (i, omega, theta[rad])).
``motor_friction``        ``(T, eps) = motor_friction(s, p, force, start)``: a
                          friction-like torque ``T tanh(omega / eps)`` that opposes
                          motion (``T`` in N*m, ``eps`` in rad/s; motor stage; integrated
                          implicitly; ``s`` the state after a sub-step's linear flow,
                          ``start`` the state at its start).
``wedge_angle``           ``theta_w = wedge_angle(theta, ctx)``: the wedge-side angle
                          the gap polynomial sees (gap stage), a whole series.
``clamp_force``           ``F = clamp_force(x_drive, f_bell, ctx)``: the clamping force
                          from the bell's force and the displacement history (force stage).
``friction_coefficient``  ``factor = mu_factor(ctx)``: a factor on the pad friction
                          coefficient per sample (torque stage).
``sensor``                ``read(channel, y, ctx)`` / ``unread(channel, y, ctx)``: how a
                          sensor reports a true series, and the best estimate of the true
                          series from a reading (for teacher-forced inputs).
``load_torque``           ``tau = load_torque(s, p, force)``: a smooth signed load torque,
                          N*m (motor stage; explicit).
``output``                ``dy = correction(signals)``: an additive correction of a
                          stage's output (a learned term's).
``voltage_series``        ``dV = voltage_series(ctx)``: a voltage added to the logged one
                          per sample (zero-order hold), V (motor stage; a learned term's
                          exogenous series).
``load_series``           ``tau = load_series(ctx)``: a load torque per sample (zero-order
                          hold), N*m (motor stage; a learned term's exogenous series).
``force_input``           ``dx = x_shift(ctx)``: a shift of the displacement the bell
                          sees, m (force stage).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, Literal, get_args

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ewb_ident.data.metrics import Z90
from ewb_ident.model.params import EWBParams, ParamInfo

Hook = Literal[
    "voltage",
    "motor_friction",
    "load_torque",
    "wedge_angle",
    "clamp_force",
    "friction_coefficient",
    "sensor",
    "output",
    "voltage_series",
    "load_series",
    "force_input",
]
#: The hooks, in the order of :data:`Hook`.
HOOKS: tuple[str, ...] = get_args(Hook)


class AbstractMechanism(eqx.Module):
    """A differentiable augmentation of one stage of the chain (see module docstring).

    Concrete mechanisms are final classes with one array field per parameter, named as
    in :meth:`param_info`, and override the hook they declare.
    """

    id: ClassVar[str] = ""
    STAGE: ClassVar[str] = ""
    hook: ClassVar[Hook] = "sensor"
    #: Further hooks the mechanism overrides besides :attr:`hook` (e.g. a friction-like
    #: torque and a signed load torque together).
    EXTRA_HOOKS: ClassVar[tuple[Hook, ...]] = ()
    #: What physics the seed model leaves out, in a brake engineer's words.
    physics: ClassVar[str] = ""
    #: Parameters that locate the model (e.g. where in the play the trace starts) but
    #: are not the physical finding: not checked for plausibility, not headlined.
    NUISANCE: ClassVar[tuple[str, ...]] = ()
    #: Trace columns the mechanism needs beyond those of its stages.
    NEEDS: ClassVar[tuple[str, ...]] = ()
    #: The static flag field that selects the mechanism's flexible form, named as the
    #: form (e.g. ``"drift"``); ``""`` for a mechanism of one form.
    FORM: ClassVar[str] = ""
    #: Tried at its stage even where the location test flags nothing: the mechanism
    #: modulates a gain the baseline refits (the friction coefficient), so the refitted
    #: gain absorbs most of it and the rest can stay under the location thresholds.
    #: Its targeted evidence test (dBIC, plausibility, explained share, the chain) then
    #: decides alone.
    SCREENED: ClassVar[bool] = False

    # ------------------------------------------------------------------ declarations

    def uses(self, hook: str) -> bool:
        """Whether the mechanism acts through ``hook`` (an instance's: a learned
        term's hook depends on its place)."""
        return hook == self.hook or hook in self.EXTRA_HOOKS

    def param_info(self) -> tuple[ParamInfo, ...]:
        """The parameters, in the order of the unconstrained vector."""
        raise NotImplementedError

    @property
    def form(self) -> str:
        """The flexible form this instance is (:meth:`refinements`), ``""`` for the
        catalog's form."""
        return self.FORM if self.FORM and getattr(self, self.FORM) else ""

    def in_form(self, form: str) -> AbstractMechanism:
        """This mechanism in the named form (``""``: the catalog's), default values for
        what the form adds.

        Raises
        ------
        ValueError
            The mechanism has no such form.
        """
        if form == self.form:
            return self
        if not form:
            return type(self)(**dict(self.static_config()) | {self.FORM: False})
        for r in self.refinements():
            if r.form == form:
                return r
        known = [r.form for r in self.refinements()]
        raise ValueError(
            f"{self.variant} has no form {form!r}"
            + (f"; its flexible form is {', '.join(known)}" if known else "; it has one form")
        )

    @property
    def may_be_null(self) -> tuple[str, ...]:
        """Physical parameters this form may leave at no effect (a drifting zero that
        starts at zero): checked against their plausibility bounds, not for being
        resolved."""
        return ()

    @property
    def stage(self) -> str:
        """The link of the chain the mechanism acts on (motor, gap, force, torque)."""
        return self.STAGE

    @property
    def variant(self) -> str:
        """A label that tells apart instances of the same id (e.g. the sensor channel)."""
        return self.id

    @property
    def stages(self) -> tuple[str, ...]:
        """Teacher-forced stages whose residuals this mechanism changes."""
        return (self.stage,)

    @property
    def channels(self) -> tuple[str, ...]:
        """Channels whose model prediction this mechanism changes (chain level)."""
        return {"motor": ("theta_deg",), "gap": ("x_m",), "force": ("force_N",)}.get(
            self.stage, ("torque_Nm",)
        )

    def static_config(self) -> tuple[tuple[str, Any], ...]:
        """Static (hashable) configuration: the non-parameter fields and their values."""
        names = {p.name for p in self.param_info()}
        return tuple(
            (f.name, getattr(self, f.name)) for f in dataclasses.fields(self) if f.name not in names
        )

    def values(self) -> dict[str, float]:
        """Parameter values as plain floats (SI units)."""
        return {p.name: float(np.asarray(getattr(self, p.name))) for p in self.param_info()}

    def with_values(self, values: Mapping[str, Any]) -> AbstractMechanism:
        """A copy with some parameter values replaced (SI units; arrays allowed)."""
        known = {p.name for p in self.param_info()}
        bad = sorted(set(values) - known)
        if bad:
            raise ValueError(f"{self.id}: unknown parameter(s) {bad}; known: {sorted(known)}")
        return dataclasses.replace(self, **dict(values))

    def unsupported_reason(self, channels: tuple[str, ...], ctx: Mapping[str, Any]) -> str | None:
        """``None`` when the mechanism can be fitted to a trace with these channels;
        otherwise the reason, in words."""
        missing = [c for c in self.NEEDS if c not in channels]
        if missing:
            return f"needs the column(s) {', '.join(missing)}"
        return None

    def starts(self, ctx: Mapping[str, Any]) -> list[dict[str, float]]:
        """Starting values (SI) for a fit; several when the cost has several valleys."""
        return [{p.name: _ref(p) for p in self.param_info()}]

    def refinements(self) -> tuple[AbstractMechanism, ...]:
        """Flexible forms of this (fitted) mechanism: the same physics in a wider family
        (a zero that drifts beside a constant offset, a limit that sets in gradually beside
        a sharp one). Each carries this mechanism's values, its added parameters at
        :meth:`form_start` (at their no-effect values the form is exactly this one), and
        its :meth:`starts` vary the added parameters. The diagnosis tries them once this
        form has been selected and keeps one only on the evidence a mechanism needs
        (``dBIC``, resolved, plausible) against this form; none for a mechanism of one
        form (:attr:`FORM` empty) or one already in its flexible form."""
        if not self.FORM or self.form:
            return ()
        return (dataclasses.replace(self, **{self.FORM: True}, **self.form_start()),)

    def form_start(self) -> dict[str, float]:
        """Start values of the parameters the flexible form adds, SI (see
        :meth:`refinements`)."""
        return {}

    def implausible_reason(
        self, values: Mapping[str, float], stderr: Mapping[str, float | None]
    ) -> str:
        """``""`` when the fitted parameters are physically plausible and resolved;
        otherwise the reason, in words (the finding is then not reported).

        *Resolved*: the parameter's 90 % interval (``± RESOLVED_Z`` standard errors)
        excludes no effect. This is not the significance test (that is the likelihood
        ratio / BIC of :func:`ewb_ident.diagnosis.diagnose.diagnose`, which stays valid when the
        mechanism's parameters are correlated and their standard errors large); it keeps a
        reported value from being indistinguishable from zero."""
        for info in self.param_info():
            if info.name in self.NUISANCE:
                continue
            v = float(values[info.name])
            lo, hi = _plausible_range(info)
            if not lo < v < hi:
                return (
                    f"{info.name} = {v:.3g} {info.unit} is outside the plausible range "
                    f"({lo:.3g}, {hi:.3g}) {info.unit}"
                )
            if info.name in self.may_be_null:
                continue
            se = stderr.get(info.name)
            if se is None or not np.isfinite(se):
                return f"{info.name} is not resolved by the data (no standard error)"
            if abs(v - _null_value(info)) < RESOLVED_Z * se:
                return (
                    f"{info.name} = {v:.3g} ± {se:.2g} {info.unit}: its 90 % interval "
                    "includes no effect"
                )
        return ""

    # ------------------------------------------------------------------------- words

    def observation(self, values: Mapping[str, float], ctx: Mapping[str, Any]) -> str:
        """What the mismatch looks like in the recording, in words."""
        return f"the {self.stage} stage does not follow the model"

    def describe(
        self,
        values: Mapping[str, float],
        stderr: Mapping[str, float | None],
        ctx: Mapping[str, Any],
    ) -> str:
        """The physics left out, and the fitted parameters with their uncertainty."""
        parts = []
        for info in self.param_info():
            if info.name in self.NUISANCE:
                continue
            parts.append(
                f"{info.name} = {fmt_pm(values[info.name], stderr.get(info.name))} {info.unit}"
            )
        return f"{self.physics}, " + ", ".join(parts)

    # ------------------------------------------------------------------------- hooks

    def load_torque(self, s: jnp.ndarray, p: EWBParams, force: jnp.ndarray) -> jnp.ndarray:
        """Smooth signed load torque on the motor, N*m (``load_torque`` hook)."""
        return jnp.zeros_like(s[1])

    def correction(self, signals: Mapping[str, Any]) -> jnp.ndarray:
        """Additive correction of the stage output (``output`` hook)."""
        return jnp.zeros_like(signals["y"])

    def voltage(self, V: jnp.ndarray, s: jnp.ndarray, p: EWBParams) -> jnp.ndarray:
        """Voltage the armature sees, V (``voltage`` hook)."""
        return V

    def motor_friction(
        self, s: jnp.ndarray, p: EWBParams, force: jnp.ndarray, start: jnp.ndarray | None = None
    ):
        """Friction torque level (N*m) and switching speed (rad/s) (``motor_friction``)."""
        return jnp.zeros_like(s[1]), jnp.ones_like(s[1])

    def wedge_angle(self, theta_deg: jnp.ndarray, ctx: Mapping[str, Any]) -> jnp.ndarray:
        """Wedge-side angle series, degrees (``wedge_angle`` hook)."""
        return theta_deg

    def clamp_force(
        self, x_drive: jnp.ndarray, f_bell: jnp.ndarray, ctx: Mapping[str, Any]
    ) -> jnp.ndarray:
        """Clamping force series, N (``clamp_force`` hook)."""
        return f_bell

    def mu_factor(self, ctx: Mapping[str, Any]) -> jnp.ndarray | float:
        """Factor on the pad friction coefficient per sample (``friction_coefficient``)."""
        return 1.0

    def read(self, channel: str, y: jnp.ndarray, ctx: Mapping[str, Any]) -> jnp.ndarray:
        """What the sensor of ``channel`` reports for the true series ``y``."""
        return y

    def unread(self, channel: str, y: jnp.ndarray, ctx: Mapping[str, Any]) -> jnp.ndarray:
        """The true series of ``channel`` estimated from the reading ``y``."""
        return y

    def voltage_series(self, ctx: Mapping[str, Any]) -> jnp.ndarray | float:
        """Voltage added to the logged one per sample, V (``voltage_series`` hook)."""
        return 0.0

    def load_series(self, ctx: Mapping[str, Any]) -> jnp.ndarray | float:
        """Load torque per sample, N*m (``load_series`` hook)."""
        return 0.0

    def x_shift(self, ctx: Mapping[str, Any]) -> jnp.ndarray | float:
        """Shift of the displacement the bell sees, m (``force_input`` hook)."""
        return 0.0


class AbstractSensorMechanism(AbstractMechanism):
    """A mechanism on one sensor channel (``sensor`` hook): how the sensor of
    :attr:`channel` reports the true series, one instance per channel it can act on."""

    hook: ClassVar[Hook] = "sensor"
    #: The channels the mechanism can act on.
    CHANNELS: ClassVar[tuple[str, ...]] = ()

    channel: str = eqx.field(static=True, default="force_N")

    def __check_init__(self):
        if self.channel not in self.CHANNELS:
            raise ValueError(
                f"{self.id}: channel must be one of {self.CHANNELS}, got {self.channel!r}"
            )

    @property
    def variant(self) -> str:
        return f"{self.id}[{self.channel}]"

    @property
    def channels(self) -> tuple[str, ...]:
        return (self.channel,)

    def unsupported_reason(self, channels, ctx) -> str | None:
        if self.channel not in channels:
            return f"the trace has no {self.channel}"
        return None


def _ref(info: ParamInfo) -> float:
    if info.transform == "logit":
        return 0.5 * (info.lower + info.upper)
    return float(info.ref)


def _plausible_range(info: ParamInfo) -> tuple[float, float]:
    """Plausibility bounds; for a logit parameter, its hard bounds less 0.5 % at each end
    (a fit that runs into a hard bound has not found an interior optimum)."""
    if info.transform == "logit":
        pad = 0.005 * (info.upper - info.lower)
        return info.lower + pad, info.upper - pad
    return float(info.lower), float(info.upper)


#: Standard errors a resolved parameter lies from no effect (a 90 % interval).
RESOLVED_Z = Z90


def _null_value(info: ParamInfo) -> float:
    """The parameter value of 'no effect' (0 for every catalog parameter)."""
    return 0.0


def fmt_pm(value: float, se: float | None, digits: int = 2) -> str:
    """``value ± se`` rounded to the standard error's leading digits."""
    if se is None or not np.isfinite(se) or se <= 0:
        return f"{value:.3g}"
    exp = int(np.floor(np.log10(se))) - (digits - 1)
    if -9 <= exp <= 6:
        dec = max(0, -exp)
        return f"{round(value, -exp):.{dec}f} ± {round(se, -exp):.{dec}f}"
    return f"{value:.3g} ± {se:.2g}"


def fmt_rate(rate: float, se: float | None) -> str:
    """A fitted rate (1/s) with its error, and the time constant it means, in words."""
    tc = 1.0 / rate
    shown = f"{tc * 1e3:.2g} ms" if tc < 0.1 else f"{tc:.2g} s"
    return f"rate {fmt_pm(rate, se)} 1/s, a time constant of about {shown}"
