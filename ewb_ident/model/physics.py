"""The links of the EWB chain as pure functions of explicit parameters.

``voltage_V`` -> (motor, eqs. 2-3) -> ``theta_deg`` -> (gap, eq. 4) -> ``x_m``
-> (bell curve, eq. 5) -> ``force_N`` -> (friction, eq. 8) -> ``torque_Nm``.

The motor is written in state-space form with state ``s = (i, omega, theta)`` in
(A, rad/s, rad): ``ds/dt = A s + B_V V + B_tau tau``. Integrating it is the job of
:mod:`ewb_ident.model.integrate`. Every function here is differentiable and vectorises.
Given NumPy arrays and numbers only, the stages compute in NumPy (eagerly, JAX would
compile a small program for every operation and shape, 10-20 ms each); given a JAX
array or inside a traced program, in JAX.
"""

from __future__ import annotations

from types import ModuleType

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

DEG_PER_RAD = 180.0 / jnp.pi


def _xp(*args):
    """JAX's NumPy if any argument is a JAX array (or a tracer), else NumPy."""
    return jnp if any(isinstance(a, jax.Array) for a in args) else np


def motor_matrices(
    R, L, kb, kT, M, v, xp: ModuleType = jnp
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """State-space form of the DC motor (seed eqs. 2-3).

    ``V = L di/dt + R i + kb omega`` and ``M domega/dt + v omega = kT i - tau``.

    Parameters
    ----------
    R, L, kb, kT, M, v
        Resistance (ohm), inductance (H), back-EMF constant (V*s/rad), torque constant
        (N*m/A), inertia (kg*m^2), viscous friction (N*m*s/rad).
    xp
        The array module: JAX's NumPy, or NumPy for analyses of given numbers outside
        a compiled program (the diagnosis's), where JAX would compile a small program
        for each of the few operations (0.1-0.2 s of a diagnosis); the same numbers.

    Returns
    -------
    A : (3, 3) array
        System matrix for the state (i [A], omega [rad/s], theta [rad]).
    B_V : (3,) array
        Input vector of the terminal voltage, per V.
    B_tau : (3,) array
        Input vector of the load torque, per N*m (it opposes motion when positive).
    """
    z = xp.zeros_like(xp.asarray(R, dtype=float))
    one = z + 1.0
    A = xp.array(
        [
            [-R / L, -kb / L, z],
            [kT / M, -v / M, z],
            [z, one, z],
        ]
    )
    B_V = xp.array([1.0 / L, z, z])
    B_tau = xp.array([z, -1.0 / M, z])
    return A, B_V, B_tau


def gap(theta_deg: ArrayLike, p2: ArrayLike, p1: ArrayLike, p0: ArrayLike) -> jnp.ndarray:
    """Piston displacement from the pinion angle (seed eq. 4).

    Parameters
    ----------
    theta_deg
        Pinion angle, degrees.
    p2, p1, p0
        Polynomial coefficients, m/deg^2, m/deg, m.

    Returns
    -------
    Piston displacement x, m (negative while the pads have not closed the gap).
    """
    theta_deg = _xp(theta_deg, p2, p1, p0).asarray(theta_deg)
    return (p2 * theta_deg + p1) * theta_deg + p0


def clamp_force(x: ArrayLike, F_rt: ArrayLike, a: ArrayLike, b: ArrayLike, c: ArrayLike):
    """Clamping force from piston displacement: a generalized bell (seed eq. 5).

    ``F = F_rt / (1 + |(x - c)/a|^(2 b))``.

    Parameters
    ----------
    x
        Piston displacement, m.
    F_rt
        Rated clamping force, N.
    a
        Half-width, m (F = F_rt/2 at x = c - a).
    b
        Slope exponent, dimensionless.
    c
        Centre, m (F = F_rt at x = c).

    Returns
    -------
    Clamping force, N.
    """
    xp = _xp(x, F_rt, a, b, c)
    u = (xp.asarray(x) - c) / a
    # |u|^(2b) = exp(b log(u^2)); the floor keeps the gradient in b finite at x = c.
    power = xp.exp(b * xp.log(u * u + 1e-300))
    return F_rt / (1.0 + power)


def brake_torque(force_N: ArrayLike, mu: ArrayLike, r_eff_m: ArrayLike) -> jnp.ndarray:
    """Brake torque at the disc from clamping force (seed eq. 8): ``T = 2 mu F r_eff``.

    Parameters
    ----------
    force_N
        Clamping force, N.
    mu
        Pad friction coefficient, dimensionless.
    r_eff_m
        Effective pad radius, m.

    Returns
    -------
    Brake torque, N*m (two pads).
    """
    return 2.0 * mu * _xp(force_N, mu, r_eff_m).asarray(force_N) * r_eff_m
