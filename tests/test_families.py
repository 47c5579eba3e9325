"""The generated game families (bench/families.py): reproducible from (family, cars, seed), documented geometry,
feasible starts, and the authors' family equal to bench/merging.py's instances."""
import dataclasses

import numpy as np
import pytest

from bench.families import FAMILIES, bound_steering, family_problem
from bench.merging import merging_problem


def _x0(problem):
    return np.array([a.x0 for a in problem.agents], dtype=float)


def test_authors_family_is_the_merging_benchmark():
    for cars, seed in ((2, 0), (5, 3), (8, 11)):
        a, b = family_problem("authors", cars, seed), merging_problem(cars, seed)
        np.testing.assert_array_equal(_x0(a), _x0(b))
        assert (a.dt, a.horizon, a.collision.min_distance, a.collision.form) == (b.dt, b.horizon, 2.0, "squared")


@pytest.mark.parametrize("name", list(FAMILIES))
def test_family_instances_are_seeded_and_start_feasible(name):
    for cars in range(2, 9):
        p = family_problem(name, cars, 4)
        assert p.num_agents == cars
        np.testing.assert_array_equal(_x0(p), _x0(family_problem(name, cars, 4)))
        assert not np.array_equal(_x0(p), _x0(family_problem(name, cars, 5)))
        xy = _x0(p)[:, :2]
        gaps = np.linalg.norm(xy[:, None] - xy[None], axis=-1)[np.triu_indices(cars, 1)]
        assert gaps.min() >= p.collision.min_distance + 0.1 - 1e-12


def test_crossing_and_head_on_geometry():
    cross = _x0(family_problem("crossing", 4, 0))
    np.testing.assert_array_equal(cross[[0, 2], 1], 0.0)           # east-bound on y = 0
    np.testing.assert_array_equal(cross[[1, 3], 0], 0.0)           # north-bound on x = 0
    np.testing.assert_allclose(cross[[1, 3], 3], np.pi / 2)
    assert np.all(cross[[0, 2], 0] < -4) and np.all(cross[[1, 3], 1] < -4)  # all before the intersection
    head = _x0(family_problem("head-on", 4, 0))
    assert np.all(head[[0, 2], 0] < -9) and np.all(head[[1, 3], 0] > 9)
    np.testing.assert_allclose(head[[1, 3], 3], np.pi)
    assert np.all(np.abs(head[:, 1]) <= 0.3)


def test_merge_long_bounds_steering_only():
    """merge-long's cars have |delta| <= 0.6 rad and free acceleration; the other merges have no control bounds, and
    every zero-control start lies strictly inside the bounds (the barrier's first iterate is interior)."""
    for cars, seed in ((2, 0), (8, 3)):
        for a in family_problem("merge-long", cars, seed).agents:
            assert tuple(a.u_min) == (-np.inf, -0.6) and tuple(a.u_max) == (np.inf, 0.6)
            assert np.all(np.asarray(a.u_min) < 0) and np.all(np.asarray(a.u_max) > 0)  # zero controls interior
    for name in ("authors", "merge-dense", "merge-narrow"):
        assert all(a.u_min is None and a.u_max is None for a in family_problem(name, 4, 0).agents)


def test_steering_bound_variant_bounds_every_car_and_keeps_tighter_bounds():
    """family_problem(..., steering_bound=b): |delta| <= b for every car, acceleration free, a family's tighter bound
    kept; and the ring's lane swap of seed 92, which without a bound steers at the domain box's edge (1.555 rad) at
    its first step, converges inside the bound with the common test passed (bench/verify.py)."""
    from bench.verify import verify_equilibrium
    from solver_cpp import solve

    for name in ("ring", "four-way", "merge-close"):
        for a in family_problem(name, 3, 92, steering_bound=0.6).agents:
            assert tuple(a.u_min) == (-np.inf, -0.6) and tuple(a.u_max) == (np.inf, 0.6)
    for a in family_problem("merge-long", 3, 0, steering_bound=0.9).agents:
        assert tuple(a.u_min) == (-np.inf, -0.6) and tuple(a.u_max) == (np.inf, 0.6)
    problem = family_problem("ring", 3, 92, steering_bound=0.6)
    r = solve(problem, time_limit=0)
    assert r.status == "converged"
    assert np.max(np.abs(np.asarray(r.u)[:, :, 1])) <= 0.6 + 1e-9
    assert verify_equilibrium(problem, r.x, r.u, best_response=False).passed
    with pytest.raises(ValueError, match="must be > 0"):
        family_problem("ring", 3, 0, steering_bound=0.0)
    p = family_problem("authors", 2, 0)
    p.agents[0] = dataclasses.replace(p.agents[0], dynamics=object())
    with pytest.raises(ValueError, match="agent 0: a steering bound needs a bicycle model"):
        bound_steering(p, 0.5)


def test_bench_merge_steering_bound_is_for_families_only():
    from app.cli import main

    assert main(["bench", "merge", "--cars", "2", "--instances", "1", "--steering-bound", "0.5", "--no-docs"]) == 2
    assert main(["bench", "merge", "--family", "ring", "--cars", "2", "--seeds", "0:1", "--steering-bound", "0",
                 "--no-docs"]) == 2


def test_unknown_family_is_named():
    with pytest.raises(ValueError, match="unknown family 'nope'"):
        family_problem("nope", 3, 0)


def test_bench_rejects_an_unknown_family():
    from app.cli import UserError, build_parser

    args = build_parser().parse_args(["bench", "merge", "--family", "merge-dense,nope", "--no-docs"])
    with pytest.raises(UserError, match="unknown family 'nope'"):
        args.func(args)


@pytest.mark.parametrize("cases, message", [("nope:2:0", "unknown family 'nope'"), ("head-on:2", "is not FAMILY:CARS:SEED"),
                                            ("head-on:1:0", "at least 2 cars")])
def test_bench_saddles_rejects_bad_cases(cases, message):
    from app.cli import UserError, build_parser

    args = build_parser().parse_args(["bench", "saddles", "--cases", cases, "--no-docs"])
    with pytest.raises(UserError, match=message):
        args.func(args)


def test_best_response_guess_is_each_players_best_response_to_the_plans_it_saw():
    """The last player of the last sweep solved against the others' final plans: its controls are a KKT point of its
    own problem with them fixed (bench/verify.py's stationarity on that one-player problem, the other car as a moving
    disc), collision free."""
    from bench.verify import max_collision_violation_m, stationarity_residual
    from solver_cpp import GameProblem, Obstacle
    from solver_cpp.best_response import best_response_guess

    # Seed 1 with one restart per sub-solve: the sub-solves converge within best_response.max_iter (without the
    # restart agent 1's first attempt stalls and the guess keeps its controls as they are; at seed 0 with
    # domain_fraction 0.99 it does not converge either way, against agent 0's plan steering at 1.3 rad).
    problem = family_problem("head-on", 2, 1)
    guess = best_response_guess(problem, rounds=1, tol=1e-8, best_response=dict(margin=0.0, restarts=1))
    x = problem.rollout(guess.u)
    assert max_collision_violation_m(problem, x) <= 1e-6
    alone = GameProblem(dt=problem.dt, horizon=problem.horizon, agents=[problem.agents[1]],
                        obstacles=[Obstacle(x[0, :, :2], problem.collision.min_distance)])
    assert stationarity_residual(alone, x[1:], guess.u[1:], relative=True)[0] < 1e-5
    with pytest.raises(ValueError, match="rounds"):
        best_response_guess(problem, rounds=0)


def test_best_response_guess_is_single_agent_solves_in_gauss_seidel_order():
    """The C++ sweeps (the best-response restart's) against single-agent games built here with the Python API: agent
    i alone, the problem's obstacles plus the others' current rolled-out positions as moving discs at (1 + margin)
    d_min, solved from its current controls with the sub-solve settings (best_response.max_iter iterations, no
    restart, no best response or passing-order search of its own, no relative stationarity test), agents in order,
    each new plan rolled out before the next agent solves. Three cars merging (merge-dense seed 0), two rounds: every agent's sub-problem
    has two moving obstacles and the second round starts from the first one's plans. Every solve here converges in
    its first attempt; a game solve's line search backtracks to just before a crossing where a sub-solve's halves
    (docs/solver.md), so the two agree to the solves' accuracy, not bit for bit."""
    from solver_cpp import GameProblem, Obstacle, WarmStart, solve
    from solver_cpp.best_response import best_response_guess

    problem = family_problem("merge-dense", 3, 0)
    N, T, nu = problem.num_agents, problem.horizon, problem.agents[0].dynamics.nu
    col = problem.collision
    margin = 0.15  # the others are kept at (1 + margin) d_min
    u = np.zeros((N, T, nu))
    x = problem.rollout(u)
    for _ in range(2):
        for i in range(N):
            others = [Obstacle(x[j][:, [col.pos_x, col.pos_y]], (1 + margin) * col.min_distance)
                      for j in range(N) if j != i]
            alone = GameProblem(dt=problem.dt, horizon=T, agents=[problem.agents[i]], collision=col,
                                obstacles=list(problem.obstacles) + others)
            r = solve(alone, warm_start=WarmStart(u=u[i:i + 1]), max_iter=100, restart=dict(count=0),
                      best_response=dict(rounds=0), order=dict(candidates=0), stationarity_tol=0)
            assert r.status == "converged" and r.attempts == 1
            u[i] = r.u[0]
            x = problem.rollout(u)
    guess = best_response_guess(problem, rounds=2, best_response=dict(margin=margin))
    assert np.abs(u).max() > 0.1  # the sub-solves moved the cars
    np.testing.assert_allclose(guess.u, u, atol=1e-2, rtol=0)


def test_best_response_sub_solvers_follow_updates():
    """The single-agent sub-solvers copy the problem at first use: after Solver.update (new initial states and
    collision distance) the sweeps must be those of a fresh set-up on the new problem, bit for bit."""
    from dataclasses import replace

    from solver_cpp import Solver

    problem = family_problem("head-on", 3, 0)
    moved = replace(problem, agents=[replace(a, x0=np.asarray(a.x0, dtype=float) + [0.0, 0.3, 0.0, 0.0])
                                     for a in problem.agents],
                    collision=replace(problem.collision, min_distance=1.2 * problem.collision.min_distance))
    solver = Solver(problem)
    before = solver.best_response(1)
    solver.update(moved)
    after = solver.best_response(1)
    fresh = Solver(moved).best_response(1)
    assert np.abs(after.u - before.u).max() > 1e-3
    np.testing.assert_array_equal(after.u, fresh.u)


def test_best_response_restart_solves_an_instance_the_schedule_alone_does_not():
    """merge-dense 8 cars seed 28 (with every other default, domain_fraction included): attempt 0 fails; without the
    best-response restart neither the rest of the schedule nor the domain rescue after it (whose bounded game is solved
    by the same settings) converges within its 300 iterations; with it the solve converges (by the attempt from the
    best-response guess, or by the domain rescue's bounded game, which has its own: which one is the path of a
    nonconvex solve whose sub-solves may themselves meet the domain edge). The bounded start, the last stage, may
    still rescue the solve without it. Both results are judged by the benchmark's
    common test (dynamics, controls in the model's domain, collisions, per-player stationarity, bench/verify.py) and
    the second-order test, not by the solver's status."""
    from bench import merge_bench
    from solver_cpp import solve

    problem = family_problem("merge-dense", 8, 28)
    records = {}
    for rounds in (0, 1):
        r = solve(problem, time_limit=0, max_iter=300, best_response=dict(rounds=rounds), order=dict(candidates=0))
        records[rounds] = (r, merge_bench.record("rd3g", problem, r, 0.0, 8, 28, "merge-dense"))
    old, new = records[0], records[1]
    # Without it nothing before the bounded start (the last stage, after every other failed) converges.
    assert (not old[1].success or old[0].bounded_start_iterations > 0) and old[0].best_response_attempts == 0
    assert new[1].success and new[1].second_order_ok, new[1].failure
    assert new[0].best_response_attempts == 1 and new[0].best_response_iterations > 0
    assert new[0].bounded_start_iterations == 0  # converged before the last stage


def test_best_response_guess_keeps_every_pair_beyond_the_margin():
    """With every sub-solve converged, each agent's last plan avoided every other agent's plan as it then was, and a
    later agent's plan avoided the earlier one's final plan: after a sweep every pair is at least (1 + margin) d_min
    apart at every step k >= 1 (pairwise distances of the rolled-out guess, numpy). The guess therefore starts
    strictly inside the game's collision constraints."""
    from solver_cpp.best_response import best_response_guess

    # Instances whose sub-solves all converge, given one restart each (the default of none leaves some unconverged).
    for name, cars, seed in (("crossing", 3, 1), ("head-on", 3, 1)):
        problem = family_problem(name, cars, seed)
        col = problem.collision
        for margin in (0.0, 0.1, 0.25):
            guess = best_response_guess(problem, rounds=1, best_response=dict(margin=margin, restarts=1))
            xy = problem.rollout(guess.u)[:, 1:, [col.pos_x, col.pos_y]]
            gaps = np.linalg.norm(xy[:, None] - xy[None], axis=-1)[np.triu_indices(cars, 1)]
            assert gaps.min() >= (1 + margin) * col.min_distance - 1e-4, (name, margin)  # sub-solve tolerance (m)
            if margin > 0:  # the margin binds: some pair sits on it
                assert gaps.min() <= (1 + margin) * col.min_distance + 1e-2, (name, margin)


def test_best_response_margin_rescues_an_attempt_stuck_at_a_contact():
    """merge-narrow 6 cars seed 22: without the margin the guess has a pair at d_min (3e-6 m beyond it) and no attempt
    of the schedule converges (1000 iterations; the domain rescue and the bounded start follow, and the solve ends
    `domain_edge`); with the default margin the attempt from the guess converges to a point that the benchmark's
    common test and the second-order test accept (bench/verify.py, not the solver's status)."""
    from bench import merge_bench
    from solver_cpp import solve

    problem = family_problem("merge-narrow", 6, 22)
    stuck = solve(problem, time_limit=0, max_iter=1000, best_response=dict(margin=0.0), order=dict(candidates=0))
    freed = solve(problem, time_limit=0, max_iter=1000)
    # No attempt of the schedule converges: the solve fails, or the domain rescue or the bounded start ran (they run
    # only after a schedule that found no equilibrium, and can solve it through their bounded games).
    assert stuck.status != "converged" or stuck.domain_iterations > 0 or stuck.bounded_start_iterations > 0
    assert freed.status == "converged" and freed.attempts == 2
    record = merge_bench.record("rd3g", problem, freed, 0.0, 6, 22, "merge-narrow")
    assert record.success and record.second_order_ok, record.failure


def test_best_response_attempt_holds_the_guess_contacts():
    """merge-long 5 cars seed 4 (steering bounded at 0.6 rad): the best-response sub-solves end with steering angles
    a hair inside the bound (their barrier at its floor), within barrier.margin (1e-4) of it. The attempt from the
    guess holds those bounds as equalities in its first partition; left out of it (neither equality nor barrier),
    they were invisible to the first Newton step, which crossed them at every step length, and the attempt ended at
    its first iteration. With attempt 0, the best-response attempt and restart 1 (no passing-order search), the
    best-response attempt is now the last: the benchmark's common test and the second-order test accept its result
    (bench/verify.py, not the solver's status)."""
    from bench import merge_bench
    from solver_cpp import solve
    from solver_cpp.best_response import best_response_guess

    problem = family_problem("merge-long", 5, 4)
    guess = np.asarray(best_response_guess(problem, rounds=1).u)
    slack = 0.6 - np.abs(guess[..., 1])
    assert slack.min() > 0 and np.count_nonzero(slack < 1e-4) > 0  # the premise: bounds inside the margin
    r = solve(problem, time_limit=0, restart=dict(count=1), order=dict(candidates=0))
    assert r.status == "converged" and r.best_response_attempts == 1 and r.attempts == 2
    record = merge_bench.record("rd3g", problem, r, 0.0, 5, 4, "merge-long")
    assert record.success and record.second_order_ok, record.failure


# Closest start pair minus d_min (m) of the stream families, worked by hand from their docstrings: crossing and
# head-on as docs/merging.md gives; four-way: two cars of one queue, 5.2 m apart less the 1 m jitter, against 1.8;
# ring: neighbours in the two lanes, 2.2 - 1 m apart along s and 2.1 m across, against 1.8 (track coordinates).
STREAM_START_FLOOR = {"crossing": 1.9, "head-on": 1.9, "four-way": 5.2 - 1.0 - 1.8,
                      "ring": float(np.hypot(2.2 - 1.0, 2.1)) - 1.8}


@pytest.mark.parametrize("name", list(FAMILIES))
def test_no_instance_is_degenerate_by_construction(name):
    """The closest start pair is no closer than the family's geometry allows (the merges: two cars side by side in
    the two lanes, at the lane spacing; the stream families: STREAM_START_FLOOR), and no state at k >= 1 is out
    of every control's reach (every car starts moving, so its steering moves its position at k = 1): the
    benchmark's exact infeasibility check has nothing to prove here."""
    from bench.verify import control_independent_states

    spec = FAMILIES[name]
    lane = getattr(spec, "main_lane_y", None)
    floor = (lane - spec.merge_lane_y - spec.min_distance) if lane is not None else STREAM_START_FLOOR[name]
    for cars in range(2, 9):
        for seed in range(200):
            xy = _x0(family_problem(name, cars, seed))[:, :2]
            gaps = np.linalg.norm(xy[:, None] - xy[None], axis=-1)[np.triu_indices(cars, 1)]
            assert gaps.min() - spec.min_distance >= floor - 1e-9, (cars, seed)
        fixed = control_independent_states(family_problem(name, cars, 0))
        assert fixed[:, 0].all() and not fixed[:, 1:].any()


class _FakeRuns:
    """run_solver stand-in: one real solve, then the same result with the CPU time of each run scripted (ms)."""

    def __init__(self, cpu_ms, iterations=None):
        import solver_cpp

        self.cpu_ms, self.iterations, self.calls = list(cpu_ms), iterations, 0
        self.result = solver_cpp.solve(family_problem("authors", 2, 0), time_limit=0, max_iter=1000)
        self.clock = 0.0

    def process_time(self):
        return self.clock

    def run_solver(self, *args):
        from dataclasses import replace

        self.clock += self.cpu_ms[self.calls] / 1e3
        r = self.result if self.iterations is None else replace(self.result, iterations=self.iterations[self.calls])
        self.calls += 1
        return r, 0.0


@pytest.mark.parametrize("cpu_ms, time_limit, calls, kept", [
    ((5.0, 3.0, 4.0), 0.0, 3, 3.0),      # short, deterministic: the fastest of 3 runs
    ((250.0, 1.0, 1.0), 0.0, 1, 250.0),  # over REPEAT_BELOW_MS: run once
    ((5.0, 3.0, 4.0), 2.0, 3, 3.0),      # far from its time limit (under a tenth of it): deterministic too
    ((5.0, 3.0, 4.0), 0.03, 1, 5.0),     # over a tenth of its time limit, which could bind: run once
])
def test_family_bench_keeps_the_fastest_of_repeated_short_solves(monkeypatch, cpu_ms, time_limit, calls, kept):
    from bench import merge_bench

    fake = _FakeRuns(cpu_ms)
    monkeypatch.setattr(merge_bench, "run_solver", fake.run_solver)
    monkeypatch.setattr("time.process_time", fake.process_time)
    rec = merge_bench.one_run(merge_bench.Job("rd3g", 2, 0, time_limit, "authors", repeats=3))
    assert fake.calls == calls and rec.cpu_ms == pytest.approx(kept)
    assert rec.success and rec.iterations == fake.result.iterations


def test_family_bench_names_a_solve_whose_repeats_differ(monkeypatch):
    from bench import merge_bench

    fake = _FakeRuns((1.0, 1.0), iterations=(5, 6))
    monkeypatch.setattr(merge_bench, "run_solver", fake.run_solver)
    monkeypatch.setattr("time.process_time", fake.process_time)
    with pytest.raises(RuntimeError, match="authors 2 cars seed 0 is not deterministic: run 2 ended converged after 6"):
        merge_bench.one_run(merge_bench.Job("rd3g", 2, 0, 0.0, "authors", repeats=2))


def test_bench_merge_rejects_repeat_below_one():
    from app.cli import main

    assert main(["bench", "merge", "--family", "authors", "--cars", "2", "--repeat", "0", "--no-docs"]) == 2


def test_family_comparison_puts_solvers_side_by_side():
    from bench.merge_bench import family_comparison

    def row(solver, cars, solved, med, p90):
        return {"family": "crossing", "solver": solver, "cars": cars, "solved": solved, "instances": 8,
                "median_cpu_ms": med, "p90_cpu_ms": p90}

    summary = [row("rd3g", 2, 8, 16.84, 23.0), row("algames", 2, 1, 99.2, 110.46), row("rd3g", 3, 7, 25.0, 37.0)]
    lines = family_comparison(summary)
    assert lines[3] == "| family | cars | rd3g | algames |"
    assert lines[5] == "| crossing | 2 | 8/8; 16.8 / 23.0 | 1/8; 99.2 / 110.5 |"
    assert lines[6] == "| crossing | 3 | 7/8; 25.0 / 37.0 | — |"
    assert family_comparison([row("rd3g", 2, 8, 1.0, 2.0)]) == []
