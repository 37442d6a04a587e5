"""The one Levenberg-Marquardt loop with each of its descents and stopping rules: the
parts compose whichever fit uses them."""

from __future__ import annotations

import numpy as np
import pytest

from ewb_ident.inference.solvers import (
    NearOptimum,
    NormalEquationsDescent,
    RelativeDecrease,
    Status,
    SVDDescent,
    levenberg_marquardt,
)

DESCENTS = [SVDDescent(), SVDDescent(marquardt=True), NormalEquationsDescent()]
STOPS = [NearOptimum(1e-8), RelativeDecrease(), RelativeDecrease(stall=0.1)]


def _rosenbrock(u):
    r = np.array([10.0 * (u[1] - u[0] ** 2), 1.0 - u[0]])
    return r, np.array([[-20.0 * u[0], 10.0], [-1.0, 0.0]])


@pytest.mark.parametrize("descent", DESCENTS, ids=repr)
@pytest.mark.parametrize("stop", STOPS, ids=repr)
def test_every_descent_with_every_stopping_rule_reaches_a_weighted_optimum(descent, stop):
    """A heavily weighted linear problem (J^T J of 1e14) and Rosenbrock's valley: each
    combination converges to the least-squares solution."""
    rng = np.random.default_rng(3)
    X = rng.standard_normal((300, 3))
    y = X @ np.array([1.0, -2.0, 0.5]) + 0.01 * rng.standard_normal(300)
    w = 1e7
    sol = levenberg_marquardt(
        lambda u: (w * (X @ u - y), w * X), np.zeros(3), descent=descent, stop=stop
    )
    assert sol.converged
    np.testing.assert_allclose(sol.u, np.linalg.lstsq(X, y, rcond=None)[0], rtol=1e-6)
    sol = levenberg_marquardt(_rosenbrock, np.array([-1.2, 1.0]), descent=descent, stop=stop)
    assert sol.converged
    np.testing.assert_allclose(sol.u, [1.0, 1.0], atol=1e-4)


@pytest.mark.parametrize("descent", DESCENTS, ids=repr)
def test_a_start_where_the_model_diverges_is_reported_not_solved(descent):
    def fun_and_jac(u):
        return np.array([np.inf, 1.0]), np.ones((2, 1))

    sol = levenberg_marquardt(fun_and_jac, np.zeros(1), descent=descent, stop=NearOptimum())
    assert sol.status is Status.NONFINITE and sol.steps == 0 and sol.cost == np.inf


def test_the_solution_keeps_what_the_function_returned_there():
    """``Solution.at``: the residuals, Jacobian and anything else at the solution (the
    fits with mechanisms keep their predictions from it)."""

    def fun_and_jac(u):
        return np.array([u[0] - 2.0]), np.ones((1, 1)), {"u": float(u[0])}

    sol = levenberg_marquardt(
        fun_and_jac, np.zeros(1), descent=NormalEquationsDescent(), stop=RelativeDecrease()
    )
    assert sol.converged and sol.at[2]["u"] == pytest.approx(2.0)
