"""Simulated races: a short deterministic race, fault and gap geometry, the JSON record."""
import math

import numpy as np
import pytest

from race.referee import fault_of
from race.setup import RaceSetup, start_states
from race.simulation import run_race
from sim.collision import footprint_gap


@pytest.fixture(scope="module")
def race(track, car, tmp_path_factory):
    setup = RaceSetup(track=track, car=car, seed=3, start="front", rd3g_top_speed_mps=2.0, opponent_top_speed_mps=1.6)
    return setup, run_race(setup, telemetry_path=tmp_path_factory.mktemp("runs") / "race.rrd")


def test_short_race_finishes_without_collision(race, track):
    setup, o = race
    assert o.winner in ("rd3g", "opponent")
    assert o.collisions == []
    assert o.min_gap_m > 0
    lap = o.lap_times_s[o.winner][0]
    # The winner drove one lap (minus its start offset) at no more than its top speed on the inside line
    # (|ey| <= 0.22 m on 1 m turns shortens the 2 pi m of turns by at most 22 %).
    shortest = track.length - 2 * math.pi * 0.23 - 0.5
    assert shortest / 2.0 < lap < 2 * track.length / 1.6
    assert o.trace_progress[-1].max() - o.trace_progress[0].max() > track.length - 0.5
    assert set(o.summary()) == {"winner", "clean_winner", "lap_times_s", "min_gap_m", "collisions", "rd3g_at_fault",
                                "off_track", "fallbacks", "solve_ms_p50", "solve_ms_p99", "prestart_ms",
                                "control_period_ms", "planner_errors", "interrupted", "race_time_s",
                                "cars", "finishing_order", "collision_events"}
    assert o.planner_errors == [] and o.summary()["planner_errors"] == 0
    assert o.summary()["interrupted"] is False and o.summary()["race_time_s"] == o.race_time_s


def test_race_is_deterministic(race):
    setup, o = race
    setup_short = setup.__class__(**{**setup.__dict__, "max_time_s": 1.0})
    again = run_race(setup_short)
    n = len(again.trace_t)
    assert np.array_equal(again.trace_states, o.trace_states[:n])


def test_start_states_one_car_length_apart(track, car):
    for start in ("front", "rear"):
        x = start_states(RaceSetup(track=track, car=car, seed=5, start=start))
        s, ey, _ = track.to_frenet(x[:, 0], x[:, 1], x[:, 2])
        ds = track.progress_difference(s[0], s[1])
        assert (ds > 0) == (start == "front")
        assert 1.75 * 0.16 - 1e-9 <= abs(ds) <= 2.25 * 0.16 + 1e-9
        assert np.all(np.abs(ey) <= 0.12 + 1e-9) and np.all(x[:, 3:] == 0)


def test_fault_is_the_car_whose_front_hits(car):
    # Car 1 directly behind car 0, both heading +x: car 1's front hits car 0's rear.
    states = np.array([[1.0, 0.0, 0.0, 1, 0, 0], [0.85, 0.0, 0.0, 2, 0, 0]])
    assert fault_of(states) == 1
    # Car 0 turned into car 1 from beside it: car 1 lies ahead along car 0's heading.
    states = np.array([[1.0, 0.0, 0.6, 1, 0, 0], [1.05, 0.08, 0.0, 1, 0, 0]])
    assert fault_of(states) == 0


def test_footprint_gap_matches_geometry(car):
    L, W = car.geometry.footprint_length_m, car.geometry.footprint_width_m
    aligned = np.array([[0.0, 0.0, 0.0, 0, 0, 0], [L + 0.1, 0.0, 0.0, 0, 0, 0]])
    assert footprint_gap(aligned, car.geometry) == pytest.approx(0.1)
    beside = np.array([[0.0, 0.0, 0.0, 0, 0, 0], [0.0, W + 0.05, 0.0, 0, 0, 0]])
    assert footprint_gap(beside, car.geometry) == pytest.approx(0.05)
    # Corner to corner at 45 degrees: the gap is the distance between the nearest corners.
    diag = np.array([[0.0, 0.0, 0.0, 0, 0, 0], [L + 0.03, W + 0.04, 0.0, 0, 0, 0]])
    assert footprint_gap(diag, car.geometry) == pytest.approx(0.05)
    overlapping = np.array([[0.0, 0.0, 0.0, 0, 0, 0], [0.05, 0.0, 0.3, 0, 0, 0]])
    assert footprint_gap(overlapping, car.geometry) == 0.0


def test_setup_validation_names_field(track, car):
    with pytest.raises(ValueError, match="opponent"):
        RaceSetup(track=track, car=car, opponent="human")
    with pytest.raises(ValueError, match="start"):
        RaceSetup(track=track, car=car, start="middle")


def test_off_track_win_is_not_clean_and_not_counted(track, car):
    """A win by a car that left the track is recorded but not counted: RaceOutcome.clean_winner is
    None and the batch win rate only counts RD3G wins without an excursion."""
    from app.commands.batch import summarise
    from race.simulation import RaceOutcome

    base = dict(lap_times_s={}, min_gap_m=0.1, collisions=[], solve_ms=np.ones(3), opponent_solve_ms=np.ones(3),
                control_period_ms=33.3, race_time_s=5.0, fallbacks=0, start_states=np.zeros((2, 6)))
    assert RaceOutcome(winner="rd3g", off_track={"rd3g": 1, "opponent": 0}, **base).clean_winner is None
    assert RaceOutcome(winner="rd3g", off_track={"rd3g": 0, "opponent": 2}, **base).clean_winner == "rd3g"
    rec = dict(cell=("rear", "fast"), collisions=0, rd3g_at_fault=0, solve_ms=np.ones(3), min_gap_m=0.1,
               fallbacks=0, opponent_off_track=0)
    records = [{**rec, "seed": 0, "winner": "rd3g", "rd3g_won": True, "rd3g_off_track": 1},   # shortcut: not counted
               {**rec, "seed": 1, "winner": "rd3g", "rd3g_won": True, "rd3g_off_track": 0},
               {**rec, "seed": 2, "winner": "opponent", "rd3g_won": False, "rd3g_off_track": 0},
               {**rec, "seed": 3, "winner": "rd3g", "rd3g_won": True, "rd3g_off_track": 0}]
    cell = {(c["start"], c["speed"]): c for c in summarise(records, 4)}[("rear", "fast")]
    assert cell["rd3g_wins"] == 2 and cell["win_rate"] == 0.5
    assert cell["rd3g_off_track_races"] == 1 and cell["rd3g_wins_off_track"] == 1


def test_race_stays_on_track(race):
    """The seeded test race: neither car leaves the drivable area, and the winner's win is clean."""
    setup, o = race
    assert o.off_track == {"rd3g": 0, "opponent": 0}
    assert o.clean_winner == o.winner


def _raising_plan(monkeypatch, cls, calls_that_raise):
    """Make cls.plan raise on the given call numbers (0 = the cold plan before the start)."""
    original = cls.plan
    n = {"calls": 0}

    def plan(self, x_self, x_others, **others):
        k = n["calls"]
        n["calls"] += 1
        if k in calls_that_raise:
            raise ValueError(f"injected planner failure {k}")
        return original(self, x_self, x_others, **others)

    monkeypatch.setattr(cls, "plan", plan)


def test_planner_exception_is_a_logged_fallback_not_a_crash(track, car, monkeypatch):
    """Both planners raise: RD3G for its cold plan and the first 15 steps (0.5 s), the MPC for steps
    30-39. The race goes on: before any plan the RD3G car gets neutral commands (zero throttle and
    steering) and so stays where it started (at rest, the simulator's drive model gives no force at
    zero throttle); later errors fall back to tracking the previous plan, so the MPC car keeps
    driving on the track. Every failed step is recorded with car, time and message, and counted as
    a fallback for RD3G."""
    from planning import MPCOpponent, RacingPlanner

    _raising_plan(monkeypatch, RacingPlanner, set(range(16)))
    _raising_plan(monkeypatch, MPCOpponent, set(range(31, 41)))
    setup = RaceSetup(track=track, car=car, seed=3, start="front", rd3g_top_speed_mps=2.0, opponent_top_speed_mps=1.6,
                      max_time_s=2.0)
    o = run_race(setup)
    period = setup.control_period_s
    rd3g = [e for e in o.planner_errors if e.car == "rd3g"]
    mpc = [e for e in o.planner_errors if e.car == "opponent"]
    assert [e.message for e in rd3g] == [f"ValueError: injected planner failure {k}" for k in range(16)]
    assert [e.time_s for e in rd3g] == pytest.approx([0.0] + [k * period for k in range(15)], abs=1e-3)  # 1 ms physics steps
    assert [e.time_s for e in mpc] == pytest.approx([k * period for k in range(30, 40)], abs=1e-3)
    assert o.summary()["planner_errors"] == 26
    assert o.fallbacks >= 15
    # Neutral from rest: the RD3G car has not moved after 0.5 s of failed planning ...
    k_end = 15
    assert np.hypot(*(o.trace_states[k_end, 0, :2] - o.start_states[0, :2])) < 1e-3
    # ... and drives off once planning works again (2 s race: well over 0.5 m of progress).
    assert o.trace_progress[-1, 0] - o.trace_progress[0, 0] > 0.5
    # The MPC car drives through its 10 failed steps at speed and stays on the track.
    speeds = np.hypot(o.trace_states[30:41, 1, 3], o.trace_states[30:41, 1, 4])
    assert np.all(speeds > 0.8)
    assert o.off_track == {"rd3g": 0, "opponent": 0}


def test_raceline_option_reaches_both_planners_and_is_validated():
    import argparse

    from app.cli import UserError
    from app.commands import race as race_cmd

    parser = argparse.ArgumentParser()
    race_cmd.register(parser.add_subparsers())
    args = parser.parse_args(["race", "--line", "centre", "--raceline-ey", "0.05"])
    setup = race_cmd.make_setup(args, 0, "front", 2.0, 1.8)
    assert setup.planner.raceline_ey_m == 0.05
    assert race_cmd.make_setup(parser.parse_args(["race"]), 0, "front", 2.0, 1.8).planner.raceline_ey_m == 0.0
    for bad in ("0.3", "nan"):  # the oval is 0.6 m wide: 0.3 m is on its edge
        with pytest.raises(UserError, match="--raceline-ey"):
            race_cmd.make_setup(parser.parse_args(["race", "--line", "centre", "--raceline-ey", bad]), 0, "front",
                                2.0, 1.8)
    # A constant offset means nothing on the racing line: refused rather than ignored.
    with pytest.raises(UserError, match="--raceline-ey.*'centre' only"):
        race_cmd.make_setup(parser.parse_args(["race", "--line", "racing", "--raceline-ey", "0.05"]), 0, "front",
                            2.0, 1.8)


def test_simulated_race_does_not_depend_on_solve_time(track, car, monkeypatch):
    """The simulated clock moves only between ticks: a planner made 5 ms slower per call (as on a loaded
    machine) gives the bit-identical race, and the planning wall time it reports grows by those 5 ms."""
    import time

    from planning import RacingPlanner

    setup = RaceSetup(track=track, car=car, seed=4, start="rear", max_time_s=1.0)
    fast = run_race(setup)
    original = RacingPlanner.plan

    def slow_plan(self, x_self, x_others, **others):
        time.sleep(0.005)
        return original(self, x_self, x_others, **others)

    monkeypatch.setattr(RacingPlanner, "plan", slow_plan)
    slow = run_race(setup)
    assert len(fast.trace_t) == len(slow.trace_t) == 30  # ticks 0..29: the 1 s limit is reached at tick 30
    assert np.array_equal(fast.trace_states, slow.trace_states)
    assert fast.solve_ms.size == slow.solve_ms.size == 30
    assert np.all(slow.solve_ms >= 5.0)


def test_sim_world_applies_each_command_for_one_control_period(track, car):
    """SimWorld behind the link: a command given at a tick drives the cars until the next tick; the states
    it reports equal a Simulator stepped by hand with the same physical commands (steering normalised
    by the car file's max_steering_rad on the way, as on the serial link)."""
    from race.commands import link_command
    from race.simulation import SimWorld
    from race.world import SimulatedClock
    from sim import Simulator
    from vehicles.protocol import CarCommand, ProtocolError

    setup = RaceSetup(track=track, car=car, seed=2)
    x0 = start_states(setup)
    by_hand = Simulator(track, [car, car], seed=setup.seed)
    by_hand.reset(x0)
    sim = Simulator(track, [car, car], seed=setup.seed)
    sim.reset(x0)
    clock = SimulatedClock(10.0)
    world = SimWorld(sim, clock, setup)
    T = setup.control_period_s
    assert world.poll().t_race is None  # before the start: the grid, nothing advances
    clock.advance(1.0)
    assert np.array_equal(world.poll().truth, x0)
    world.go(clock.now())
    commands = [(0.5, 0.1), (0.3, -0.2), (0.0, 0.0)]
    for throttle, steering in commands:  # one loop tick each: observe, command, the clock moves on
        packet = world.poll()
        assert np.array_equal(packet.truth, by_hand.states)
        assert packet.t_race == pytest.approx(by_hand.time)
        world.set_commands({0: link_command(car, throttle, steering), 1: link_command(car, 0.4, 0.0)})
        clock.advance(T)
        by_hand.step([[throttle, steering / car.actuators.max_steering_rad * car.actuators.max_steering_rad],
                      [0.4, 0.0]], T)
    assert np.array_equal(world.poll().truth, by_hand.states) and not np.array_equal(by_hand.states, x0)
    assert world.trace_t == pytest.approx([0.0, T, 2 * T, 3 * T], abs=1e-3)  # the states the loop observed
    with pytest.raises(ProtocolError, match="car 0 steering is NaN"):
        world.set_commands({0: CarCommand(float("nan"), 0.0)})
