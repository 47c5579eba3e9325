"""Passing-order search (setting group `order`, solver_cpp/src/passing_order.cpp), before Newton and as the rescue.

A symmetric two-car crossing has two local equilibria, one per passing order (east-bound first or north-bound
first). The search before Newton must find both, report the order of the one it returns, and each must pass the
independent checks: bench/verify.py's per-player stationarity and SLSQP best responses, and the second-order test.
The order reported is checked against the geometry: the car that crosses the other's lane first. As the rescue (the
default) the search runs only when the restart schedule ends without an equilibrium: a solve the schedule finishes
is the same with and without it, and a failing one becomes an equilibrium the independent checks confirm."""
from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from bench.verify import verify_equilibrium
from solver_cpp import Agent, Collision, GameProblem, KinematicBicycle, QuadraticCost, Solver, solve
from solver_cpp.problem_file import problem_to_dict, result_to_dict

TOL = 1e-5  # best-response checks need an accurate solve (bench/verify.py)


def crossing(offset: float = 0.2) -> GameProblem:
    """Car 0 east along y = 0 from x = -5, car 1 north along x = 0 from y = -5 - offset, both at 2 m/s: without
    avoidance they meet at the origin, and either may go first."""
    bike = KinematicBicycle(lf=1.0, lr=1.0)
    east = Agent(bike, (-5.0, 0.0, 2.0, 0.0),
                 QuadraticCost(x_ref=(0.0, 0.0, 2.0, 0.0), Q_ref=(0.0, 0.5, 0.05, 1.0), R=(0.3, 0.3)))
    north = Agent(bike, (0.0, -5.0 - offset, 2.0, np.pi / 2),
                  QuadraticCost(x_ref=(0.0, 0.0, 2.0, np.pi / 2), Q_ref=(0.5, 0.0, 0.05, 1.0), R=(0.3, 0.3)))
    return GameProblem(dt=0.2, horizon=25, agents=[east, north],
                       collision=Collision(min_distance=1.6, form="distance"))


def first_across(x: np.ndarray) -> int:
    """The car that crosses the other's lane first: car 0 crosses x = 0, car 1 crosses y = 0 (first step past)."""
    step0 = int(np.argmax(x[0, :, 0] > 0.0))
    step1 = int(np.argmax(x[1, :, 1] > 0.0))
    return 0 if step0 < step1 else 1


@pytest.fixture(scope="module")
def searched():
    return solve(crossing(), tol=TOL, time_limit=0, order=dict(candidates=2, polish=2, before_newton=True))


def test_the_search_finds_both_orders_and_reports_the_returned_one(searched):
    r = searched
    assert r.status == "converged"
    assert [(p["i"], p["j"]) for p in r.passing_order] == [(0, 1)]  # the rolled-out guess collides
    assert len(r.orders) == 2 and sorted(c["requested"] for c in r.orders) == [[-1], [1]]
    solved = [c for c in r.orders if c["equilibrium"]]
    assert len(solved) == 2 and {tuple(c["found"]) for c in solved} == {(-1,), (1,)}
    returned = [c for c in r.orders if c["returned"]]
    assert len(returned) == 1 and returned[0]["found"] == [r.passing_order[0]["winding"]]
    assert r.other_orders == [[-r.passing_order[0]["winding"]]]
    assert r.order_attempts == 2 and r.attempts == 2
    # The order named in the result is the geometry's: the car that crosses the other's lane first.
    assert r.passing_order[0]["first"] == first_across(r.x)
    assert 1.6 - 1e-6 <= r.passing_order[0]["gap"] < 1.7  # the pair touches the collision distance
    doc = result_to_dict(r)
    assert doc["passing_order"][0]["first"] == r.passing_order[0]["first"]
    assert len(doc["orders"]) == 2 and doc["other_orders"] == r.other_orders


def test_each_order_is_a_local_equilibrium_by_the_independent_checks(searched):
    problem = crossing()
    firsts = set()
    for c in searched.orders:
        assert c["equilibrium"] and c["status"] == "converged"  # the solver's second-order test passed
        x = problem.rollout(c["u"])
        report = verify_equilibrium(problem, x, c["u"], best_response_starts=2)  # stationarity, SLSQP best responses
        assert report.passed, report.failures
        firsts.add(first_across(x))
    assert firsts == {0, 1}  # the two equilibria differ in who goes first
    returned = next(c for c in searched.orders if c["returned"])
    assert np.abs(returned["u"] - searched.u).max() < 1e-12


def test_a_solve_the_schedule_finishes_does_not_search_and_the_order_is_still_reported():
    r = solve(crossing(), tol=TOL, time_limit=0)
    assert r.status == "converged" and r.orders == [] and r.order_attempts == 0
    off = solve(crossing(), tol=TOL, time_limit=0, order=dict(candidates=0))
    assert off.iterations == r.iterations and np.array_equal(off.u, r.u)
    assert len(r.passing_order) == 1 and r.passing_order[0]["first"] == first_across(r.x)


def numpy_passing_order(problem: GameProblem, x: np.ndarray) -> list[tuple[int, int, int, float]]:
    """Independent of the solver: the pairs whose zero-control rollout comes closer than d_min at some step 1..T, each
    with the sign of the angle p_j - p_i turns through over x (summed step angles) and its smallest distance in x."""
    guess = problem.rollout(np.zeros((len(problem.agents), problem.horizon, 2)))
    d_min = problem.collision.min_distance
    out = []
    for i in range(len(problem.agents)):
        for j in range(i + 1, len(problem.agents)):
            if np.linalg.norm(guess[j, 1:, :2] - guess[i, 1:, :2], axis=1).min() >= d_min:
                continue
            d = x[j, :, :2] - x[i, :, :2]
            turn = np.arctan2(d[:-1, 0] * d[1:, 1] - d[:-1, 1] * d[1:, 0], (d[:-1] * d[1:]).sum(axis=1)).sum()
            out.append((i, j, 1 if turn >= 0 else -1, float(np.linalg.norm(d[1:], axis=1).min())))
    return out


def test_a_solve_without_search_skips_the_scan_and_reports_the_order_of_its_own_problem_when_asked():
    solver = Solver(crossing(), tol=TOL, time_limit=0)
    r = solver.solve()
    assert r.status == "converged" and r.orders == []
    assert r.passing_order_found == []  # the solve neither rolled out nor scanned the initial guess
    solver.update(crossing(offset=3.0))  # car 1 three metres further back: its zero-control rollout never conflicts
    later = solver.solve()
    expected = numpy_passing_order(crossing(), r.x)
    assert len(expected) == 1  # the crossing's own zero-control rollout collides
    got = [(p["i"], p["j"], p["winding"], p["gap"]) for p in r.passing_order]  # computed now, for its own problem
    assert got[0][:3] == expected[0][:3] and abs(got[0][3] - expected[0][3]) < 1e-12
    assert later.passing_order == [] == numpy_passing_order(crossing(offset=3.0), later.x)


@pytest.mark.parametrize("group, message", [
    (dict(candidates=-1), "solver.order.candidates must be >= 0"),
    (dict(candidates=4, polish=0), "solver.order.polish must be >= 1"),
    (dict(candidates=4, polish_iter=0), "solver.order.polish_iter must be >= 1"),
    (dict(candidates=4, max_iter=0), "solver.order.max_iter must be >= 1"),
    (dict(candidates=4, offset=-0.5), "solver.order.offset must be finite and >= 0"),
    (dict(offset=float("nan")), "solver.order.offset must be finite"),
    (dict(samples=3), "solver.order.samples is not a solver setting"),
])
def test_settings_validation_names_the_field(group, message):
    with pytest.raises(ValueError, match=message.replace(".", r"\.")):
        solve(crossing(), order=group)


def test_solve_command_writes_the_orders_and_rejects_a_bad_setting(tmp_path, capsys):
    good, out = tmp_path / "p.json", tmp_path / "r.json"
    good.write_text(json.dumps(problem_to_dict(crossing(), solver={"tol": TOL, "order": {"candidates": 2, "before_newton": True}})))
    assert main(["solve", str(good), "--out", str(out), "--time-limit", "0"]) == 0
    doc = json.loads(out.read_text())
    assert len(doc["passing_order"]) == 1 and doc["passing_order"][0]["first"] == first_across(np.asarray(doc["x"]))
    assert sum(c["equilibrium"] for c in doc["orders"]) == 2 and len(doc["other_orders"]) == 1
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(problem_to_dict(crossing(), solver={"order": {"polish_iter": 0}})))
    assert main(["solve", str(bad)]) == 2
    assert f"{bad}: solver.order.polish_iter must be >= 1" in capsys.readouterr().err


# A head-on pair (bench.families, tuned family, seed 24) under a short restart schedule that ends without an
# equilibrium (line_search_failed): one restart, no best-response attempt, no escape from a saddle. The search solves
# both orders and returns one.
SHORT_SCHEDULE = dict(restart=dict(count=1), best_response=dict(rounds=0), second_order=dict(escapes=0))


def test_the_rescue_turns_a_failed_schedule_into_a_verified_equilibrium():
    from bench.families import family_problem

    problem = family_problem("head-on", 2, 24)
    failed = solve(problem, tol=TOL, time_limit=0, order=dict(candidates=0), **SHORT_SCHEDULE)
    assert failed.status != "converged" and failed.order_attempts == 0
    rescued = solve(problem, tol=TOL, time_limit=0, **SHORT_SCHEDULE)
    assert rescued.status == "converged" and rescued.order_attempts >= 1
    # The schedule (attempt 0 and restart 1: no best-response attempt, no escape) ran in full before it. (Without the
    # search the failed schedule is followed by the domain rescue, whose attempts `failed.attempts` also counts.)
    assert rescued.attempts == 2 + rescued.order_attempts
    assert sum(c["returned"] for c in rescued.orders) == 1
    assert all(so >= 0 for so in rescued.second_order)  # the solver's second-order test
    report = verify_equilibrium(problem, np.asarray(rescued.x), np.asarray(rescued.u), best_response_starts=2)
    assert report.passed, report.failures  # stationarity and each player's SLSQP best response, independent


def test_the_search_before_the_seeded_restarts_reaches_a_merge_the_restarts_miss():
    """Table I's 7 cars seed 70 fails through one pair: main-lane car 2 (x 11.4 m, 2.36 m/s) and merging car 4
    (1.1 m behind it, 2.59 m/s). Alone, the two are the same game: most of the barrier variants, the best-response
    attempt and the seeded restarts stall where car 2 stays ahead (not an equilibrium) or converge side by side (a
    saddle), and the passing-order search's guess with car 4 first reaches the equilibrium. It runs after restart
    attempt 3, so the equilibrium comes within max_iter (run only after the 19 restarts, the search needed its own
    budget on top: over 1000 iterations in all)."""
    import dataclasses

    from bench.merging import merging_problem

    game = merging_problem(7, 70)
    problem = dataclasses.replace(game, agents=[game.agents[2], game.agents[4]])
    r = solve(problem, tol=TOL, time_limit=0, max_iter=1000)
    assert r.status == "converged"
    assert r.iterations <= 1000  # the solve's own budget
    assert all(so > 0 for so in r.second_order)  # the solver's second-order test
    report = verify_equilibrium(problem, np.asarray(r.x), np.asarray(r.u), best_response_starts=2)
    assert report.passed, report.failures  # stationarity and each player's SLSQP best response, independent
