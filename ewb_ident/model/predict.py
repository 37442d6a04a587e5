"""The chain with mechanisms plugged in: predictions of each stage and of the whole chain.

:func:`predict` evaluates one teacher-forced stage (its input is the measured channel,
corrected by any sensor mechanism on it) or the whole chain from the voltage, calling
each mechanism at its hook (see :mod:`ewb_ident.mechanisms.base`). Without mechanisms
it gives exactly the seed model of :mod:`ewb_ident.model.physics` /
:mod:`ewb_ident.model.integrate`.

The motor with mechanisms
-------------------------
:func:`motor_states` hands the mechanisms' motor hooks (``voltage``, ``load_torque``,
``motor_friction``, ``voltage_series``, ``load_series``) to the one integrator,
:func:`ewb_ident.model.integrate.integrate_motor`, as its terms; :func:`n_substeps` is
the one sub-step rule for them. :func:`simulate_chain` and :func:`simulate_motor` are
:func:`predict` from the voltage alone.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ewb_ident.model.integrate import (
    EXPONENTIAL,
    Integrator,
    LoadTorque,
    MotorTerms,
    integrate_motor,
    warn_if_heun_unstable,
)
from ewb_ident.model.numerics import numerics
from ewb_ident.model.params import EWBParams
from ewb_ident.model.physics import DEG_PER_RAD, brake_torque, clamp_force, gap

if TYPE_CHECKING:  # the mechanisms implement hooks this module calls
    from ewb_ident.mechanisms.base import AbstractMechanism

#: The evaluator's insertion points, in the order of the chain: each place where physics
#: can enter, with the hooks (:mod:`ewb_ident.mechanisms.base`) through which a catalog
#: mechanism, a function given to :func:`simulate_chain` or a learned term
#: (:data:`ewb_ident.mechanisms.learned.PLACES`) acts there. ``output:<stage>`` is the
#: ``output`` hook at that stage (an additive correction of its output). The sensors are
#: one place per channel, ``sensor.<channel>``. docs/model.md has the table in words.
INSERTION_POINTS: dict[str, tuple[str, ...]] = {
    "motor.electrical": ("voltage", "voltage_series"),
    "motor.mechanical": ("load_torque", "motor_friction", "load_series"),
    "gap": ("wedge_angle",),
    "drive": ("output:gap",),
    "force.input": ("force_input",),
    "force.output": ("clamp_force", "output:force"),
    "friction": ("friction_coefficient",),
    "torque.output": ("output:torque",),
    "sensor": ("sensor",),
}

#: Hooks that act inside the motor integration, within each sample (the integrator's
#: ``voltage``, ``load`` and ``friction`` terms).
MOTOR_HOOKS: tuple[str, ...] = ("voltage", "motor_friction", "load_torque")


def insertion_points(mechanism: AbstractMechanism) -> tuple[str, ...]:
    """The insertion points (keys of :data:`INSERTION_POINTS`, a sensor's as
    ``sensor.<channel>`` when it names one) at which a mechanism acts."""
    out = []
    for place, hooks in INSERTION_POINTS.items():
        for spec in hooks:
            hook, _, stage = spec.partition(":")
            if mechanism.uses(hook) and (not stage or mechanism.stage == stage):
                channel = getattr(mechanism, "channel", None)
                out.append(f"sensor.{channel}" if place == "sensor" and channel else place)
                break
    return tuple(out)


def n_substeps(dt: float, mechanisms: Sequence[AbstractMechanism]) -> int:
    """Motor sub-steps per sample interval ``dt`` (s) for these mechanisms (the one rule,
    :meth:`ewb_ident.model.integrate.Integrator.substeps`)."""
    within = any(m.uses(h) for m in mechanisms for h in MOTOR_HOOKS)
    return EXPONENTIAL.substeps(dt, within)


def motor_terms(
    p: EWBParams,
    mechanisms: Sequence[AbstractMechanism],
    series: tuple[jnp.ndarray, jnp.ndarray] | None = None,
) -> MotorTerms:
    """The mechanisms' motor hooks as the integrator's terms, at parameters ``p``."""
    return MotorTerms(
        voltage=tuple(partial(_voltage_hook, m, p) for m in mechanisms if m.uses("voltage")),
        load=tuple(partial(_load_hook, m, p) for m in mechanisms if m.uses("load_torque")),
        friction=tuple(
            partial(_friction_hook, m, p) for m in mechanisms if m.uses("motor_friction")
        ),
        series=series,
    )


def _voltage_hook(m, p, V, s):
    return m.voltage(V, s, p)


def _load_hook(m, p, s, force):
    return m.load_torque(s, p, force)


def _friction_hook(m, p, s1, force, start):
    return m.motor_friction(s1, p, force, start=start)


def motor_states(
    p: EWBParams,
    voltage_V: jnp.ndarray,
    dt: jnp.ndarray,
    theta0_deg: jnp.ndarray,
    mechanisms: Sequence[AbstractMechanism],
    n_sub: int,
    method: str = "exponential",
    series: tuple[jnp.ndarray, jnp.ndarray] | None = None,
) -> jnp.ndarray:
    """Motor states (i [A], omega [rad/s], theta [rad]) at the sample times, shape (n, 3):
    :func:`ewb_ident.model.integrate.integrate_motor` with the mechanisms' motor hooks.

    Without motor mechanisms: exact over each sample for the ``exponential`` method,
    ``n_sub`` Heun sub-steps for ``heun`` (the seed paper's integrator; with motor
    mechanisms the method is the exponential one). ``series``: a voltage (V) added to
    the logged one and a load torque (N*m), per sample, each held over its sample (the
    ``voltage_series`` and ``load_series`` hooks); both enter the linear flow exactly.
    """
    terms = motor_terms(p, mechanisms, series)
    if not terms.empty:
        method = "exponential"
    return integrate_motor(p, voltage_V, dt, theta0_deg, n_sub, method, terms)


def play(y: jnp.ndarray, width: jnp.ndarray) -> jnp.ndarray:
    """Play (backlash) operator of half width ``width``, starting centred."""

    def step(w, v):
        w = jnp.clip(w, v - width, v + width)
        return w, w

    return jax.lax.scan(step, y[0], y)[1]


def _context(d: Mapping[str, Any]) -> dict[str, Any]:
    ctx: dict[str, Any] = {
        "dt": d["dt"],
        "t": d.get("t"),
        # Basis series of learned terms, by place (``ewb_ident.diagnosis.discovery``).
        "learned": d.get("learned", {}),
    }
    meas = d["meas"]
    if "disc_speed_rad_s" in meas:
        ctx["disc_speed"] = meas["disc_speed_rad_s"]
        ctx["omega_ref"] = d.get("omega_ref")
    return ctx


def predict(
    stages: str | Sequence[str],
    p: EWBParams,
    theta0_deg: jnp.ndarray,
    mechanisms: Sequence[AbstractMechanism],
    d: Mapping[str, Any],
    n_sub: int,
    method: str = "exponential",
    *,
    speed: bool = False,
) -> dict[str, jnp.ndarray]:
    """Predicted channels of one or several teacher-forced stages, or of ``"chain"``: the
    one evaluator of the chain, with or without mechanisms, for least squares, the
    posterior, the diagnosis and :func:`simulate_chain`.

    Parameters
    ----------
    stages
        ``"chain"``, a stage name, or several stage names (their predictions merged).
    p, theta0_deg
        Base parameters (SI) and the start angle, degrees.
    mechanisms
        Mechanism instances with their parameter values.
    d
        Data: ``meas`` (measured columns), ``dt`` (s), ``t`` (s), ``r_eff`` (m),
        ``omega_ref`` (rad/s), ``x_play`` (m; half width of the play filter on the
        measured displacement that drives a hysteresis state); optionally ``forced``
        (for ``"chain"``: per output channel ``x_m``, ``force_N``, ``torque_Nm``, a flag
        that, where above 0, makes the stage read its measured input instead of the
        simulated one, so that one compiled program serves the chain and each
        teacher-forced stage, the choice made by data).
    n_sub
        Motor sub-steps per sample (:func:`n_substeps`; for the seed model with the
        ``heun`` method, :meth:`ewb_ident.model.integrate.Integrator.substeps`).
    method
        ``exponential`` (exact over each sample) or ``heun`` (the seed paper's), for the
        motor without motor mechanisms.
    speed
        Also return the motor's speed, ``omega_rad_s`` (rad/s; motor and chain).
    """
    if not isinstance(stages, str):
        out: dict[str, jnp.ndarray] = {}
        for s in stages:
            out |= predict(s, p, theta0_deg, mechanisms, d, n_sub, method, speed=speed)
        return out
    stage = stages
    meas = d["meas"]
    ctx = _context(d)
    sensors = _Sensors(tuple(m for m in mechanisms if m.uses("sensor")), ctx)
    out = {}
    if stage in ("motor", "chain"):
        s = motor_states(
            p, meas["voltage_V"], d["dt"], theta0_deg, mechanisms, n_sub, method,
            _motor_series(mechanisms, ctx),
        )  # fmt: skip
        theta = s[:, 2] * DEG_PER_RAD
        out["theta_deg"] = sensors.read("theta_deg", theta)
        out["current_A"] = sensors.read("current_A", s[:, 0])
        if speed:
            out["omega_rad_s"] = s[:, 1]
        if stage == "motor":
            return out
        theta = _forced(d, "x_m", lambda: sensors.unread("theta_deg", meas["theta_deg"]), theta)
    elif stage == "gap":
        theta = sensors.unread("theta_deg", meas["theta_deg"])

    if stage in ("gap", "chain"):
        x = _gap(stage, theta, p, mechanisms, d, ctx, sensors)
        out["x_m"] = sensors.read("x_m", x)
        if stage == "gap":
            return out
        x = _forced(d, "force_N", lambda: sensors.unread("x_m", meas["x_m"]), x)
        x_drive = x
    elif stage == "force":
        x = sensors.unread("x_m", meas["x_m"])
        x_drive = x

    if stage in ("force", "chain"):
        F = _force(stage, x, x_drive, p, mechanisms, d, ctx, sensors)
        out["force_N"] = sensors.read("force_N", F)
        if stage == "force":
            return out
        F = _forced(d, "torque_Nm", lambda: sensors.unread("force_N", meas["force_N"]), F)
    else:  # torque stage
        F = sensors.unread("force_N", meas["force_N"])
    out["torque_Nm"] = sensors.read("torque_Nm", _torque(F, p, mechanisms, d, ctx))
    return out


def _forced(d: Mapping[str, Any], ch: str, measured, simulated: jnp.ndarray) -> jnp.ndarray:
    """The input of the stage that predicts ``ch`` on the chain: the measured one
    (``measured()``) where ``d["forced"][ch]`` is above 0, else the simulated one."""
    forced = d.get("forced")
    if forced is None:
        return simulated
    return jnp.where(forced[ch] > 0, measured(), simulated)


def _motor_series(mechanisms, ctx) -> tuple[jnp.ndarray, jnp.ndarray] | None:
    """The per-sample voltage and load torque of the ``voltage_series`` and
    ``load_series`` hooks (``None`` when no mechanism uses them)."""
    dv = [m.voltage_series(ctx) for m in mechanisms if m.uses("voltage_series")]
    dtau = [m.load_series(ctx) for m in mechanisms if m.uses("load_series")]
    if not dv and not dtau:
        return None
    return jnp.asarray(sum(dv) if dv else 0.0), jnp.asarray(sum(dtau) if dtau else 0.0)


class _Sensors:
    """The sensor mechanisms: ``read`` what a sensor shows of a true value, ``unread``
    the true value behind a measured one (in reverse order)."""

    def __init__(self, mechanisms: tuple, ctx: dict[str, Any]):
        self.mechanisms, self.ctx = mechanisms, ctx

    def read(self, ch: str, y: jnp.ndarray) -> jnp.ndarray:
        for m in self.mechanisms:
            y = m.read(ch, y, self.ctx)
        return y

    def unread(self, ch: str, y: jnp.ndarray) -> jnp.ndarray:
        for m in reversed(self.mechanisms):
            y = m.unread(ch, y, self.ctx)
        return y


def _gap(stage, theta, p, mechanisms, d, ctx, sensors) -> jnp.ndarray:
    """Piston displacement from the pinion angle, through the wedge mechanisms (play)."""
    wedge = [m for m in mechanisms if m.uses("wedge_angle")]
    theta_w = theta
    if wedge and stage == "gap" and "theta_deg" in d.get("drive", {}):
        # A measured angle drives the play: use it averaged where it stands still.
        theta_w = sensors.unread("theta_deg", d["drive"]["theta_deg"])
    for m in wedge:
        theta_w = m.wedge_angle(theta_w, ctx)
    x = gap(theta_w, p.p2, p.p1, p.p0)
    return _correct("gap", x, mechanisms, ctx | {"theta": theta})


def _force(stage, x, x_drive, p, mechanisms, d, ctx, sensors) -> jnp.ndarray:
    """Clamping force from the displacement, through the force mechanisms (hysteresis
    driven by the motion history ``x_drive``)."""
    force_mechs = [m for m in mechanisms if m.uses("clamp_force")]
    if stage == "force" and force_mechs:
        drive = d.get("drive", {})
        if "x_model" in drive:  # a noise-free motion history (from the voltage)
            x_drive = drive["x_model"]
        else:
            if "x_m" in drive:
                x_drive = sensors.unread("x_m", drive["x_m"])
            x_drive = play(x_drive, d["x_play"])
    x_bell = x
    for m in mechanisms:
        if m.uses("force_input"):
            x_bell = x_bell + m.x_shift(ctx)
    F = clamp_force(x_bell, p.F_rt, p.a, p.b, p.c)
    f_bell = F
    for m in force_mechs:
        F = m.clamp_force(x_drive, F, ctx)
    return _correct("force", F, mechanisms, ctx | {"x": x, "x_drive": x_drive, "f_bell": f_bell})


def _torque(F, p, mechanisms, d, ctx) -> jnp.ndarray:
    """Brake torque from the clamping force, through the friction-coefficient mechanisms
    (those driven by dissipated energy by two fixed-point passes)."""
    mu_mechs = [m for m in mechanisms if m.uses("friction_coefficient")]
    factor = 1.0
    for m in mu_mechs:
        if not getattr(m, "USES_ENERGY", False):
            factor = factor * m.mu_factor(ctx)
    torque = brake_torque(F, p.mu * factor, d["r_eff"])
    energy_mechs = [m for m in mu_mechs if getattr(m, "USES_ENERGY", False)]
    if energy_mechs:
        # The energy depends on the torque it lowers: two fixed-point passes (the error
        # after the second is of the order of the fade squared).
        faded = torque
        for _ in range(2):
            power = faded * ctx["disc_speed"]
            ctx["power_W"] = power
            ctx["energy_J"] = jnp.concatenate([jnp.zeros(1), jnp.cumsum(power[:-1])]) * d["dt"]
            faded = torque
            for m in energy_mechs:
                faded = faded * m.mu_factor(ctx)
        torque = faded
    return _correct("torque", torque, mechanisms, ctx | {"force": F, "torque0": torque})


def _correct(stage: str, y, mechanisms, signals) -> jnp.ndarray:
    """Add the ``output`` corrections of ``stage`` (learned terms) to ``y``."""
    for m in mechanisms:
        if m.uses("output") and m.stage == stage:
            y = y + m.correction(signals | {"y": y})
    return y


# ----------------------------------------------------------------------- simulation


@dataclass(frozen=True)
class LoadTorqueFunction:
    """A load torque given as a function ``tau(state, params)`` (N*m; the state (i,
    omega, theta [rad])), plugged into the ``load_torque`` hook of the motor."""

    tau: LoadTorque
    stage: str = "motor"

    def uses(self, hook: str) -> bool:
        return hook == "load_torque"

    def load_torque(self, s: jnp.ndarray, p: EWBParams, force: jnp.ndarray) -> jnp.ndarray:
        return self.tau(s, p)


def _simulate(params, voltage_V, dt, theta0_deg, r_eff_m, stage, integrator, load_torque):
    """:func:`predict` of ``stage`` from the voltage alone, with the motor's speed."""
    if load_torque is not None and integrator.method == "heun":
        raise ValueError(
            "the seed's Heun method integrates only the seed's motor, without load torque: "
            "use the exponential integrator for a load torque"
        )
    mechanisms = () if load_torque is None else (LoadTorqueFunction(load_torque),)
    n_sub = integrator.substeps(float(dt), bool(mechanisms))
    if integrator.method == "heun":
        warn_if_heun_unstable(params, float(dt) / n_sub)
    d = {"meas": {"voltage_V": jnp.asarray(voltage_V)}, "dt": dt, "r_eff": r_eff_m}
    out = predict(stage, params, theta0_deg, mechanisms, d, n_sub, integrator.method, speed=True)
    return {k: out[k] for k in ("current_A", "omega_rad_s", "theta_deg")} | out


# simulate_motor and simulate_chain: public signatures and docstrings of their own, alike in
# shape, over one _simulate.
@numerics
def simulate_motor(
    params: EWBParams,
    voltage_V: ArrayLike,
    dt: float,
    theta0_deg: ArrayLike = 0.0,
    *,
    integrator: Integrator = EXPONENTIAL,
    load_torque: LoadTorque | None = None,
) -> dict[str, jnp.ndarray]:
    """Motor stage: logged voltage -> current and pinion angle at the sample times.

    Parameters
    ----------
    params
        Model parameters (the motor ones are used).
    voltage_V
        Voltage at each sample, V, held until the next sample (zero-order hold).
    dt
        Sample interval, s.
    theta0_deg
        Pinion angle at the first sample, degrees (the motor starts at rest).
    integrator
        Integration method (see :class:`ewb_ident.model.integrate.Integrator`).
    load_torque
        Optional load torque ``tau(state, params)``, N*m (exponential method only).

    Returns
    -------
    dict with ``current_A`` (A), ``omega_rad_s`` (rad/s) and ``theta_deg`` (degrees).

    Raises
    ------
    ValueError
        A load torque with the ``heun`` method.
    """
    return _simulate(params, voltage_V, dt, theta0_deg, None, "motor", integrator, load_torque)


@numerics
def simulate_chain(
    params: EWBParams,
    voltage_V: ArrayLike,
    dt: float,
    theta0_deg: ArrayLike = 0.0,
    r_eff_m: ArrayLike = 0.15,
    *,
    integrator: Integrator = EXPONENTIAL,
    load_torque: LoadTorque | None = None,
) -> dict[str, jnp.ndarray]:
    """The whole chain from the logged voltage alone: :func:`predict` of ``"chain"``.

    Parameters
    ----------
    r_eff_m
        Effective pad radius, m.
    params, voltage_V, dt, theta0_deg, integrator, load_torque
        As for :func:`simulate_motor` (all model parameters are used).

    Returns
    -------
    dict with ``current_A``, ``omega_rad_s``, ``theta_deg``, ``x_m``, ``force_N`` and
    ``torque_Nm`` at the sample times (SI units, angle in degrees).
    """
    return _simulate(params, voltage_V, dt, theta0_deg, r_eff_m, "chain", integrator, load_torque)
