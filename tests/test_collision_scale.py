"""The collision constraint with a scaled first position coordinate (Collision.pos_x_scale: the ellipse
|(a dx, dy)| >= d_min, as the planners use for the Frenet along-track stretch), against hand-worked
equilibria of single integrators pulled to the origin. Pulled together, two agents end with their gap g at
the point of the ellipse |(a gx, gy)| = d_min nearest its centre: (d_min / a, 0) if a > 1, (0, d_min) if a < 1
(the circle's d_min in any direction without a scale); an agent pulled onto a fixed obstacle likewise.
Derivatives are checked against finite differences in tests/test_derivatives.py."""
from __future__ import annotations

import numpy as np
import pytest

from bench.baselines import solve_algames, solve_ilqgames
from solver_cpp import Agent, Collision, GameProblem, LinearModel, Obstacle, QuadraticCost, solve
from solver_cpp.problem_file import ProblemFileError, problem_from_dict, problem_to_dict

D_MIN = 1.0
T = 6


def _pulled(starts, scale, obstacles=()) -> GameProblem:
    """Single integrators p_{k+1} = p_k + u_k, each pulled to the origin."""
    cost = QuadraticCost(x_ref=(0.0, 0.0), Q_ref=(1.0, 1.0), R=(0.1, 0.1))
    agents = [Agent(LinearModel(np.eye(2), np.eye(2)), x0, cost) for x0 in starts]
    return GameProblem(dt=1.0, horizon=T, agents=agents,
                       collision=Collision(D_MIN, pos_x_scale=None if scale is None else [scale] * T),
                       obstacles=list(obstacles))


def _nearest_gap(scale):
    """The ellipse point nearest its centre (the gap, up to sign), or None for the circle (any direction)."""
    if scale is None:
        return None
    return np.array([D_MIN / scale, 0.0]) if scale > 1 else np.array([0.0, D_MIN])


@pytest.mark.parametrize("run, tol", [(solve, 1e-3), (solve_ilqgames, 1e-3), (solve_algames, 1e-3)])
@pytest.mark.parametrize("scale", [None, 0.5, 2.0])
def test_two_agents_pulled_together_end_on_the_ellipse_nearest_its_centre(run, tol, scale):
    result = run(_pulled([(-3.0, -0.2), (3.0, 0.2)], scale))
    assert result.status == "converged"
    gap = result.x[1, -1] - result.x[0, -1]
    a = 1.0 if scale is None else scale
    assert np.hypot(a * gap[0], gap[1]) == pytest.approx(D_MIN, abs=tol)  # the constraint is active
    assert result.x[0, -1] == pytest.approx(-result.x[1, -1], abs=tol)    # symmetric
    nearest = _nearest_gap(scale)
    # The baselines may also stop at the ellipse's far vertex (a stationary point of the pull): RD3G's shape only.
    if nearest is not None and run is solve:
        assert np.abs(gap) == pytest.approx(nearest, abs=10 * tol)


@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_an_agent_pulled_onto_an_obstacle_ends_on_the_same_ellipse(scale):
    fixed = Obstacle(positions=np.zeros((T + 1, 2)), min_distance=D_MIN)
    result = solve(_pulled([(3.0, 0.2)], scale, [fixed]))
    assert result.status == "converged"
    # To the solve's accuracy (it stops at a residual norm of 5e-4); the far vertex is 0.5 m away.
    assert np.abs(result.x[0, -1]) == pytest.approx(_nearest_gap(scale), abs=1e-3)


@pytest.mark.parametrize("scale, message", [([0.5] * (T - 1), "collision.pos_x_scale must be empty or 6 numbers"),
                                            ([0.5] * (T - 1) + [0.0], r"collision.pos_x_scale\[5\] \(step k = 6\)"),
                                            ([0.5] * (T - 1) + [np.nan], r"collision.pos_x_scale\[5\]")])
def test_a_bad_scale_is_an_error_naming_the_entry(scale, message):
    problem = _pulled([(-3.0, 0.0), (3.0, 0.0)], None)
    problem.collision.pos_x_scale = scale
    with pytest.raises(ValueError, match=message):
        solve(problem)


def test_problem_file_round_trip_keeps_the_scale():
    problem = _pulled([(-3.0, 0.0), (3.0, 0.0)], 0.5)
    again, _, _ = problem_from_dict(problem_to_dict(problem))
    assert list(again.collision.pos_x_scale) == [0.5] * T
    data = problem_to_dict(problem)
    data["collision"]["pos_x_scale"] = [0.5] * (T - 1) + [-1.0]
    with pytest.raises(ProblemFileError, match="pos_x_scale"):
        problem_from_dict(data, "game.json")
