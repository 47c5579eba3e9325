"""Planning a fleet (issue 29): a run of fallback steps tracks the last plan the car used, an obstacle
too close to a player joins the game, the planners of one control step run concurrently with the same
plans as in turn, and the fleet batch's default."""
import dataclasses
import threading

import numpy as np
import pytest

from planning import MPCOpponent
from planning.frenet import EPSI, EY, S
from race import planning as race_planning
from race.planning import PlanJob, RacePlanners, make_planner
from race.roster import parse_cars
from race.setup import RaceSetupError, RaceSpec, start_states


# ---------------------------------------------------------------- fallback runs
def test_a_run_of_fallbacks_steers_back_to_the_last_plan_used():
    """On the oval's straight (s 4.2-6 m, curvature 0) the car plans once along the centre line, then
    every step falls back for 1 s from a state 3 cm left of it heading 0.15 rad further left. Tracking
    that plan brings the car back to the centre line. Re-anchoring the reference at the car each step
    (the earlier fallback) left the car heading off the line: it drifted on to 0.13 m in that second."""
    setup = RaceSpec(line="centre").load()  # the constant reference: the centre line
    planner = make_planner(MPCOpponent, setup, 1.8)
    assert np.all(setup.track.curvature(np.linspace(4.2, 6.0, 50)) == 0)
    nobody = np.zeros((0, 4))
    first = planner.plan(np.array([4.2, 0.0, 1.2, 0.0]), nobody)
    assert first.used != "fallback" and np.max(np.abs(first.x[0, :, EY])) < 0.01  # the plan: along the centre
    step = planner.tm.rollout_model(setup.control_period_s)
    x = np.array([4.2 + 1.2 * setup.control_period_s, 0.03, 1.2, 0.15])
    ey = []
    for _ in range(30):  # 1 s of fallback steps in closed loop (planning model, one control period each)
        plan = planner.fallback_plan(x, nobody, "test: no plan this step")
        x = np.asarray(step.rollout(x, plan.u[:1]))[1]
        ey.append(float(x[EY]))
    assert x[S] < 6.0                                   # still on the straight
    assert max(ey) < 0.06 and abs(ey[-1]) < 0.02 and abs(float(x[EPSI])) < 0.05


def test_a_run_of_fallbacks_past_the_plans_horizon_returns_to_the_track():
    """The last plan used ends turning left (constant 0.03 rad steering from the centre line at
    1 m/s: 0.16 m left and 0.33 rad off the track's heading after the 1 s horizon, inside the 0.223 m
    track-limit bound). Then 3 s of fallback steps: the car follows that plan for its horizon, then the
    track's own reference (centre line, heading along the track, at most the top speed). Holding the
    plan's last state instead kept the car heading 0.33 rad off the track, across the track limit within the
    next half second."""
    setup = RaceSpec(line="centre").load()  # the constant reference: the centre line
    planner = make_planner(MPCOpponent, setup, 1.8)
    c = planner.config
    nobody = np.zeros((0, 4))
    x = np.array([4.2, 0.0, 1.0, 0.0])
    planner.plan(x, nobody)
    turning = np.tile([0.0, 0.03], (c.horizon, 1))  # zero acceleration, constant left steering
    planner._reference = np.asarray(planner.tm.rollout_model(c.plan_dt_s).rollout(x, turning))
    planner._reference_age_s = 0.0
    end = planner._reference[-1]
    assert 0.05 < end[EY] < planner.tm.ey_bound([end[S]]) and end[EPSI] > 0.3  # a plan that ends turning
    step = planner.tm.rollout_model(setup.control_period_s)
    states = []
    for _ in range(90):  # 3 s of fallback steps in closed loop (planning model, one control period each)
        plan = planner.fallback_plan(x, nobody, "test: no plan this step")
        x = np.asarray(step.rollout(x, plan.u[:1]))[1]
        states.append(x)
    states = np.array(states)
    assert all(abs(x_k[EY]) < planner.tm.ey_bound([x_k[S]]) for x_k in states)
    assert abs(x[EY] - c.raceline_ey_m) < 0.05 and abs(x[EPSI]) < 0.1
    assert np.all(states[:, 2] <= c.top_speed_mps + 1e-6)


# ---------------------------------------------------------------- who plays in an RD3G car's game
@pytest.mark.parametrize("ey2, players, obstacles", [(0.12, [1, 2], [3]), (0.22, [1], [2, 3])])
def test_an_obstacle_inside_a_players_collision_distance_becomes_a_player(ey2, players, obstacles):
    """On the oval's straight: rd3g1 at s = 4.5 m; car 1 (nearest, its game's player) 0.3 m ahead at
    ey = -0.06; car 2 0.36 m ahead beside car 1; car 3 1.4 m ahead (in reach: an obstacle). The
    collision distance is 0.25 m sideways (the lateral clearance; 2 cm more for the first step: 0.27 m),
    measured with the along-track gap scaled by (0.25 / 0.195) x (1 - 1/m x 0.223 m) (the window reaches
    the 1 m turn; ey_max is the track-limit bound) = 0.996. Car 2 at ey 0.12 is hypot(0.996 x 0.06, 0.18)
    = 0.190 m from car 1: inside, so it plays; at ey 0.22 it is hypot(0.060, 0.28) = 0.286 m away (a
    lateral gap counts in full) and stays an obstacle. Car 3 is 1 m or more from both."""
    setup = RaceSpec(roster=parse_cars("rd3g,mpc,mpc,mpc"), seed=0).load()
    planners = RacePlanners(dataclasses.replace(setup, planner_threads=1))
    planner = planners.models["rd3g1"]
    at_plan = np.array([[4.5, -0.1, 1.9, 0.0], [4.8, -0.06, 1.8, 0.0], [4.86, ey2, 1.8, 0.0], [5.9, 0.15, 1.8, 0.0]])
    assert planner.tm.collision_distance() == 0.25 and planner.tm.footprint_distance() == pytest.approx(0.195, abs=1e-3)
    assert planner.tm.along_track_scale(at_plan[:, S], at_plan[:, EY]) == pytest.approx(
        0.25 / planner.tm.footprint_distance() * (1.0 - 0.2234), abs=1e-3)
    assert planners._others(0, planner, at_plan) == (players, obstacles)


# ---------------------------------------------------------------- planners on two cores
def _jobs(setup, steps: int):
    """Planning jobs of the grid's cars moving on at 1 m/s along their headings (no planner involved)."""
    x0 = start_states(setup)
    jobs = []
    for k in range(steps):
        states = {}
        for name, x in zip(setup.names, x0):
            moved = np.array(x, dtype=float)
            moved[0] += k * setup.control_period_s * np.cos(moved[2])
            moved[1] += k * setup.control_period_s * np.sin(moved[2])
            moved[3] = 1.0
            states[name] = moved
        jobs.append(PlanJob(k, k * setup.control_period_s, states))
    return jobs


def test_planners_in_two_threads_give_the_plans_made_in_turn():
    setup = RaceSpec(roster=parse_cars("rd3g,rd3g,mpc,mpc"), seed=3).load()
    results = {}
    for threads in (1, 2):
        planners = RacePlanners(dataclasses.replace(setup, planner_threads=threads))
        assert (planners._pool is None) == (threads == 1)
        try:
            results[threads] = [planners.plan(job) for job in _jobs(setup, 6)]
        finally:
            planners.close()
    for one, two in zip(results[1], results[2]):
        assert list(one.cars) == list(two.cars) == list(setup.names)
        for name in setup.names:
            a, b = one.cars[name], two.cars[name]
            assert (a.throttle, a.steering_rad, a.plan.used) == (b.throttle, b.steering_rad, b.plan.used)
            np.testing.assert_array_equal(a.plan.x, b.plan.x)


def test_planners_in_two_threads_give_the_plans_made_in_turn_with_a_car_off_the_track():
    """As above with mpc3 0.5 m outside the track's edge, heading away from it (buzzracer:full seed 19:
    an MPC car leaves the track at the start and circles outside it): after the cold plan it falls back,
    the other cars plan around it; every plan is the same with 2 threads as in turn."""
    setup = RaceSpec(roster=parse_cars("rd3g,rd3g,mpc,mpc"), seed=3).load()
    jobs = _jobs(setup, 6)
    for job in jobs:
        x = job.states["mpc3"]
        s, ey, _ = setup.track.to_frenet(x[0], x[1])
        out = 0.5 * float(setup.track.width(s)) + 0.5  # 0.5 m beyond the edge on the car's side
        heading = float(setup.track.heading(s))
        side = 1.0 if float(ey) >= 0 else -1.0
        x[0] -= side * out * np.sin(heading)
        x[1] += side * out * np.cos(heading)
        x[2] = heading + side * 0.8
        assert not setup.track.is_inside(x[0], x[1])
    results = {}
    for threads in (1, 2):
        planners = RacePlanners(dataclasses.replace(setup, planner_threads=threads))
        try:
            results[threads] = [planners.plan(job) for job in jobs]
        finally:
            planners.close()
    for one, two in zip(results[1], results[2]):
        for name in setup.names:
            a, b = one.cars[name], two.cars[name]
            assert (a.throttle, a.steering_rad, a.plan.used, a.plan.error) == (b.throttle, b.steering_rad, b.plan.used, b.plan.error)
            np.testing.assert_array_equal(a.plan.x, b.plan.x)


def test_each_cars_rollout_models_are_its_own_and_agree_when_used_concurrently():
    """Every car's track model keeps its own C++ rollout models (one per time step; a cache shared by the
    class would be filled and evicted by the planners of one step at once), and rolling out from several
    threads at the same time gives the rollouts computed in turn, which match an explicit Euler step of the
    Frenet kinematic bicycle (the model's equations, computed here) on a straight."""
    setup = RaceSpec(roster=parse_cars("mpc,mpc,mpc,mpc"), seed=0).load()
    planners = RacePlanners(dataclasses.replace(setup, planner_threads=1))
    models = [planners.models[name].tm for name in setup.names]
    dts = (0.1, setup.control_period_s, 0.05, 0.02, 0.04)
    assert len({id(tm.rollout_model(dt)) for tm in models for dt in dts}) == len(models) * len(dts)
    assert all(tm.rollout_model(dt) is tm.rollout_model(dt) for tm in models for dt in dts)
    x0 = np.array([4.2, 0.02, 1.0, 0.01])  # on the oval's straight (curvature 0)
    u = np.tile([0.5, 0.05], (20, 1))
    in_turn = {(i, dt): np.asarray(tm.rollout_model(dt).rollout(x0, u)) for i, tm in enumerate(models) for dt in dts}
    barrier, concurrent = threading.Barrier(len(models), timeout=20.0), {}

    def roll(i):
        barrier.wait()
        for _ in range(50):
            for dt in dts:
                concurrent[i, dt] = np.asarray(models[i].rollout_model(dt).rollout(x0, u))

    workers = [threading.Thread(target=roll, args=(i,)) for i in range(len(models))]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    assert concurrent.keys() == in_turn.keys()
    for key, x in in_turn.items():
        np.testing.assert_array_equal(concurrent[key], x)
    g = setup.car.geometry
    for dt in dts:  # the reference: explicit Euler on the straight (kappa 0)
        x = x0.copy()
        for a, delta in u:
            beta = np.arctan(g.lr_m * np.tan(delta) / (g.lf_m + g.lr_m))
            x = x + dt * np.array([x[2] * np.cos(x[3] + beta), x[2] * np.sin(x[3] + beta), a, x[2] * np.sin(beta) / g.lr_m])
        assert setup.track.curvature(x[0]) == 0
        np.testing.assert_allclose(in_turn[0, dt][-1], x, rtol=1e-12, atol=1e-12)


def test_the_plans_of_one_step_run_at_the_same_time(monkeypatch):
    """Two cars' plans meet at a two-party barrier: with the pool both wait there together; in turn the
    first would wait alone (BrokenBarrierError after the timeout)."""
    setup = dataclasses.replace(RaceSpec(roster=parse_cars("mpc,mpc"), seed=0).load(), planner_threads=2)
    planners = RacePlanners(setup)
    barrier, threads = threading.Barrier(2, timeout=20.0), set()
    original = race_planning.plan_step

    def meet_then_plan(planner, *args, **kw):
        threads.add(threading.current_thread().name)
        barrier.wait()
        return original(planner, *args, **kw)

    monkeypatch.setattr(race_planning, "plan_step", meet_then_plan)
    try:
        result = planners.plan(_jobs(setup, 1)[0])
    finally:
        planners.close()
    assert set(result.cars) == {"mpc1", "mpc2"} and len(threads) == 2
    assert planners._pool is None  # closed: a later plan runs in turn


def test_planner_threads_must_be_a_positive_integer():
    for bad in (0, -1, 1.5, True):
        with pytest.raises(RaceSetupError) as exc:
            RaceSpec(planner_threads=bad).load()
        assert exc.value.field == "planner_threads"


# ---------------------------------------------------------------- fleet batch default
def test_fleet_batch_defaults_to_100_seeds(monkeypatch, capsys):
    from app.cli import main
    from app.commands import batch

    seen = {}

    def fake_run_races(jobs, workers=1, cluster=None, timeout=None):
        seen["jobs"] = jobs
        return [{"cell": cell, "seed": r, "cars": 4, "position": 1 if cell[1] == "rd3g" else 2,
                 "unfinished": False, "at_fault": 0, "collisions": 0} for _, cell, r, *_ in jobs]

    monkeypatch.setattr(batch, "run_races", fake_run_races)
    assert main(["batch", "--cars", "rd3g,mpc,mpc,mpc"]) == 0
    seeds = sorted({r for _, _, r, *_ in seen["jobs"]})
    assert seeds == list(range(100)) and len(seen["jobs"]) == 200  # each seed as given and as counterfactual
