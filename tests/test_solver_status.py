"""Every solver status is reachable, and each is reported for the reason it names; warm starts help."""
import numpy as np

from bench.merging import merging_problem
from bench.verify import dynamics_defect, max_collision_violation_m
from solver_cpp import WarmStart, _core, solve

ALL_STATUSES = {"converged", "max_iterations", "line_search_failed", "numerical_error", "time_limit", "stalled", "saddle"}


def test_status_list_is_the_tested_one():
    # A status added to the C++ enum without a test here makes this fail.
    assert set(_core.Status.__members__) == ALL_STATUSES


def test_converged():
    problem = merging_problem(3, 2)
    result = solve(problem)
    assert result.status == "converged" and result.converged
    assert result.residual_norm < 5e-4  # the default tol
    assert result.residual_history[-1] == result.residual_norm
    assert dynamics_defect(problem, result.x, result.u) < 5e-4
    assert max_collision_violation_m(problem, result.x) <= 1e-6


def test_saddle():
    # The analytic saddle of tests/test_second_order.py: each player stops in front of its disc, where sliding
    # round it lowers its cost; the first-order conditions hold there.
    from test_second_order import _disc_game

    result = solve(_disc_game(1.0, 2.0), tol=1e-9)
    assert result.status == "saddle" and not result.converged
    assert result.residual_norm < 1e-9
    assert np.all(result.second_order < 0)
    assert solve(_disc_game(1.0, 1.0), tol=1e-9).status == "converged"  # the same point is an equilibrium there


def test_max_iterations():
    result = solve(merging_problem(3, 2), max_iter=1)
    assert result.status == "max_iterations" and not result.converged
    assert result.iterations == 1
    assert result.residual_norm > 5e-4


def test_time_limit():
    # An 8-car merge needs ~40 Newton iterations; a 1 microsecond budget is spent before the first step.
    result = solve(merging_problem(8, 0), time_limit=1e-6)
    assert result.status == "time_limit"
    assert result.iterations == 0
    assert result.x.shape == (8, 21, 4)  # trajectories of the initial guess are still returned
    assert solve(merging_problem(8, 0)).status == "converged"  # the limit, not the problem, stopped it


def test_stalled():
    # merging_problem(4, 36) with one restart: the three attempts (initial guess, best-response guess, rho_init x 10)
    # stop making progress (merit down < 1% over stall_window iterations) with |r| ~ 2e-2, before max_iter.
    result = solve(merging_problem(4, 36), restarts=1, max_iter=1000)
    assert result.status == "stalled"
    assert result.attempts == 3 and result.best_response_attempts == 1
    assert result.residual_norm > 1e-2
    assert result.iterations < 1000  # stopped before max_iter


def test_line_search_failed():
    # The same instance with stall detection (both rules) and restarts off runs into a point where neither the
    # Newton step nor the Levenberg-Marquardt fallbacks decrease the merit.
    result = solve(merging_problem(4, 36), restarts=0, stall_window=0, stall_floor_window=0)
    assert result.status == "line_search_failed"
    assert result.residual_norm > 5e-4
    assert result.iterations < 100


def test_stall_at_rho_floor():
    # The floor rule alone (stall_window off) recognises the point where test_line_search_failed ends: ||r|| no longer
    # falls with rho at its floor. It stops there as stalled, with the same residual, before the line search fails.
    failed = solve(merging_problem(4, 36), restarts=0, stall_window=0, stall_floor_window=0)
    stalled = solve(merging_problem(4, 36), restarts=0, stall_window=0, stall_floor_window=3)
    assert failed.status == "line_search_failed" and stalled.status == "stalled"
    assert stalled.iterations < failed.iterations
    assert abs(stalled.residual_norm - failed.residual_norm) <= 1e-4 * failed.residual_norm


def test_numerical_error():
    # Input validation accepts any finite number; an initial speed of 1e300 m/s overflows the cost
    # gradient (2 Q (v - v_ref) -> inf) at the first residual evaluation.
    problem = merging_problem(3, 0)
    problem.agents[0].x0 = [0.0, 1.1, 1e300, 0.0]
    result = solve(problem)
    assert result.status == "numerical_error"
    assert result.iterations == 0


def test_warm_start_from_shifted_solution_needs_fewer_iterations():
    # Receding horizon: solve, advance every car one step along its equilibrium trajectory, solve again
    # cold and warm (controls and multipliers shifted by one step).
    first = solve(merging_problem(4, 0), tol=1e-8)
    assert first.status == "converged"
    problem = merging_problem(4, 0)
    for i, agent in enumerate(problem.agents):
        agent.x0 = first.x[i, 1]
    cold = solve(problem, tol=1e-8)
    warm = solve(problem, tol=1e-8, warm_start=WarmStart.shifted(first))
    assert cold.status == warm.status == "converged"
    assert warm.iterations < cold.iterations
    # Same equilibrium either way.
    np.testing.assert_allclose(warm.x, cold.x, atol=1e-5, rtol=0)


def test_more_restarts_change_only_solves_that_used_every_restart():
    from bench.families import family_problem

    problem = family_problem("crossing", 2, 21)  # converges in restart 4 (attempt 6, the best-response one included)
    assert solve(problem, time_limit=0, restarts=3).status != "converged"
    enough = solve(problem, time_limit=0, restarts=4)
    assert enough.status == "converged"
    for restarts in (5, 19, 40):
        more = solve(problem, time_limit=0, restarts=restarts)
        assert (more.status, more.iterations, more.attempts) == (enough.status, enough.iterations, enough.attempts)
        assert np.array_equal(more.u, enough.u)


def test_a_crawl_counts_as_a_stall():
    from bench.families import family_problem
    from bench.verify import verify_equilibrium

    # Without the crawl rule an attempt spends hundreds of iterations in barrier subproblems whose ||r|| falls by a
    # fraction of a percent per iteration, and max_iter ends the solve.
    problem = family_problem("head-on", 7, 20)
    crawled = solve(problem, time_limit=0, crawl_window=0)
    assert crawled.status == "max_iterations"
    history = np.asarray(crawled.residual_history)
    assert history[-1] > 0.5 * history[-41]  # the final 40 iterations did not halve ||r||
    result = solve(problem, time_limit=0)
    assert result.status == "converged" and result.iterations < 1000
    report = verify_equilibrium(problem, result.x, result.u, best_response=False)
    assert report.passed, report.failures
