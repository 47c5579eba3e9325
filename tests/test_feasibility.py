"""Feasibility of a game (bench/verify.py: control_independent_states, fixed_state_infeasibility, find_feasible_point,
problem_feasibility) on hand-built problems whose answer is known by hand, and the `bench merge` flags that go with
it (--seeds, --seed-start, --max-iter, --time-limit 0, the CPU and feasibility columns)."""
import json

import numpy as np
import pytest

from app.cli import main
from bench import verify
from solver_cpp import Agent, Collision, GameProblem, KinematicBicycle, LinearModel, QuadraticCost

COST = QuadraticCost(x_ref=(0.0, 0.0, 2.0, 0.0), Q_ref=(0.0, 0.1, 0.01, 0.0), R=(0.3, 0.3))


def _double_integrator(dt=0.2):
    """x = (px, py, vx, vy), u = (ax, ay): p_{k+1} = p_k + dt v_k, v_{k+1} = v_k + dt u_k, so p_1 depends on x_0
    alone and p_2 on u_0."""
    A = np.eye(4)
    A[0, 2] = A[1, 3] = dt
    B = np.zeros((4, 2))
    B[2, 0] = B[3, 1] = dt
    return LinearModel(A, B)


def test_control_independent_states_match_the_double_integrator_by_hand():
    model = _double_integrator()
    cost = QuadraticCost(x_ref=(0, 0, 0, 0), Q_ref=(0, 0, 0, 0), R=(1.0, 1.0))
    p = GameProblem(dt=0.2, horizon=4, agents=[Agent(model, (0, 0, 1, 0), cost), Agent(model, (5, 0, -1, 0), cost)],
                    collision=Collision(1.0))
    fixed = verify.control_independent_states(p)
    expected = np.zeros((5, 4), dtype=bool)
    expected[0] = True            # x_0 is data
    expected[1, :2] = True        # p_1 = p_0 + dt v_0; v_1 = v_0 + dt u_0 moves with u_0
    np.testing.assert_array_equal(fixed[0], expected)
    np.testing.assert_array_equal(fixed[1], expected)


def test_cars_overlapping_at_step_one_are_proven_infeasible():
    # Kinematic bicycle at rest: p_1 = p_0 + dt v_0 (cos, sin)(theta + beta) = p_0 whatever u_0 (v_0 = 0), and the two
    # cars are sqrt(1 + 0.25) = 1.118 m apart < d_min 2 m at k = 1.
    bike = KinematicBicycle(1.0, 1.0)
    p = GameProblem(dt=0.2, horizon=10, agents=[Agent(bike, (0, 0, 0, 0), COST), Agent(bike, (1.0, 0.5, 0, 0), COST)],
                    collision=Collision(2.0, "squared"))
    rep = verify.problem_feasibility(p)
    assert rep.status == "infeasible"
    assert "agents 0 and 1 at step 1" in rep.detail and "1.118 m" in rep.detail
    # Double integrator driving into each other: p_1 = (0.2, 0) and (0.8, 0), 0.6 m apart < 1 m, for any u.
    model = _double_integrator()
    cost = QuadraticCost(x_ref=(0, 0, 0, 0), Q_ref=(0, 0, 0, 0), R=(1.0, 1.0))
    q = GameProblem(dt=0.2, horizon=6, agents=[Agent(model, (0, 0, 1, 0), cost), Agent(model, (1, 0, -1, 0), cost)],
                    collision=Collision(1.0))
    rep = verify.problem_feasibility(q)
    assert rep.status == "infeasible" and "0.600 m apart" in rep.detail
    # ... and a fixed state beyond a state bound: px_1 = 0.2 > x_max 0.1.
    r = GameProblem(dt=0.2, horizon=6, agents=[Agent(model, (0, 0, 1, 0), cost, x_max=(0.1, np.inf, np.inf, np.inf))])
    rep = verify.problem_feasibility(r)
    assert rep.status == "infeasible" and "violates x_max 0.1" in rep.detail


def _head_on(cars=2, u_bounds=None):
    """Cars on y = 0 driving at each other at 2 m/s from 8 m apart (queues 4 m): with zero controls they meet."""
    agents = []
    for i in range(cars):
        east = i % 2 == 0
        s = 4.0 + 4.0 * (i // 2)
        lo, hi = u_bounds if u_bounds else (None, None)
        agents.append(Agent(KinematicBicycle(1.0, 1.0), (-s if east else s, 0.0, 2.0, 0.0 if east else np.pi), COST,
                            u_min=lo, u_max=hi))
    return GameProblem(dt=0.2, horizon=25, agents=agents, collision=Collision(2.0, "distance"))


@pytest.mark.parametrize("cars,u_bounds", [(2, None), (4, None), (2, ((-3.0, -0.5), (1.0, 0.5)))])
def test_separable_cars_are_found_feasible_with_a_point_verify_accepts(cars, u_bounds):
    p = _head_on(cars, u_bounds)
    T, nu = p.horizon, 2
    # The zero-control start collides (so the search had work to do), by bench/verify.py on the plain rollout.
    assert verify.max_collision_violation_m(p, p.rollout(np.zeros((cars, T, nu)))) > 1.0
    assert verify.fixed_state_infeasibility(p) == []
    rep = verify.problem_feasibility(p)
    assert rep.status == "feasible", rep.detail
    assert verify.dynamics_defect(p, rep.x, rep.u) <= 1e-9
    assert verify.max_collision_violation_m(p, rep.x) <= verify.FEASIBILITY_TOL_M
    assert verify.max_bound_violation(p, rep.x, rep.u) <= 0.0
    np.testing.assert_array_equal(rep.x, p.rollout(rep.u))


def test_a_search_that_finds_nothing_says_unknown_not_infeasible():
    # Double integrator, |a| <= 0.1 m/s^2, closing at 6 m/s from 3 m: p_1 is 3 - 6 dt = 1.8 m apart (fine, and fixed),
    # p_2 coasting 0.6 m apart, and u_0 moves each p_2 by at most dt^2 0.1 = 0.004 m: d_min 1 m is violated by
    # >= 0.39 m. Infeasible, but p_2 depends on u_0, so only the search runs, and it must not claim a feasible point.
    model = _double_integrator()
    cost = QuadraticCost(x_ref=(0, 0, 0, 0), Q_ref=(0, 0, 0, 0), R=(1.0, 1.0))
    agents = [Agent(model, (0, 0, 3, 0), cost, u_min=(-0.1, -0.1), u_max=(0.1, 0.1)),
              Agent(model, (3, 0, -3, 0), cost, u_min=(-0.1, -0.1), u_max=(0.1, 0.1))]
    p = GameProblem(dt=0.2, horizon=5, agents=agents, collision=Collision(1.0))
    rep = verify.problem_feasibility(p)
    assert verify.fixed_state_infeasibility(p) == []
    assert rep.status == "unknown" and rep.x is None
    assert rep.max_violation_m > 0.38


# ------------------------------------------------------------------------------------------------
# The CLI
@pytest.mark.parametrize("extra,flag", [
    (["--seeds", "5:2"], "--seeds"), (["--seeds", "3"], "--seeds"), (["--seeds", "a:b"], "--seeds"),
    (["--seeds=-1:2"], "--seeds"), (["--seeds", "0:2", "--instances", "2"], "--seeds"),
    (["--seed-start", "-3"], "--seed-start"), (["--instances", "0"], "--instances"),
    (["--max-iter", "0"], "--max-iter"), (["--max-iter", "-5"], "--max-iter"),
    (["--time-limit", "-1"], "--time-limit"), (["--time-limit", "nan"], "--time-limit"),
])
def test_bad_budget_and_seed_flags_exit_2_naming_the_flag(capsys, extra, flag):
    for base in (["bench", "merge", "--family", "authors", "--cars", "2", "--no-docs"],
                 ["bench", "merge", "--cars", "2", "--no-docs"]):
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and flag in err, err


def test_family_run_with_seeds_and_max_iter_reports_cpu_time_and_feasibility(tmp_path, capsys):
    out = tmp_path / "fam.json"
    # max_iter 1: no solve can finish, so both instances (seeds 3 and 4) fail and each gets a feasibility verdict.
    argv = ["bench", "merge", "--family", "authors", "--cars", "3", "--seeds", "3:5", "--max-iter", "1",
            "--time-limit", "0", "--workers", "1", "--no-docs", "--json", str(out)]
    assert main(argv) == 0
    md = capsys.readouterr().out
    assert "CPU ms median / p90 / max" in md and "infeasible / unknown" in md and "max_iter 1, time limit none" in md
    data = json.loads(out.read_text())
    (row,) = data["results"]
    for key in ("family", "solver", "cars", "instances", "solved", "second_order_confirmed", "converged_but_rejected",
                "statuses", "median_ms", "p90_ms", "max_ms", "median_iterations", "p90_iterations", "max_iterations",
                "failures"):  # the keys before this change stay
        assert key in row
    # The rescues after a failed schedule have budgets of their own (Settings::max_iter), so a solve may count more.
    assert row["instances"] == 2 and row["solved"] == 0 and row["max_iterations"] >= 1
    assert row["statuses"] == {"max_iterations": 2}
    assert 0 < row["median_cpu_ms"] <= row["p90_cpu_ms"] <= row["max_cpu_ms"]
    assert row["infeasible"] + row["failed_feasible"] + row["feasibility_unknown"] == 2
    assert row["success_rate"] == 0.0 and row["solvable"] == 2 - row["infeasible"]
    assert [f["seed"] for f in data["failed_instances"]] == [3, 4]
    # The authors' merge keeps every car in a lane 2.2 m from the other (d_min 2): feasible, and found so.
    assert {f["feasibility"] for f in data["failed_instances"]} == {"feasible"}
    assert data["budget"]["max_iter"] == 1 and data["budget"]["time_limit_s"] == 0 and data["budget"]["seeds"] == [3, 5]


def test_seed_start_and_instances_pick_the_same_seeds_as_seeds(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    base = ["bench", "merge", "--family", "merge-dense", "--cars", "2", "--max-iter", "1", "--time-limit", "0",
            "--workers", "1", "--no-docs"]
    assert main([*base, "--seed-start", "7", "--instances", "2", "--json", str(a)]) == 0
    assert main([*base, "--seeds", "7:9", "--json", str(b)]) == 0
    seeds = lambda p: [f["seed"] for f in json.loads(p.read_text())["failed_instances"]]  # noqa: E731
    assert seeds(a) == seeds(b) == [7, 8]
