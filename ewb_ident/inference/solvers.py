"""One Levenberg-Marquardt for every fit: :func:`levenberg_marquardt`, which returns a
:class:`Solution` with a :class:`Status` code.

Its parts are pluggable as in optimistix's solvers (``optimistix/_solver/
levenberg_marquardt.py``: a descent, a search, a termination):

descent
    How the damped step is solved from the linearisation at a point:
    :class:`SVDDescent` (the SVD of the Jacobian, damping uniform in the O(1)
    coordinates or Marquardt's per column: the seed model's stage and chain fits) or
    :class:`NormalEquationsDescent` (the normal equations with Marquardt's damping: the
    fits with mechanisms).
damping
    Nielsen's update of the damping from the ratio of the cost's actual to predicted
    decrease (optimistix's trust-region search does the same job), from the descent's
    initial damping.
stop
    When a point is converged: :class:`NearOptimum` (the optimum within a fraction of a
    standard error, judged from the Gauss-Newton step's predicted decrease: the seed
    model's fits) or :class:`RelativeDecrease` (a small relative decrease of the cost or
    a small step, with an optional rule that ends a slide along a weak direction: the
    fits with mechanisms).

The loop runs in NumPy around one compiled function of the residuals and their
Jacobian, not compiled whole as optimistix's solver is: ``benchmarks/bench_lm.py``
(``reports/bench_lm.md``) measured optimistix's solver on the shipped traces 3-5x
slower cold (it compiles a whole solver per problem) and up to 2.6x slower warm (it
takes about ten times the steps from the fits' starts, which lie near the optimum).
``tests/test_fit.py`` checks that this loop reaches the optimum optimistix's reaches.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

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
        Sum of squared residuals there (``inf`` where they are not finite).
    status
        How the solve ended.
    steps
        Steps taken.
    detail
        The solver's own words for a failure, else ``""``.
    at
        What ``fun_and_jac`` returned at ``u`` (``None`` where the start was not
        finite).
    """

    u: np.ndarray
    cost: float
    status: Status
    steps: int
    detail: str = ""
    at: tuple | None = None

    @property
    def converged(self) -> bool:
        return self.status is Status.SUCCESSFUL


# ----------------------------------------------------------------------------- loop


def levenberg_marquardt(
    fun_and_jac: Callable[[np.ndarray], tuple],
    u0: np.ndarray,
    *,
    descent: Descent,
    stop: Stop,
    max_steps: int = 300,
) -> Solution:
    """Minimise ``sum(r(u)^2)`` by Levenberg-Marquardt, ``fun_and_jac(u)`` returning the
    residuals ``r``, their Jacobian ``J`` and anything else (its whole return at the
    solution is kept, ``Solution.at``).

    Each step: the ``descent`` gives the damped step and the decrease of the cost it
    predicts; the trial point is evaluated with its Jacobian, which is kept if the step
    is taken. A step is taken when it lowers the cost (``rho``, the actual over the
    predicted decrease, positive) to a point where the residuals and the descent's
    linearisation are finite (not to where the model diverges, or its Jacobian
    overflows), and the damping then follows Nielsen's update,
    ``lam *= max(1/3, 1 - (2 rho - 1)^3)``; a refused step doubles the factor by
    which ``lam`` grows. Converged when ``stop`` says so, at the start or after a step
    taken, or when no step lowers the cost (``lam`` above 1e16: a minimum to working
    precision).
    """
    u = np.asarray(u0, dtype=float)
    at = fun_and_jac(u)
    point = descent.linearise(np.asarray(at[0]), np.asarray(at[1]))
    if point is None:
        return Solution(u, _cost(np.asarray(at[0])), Status.NONFINITE, 0)
    if u.size == 0 or stop.at_start(point):
        return Solution(u, point.cost, Status.SUCCESSFUL, 0, at=at)
    lam, nu = descent.initial_damping, 2.0
    gains: list[float] = []  # the cost's decrease at each step taken
    for step in range(1, max_steps + 1):
        proposal = point.step(lam)
        if proposal is None:  # the damped system is singular: more damping
            lam, nu = lam * nu, nu * 2.0
            continue
        delta, predicted = proposal
        u_new = u + delta
        at_new = fun_and_jac(u_new)
        trial = descent.linearise(np.asarray(at_new[0]), np.asarray(at_new[1]))
        rho = -1.0
        if trial is not None and np.isfinite(predicted) and predicted > 0:
            rho = (point.cost - trial.cost) / predicted
        if rho > 0:
            gains.append(point.cost - trial.cost)
            before, u_before = point, u
            u, point, at = u_new, trial, at_new
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if stop.after_step(before, point, delta, u_before, gains):
                return Solution(u, point.cost, Status.SUCCESSFUL, step, at=at)
        else:
            lam, nu = lam * nu, nu * 2.0
            if lam > 1e16:  # no step lowers the cost: a minimum to working precision
                return Solution(u, point.cost, Status.SUCCESSFUL, step, at=at)
    return Solution(u, point.cost, Status.MAX_STEPS, max_steps, at=at)


def _cost(r: np.ndarray) -> float:
    with np.errstate(over="ignore", invalid="ignore"):
        cost = float(r @ r)
    return cost if np.isfinite(cost) else float("inf")


# ----------------------------------------------------------------------------- descents


class Point(Protocol):
    """The linearisation of the residuals at a point, as a descent factorises it."""

    r: np.ndarray
    J: np.ndarray
    cost: float

    def step(self, lam: float) -> tuple[np.ndarray, float] | None:
        """The step damped by ``lam`` and the decrease of ``sum(r^2)`` it predicts
        (``None``: the damped system could not be solved)."""

    def gauss_newton_decrease(self) -> float:
        """The decrease of ``sum(r^2)`` the undamped Gauss-Newton step predicts, along
        the directions whose condition number is within :data:`NULL_LIMIT`."""

    def gradient_vanishes(self) -> bool:
        """Whether the gradient, in Marquardt's scaling, is below 1e-10 of the residuals'
        norm."""


class Descent(Protocol):
    """How :func:`levenberg_marquardt` linearises the residuals and solves its step."""

    initial_damping: float

    def linearise(self, r: np.ndarray, J: np.ndarray) -> Point | None:
        """The point's linearisation, or ``None`` where it is not finite."""


@dataclass(frozen=True)
class SVDDescent:
    """The damped step ``-(J^T J + lam I)^-1 J^T r`` in the coordinates ``u``, solved
    from the SVD of ``J``, not the normal equations (which square a condition number
    of 1e4-1e6 along the seed model's valleys); a refused step costs no new
    factorisation.

    Damping the same in every direction of ``u`` (whose coordinates are O(1) by
    construction, as in optimistix's solver), from 1: a step of about one unit where the
    data say little, Gauss-Newton where they say much. With ``marquardt=True`` each
    column of ``J`` is scaled to unit norm first (Marquardt's damping
    ``lam diag(J^T J)``), from 1e-3: it moves fast along a parameter whose effect fades
    (L drifting to 0 at 100 Hz, where uniform damping crawls for the step limit) but
    crawls along some curved valleys that uniform damping crosses;
    :func:`ewb_ident.inference.least_squares.fit` runs the second when the first
    reaches its step limit.
    """

    marquardt: bool = False

    @property
    def initial_damping(self) -> float:
        return 1e-3 if self.marquardt else 1.0

    def linearise(self, r: np.ndarray, J: np.ndarray) -> SVDPoint | None:
        return SVDPoint.of(r, J, self.marquardt)


@dataclass(frozen=True)
class NormalEquationsDescent:
    """The damped step ``-(J^T J + lam D)^-1 J^T r`` from the normal equations, with
    Marquardt's scaling ``D = diag(J^T J)`` (floored at 1e-12 of its largest entry), from
    a damping of 1e-3: a pure number, as the scale is the Jacobian's (one scaled by
    the largest diagonal, Nielsen's start for an identity damping, would damp a heavily
    weighted problem's steps to nothing and end it, "converged", where it started).
    A point where ``J^T J`` or ``J^T r`` overflows is not finite (a step there, to an
    exponent's parameter far out, is refused)."""

    initial_damping: float = 1e-3

    def linearise(self, r: np.ndarray, J: np.ndarray) -> NormalPoint | None:
        with np.errstate(over="ignore", invalid="ignore"):
            cost = float(r @ r)
            A, g = J.T @ J, J.T @ r
        if not (np.isfinite(cost) and np.all(np.isfinite(A)) and np.all(np.isfinite(g))):
            return None
        return NormalPoint(r, J, cost, A, g)


#: Directions of ``u`` along which the Jacobian's condition number exceeds this are
#: null for the convergence tests: along them the gradient's rounding error, not the
#: data, sets the predicted decrease.
NULL_LIMIT = 1e6


@dataclass(frozen=True)
class SVDPoint:
    """The residuals at a point and the SVD of their column-scaled Jacobian."""

    r: np.ndarray
    J: np.ndarray
    cost: float
    scale: np.ndarray
    s: np.ndarray
    Vt: np.ndarray
    b: np.ndarray  # U^T r

    @classmethod
    def of(cls, r: np.ndarray, J: np.ndarray, marquardt: bool) -> SVDPoint | None:
        """The linearisation from residuals ``r`` and their Jacobian ``J`` (columns
        scaled to unit norm if ``marquardt``, else all by 1), or ``None`` where they are
        not finite (a diverging model, an exponent's parameter far out)."""
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
        return cls(r, J, cost, scale, s, Vt, U.T @ r)

    def step(self, lam: float) -> tuple[np.ndarray, float]:
        f = self.s / (self.s**2 + lam)
        delta = -(self.Vt.T @ (f * self.b)) / self.scale
        keep = (lam / (self.s**2 + lam)) ** 2
        return delta, float(np.sum(self.b**2 * (1.0 - keep)))

    def gauss_newton_decrease(self) -> float:
        """For residuals in units of their noise: the squared distance to the
        linearised optimum in standard errors."""
        if not self.s.size:
            return 0.0
        ok = self.s * NULL_LIMIT > float(self.s[0])
        return float(np.sum(self.b[ok] ** 2))

    def gradient_vanishes(self) -> bool:
        return _gradient_vanishes(self.J.T @ self.J, self.J.T @ self.r, self.cost)


@dataclass(frozen=True)
class NormalPoint:
    """The residuals at a point and their normal equations ``A = J^T J``, ``g = J^T r``."""

    r: np.ndarray
    J: np.ndarray
    cost: float
    A: np.ndarray
    g: np.ndarray

    def step(self, lam: float) -> tuple[np.ndarray, float] | None:
        A, g = self.A, self.g
        D = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
        try:
            delta = np.linalg.solve(A + lam * np.diag(D), -g)
        except np.linalg.LinAlgError:
            return None
        with np.errstate(over="ignore", invalid="ignore"):
            return delta, float(-2.0 * g @ delta - delta @ A @ delta)

    def gauss_newton_decrease(self) -> float:
        """As :meth:`SVDPoint.gauss_newton_decrease`, from the SVD of the Jacobian with
        unit columns."""
        point = SVDPoint.of(self.r, self.J, marquardt=True)
        return float("inf") if point is None else point.gauss_newton_decrease()

    def gradient_vanishes(self) -> bool:
        return _gradient_vanishes(self.A, self.g, self.cost)


def _gradient_vanishes(A: np.ndarray, g: np.ndarray, cost: float) -> bool:
    """Whether the gradient ``g``, in Marquardt's scaling ``diag(A)``, is below 1e-10 of
    the residuals' norm."""
    D = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
    return float(np.max(np.abs(g) / np.sqrt(D))) <= 1e-10 * max(np.sqrt(cost), 1e-300)


# ----------------------------------------------------------------------------- stopping


class Stop(Protocol):
    """When :func:`levenberg_marquardt` has converged."""

    def at_start(self, point: Point) -> bool:
        """Whether the start is converged."""

    def after_step(
        self, before: Point, after: Point, delta: np.ndarray, u: np.ndarray, gains: list[float]
    ) -> bool:
        """Whether the point reached by the step ``delta`` from ``u`` (at ``before``) is
        converged; ``gains``: the cost's decrease at each step taken so far."""


@dataclass(frozen=True)
class NearOptimum:
    """Converged when the decrease of ``sum(r^2)`` the undamped Gauss-Newton step
    predicts is at most ``tol`` times the residual variance ``sum(r^2) / (N - k)``.

    For weighted residuals that decrease is the squared distance to the optimum in
    standard errors: "within ``sqrt(tol)`` standard errors of the optimum" whatever the
    parameters' scales, so neither a step made small by damping nor a slow slide along
    a valley passes for convergence. Directions with a singular value below
    1/:data:`NULL_LIMIT` of the largest are left out of the test: along them the
    gradient's rounding error, not the data, sets the prediction, and the fits hold
    such a direction's parameter (:mod:`ewb_ident.inference.null_directions`).
    """

    tol: float = 1e-8

    def at_start(self, point: Point) -> bool:
        return self._near(point)

    def after_step(self, before, after, delta, u, gains) -> bool:
        return self._near(after)

    def _near(self, point: Point) -> bool:
        dof = max(point.r.size - point.J.shape[1], 1)
        return point.gauss_newton_decrease() <= self.tol * point.cost / dof


#: Steps over which :class:`RelativeDecrease` judges a stall.
STALL_STEPS = 10


@dataclass(frozen=True)
class RelativeDecrease:
    """Converged when a step lowers the cost by at most ``rtol`` of it, or moves ``u`` by
    at most ``xtol`` relative to its norm, or the gradient vanishes (in Marquardt's
    scaling, below 1e-10 of the residuals' norm).

    ``stall``: for residuals in units of their noise (the cost a chi-square), also
    converged when the last :data:`STALL_STEPS` steps lowered the cost by less than
    ``stall`` together and the Gauss-Newton step predicts less than 1 more (the optimum
    of the linearised model within one standard error). This ends a slide along a
    weakly determined direction, where each step gains a few thousandths and the step
    limit would be reached with a gain below one unit (e.g. 0.74 in 200 steps, 3.6 s,
    by a Coulomb and Stribeck friction whose two levels trade off); such a direction's
    parameters are then reported with standard errors that say so.
    """

    rtol: float = 1e-9
    xtol: float = 1e-9
    stall: float | None = None

    def at_start(self, point: Point) -> bool:
        return point.gradient_vanishes()

    def after_step(self, before, after, delta, u, gains) -> bool:
        if before.cost - after.cost <= self.rtol * before.cost:
            return True
        if np.linalg.norm(delta) <= self.xtol * (np.linalg.norm(u) + self.xtol):
            return True
        if (
            self.stall is not None
            and len(gains) >= STALL_STEPS
            and sum(gains[-STALL_STEPS:]) < self.stall
            and after.gauss_newton_decrease() < 1.0
        ):
            return True
        return after.gradient_vanishes()
