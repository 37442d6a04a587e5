"""The motor integrator: the logged voltage (zero-order hold) -> motor states.

One function, :func:`integrate_motor`, integrates the motor for every evaluation of the
model (the fits, the posterior, the diagnosis, :func:`ewb_ident.simulate_chain`), and one
rule, :meth:`Integrator.substeps`, says how many sub-steps each sample interval takes.

Why an exponential integrator
-----------------------------
The seed paper integrates the motor with Heun's method at a fixed 0.01 s. The
armature's electrical pole sits at ``-R/L`` (L/R = 1-5 ms, i.e. -200 to -1000 1/s);
Heun is stable only for ``|1 + z + z^2/2| <= 1`` with ``z = h lambda``, i.e.
``h < 2 L/R`` = 2-10 ms. At 0.01 s the current, and with it the whole simulation,
diverges.

The motor is linear in its state and the logged voltage is held constant over each
sample interval. We therefore propagate it exactly with ``exp(A h)``: the seed's motor
is the exact solution of the ODE at the sample times for any sample rate, at the cost of
a 3x3 matrix-vector product per sample. What the seed leaves out enters the motor
through :class:`MotorTerms` (its insertion points: the voltage the armature sees, a load
torque, a friction-like torque, and series held per sample). A term that depends on
the state within a sample splits each sample interval into sub-steps no longer than
:data:`MAX_SUBSTEP_S`: exact linear flow, a load torque held over the sub-step at the
trapezoidal mean of its values (second order), then an implicit friction update (first
order). ``tests/test_simulate.py`` checks the integrator against an independent
fine-step reference and measures both orders, and why the sub-step is 0.5 ms;
``benchmarks/`` measures the speed.

Heun at the seed's step is kept (``method="heun"``, the seed's motor only) to reproduce
the paper; it warns when the step is unstable for the given parameters.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from ewb_ident.model.params import EWBParams
from ewb_ident.model.physics import DEG_PER_RAD, clamp_force, gap, motor_matrices
from ewb_ident.runtime.programs import program

#: ``tau(state, params) -> N*m``: a load torque on the motor from the state (i, omega,
#: theta [rad]). It must be a hashable, pure function (it is a static argument of jit).
LoadTorque = Callable[[jnp.ndarray, EWBParams], jnp.ndarray]

Method = Literal["exponential", "heun"]


class NumericalWarning(UserWarning):
    """A numerical setting that makes results unreliable (e.g. an unstable step)."""


#: Longest motor sub-step when a term depends on the state within a sample, s. The
#: friction update is first order, so its bias falls in proportion to the step: at
#: 0.5 ms the concealed stiction trace's fitted ``tau_c`` moves by half its standard
#: error against 0.25 ms, at 1 ms by one (``reports/substep_bias.txt``), and a stiction
#: motor's angle is within 1 % of the effect of its limit
#: (``tests/test_simulate.py::test_the_substep_rule_resolves_friction_and_load``).
MAX_SUBSTEP_S = 5.0e-4

#: Newton steps of the implicit friction update.
FRICTION_NEWTON_STEPS = 3


@dataclass(frozen=True)
class Integrator:
    """How the motor ODE is integrated between samples.

    Parameters
    ----------
    method
        ``"exponential"`` (default; exact for the seed's motor, sub-steps with terms) or
        ``"heun"`` (the seed paper's explicit method, for the seed's motor).
    max_substep_s
        Longest sub-step with a term that depends on the state within a sample
        (exponential method), s; ``None``: :data:`MAX_SUBSTEP_S`.
    heun_step_s
        Step of the Heun method, s (seed: 0.01 s). Rounded so that a whole number of
        steps fills each sample interval; never longer than the interval.
    """

    method: Method = "exponential"
    max_substep_s: float | None = None
    heun_step_s: float = 0.01

    def substeps(self, dt: float, within_sample: bool) -> int:
        """Number of sub-steps per sample interval ``dt`` (s): the one sub-step rule.

        ``within_sample``: whether a term depends on the state within a sample
        (:attr:`MotorTerms.within_sample`); without one the exponential method is exact
        over the whole interval.
        """
        if self.method == "heun":
            return max(1, round(dt / self.heun_step_s))
        if not within_sample:
            return 1
        step = MAX_SUBSTEP_S if self.max_substep_s is None else self.max_substep_s
        return max(1, math.ceil(dt / step - 1e-9))


#: The default integrator, and the seed paper's.
EXPONENTIAL = Integrator()
SEED_HEUN = Integrator(method="heun", heun_step_s=0.01)


def _mm(A: jnp.ndarray, B: jnp.ndarray) -> jnp.ndarray:
    """Small (batched) matrix product as a fused multiply-add: XLA on the CPU calls a
    library routine per ``dot``, whose overhead dominates for 3x3 to 9x9 matrices."""
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)


def matvec(A: jnp.ndarray, x: jnp.ndarray) -> jnp.ndarray:
    """Small matrix-vector product as a fused multiply-add (see :func:`_mm`)."""
    return jnp.sum(A * x[None, :], axis=1)


def expm_fixed(X: jnp.ndarray, squarings: int = 8, order: int = 14) -> jnp.ndarray:
    """Matrix exponential by scaling and squaring with a fixed number of squarings.

    No data-dependent control flow, so its derivatives are cheap (``jax.scipy``'s
    ``expm`` picks its scaling at run time and differentiates through a Frechet
    derivative of twice the size). Accurate to rounding for ``||X|| <~ 2^squarings``:
    the motor's ``||A h||`` is below 100 for every admissible armature and sample rate.
    """
    Y = X / (2.0**squarings)
    term = jnp.eye(X.shape[0], dtype=X.dtype)
    E = term
    for k in range(1, order + 1):
        term = _mm(term, Y) / k
        E = E + term
    for _ in range(squarings):
        E = _mm(E, E)
    return E


def phi_matrices(A: jnp.ndarray, h: ArrayLike) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """``exp(A h)``, ``h phi_1(A h)`` and ``h phi_2(A h)`` from one block exponential.

    ``phi_1(z) = (e^z - 1)/z`` and ``phi_2(z) = (e^z - 1 - z)/z^2`` (matrix versions),
    read off ``expm([[A h, I, 0], [0, 0, I], [0, 0, 0]])`` (Al-Mohy & Higham 2011).
    """
    n = A.shape[0]
    eye = jnp.eye(n, dtype=A.dtype)
    zero = jnp.zeros((n, n), dtype=A.dtype)
    big = jnp.block([[A * h, eye, zero], [zero, zero, eye], [zero, zero, zero]])
    X = expm_fixed(big)
    return X[:n, :n], h * X[:n, n : 2 * n], h * X[:n, 2 * n :]


def zoh_map(A: jnp.ndarray, B: jnp.ndarray, h: ArrayLike) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``exp(A h)`` and ``h phi_1(A h) B``: the exact map of ``s' = A s + B u`` over a step
    ``h`` with ``u`` held, ``s -> F s + g u``, from the exponential of the augmented
    matrix ``[[A h, B h], [0, 0]]`` (one size larger than ``A``; a ninth of the work of
    :func:`phi_matrices`' block for the 3-state motor, whose exponential is most of the
    cost of a fit's compiled evaluation)."""
    n = A.shape[0]
    top = jnp.concatenate([A * h, (B * h)[:, None]], axis=1)
    X = expm_fixed(jnp.concatenate([top, jnp.zeros((1, n + 1), dtype=A.dtype)], axis=0))
    return X[:n, :n], X[:n, n]


def zoh_exact(A, B, h: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`zoh_map` in NumPy for any step: ``exp(A h)`` and ``h phi_1(A h) B`` for
    each column of ``B`` (n, k), by SciPy's adaptive scaling and squaring. For analyses
    outside the compiled fit (the diagnosis), where an armature whose ``L/R`` is far
    below the step (``||A h||`` in the thousands, beyond :func:`expm_fixed`'s range) has
    a response that is fast, not one that overflows."""
    from scipy.linalg import expm

    A = np.asarray(A, float)
    B = np.asarray(B, float).reshape(A.shape[0], -1)
    n, k = B.shape
    m = np.zeros((n + k, n + k))
    m[:n, :n], m[:n, n:] = A * h, B * h
    E = expm(m)
    return E[:n, :n], E[:n, n:]


def heun_amplification(params: EWBParams, h: float) -> float:
    """Spectral radius of Heun's step ``1 + z + z^2/2`` on the motor's poles.

    Above 1 the seed's integration diverges. ``h`` in s.
    """
    A, _, _ = motor_matrices(params.R, params.L, params.kb, params.kT, params.M, params.v)
    z = np.linalg.eigvals(np.asarray(A, dtype=float)[:2, :2]) * h
    return float(np.max(np.abs(1.0 + z + 0.5 * z * z)))


def _sample_map(A, B_V, h, n_sub: int, method: Method) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The affine map ``s -> F s + g V`` over one sample interval, without load torque.

    Exact (``exp``) for the exponential method; Heun's own polynomial map for ``heun``.
    """
    n = A.shape[0]
    if method == "heun":
        eye = jnp.eye(n, dtype=A.dtype)
        F = eye + h * A + 0.5 * h * h * _mm(A, A)
        g = matvec(h * eye + 0.5 * h * h * A, B_V)
    else:
        F, g = zoh_map(A, B_V, h)
    Fs, gs = F, g
    for _ in range(n_sub - 1):
        Fs, gs = _mm(F, Fs), matvec(F, gs) + g
    return Fs, gs


class MotorTerms(NamedTuple):
    """What enters the motor besides the logged voltage: the motor's insertion points.

    Each is a pure function closing over the parameters it needs (a catalog mechanism's
    hook, a learned term, a load torque given as a function); ``force`` is the model's
    clamping force at the state's angle, ``F_bell(gap(theta))``, N.

    Attributes
    ----------
    voltage
        ``V_eff = f(V, s)``: the voltage the armature sees, V (motor electrical).
    load
        ``tau = f(s, force)``: a smooth signed load torque, N*m (motor mechanical).
    friction
        ``(T, eps) = f(s1, force, start)``: a friction-like torque ``T tanh(omega / eps)``
        that opposes motion (N*m, rad/s; ``s1`` the state after a sub-step's linear flow,
        ``start`` the state at its start), integrated implicitly.
    series
        A voltage (V) added to the logged one and a load torque (N*m), per sample, each
        held over its sample; ``None`` for none.
    """

    voltage: tuple[Callable, ...] = ()
    load: tuple[Callable, ...] = ()
    friction: tuple[Callable, ...] = ()
    series: tuple[jnp.ndarray, jnp.ndarray] | None = None

    @property
    def within_sample(self) -> bool:
        """Whether a term depends on the state within a sample (so the motor needs
        sub-steps, :meth:`Integrator.substeps`)."""
        return bool(self.voltage or self.load or self.friction)

    @property
    def empty(self) -> bool:
        """No term at all: the seed's linear motor."""
        return not self.within_sample and self.series is None


#: The seed's motor: no term.
NO_TERMS = MotorTerms()


def integrate_motor(
    params: EWBParams,
    voltage_V: jnp.ndarray,
    dt: ArrayLike,
    theta0_deg: ArrayLike,
    n_sub: int,
    method: Method = "exponential",
    terms: MotorTerms | None = None,
) -> jnp.ndarray:
    """The motor integrator: states (i [A], omega [rad/s], theta [rad]) at the sample
    times, shape (n, 3), from rest at ``theta0_deg``.

    Without terms the motor is the linear recurrence ``s[k+1] = F s[k] + g V[k]``: ``F``,
    ``g`` exact over the interval for the ``exponential`` method, ``n_sub`` Heun steps
    for ``heun`` (the seed paper's integrator). With terms (exponential method only),
    ``n_sub`` sub-steps per sample, each the exact linear flow with the voltage the
    ``voltage`` terms let through and the held ``series``, a load torque held over the
    sub-step at the mean of its values at the start and where that leads (trapezoidal,
    second order), then an implicit (backward Euler) step of the friction-like torques,
    each ``T tanh(omega / eps)`` (a torque ``T`` that opposes motion, switching over a
    speed scale ``eps``): with ``omega_free`` the speed after the linear flow, ``omega``
    solves ``omega = omega_free - (h / M) sum T tanh(omega / eps)``. It starts from the
    Coulomb limit (``eps -> 0``, Moreau's time-stepping scheme: stuck, ``omega = 0``,
    when ``|omega_free| <= h sum T / M``) and takes :data:`FRICTION_NEWTON_STEPS` Newton
    steps, so a stiff, nearly set-valued friction is integrated stably and stays
    differentiable for the fit; an actuator held by friction stays still. The splitting
    is first order in ``h``.

    Raises
    ------
    ValueError
        ``method="heun"`` with terms: the seed's Heun integrates only the seed's motor.
    """
    terms = NO_TERMS if terms is None else terms
    A, B_V, B_tau = motor_matrices(params.R, params.L, params.kb, params.kT, params.M, params.v)
    dtype = A.dtype
    s0 = jnp.zeros(3, dtype=dtype).at[2].set(theta0_deg / DEG_PER_RAD)
    if terms.empty:
        n_seed = n_sub if method == "heun" else 1  # exact over a sample: one step
        F, g = _sample_map(A, B_V, dt / n_seed, n_seed, method)

        def linear_step(s, V):
            return matvec(F, s) + g * V, s

        return jax.lax.scan(linear_step, s0, jnp.asarray(voltage_V, dtype=dtype))[1]
    if method == "heun":
        raise ValueError(
            "the seed's Heun method integrates only the seed's motor, without load "
            "torques, friction or added voltages; use method='exponential'"
        )
    p = params
    h = dt / n_sub
    E, P1, _ = phi_matrices(A, h)
    g = matvec(P1, B_V)
    g_tau = matvec(P1, B_tau)  # exact response to a load torque held over the sub-step

    def force_of(theta_rad):
        x = gap(theta_rad * DEG_PER_RAD, p.p2, p.p1, p.p0)
        return clamp_force(x, p.F_rt, p.a, p.b, p.c)

    def substep(s, V, tau_ext):
        v_eff = V
        for f in terms.voltage:
            v_eff = f(v_eff, s)
        s1 = matvec(E, s) + g * v_eff + g_tau * tau_ext
        if terms.load:
            # The load torque as an input held over the sub-step (exact for a constant
            # one), trapezoidal in its value: at the start, then the mean with its value
            # where that leads (Heun).
            def loaded(tau):
                return s1 + g_tau * tau

            tau0 = sum(f(s, force_of(s[2])) for f in terms.load)
            ahead = loaded(tau0)
            tau1 = sum(f(ahead, force_of(ahead[2])) for f in terms.load)
            s1 = loaded(0.5 * (tau0 + tau1))
        if terms.friction:
            force = force_of(s1[2])
            parts = [f(s1, force, s) for f in terms.friction]
            w = s1[1]
            k = h / p.M
            total = sum(t for t, _ in parts)
            # Start from the Coulomb (Moreau) solution, the limit of vanishing scales ...
            stuck = jnp.abs(w) <= k * total
            v = jnp.where(stuck, 0.0, w - k * total * jnp.sign(w))
            lo, hi = jnp.minimum(w, 0.0), jnp.maximum(w, 0.0)
            # ... then Newton on v - w + k sum T tanh(v / eps) = 0 (monotone; the root lies
            # between 0 and w since friction only opposes motion).
            for _ in range(FRICTION_NEWTON_STEPS):
                th = [jnp.tanh(v / eps) for _, eps in parts]
                res = v - w + k * sum(t * a for (t, _), a in zip(parts, th, strict=True))
                dres = 1.0 + k * sum(
                    t / eps * (1.0 - a * a) for (t, eps), a in zip(parts, th, strict=True)
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

    volts = jnp.asarray(voltage_V, dtype=dtype)
    dv, dtau = (jnp.zeros_like(volts),) * 2 if terms.series is None else terms.series
    xs = (volts, jnp.broadcast_to(dv, volts.shape), jnp.broadcast_to(dtau, volts.shape))
    return jax.lax.scan(sample, s0, xs)[1]


@program
def motor_angle_rad(params: EWBParams, voltage_V, dt, theta0_deg) -> jnp.ndarray:
    """Pinion angle (rad) at the sample times from the logged voltage (V, zero-order
    hold, interval ``dt`` s), exact over each interval, from rest at ``theta0_deg``."""
    return integrate_motor(params, voltage_V, dt, theta0_deg, 1)[:, 2]


def warn_if_heun_unstable(params: EWBParams, h: float) -> None:
    """Warn (:class:`NumericalWarning`) when Heun's step ``h`` (s) diverges on this motor."""
    try:
        rho = heun_amplification(params, h)
    except jax.errors.ConcretizationTypeError:  # traced parameters: checked by the caller
        return
    if rho > 1.0:
        warnings.warn(
            f"Heun's method at h = {h:g} s is unstable for this motor (L/R = "
            f"{float(params.L) / float(params.R) * 1e3:.3g} ms; step amplification "
            f"{rho:.3g} > 1): the simulation diverges. Use the default exponential "
            "integrator, or h < 2 L/R.",
            NumericalWarning,
            stacklevel=4,
        )


#: Longest sub-step of the motor states resolved within each sample interval, s.
FINE_STEP_S = 2.5e-4


def motor_fine(values: Mapping[str, float], trace) -> dict[str, np.ndarray]:
    """The motor model's states within each sample interval from the logged voltage
    (the fit's parameters ``values``; exact zero-order-hold flow at sub-steps of at most
    :data:`FINE_STEP_S`): ``current`` (A), ``speed`` (rad/s), ``angle`` (deg), each of
    shape (n, m + 1), the interval's start and end included. At the sample times they
    are the motor stage's own prediction."""
    dt, n = trace.dt, trace.n
    m = max(1, int(np.ceil(dt / FINE_STEP_S - 1e-9)))
    A, B_V, _ = motor_matrices(*(float(values[k]) for k in ("R", "L", "kb", "kT", "M", "v")), np)
    Ad, bd = zoh_exact(A, B_V, dt / m)
    bd = bd[:, 0]
    V = trace["voltage_V"]
    # The flow over a whole sample, then each sub-step from the sample's start state.
    Am = np.linalg.matrix_power(Ad, m)
    bm = sum(np.linalg.matrix_power(Ad, j) @ bd for j in range(m))
    starts = np.empty((n, 3))
    x = np.array([0.0, 0.0, float(values.get("theta0_deg", 0.0)) / DEG_PER_RAD])
    for k in range(n):
        starts[k] = x
        x = Am @ x + bm * V[k]
    out = np.empty((n, m + 1, 3))
    S = starts
    out[:, 0] = S
    for j in range(1, m + 1):
        S = S @ Ad.T + bd[None, :] * V[:, None]
        out[:, j] = S
    return {"current": out[..., 0], "speed": out[..., 1], "angle": out[..., 2] * DEG_PER_RAD}
