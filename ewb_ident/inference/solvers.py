"""The two Levenberg-Marquardt solvers behind one interface: each returns a
:class:`Solution` with a :class:`Status` code (as optimistix's ``RESULTS``).

:func:`optimistix_lm`
    The seed model's stage and chain fits: optimistix's solver compiled whole, once per
    problem shape, and reused across traces of that shape.
:func:`levenberg_marquardt`
    Fits with mechanisms: a NumPy loop around two compiled functions (residuals; with
    their Jacobian), since compiling a whole solver for every combination of mechanisms
    costs ten times more than the solve.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ewb_ident.model.programs import program


class Status(enum.Enum):
    """How a solve ended."""

    SUCCESSFUL = "successful"
    MAX_STEPS = "step limit reached before the tolerances were met"
    NONFINITE = "the model produced non-finite values"
    FAILED = "the solver failed"


@dataclass(frozen=True)
class Solution:
    """Where a solver stopped, and how.

    Attributes
    ----------
    u
        The unconstrained parameter vector.
    cost
        Sum of squared residuals there (``None`` when the solver does not report it).
    status
        How the solve ended.
    steps
        Steps taken.
    detail
        The solver's own words for a failure, else ``""``.
    """

    u: np.ndarray
    cost: float | None
    status: Status
    steps: int
    detail: str = ""

    @property
    def converged(self) -> bool:
        return self.status is Status.SUCCESSFUL


@program
def _optimistix_solve(problem, u0, data, rtol, atol, max_steps):
    """The solution, optimistix's result index and the steps taken."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(problem, solver, u0, args=data, max_steps=max_steps, throw=False)
    return sol.value, sol.result._value, sol.stats["num_steps"]


def optimistix_lm(problem, u0, data, *, rtol: float, atol: float, max_steps: int) -> Solution:
    """Minimise ``sum(problem(u, data)^2)`` with optimistix's Levenberg-Marquardt."""
    value, result, steps = _optimistix_solve(problem, u0, data, rtol, atol, max_steps)
    result = int(result)
    if result == int(optx.RESULTS.successful._value):
        status, detail = Status.SUCCESSFUL, ""
    elif result == int(optx.RESULTS.nonlinear_max_steps_reached._value):
        status, detail = Status.MAX_STEPS, ""
    else:
        status = Status.FAILED
        messages = optx.RESULTS._index_to_message
        detail = messages[result] if 0 <= result < len(messages) else f"optimistix result {result}"
    return Solution(value, None, status, int(steps), detail)


def levenberg_marquardt(
    fun: Callable[[jnp.ndarray], jnp.ndarray],
    fun_and_jac: Callable[[jnp.ndarray], tuple],
    u0: np.ndarray,
    *,
    max_steps: int = 200,
    rtol: float = 1e-9,
    xtol: float = 1e-9,
) -> Solution:
    """Minimise ``sum(fun(u)^2)`` by Levenberg-Marquardt: the solver of fits with
    mechanisms.

    ``fun_and_jac(u)`` returns the residuals, their Jacobian and anything else (ignored).
    The loop runs in NumPy around these two compiled functions: compiling a whole solver
    for every combination of mechanisms costs ten times more than the solve. Marquardt's
    diagonal scaling; Nielsen's update of the damping. Converged when the relative
    decrease of the cost, or the step relative to ``u``, falls below the tolerances, or
    the gradient vanishes.
    """
    u = np.asarray(u0, dtype=float)
    r, J, _ = fun_and_jac(jnp.asarray(u))
    r, J = np.asarray(r), np.asarray(J)
    cost = float(r @ r)
    if not np.isfinite(cost):
        return Solution(u, float("inf"), Status.NONFINITE, 0)
    with np.errstate(over="ignore", invalid="ignore"):
        A, g = J.T @ J, J.T @ r
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(g))):
        return Solution(u, cost, Status.NONFINITE, 0)
    # The damping multiplies Marquardt's scale diag(J^T J), so it is a pure number: one
    # scaled by the largest diagonal (Nielsen's start for an identity damping) would damp
    # a weighted problem's steps to nothing and end it, "converged", where it started.
    lam = 1e-3
    nu = 2.0
    for step in range(1, max_steps + 1):
        if A.size == 0:
            return Solution(u, cost, Status.SUCCESSFUL, step)
        D = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
        if float(np.max(np.abs(g) / np.sqrt(D))) <= 1e-10 * max(np.sqrt(cost), 1e-300):
            return Solution(u, cost, Status.SUCCESSFUL, step)
        try:
            delta = np.linalg.solve(A + lam * np.diag(D), -g)
        except np.linalg.LinAlgError:
            lam, nu = lam * nu, nu * 2
            continue
        u_new = u + delta
        r_new = np.asarray(fun(jnp.asarray(u_new)))
        with np.errstate(over="ignore", invalid="ignore"):
            cost_new = float(r_new @ r_new)
            predicted = float(-2.0 * g @ delta - delta @ A @ delta)
        rho = (cost - cost_new) / predicted if np.isfinite(predicted) and predicted > 0 else -1.0
        if np.isfinite(cost_new) and rho > 0:
            r_j, J_j, _ = fun_and_jac(jnp.asarray(u_new))
            r_j, J_j = np.asarray(r_j), np.asarray(J_j)
            with np.errstate(over="ignore", invalid="ignore"):
                A_j, g_j = J_j.T @ J_j, J_j.T @ r_j
            # A step to where the model has no slope, or one so steep that J^T J
            # overflows (an exponent's parameter far out): not taken.
            if not (np.all(np.isfinite(A_j)) and np.all(np.isfinite(g_j))):
                lam, nu = lam * nu, nu * 2.0
                continue
            small = cost - cost_new <= rtol * cost
            tiny = np.linalg.norm(delta) <= xtol * (np.linalg.norm(u) + xtol)
            u, cost = u_new, cost_new
            r, J, A, g = r_j, J_j, A_j, g_j
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if small or tiny:
                return Solution(u, cost, Status.SUCCESSFUL, step)
        else:
            lam, nu = lam * nu, nu * 2.0
            if lam > 1e16:
                return Solution(u, cost, Status.SUCCESSFUL, step)
    return Solution(u, cost, Status.MAX_STEPS, max_steps)
