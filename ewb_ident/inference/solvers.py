"""The two Levenberg-Marquardt solvers behind one interface: each returns a
:class:`Solution` with a :class:`Status` code. Both are NumPy loops around compiled
functions: a solver compiled whole (optimistix's, which the seed model's fits used
before) is compiled once per problem configuration, several seconds per stage and
free set, more than the whole warm fit; the loop costs a fraction of a millisecond of
Python per step beside the compiled evaluation.

:func:`seed_levenberg_marquardt`
    The seed model's stage and chain fits: one compiled function gives the residuals
    and their Jacobian; the damped step is solved from the SVD of the column-scaled
    Jacobian, and convergence is judged in standard errors
    (``tests/test_fit.py`` checks it reaches the optimum optimistix's solver reaches).
:func:`levenberg_marquardt`
    Fits with mechanisms: two compiled functions (residuals; with their Jacobian), the
    step from the normal equations, convergence on the relative decrease of the cost.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


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
    at
        What ``fun_and_jac`` returned at ``u``, where the solver keeps it
        (:func:`levenberg_marquardt`), else ``None``.
    """

    u: np.ndarray
    cost: float | None
    status: Status
    steps: int
    detail: str = ""
    at: tuple | None = None

    @property
    def converged(self) -> bool:
        return self.status is Status.SUCCESSFUL


def levenberg_marquardt(
    fun: Callable[[np.ndarray], np.ndarray] | None,
    fun_and_jac: Callable[[np.ndarray], tuple],
    u0: np.ndarray,
    *,
    max_steps: int = 200,
    rtol: float = 1e-9,
    xtol: float = 1e-9,
    stall: float | None = None,
) -> Solution:
    """Minimise ``sum(fun(u)^2)`` by Levenberg-Marquardt: the solver of fits with
    mechanisms.

    ``fun_and_jac(u)`` returns the residuals, their Jacobian and anything else (its
    return at the solution is kept, ``Solution.at``);
    ``fun(u)`` the residuals alone, for trial steps (``None``: a trial point is
    evaluated by ``fun_and_jac``, and its Jacobian kept if the step is taken).
    The loop runs in NumPy around these two compiled functions: compiling a whole solver
    for every combination of mechanisms costs ten times more than the solve. Marquardt's
    diagonal scaling; Nielsen's update of the damping. Converged when the relative
    decrease of the cost, or the step relative to ``u``, falls below the tolerances, or
    the gradient vanishes.

    ``stall``: for residuals in units of their noise (the cost a chi-square), also
    converged when the last :data:`STALL_STEPS` steps lowered the cost by less than
    ``stall`` together and the Gauss-Newton step predicts less than 1 more (the optimum
    of the linearised model within one standard error). This ends a slide along a
    weakly determined direction, where each step gains a few thousandths and the step
    limit would be reached with a gain below one unit (e.g. 0.74 in 200 steps, 3.6 s,
    by a Coulomb and Stribeck friction whose two levels trade off); such a direction's
    parameters are then reported with standard errors that say so.
    """
    u = np.asarray(u0, dtype=float)
    at = fun_and_jac(u)
    r, J = np.asarray(at[0]), np.asarray(at[1])
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
    gains: list[float] = []  # the cost's decrease at each step taken
    for step in range(1, max_steps + 1):
        if A.size == 0:
            return Solution(u, cost, Status.SUCCESSFUL, step, at=at)
        D = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
        if float(np.max(np.abs(g) / np.sqrt(D))) <= 1e-10 * max(np.sqrt(cost), 1e-300):
            return Solution(u, cost, Status.SUCCESSFUL, step, at=at)
        try:
            delta = np.linalg.solve(A + lam * np.diag(D), -g)
        except np.linalg.LinAlgError:
            lam, nu = lam * nu, nu * 2
            continue
        u_new = u + delta
        if fun is None:  # the trial point with its Jacobian, kept if the step is taken
            trial = fun_and_jac(u_new)
            r_new = np.asarray(trial[0])
        else:
            r_new = np.asarray(fun(u_new))
        with np.errstate(over="ignore", invalid="ignore"):
            cost_new = float(r_new @ r_new)
            predicted = float(-2.0 * g @ delta - delta @ A @ delta)
        rho = (cost - cost_new) / predicted if np.isfinite(predicted) and predicted > 0 else -1.0
        if np.isfinite(cost_new) and rho > 0:
            at_new = trial if fun is None else fun_and_jac(u_new)
            r_j, J_j = np.asarray(at_new[0]), np.asarray(at_new[1])
            with np.errstate(over="ignore", invalid="ignore"):
                A_j, g_j = J_j.T @ J_j, J_j.T @ r_j
            # A step to where the model has no slope, or one so steep that J^T J
            # overflows (an exponent's parameter far out): not taken.
            if not (np.all(np.isfinite(A_j)) and np.all(np.isfinite(g_j))):
                lam, nu = lam * nu, nu * 2.0
                continue
            small = cost - cost_new <= rtol * cost
            tiny = np.linalg.norm(delta) <= xtol * (np.linalg.norm(u) + xtol)
            gains.append(cost - cost_new)
            u, cost, at = u_new, cost_new, at_new
            r, J, A, g = r_j, J_j, A_j, g_j
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if small or tiny:
                return Solution(u, cost, Status.SUCCESSFUL, step, at=at)
            if (
                stall is not None
                and len(gains) >= STALL_STEPS
                and sum(gains[-STALL_STEPS:]) < stall
                and (point := _Linearised.of(r, J, marquardt=True)) is not None
                and point.gauss_newton_decrease() < 1.0
            ):
                return Solution(u, cost, Status.SUCCESSFUL, step, at=at)
        else:
            lam, nu = lam * nu, nu * 2.0
            if lam > 1e16:
                return Solution(u, cost, Status.SUCCESSFUL, step, at=at)
    return Solution(u, cost, Status.MAX_STEPS, max_steps, at=at)


#: Steps over which :func:`levenberg_marquardt` judges a stall.
STALL_STEPS = 10


def seed_levenberg_marquardt(
    fun_and_jac: Callable[[np.ndarray], tuple],
    u0: np.ndarray,
    *,
    max_steps: int = 300,
    gn_tol: float = 1e-8,
    marquardt: bool = False,
) -> Solution:
    """Minimise ``sum(r(u)^2)`` by Levenberg-Marquardt, ``fun_and_jac(u)`` returning the
    residuals ``r`` and their Jacobian ``J`` (anything after them is ignored).

    Step. The damped step ``-(J^T J + lam I)^-1 J^T r``, with Nielsen's update of
    ``lam`` from 1: damping the same in every direction of ``u``, whose coordinates are
    O(1) by construction (as in optimistix's solver). With ``marquardt=True`` each
    column of ``J`` is scaled to unit norm first (Marquardt's damping
    ``lam diag(J^T J)``, from 1e-3), which moves fast along a
    parameter whose effect fades (L drifting to 0 at 100 Hz, where identity damping
    crawls for the step limit) but crawls along some curved valleys that identity
    damping crosses; :func:`ewb_ident.inference.least_squares.fit` runs the second
    when the first reaches its step limit. The step is solved from the SVD of ``J``,
    not the normal equations (which square a condition number of 1e4-1e6 along such
    valleys); a rejected step costs no new factorisation, and every trial point is
    evaluated with its Jacobian, kept when the step is taken.

    Convergence: the decrease of ``sum(r^2)`` the undamped Gauss-Newton step predicts
    is at most ``gn_tol`` times the residual variance ``sum(r^2) / (N - k)``. For
    weighted residuals that decrease is the squared distance to the optimum in
    standard errors: "within ``sqrt(gn_tol)`` standard errors of the optimum" whatever
    the parameters' scales, so neither a step made small by damping nor a slow slide
    along a valley passes for convergence. Directions with a singular value below
    1/:data:`NULL_LIMIT` of the largest (a condition number above 1e6) are left out of
    the test: along them the gradient's rounding error, not the data, sets the
    prediction, and the fits hold such a direction's parameter
    (:mod:`ewb_ident.inference.null_directions`). A point from which no step lowers the
    cost is a minimum to working precision (converged).
    """
    u = np.asarray(u0, dtype=float)
    point = _Linearised.at(fun_and_jac, u, marquardt)
    if point is None:
        return Solution(u, float("inf"), Status.NONFINITE, 0)
    if u.size == 0 or point.near_optimum(gn_tol):
        return Solution(u, point.cost, Status.SUCCESSFUL, 0)
    # Identity damping starts at 1 (a step of about one unit of the O(1) coordinates
    # where the data say little, Gauss-Newton where they say much, as optimistix's
    # trust region does); Marquardt's, relative to unit columns, at 1e-3.
    lam, nu = (1e-3 if marquardt else 1.0), 2.0
    for step in range(1, max_steps + 1):
        delta, predicted = point.step(lam)
        trial = _Linearised.at(fun_and_jac, u + delta, marquardt)
        rho = (point.cost - trial.cost) / predicted if trial is not None and predicted > 0 else -1
        if rho > 0:
            u, point = u + delta, trial
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if point.near_optimum(gn_tol):
                return Solution(u, point.cost, Status.SUCCESSFUL, step)
        else:
            lam, nu = lam * nu, nu * 2.0
            if lam > 1e16:  # no step lowers the cost: a minimum to working precision
                return Solution(u, point.cost, Status.SUCCESSFUL, step)
    return Solution(u, point.cost, Status.MAX_STEPS, max_steps)


#: Directions of ``u`` along which the Jacobian's condition number exceeds this are
#: null for the convergence test: along them the gradient's rounding error, not the
#: data, sets the predicted decrease.
NULL_LIMIT = 1e6


@dataclass(frozen=True)
class _Linearised:
    """The residuals at a point and the SVD of their column-scaled Jacobian."""

    cost: float
    n: int
    scale: np.ndarray
    s: np.ndarray
    Vt: np.ndarray
    b: np.ndarray  # U^T r

    @classmethod
    def at(cls, fun_and_jac, u: np.ndarray, marquardt: bool) -> _Linearised | None:
        """The linearisation at ``u`` (columns scaled to unit norm if ``marquardt``, else
        all by the largest), or ``None`` where the residuals or the Jacobian are not
        finite (a diverging model, an exponent's parameter far out)."""
        out = fun_and_jac(u)
        return cls.of(np.asarray(out[0]), np.asarray(out[1]), marquardt)

    @classmethod
    def of(cls, r: np.ndarray, J: np.ndarray, marquardt: bool) -> _Linearised | None:
        """The linearisation from residuals ``r`` and their Jacobian ``J`` (see :meth:`at`)."""
        with np.errstate(over="ignore", invalid="ignore"):
            cost = float(r @ r)
            scale = np.linalg.norm(J, axis=0)
        if not (np.isfinite(cost) and np.all(np.isfinite(J)) and np.all(np.isfinite(scale))):
            return None
        if marquardt:
            scale = np.maximum(scale, 1e-150 + 1e-12 * float(np.max(scale, initial=0.0)))
        else:
            scale = np.ones_like(scale)
        U, s, Vt = np.linalg.svd(J / scale, full_matrices=False)
        return cls(cost, r.size, scale, s, Vt, U.T @ r)

    def step(self, lam: float) -> tuple[np.ndarray, float]:
        """The damped step and the decrease of ``sum(r^2)`` it predicts."""
        f = self.s / (self.s**2 + lam)
        delta = -(self.Vt.T @ (f * self.b)) / self.scale
        keep = (lam / (self.s**2 + lam)) ** 2
        return delta, float(np.sum(self.b**2 * (1.0 - keep)))

    def gauss_newton_decrease(self) -> float:
        """The decrease of ``sum(r^2)`` the undamped Gauss-Newton step predicts, along
        the directions whose condition number is within :data:`NULL_LIMIT`: for
        residuals in units of their noise, the squared distance to the linearised
        optimum in standard errors."""
        if not self.s.size:
            return 0.0
        ok = self.s * NULL_LIMIT > float(self.s[0])
        return float(np.sum(self.b[ok] ** 2))

    def near_optimum(self, gn_tol: float) -> bool:
        """Whether the Gauss-Newton step's predicted decrease is within the tolerance."""
        dof = max(self.n - self.s.size, 1)
        return self.gauss_newton_decrease() <= gn_tol * self.cost / dof
