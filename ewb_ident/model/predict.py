"""The chain with mechanisms plugged in: predictions of each stage and of the whole chain.

:func:`predict` evaluates one teacher-forced stage (its input is the measured channel,
corrected by any sensor mechanism on it) or the whole chain from the voltage, calling
each mechanism at its hook (see :mod:`ewb_ident.mechanisms.base`). Without mechanisms
it gives exactly the seed model of :mod:`ewb_ident.model.physics` /
:mod:`ewb_ident.model.integrate`.

The motor with mechanisms
-------------------------
:func:`motor_states` splits each sub-step (at most :data:`MAX_SUBSTEP_S`) into the
exact linear flow of the armature and rotor (``exp(A h)``, as in
:mod:`ewb_ident.model.integrate`) with the voltage the ``voltage`` hooks let through, followed
by an implicit (backward Euler) step of the friction-like torques of the
``motor_friction`` hooks, each ``T tanh(omega / eps)`` (a torque ``T`` that opposes
motion, switching over a speed scale ``eps``): with ``omega_free`` the speed after the
linear flow, ``omega`` solves ``omega = omega_free - (h / M) sum T tanh(omega / eps)``.
It starts from the Coulomb limit (``eps -> 0``, Moreau's time-stepping scheme: stuck,
``omega = 0``, when ``|omega_free| <= h sum T / M``) and takes a few Newton steps, so a
stiff, nearly set-valued friction is integrated stably and stays differentiable for the
fit; an actuator held by friction stays still. The splitting is first order in ``h``.
The model clamping force a wedge load needs is ``F_bell(gap(theta))`` at the
state's angle.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp

from ewb_ident.model.integrate import matvec, phi_matrices, seed_motor_states
from ewb_ident.model.params import EWBParams
from ewb_ident.model.physics import DEG_PER_RAD, brake_torque, clamp_force, gap, motor_matrices

if TYPE_CHECKING:  # the mechanisms implement hooks this module calls
    from ewb_ident.mechanisms.base import AbstractMechanism

#: Longest sub-step of the motor integration with mechanisms, s.
MAX_SUBSTEP_S = 5.0e-4

#: Newton steps of the implicit friction update.
FRICTION_NEWTON_STEPS = 3

#: Hooks that act inside the motor integration.
MOTOR_HOOKS: tuple[str, ...] = ("voltage", "motor_friction", "load_torque")


def n_substeps(dt: float, mechanisms: Sequence[AbstractMechanism]) -> int:
    """Motor sub-steps per sample interval ``dt`` (s) for these mechanisms."""
    if not any(m.uses(h) for m in mechanisms for h in MOTOR_HOOKS):
        return 1
    return max(1, math.ceil(dt / MAX_SUBSTEP_S - 1e-9))


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
    """Motor states (i [A], omega [rad/s], theta [rad]) at the sample times, shape (n, 3).

    Without motor mechanisms this is :func:`ewb_ident.model.integrate.seed_motor_states`:
    exact over each sample for the ``exponential`` method, ``n_sub`` Heun sub-steps for
    ``heun`` (the seed paper's integrator). ``series``: a voltage (V) added to the
    logged one and a load torque (N*m), per sample, each held over its sample
    (the ``voltage_series`` and ``load_series`` hooks); both enter the linear flow
    exactly.
    """
    volt = [m for m in mechanisms if m.uses("voltage")]
    fric = [m for m in mechanisms if m.uses("motor_friction")]
    load = [m for m in mechanisms if m.uses("load_torque")]
    if not volt and not fric and not load and series is None:
        n_seed = n_sub if method == "heun" else 1
        return seed_motor_states(p, voltage_V, dt, theta0_deg, n_seed, method, None)
    A, B_V, B_tau = motor_matrices(p.R, p.L, p.kb, p.kT, p.M, p.v)
    h = dt / n_sub
    E, P1, _ = phi_matrices(A, h)
    g = matvec(P1, B_V)
    g_tau = matvec(P1, B_tau)  # exact response to a load torque held over the sub-step
    s0 = jnp.zeros(3, dtype=A.dtype).at[2].set(theta0_deg / DEG_PER_RAD)

    def force_of(theta_rad):
        x = gap(theta_rad * DEG_PER_RAD, p.p2, p.p1, p.p0)
        return clamp_force(x, p.F_rt, p.a, p.b, p.c)

    def substep(s, V, tau_ext):
        v_eff = V
        for m in volt:
            v_eff = m.voltage(v_eff, s, p)
        s1 = matvec(E, s) + g * v_eff + g_tau * tau_ext
        if load:
            # The load torque as an input held over the sub-step (exact for a constant
            # one), trapezoidal in its value: at the start, then the mean with its value
            # where that leads (Heun).
            def loaded(tau):
                return s1 + g_tau * tau

            tau0 = sum(m.load_torque(s, p, force_of(s[2])) for m in load)
            ahead = loaded(tau0)
            tau1 = sum(m.load_torque(ahead, p, force_of(ahead[2])) for m in load)
            s1 = loaded(0.5 * (tau0 + tau1))
        if fric:
            force = force_of(s1[2])
            terms = [m.motor_friction(s1, p, force, start=s) for m in fric]
            w = s1[1]
            k = h / p.M
            total = sum(t for t, _ in terms)
            # Start from the Coulomb (Moreau) solution, the limit of vanishing scales ...
            stuck = jnp.abs(w) <= k * total
            v = jnp.where(stuck, 0.0, w - k * total * jnp.sign(w))
            lo, hi = jnp.minimum(w, 0.0), jnp.maximum(w, 0.0)
            # ... then Newton on v - w + k sum T tanh(v / eps) = 0 (monotone; the root lies
            # between 0 and w since friction only opposes motion).
            for _ in range(FRICTION_NEWTON_STEPS):
                th = [jnp.tanh(v / eps) for _, eps in terms]
                res = v - w + k * sum(t * a for (t, _), a in zip(terms, th, strict=True))
                dres = 1.0 + k * sum(
                    t / eps * (1.0 - a * a) for (t, eps), a in zip(terms, th, strict=True)
                )
                v = jnp.clip(v - res / dres, lo, hi)
            theta = jnp.where(stuck & (jnp.abs(v) < 1e-12), s[2], s1[2] + 0.5 * h * (v - w))
            s1 = s1.at[1].set(v).at[2].set(theta)
        return s1

    def sample(s, xs):
        V, dv, tau_ext = xs

        def sub(c, _):
            return substep(c, V + dv, tau_ext), None

        s_next = jax.lax.scan(sub, s, None, length=n_sub)[0]
        return s_next, s

    volts = jnp.asarray(voltage_V, dtype=A.dtype)
    dv, dtau = (jnp.zeros_like(volts),) * 2 if series is None else series
    xs = (volts, jnp.broadcast_to(dv, volts.shape), jnp.broadcast_to(dtau, volts.shape))
    return jax.lax.scan(sample, s0, xs)[1]


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
) -> dict[str, jnp.ndarray]:
    """Predicted channels of one or several teacher-forced stages, or of ``"chain"``: the
    one evaluator of the chain, with or without mechanisms, for least squares, the
    posterior and the diagnosis.

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
        measured displacement that drives a hysteresis state).
    n_sub
        Motor sub-steps per sample (:func:`n_substeps`; for the seed model with the
        ``heun`` method, :meth:`ewb_ident.model.integrate.Integrator.substeps`).
    method
        ``exponential`` (exact over each sample) or ``heun`` (the seed paper's), for the
        motor without motor mechanisms.
    """
    if not isinstance(stages, str):
        out: dict[str, jnp.ndarray] = {}
        for s in stages:
            out |= predict(s, p, theta0_deg, mechanisms, d, n_sub, method)
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
        if stage == "motor":
            return out
    elif stage == "gap":
        theta = sensors.unread("theta_deg", meas["theta_deg"])

    if stage in ("gap", "chain"):
        x = _gap(stage, theta, p, mechanisms, d, ctx, sensors)
        out["x_m"] = sensors.read("x_m", x)
        if stage == "gap":
            return out
        x_drive = x
    elif stage == "force":
        x = sensors.unread("x_m", meas["x_m"])
        x_drive = x

    if stage in ("force", "chain"):
        F = _force(stage, x, x_drive, p, mechanisms, d, ctx, sensors)
        out["force_N"] = sensors.read("force_N", F)
        if stage == "force":
            return out
    else:  # torque stage
        F = sensors.unread("force_N", meas["force_N"])
    out["torque_Nm"] = sensors.read("torque_Nm", _torque(F, p, mechanisms, d, ctx))
    return out


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
