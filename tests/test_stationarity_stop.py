"""The stopping test's relative stationarity (Settings::stationarity_tol): a result reported converged is stationary
to that fraction of the cost-gradient scale by the benchmark's independent KKT check (bench/verify.py: per player, a
bounded least-squares fit of the multipliers of the nearly active constraints, scipy's BVLS), whatever the size of
the game's cost gradients."""
import numpy as np
import pytest

from bench.families import family_problem
from bench.verify import cost_gradient_scale, stationarity_residual
from solver_cpp import solve

STATIONARITY_TOL = 5e-4  # the default of Settings::stationarity_tol (solver_cpp/include/rd3g/problem.hpp)


@pytest.mark.parametrize("family,cars,seed", [
    ("four-way", 2, 4),  # cost gradients of scale 0.15, a contact 0.4 mm open: ||r|| < tol alone stopped at 2.2e-3
    ("four-way", 3, 1),
    ("merge-quick", 2, 0),
    ("merge-close", 3, 2),
])
def test_a_converged_result_is_stationary_relative_to_its_cost_gradients(family, cars, seed):
    problem = family_problem(family, cars, seed)
    r = solve(problem, time_limit=0, max_iter=1000)
    assert r.status == "converged"
    x, u = np.asarray(r.x), np.asarray(r.u)
    # The solver's own multipliers are one admissible choice in the check's least-squares fit, and its test counts
    # fewer constraints as nearly active: the check can only find a smaller residual.
    assert stationarity_residual(problem, x, u, relative=True).max() <= STATIONARITY_TOL
    assert cost_gradient_scale(problem, x, u) > 0


def _scaled_costs(problem, c: float):
    for agent in problem.agents:
        for name in ("Q_ref", "Q", "R", "Qf_ref", "Qf"):
            if getattr(agent.cost, name) is not None:
                setattr(agent.cost, name, np.asarray(getattr(agent.cost, name), dtype=float) * c)
        agent.lead_weight *= c
    return problem


@pytest.mark.parametrize("scale", [0.1, 10.0])
def test_the_test_is_relative_not_absolute(scale):
    # Scaling every cost by c scales the cost gradients and the multipliers by c and leaves the equilibria where they
    # are: the absolute tol alone stops at a relative stationarity c times larger for small c; this test does not.
    problem = _scaled_costs(family_problem("four-way", 2, 4), scale)
    r = solve(problem, time_limit=0, max_iter=1000)
    assert r.status == "converged"
    assert stationarity_residual(problem, np.asarray(r.x), np.asarray(r.u), relative=True).max() <= STATIONARITY_TOL


def test_the_lead_term_counts_in_the_cost_gradients():
    # A racing lead term adds a constant gradient on one state component (bench/verify.py's _cost_gradient has it).
    problem = family_problem("merge-quick", 2, 0)
    for agent in problem.agents:
        agent.lead_weight, agent.lead_index = 0.05, 0
    r = solve(problem, time_limit=0, max_iter=1000)
    assert r.status == "converged"
    assert stationarity_residual(problem, np.asarray(r.x), np.asarray(r.u), relative=True).max() <= STATIONARITY_TOL


def test_a_negative_tolerance_is_refused_by_name():
    with pytest.raises(ValueError, match="stationarity_tol"):
        solve(family_problem("four-way", 2, 4), stationarity_tol=-1.0)
