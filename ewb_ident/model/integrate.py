"""Integrating the chain: voltage (zero-order hold) -> motor -> gap -> force -> torque.

Why an exponential integrator
-----------------------------
The seed paper integrates the motor with Heun's method at a fixed 0.01 s. The
armature's electrical pole sits at ``-R/L`` (L/R = 1-5 ms, i.e. -200 to -1000 1/s);
Heun is stable only for ``|1 + z + z^2/2| <= 1`` with ``z = h lambda``, i.e.
``h < 2 L/R`` = 2-10 ms. At 0.01 s the current, and with it the whole simulation,
diverges.

The motor is linear in its state and the logged voltage is held constant over each
sample interval. We therefore integrate it with an exponential integrator (ETD2RK,
Cox & Matthews 2002): the linear part, stiff electrical pole included, is propagated
exactly with ``exp(A h)``; a load torque ``tau(state)`` (zero in the seed's baseline,
the hook for missing physics such as the wedge reaction) enters through the
``phi_1``/``phi_2`` functions with second-order accuracy. With ``tau = 0`` the result is
the exact solution of the ODE at the sample times for any sample rate, at the cost of a
3x3 matrix-vector product per sample. With a load torque, each sample interval is split
into sub-steps no longer than ``max_substep_s``. ``tests/test_simulate.py`` checks both
against an independent fine-step reference; ``benchmarks/`` measures the speed.

Heun at the seed's step is kept (``method="heun"``) to reproduce the paper; it warns
when the step is unstable for the given parameters.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from ewb_ident.model.numerics import numerics
from ewb_ident.model.params import EWBParams
from ewb_ident.model.physics import DEG_PER_RAD, brake_torque, clamp_force, gap, motor_matrices
from ewb_ident.runtime.programs import program

#: ``tau(state, params) -> N*m``: a load torque on the motor from the state (i, omega,
#: theta [rad]). It must be a hashable, pure function (it is a static argument of jit).
LoadTorque = Callable[[jnp.ndarray, EWBParams], jnp.ndarray]

Method = Literal["exponential", "heun"]


class NumericalWarning(UserWarning):
    """A numerical setting that makes results unreliable (e.g. an unstable step)."""


@dataclass(frozen=True)
class Integrator:
    """How the motor ODE is integrated between samples.

    Parameters
    ----------
    method
        ``"exponential"`` (default; exact for the linear motor, ETD2RK with a load
        torque) or ``"heun"`` (the seed paper's explicit method).
    max_substep_s
        Longest sub-step with a load torque (exponential method), s.
    heun_step_s
        Step of the Heun method, s (seed: 0.01 s). Rounded so that a whole number of
        steps fills each sample interval; never longer than the interval.
    """

    method: Method = "exponential"
    max_substep_s: float = 1.0e-3
    heun_step_s: float = 0.01

    def substeps(self, dt: float, has_load: bool) -> int:
        """Number of sub-steps per sample interval ``dt`` (s)."""
        if self.method == "heun":
            return max(1, round(dt / self.heun_step_s))
        if not has_load:
            return 1
        return max(1, math.ceil(dt / self.max_substep_s - 1e-9))


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


def seed_motor_states(
    params: EWBParams,
    voltage_V: jnp.ndarray,
    dt: ArrayLike,
    theta0_deg: ArrayLike,
    n_sub: int,
    method: Method,
    load_torque: LoadTorque | None,
) -> jnp.ndarray:
    """Motor states (i, omega, theta[rad]) at the sample times, shape (n, 3).

    Without a load torque the motor is the linear recurrence ``s[k+1] = F s[k] + g V[k]``
    (``F``, ``g`` exact over the interval). With a load torque: ETD2RK (or Heun) sub-steps.
    """
    A, B_V, B_tau = motor_matrices(params.R, params.L, params.kb, params.kT, params.M, params.v)
    dtype = A.dtype
    V = jnp.asarray(voltage_V, dtype=dtype)
    s0 = jnp.array([0.0, 0.0, 0.0], dtype=dtype).at[2].set(theta0_deg / DEG_PER_RAD)
    h = dt / n_sub

    if load_torque is None:
        F, g = _sample_map(A, B_V, h, n_sub, method)

        def linear_step(s, V):
            return matvec(F, s) + g * V, s

        return jax.lax.scan(linear_step, s0, V)[1]

    def tau(s):
        return load_torque(s, params)

    if method == "heun":

        def rhs(s, V):
            return matvec(A, s) + B_V * V + B_tau * tau(s)

        def substep(s, V):
            k1 = rhs(s, V)
            k2 = rhs(s + h * k1, V)
            return s + 0.5 * h * (k1 + k2)

    else:
        E, P1, P2 = phi_matrices(A, h)

        def substep(s, V):
            N0 = B_V * V + B_tau * tau(s)
            a = matvec(E, s) + matvec(P1, N0)
            return a + matvec(P2, B_tau * (tau(a) - tau(s)))

    def step(s, V):
        return jax.lax.fori_loop(0, n_sub, lambda _, s: substep(s, V), s), s

    _, states = jax.lax.scan(step, s0, V)
    return states


@program
def motor_angle_rad(params: EWBParams, voltage_V, dt, theta0_deg) -> jnp.ndarray:
    """Pinion angle (rad) at the sample times from the logged voltage (V, zero-order
    hold, interval ``dt`` s), exact over each interval, from rest at ``theta0_deg``."""
    return seed_motor_states(params, voltage_V, dt, theta0_deg, 1, "exponential", None)[:, 2]


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
        Integration method (see :class:`Integrator`).
    load_torque
        Optional load torque ``tau(state, params)``, N*m.

    Returns
    -------
    dict with ``current_A`` (A), ``omega_rad_s`` (rad/s) and ``theta_deg`` (degrees).
    """
    n_sub = integrator.substeps(float(dt), load_torque is not None)
    if integrator.method == "heun":
        _warn_if_heun_unstable(params, float(dt) / n_sub)
    states = seed_motor_states(
        params, jnp.asarray(voltage_V), dt, theta0_deg, n_sub, integrator.method, load_torque
    )
    return {
        "current_A": states[:, 0],
        "omega_rad_s": states[:, 1],
        "theta_deg": states[:, 2] * DEG_PER_RAD,
    }


def _warn_if_heun_unstable(params: EWBParams, h: float) -> None:
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
            stacklevel=3,
        )


def chain_from_theta(
    params: EWBParams, theta_deg: ArrayLike, r_eff_m: ArrayLike
) -> dict[str, jnp.ndarray]:
    """Gap, force and torque stages from a pinion angle (measured or simulated).

    Returns
    -------
    dict with ``x_m`` (m), ``force_N`` (N) and ``torque_Nm`` (N*m).
    """
    x = gap(theta_deg, params.p2, params.p1, params.p0)
    F = clamp_force(x, params.F_rt, params.a, params.b, params.c)
    return {"x_m": x, "force_N": F, "torque_Nm": brake_torque(F, params.mu, r_eff_m)}


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
    """The whole chain from the logged voltage alone.

    Parameters
    ----------
    params
        Model parameters.
    voltage_V
        Voltage at each sample, V (zero-order hold).
    dt
        Sample interval, s.
    theta0_deg
        Pinion angle at the first sample, degrees.
    r_eff_m
        Effective pad radius, m.
    integrator, load_torque
        As for :func:`simulate_motor`.

    Returns
    -------
    dict with ``current_A``, ``omega_rad_s``, ``theta_deg``, ``x_m``, ``force_N`` and
    ``torque_Nm`` at the sample times (SI units, angle in degrees).
    """
    motor = simulate_motor(
        params, voltage_V, dt, theta0_deg, integrator=integrator, load_torque=load_torque
    )
    return motor | chain_from_theta(params, motor["theta_deg"], r_eff_m)


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
    A, B_V, _ = motor_matrices(*(float(values[k]) for k in ("R", "L", "kb", "kT", "M", "v")))
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
