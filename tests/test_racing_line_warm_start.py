"""Following the racing line: the warm start brought inside the track-limit bounds before a solve
(_RecedingHorizon._inside_bounds), checked against the plan's own bounds on a circle track, and the
other cars of RD3G's game on their own line (RacingPlanner.line_for); the retry's guess after a failed warm
start, on either line (_RecedingHorizon._tracking_guess)."""
from __future__ import annotations

import numpy as np
import pytest

from planning import CommandMapper, FrenetTrackModel, MPCOpponent, PlannerConfig, RacingPlanner
from planning.frenet import EY, V
from planning.reference import planner_racing_line
from solver_cpp import GameProblem, WarmStart
from tracks.io import load_track
from vehicles.params import load_car_params

from test_stage_reference import constant_line, ring

DT = 0.1


def _mpc_on_the_ring(line_ey=0.0, line_speed=1.2):
    track, car = ring(), load_car_params("buzzracer")
    config = PlannerConfig(top_speed_mps=2.0, line="racing")
    planner = MPCOpponent(FrenetTrackModel(track, car, config), CommandMapper(car, 1 / 30, config.max_brake_mps2),
                          config, 1 / 30)
    planner.line = constant_line(track, line_ey, line_speed)
    return planner


def _problem(planner, x0, top):
    limits = planner.ey_limits([x0[0]])
    agent = planner._agent(x0, top, limits, planner._cost(top, None, x0), 0.0)
    return GameProblem(dt=DT, horizon=planner.config.horizon, agents=[agent]), limits


def _rollout(planner, x0, u):
    return np.asarray(planner.tm.rollout_model(DT).rollout(np.asarray(x0, dtype=float), u))


def _steer_along(planner, radius):
    """Wheel angle whose kinematic-bicycle CG path has curvature 1/radius: sin(beta)/lr = 1/radius,
    tan(delta) = (lf + lr) tan(beta) / lr."""
    g = planner.tm.car.geometry
    beta = np.arcsin(g.lr_m / radius)
    return float(np.arctan((g.lf_m + g.lr_m) * np.tan(beta) / g.lr_m))


def test_a_plan_running_off_the_track_is_steered_back_inside():
    # Straight wheels on the unit circle leave it to the outside (ey < 0): about 1.5 m of a tangent in 1 s,
    # which ends about sqrt(1 + 1.5^2) - 1 = 0.80 m outside the circle, far beyond the bound.
    planner = _mpc_on_the_ring()
    x0 = np.array([1.0, 0.0, 1.5, 0.0])
    problem, (low, high) = _problem(planner, x0, top=2.0)
    u = np.zeros((planner.config.horizon, 2))
    assert np.min(_rollout(planner, x0, u)[1:, EY]) < low            # the warm start leaves the bound
    u[:, 0] = 0.3                                                     # accelerating: kept as they are
    first_out = int(np.argmax(_rollout(planner, x0, u)[1:, EY] < low))  # stage first_out + 1 is the first out
    assert first_out >= 2
    warm = planner._inside_bounds(problem, WarmStart(u=u[None]))
    repaired = np.asarray(warm.u)[0]
    x = _rollout(planner, x0, repaired)
    assert np.all(x[1:, EY] >= low) and np.all(x[1:, EY] <= high)
    assert repaired[:, 0] == pytest.approx(u[:, 0], abs=0)
    assert repaired[:first_out - 1] == pytest.approx(u[:first_out - 1], abs=0)  # before its heading acts: kept


def test_a_feasible_warm_start_is_kept():
    planner = _mpc_on_the_ring()
    x0 = np.array([1.0, 0.0, 1.0, 0.0])
    problem, _ = _problem(planner, x0, top=1.2)
    u = np.tile([0.5, _steer_along(planner, 1.0)], (planner.config.horizon, 1))
    u[2:, 0] = 0.0                                                                 # 1.0, 1.05, 1.1 m/s, then constant: below 1.2
    warm = planner._inside_bounds(problem, WarmStart(u=u[None]))
    assert np.asarray(warm.u)[0] == pytest.approx(u, abs=0)


def test_other_cars_of_the_game_race_their_own_line():
    # A slow RD3G car (1.6 m/s) and a 2 m/s opponent on the oval: the opponent's line is the one a 2 m/s car
    # races, whose speed reaches 2 m/s on the straights; on the slow car's line (at most 1.6 m/s) the
    # opponent at 2 m/s would be bound to slow down by 0.2 m/s in every plan.
    track, car = load_track("oval"), load_car_params("buzzracer")
    config = PlannerConfig(top_speed_mps=1.6, line="racing")
    planner = RacingPlanner(FrenetTrackModel(track, car, config), CommandMapper(car, 1 / 30, config.max_brake_mps2),
                            config, 1 / 30, opponent_top_speed_mps=2.0)
    fast = planner.line_for(2.0)
    assert float(np.max(planner.line.speed_mps)) <= 1.6 + 1e-9
    assert float(np.max(fast.speed_mps)) == pytest.approx(2.0)
    assert planner.line_for(1.6) is planner.line
    assert fast.speed_mps == pytest.approx(planner_racing_line(track, car, 2.0, config).speed_mps)
    s_top = float(fast.s[int(np.argmax(fast.speed_mps))])                 # where the 2 m/s line is at its top speed
    x_other = np.array([s_top, float(fast.lateral_offset(s_top)), 2.0, 0.0])
    assert planner.speed_cap(x_other, 2.0, planner._stages(x_other, fast)) > 1.8


def test_the_retry_guess_tracks_the_line_inside_the_bounds():
    # From 0.1 m inside the ring's centre line, heading 0.3 rad outwards at 1.8 m/s against a 1.2 m/s bound:
    # the guess turns back towards the line (ey 0) and slows to the bound, inside the track-limit bounds.
    planner = _mpc_on_the_ring()
    x0 = np.array([1.0, 0.1, 1.8, 0.3])
    problem, (low, high) = _problem(planner, x0, top=1.2)
    guess = planner._tracking_guess(problem, WarmStart(u=np.zeros((1, planner.config.horizon, 2))))
    x = _rollout(planner, x0, np.asarray(guess.u)[0])
    assert np.all(x[1:, EY] >= low) and np.all(x[1:, EY] <= high)
    assert abs(x[-1, EY]) < 0.1 and x[-1, V] <= 1.2 + 1e-9 and x[-1, V] > 1.0


def test_on_the_centre_line_the_retry_guess_stays_in_the_turn_where_zero_controls_leave_it():
    # The retry after a warm start that failed at once, on the centre line (the cost's constant reference ey 0):
    # from 0.12 m inside the unit ring's centre line at 1.9 m/s, heading along it. The solver's own guess, zero
    # controls, drives the tangent: after 1 s at 1.9 m/s (no acceleration) the CG is
    # sqrt((1 - 0.12)^2 + 1.9^2) - 1 = 1.09 m outside the circle, far beyond the track-limit bound. The tracking
    # guess stays inside the bounds and ends near the centre line. (The planning model integrates in 0.1 s steps:
    # 3 % off the exact tangent.)
    planner = _mpc_on_the_ring()
    planner.line = None
    x0 = np.array([1.0, 0.12, 1.9, 0.0])
    problem, (low, high) = _problem(planner, x0, top=2.0)
    u = np.zeros((planner.config.horizon, 2))
    straight = _rollout(planner, x0, u)
    assert straight[-1, EY] == pytest.approx(-(np.hypot(1.0 - 0.12, 1.9) - 1.0), rel=0.05)  # discrete steps
    assert straight[-1, EY] < low
    guess = planner._tracking_guess(problem, WarmStart(u=u[None]))
    x = _rollout(planner, x0, np.asarray(guess.u)[0])
    assert np.all(x[1:, EY] >= low) and np.all(x[1:, EY] <= high)
    assert abs(x[-1, EY]) < 0.06 and np.all(x[1:, V] <= 2.0 + 1e-9)
