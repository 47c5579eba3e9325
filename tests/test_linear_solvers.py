"""The structured Riccati solve must give the same Newton steps (hence the same iterates and solution) as
the general sparse LU on the same system; the paper's least-squares options must reach an equilibrium too."""
import numpy as np
import pytest

from bench.merging import merging_problem
from solver_cpp import Solver, solve


@pytest.mark.parametrize("cars, seed", [(2, 0), (3, 1), (5, 2), (8, 1)])
def test_riccati_matches_sparse_lu(cars, seed):
    a = solve(merging_problem(cars, seed), linear_solver="riccati")
    b = solve(merging_problem(cars, seed), linear_solver="sparse_lu")
    assert a.status == b.status == "converged"
    assert a.iterations == b.iterations
    np.testing.assert_allclose(a.x, b.x, atol=1e-9, rtol=0)
    np.testing.assert_allclose(a.u, b.u, atol=1e-9, rtol=0)


def test_riccati_is_used_when_no_constraint_is_an_equality():
    s = Solver(merging_problem(8, 1))
    info = s._solver.solve(None).info
    assert info.riccati_solves == info.iterations > 0  # this instance never holds a constraint as an equality
