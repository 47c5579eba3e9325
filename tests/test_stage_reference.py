"""Stage-varying references: the solver's per-step x_ref (QuadraticCost.x_ref_steps) against the
closed-form least-squares solution of an unconstrained LQ problem, and the racing line as the
planners' reference (planning.reference) against arc lengths computed by hand on a circle track."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from planning import CommandMapper, FrenetTrackModel, MPCOpponent, PlannerConfig
from planning.frenet import EY, S, V
from planning.reference import stage_reference
from solver_cpp import Agent, GameProblem, LinearModel, QuadraticCost, Solver, make_settings
from tracks import track_from_dict
from tracks.racing_line import RacingLine, RacingLineLimits
from vehicles.params import load_car_params

T = 6


def _lq_problem(x_ref_steps, q=2.0, r=0.5):
    """Scalar integrator x_{k+1} = x_k + u_k from x_0 = 0.3."""
    cost = QuadraticCost(x_ref=[0.0], Q_ref=[q], R=[r], x_ref_steps=x_ref_steps)
    return GameProblem(dt=1.0, horizon=T, agents=[Agent(LinearModel(A=[[1.0]], B=[[1.0]]), x0=[0.3], cost=cost)])


def test_per_step_reference_matches_least_squares():
    # min sum_k r u_k^2 + q (x_k - ref_k)^2, x_k = x_0 + sum_{j<k} u_j: a linear least-squares problem in u.
    ref = np.array([0.5, 1.0, -0.2, 0.7, 0.7, 0.1])
    q, r = 2.0, 0.5
    result = Solver(_lq_problem(ref[:, None], q, r), make_settings(tol=1e-10)).solve()
    lower = np.tril(np.ones((T, T)))                          # x_{1..T} = 0.3 + lower @ u
    a = np.vstack([math.sqrt(q) * lower, math.sqrt(r) * np.eye(T)])
    b = np.concatenate([math.sqrt(q) * (ref - 0.3), np.zeros(T)])
    u = np.linalg.lstsq(a, b, rcond=None)[0]
    assert np.asarray(result.u)[0, :, 0] == pytest.approx(u, abs=1e-6)


def test_constant_steps_equal_the_constant_reference():
    steps = Solver(_lq_problem(np.full((T, 1), 0.8)), make_settings(tol=1e-10)).solve()
    constant = _lq_problem(None)
    constant.agents[0].cost.x_ref = [0.8]
    plain = Solver(constant, make_settings(tol=1e-10)).solve()
    assert np.asarray(steps.u) == pytest.approx(np.asarray(plain.u), abs=1e-9)


def test_per_step_reference_of_the_wrong_shape_is_named():
    with pytest.raises(ValueError, match=r"agents\[0\]\.cost\.x_ref_steps must have shape \(1, 6\)"):
        Solver(_lq_problem(np.zeros((T - 1, 1))), make_settings())


def test_per_step_reference_survives_the_problem_file():
    from solver_cpp.problem_file import problem_from_dict, problem_to_dict

    ref = np.array([[0.5], [1.0], [-0.2], [0.7], [0.7], [0.1]])
    problem, _, _ = problem_from_dict(problem_to_dict(_lq_problem(ref)))
    assert np.asarray(problem.agents[0].cost.x_ref_steps) == pytest.approx(ref)
    with pytest.raises(ValueError, match=r"x_ref_steps"):
        problem_from_dict({**problem_to_dict(_lq_problem(ref)), "agents": [
            {**problem_to_dict(_lq_problem(ref))["agents"][0], "cost": {"x_ref": [0], "Q_ref": [1], "R": [1],
                                                                       "x_ref_steps": [[0.1], ["a"]]}}]})


# ----------------------------------------------------------------------------------------------- the racing line
R, WIDTH = 1.0, 0.6


def ring():
    return track_from_dict({"name": "ring", "closed": True, "width": WIDTH, "start": [0.0, -R, 0.0],
                            "segments": [{"type": "arc", "radius": R, "angle_deg": 360}]})


def constant_line(track, ey, speed, top=2.0):
    """A line at constant offset ey and speed on the ring (built by hand, not optimised)."""
    n = 400
    limits = RacingLineLimits(lateral_accel_mps2=4.0, accel_mps2=3.0, brake_mps2=4.0, top_speed_mps=top,
                              half_width_m=0.05, margin_m=0.03)
    return RacingLine(track.name, float(track.length), limits, np.full(n, ey), np.full(n, speed),
                      np.full(n, 1.0 / (R - ey)), np.full(n, 2 * math.pi * (R - ey) / n))


def test_stages_on_a_circle_advance_at_the_offset_progress_rate():
    # At offset ey on a left circle of radius R the car at v covers centre-line arc length v R / (R - ey) per second.
    track, ey, v, dt = ring(), 0.12, 1.5, 0.1
    line = constant_line(track, ey, v)
    stages = stage_reference(line, track.curvature, 2.0, v, T, dt, accel_mps2=3.0, brake_mps2=4.0)
    k = np.arange(1, T + 1)
    assert stages.s == pytest.approx(2.0 + k * dt * v * R / (R - ey), rel=1e-9)
    assert stages.ey == pytest.approx(np.full(T, ey))
    assert stages.v == pytest.approx(np.full(T, v))


def test_stages_from_a_lower_speed_accelerate_at_the_drive_limit():
    # From 0.9 m/s towards 1.5 m/s at 3 m/s^2: 0.9, 1.2, 1.5, 1.5, ... ; on the centre line (ey 0) s = sum v dt.
    track = ring()
    line = constant_line(track, 0.0, 1.5)
    stages = stage_reference(line, track.curvature, 0.0, 0.9, T, 0.1, accel_mps2=3.0, brake_mps2=4.0)
    speeds = [0.9, 1.2, 1.5, 1.5, 1.5, 1.5]
    assert stages.s == pytest.approx(np.cumsum(speeds) * 0.1, rel=1e-9)


def test_mpc_cost_follows_the_line_at_the_horizon_stages():
    track = ring()
    car = load_car_params("buzzracer")
    config = PlannerConfig(top_speed_mps=2.0)
    planner = MPCOpponent(FrenetTrackModel(track, car, config), CommandMapper(car, 1 / 30, config.max_brake_mps2),
                          config, 1 / 30)
    # An offset varying along the ring: ey(s) = 0.1 sin(2 pi s / L), constant speed 1.2 m/s (below the top speed).
    line = constant_line(track, 0.0, 1.2)
    s_grid = line.s
    line = dataclasses.replace(line, ey=0.1 * np.sin(2 * math.pi * s_grid / track.length))
    planner.line = line
    x0 = np.array([1.0, 0.0, 1.2, 0.0])
    cost = planner._cost(2.0, None, x0)
    # By hand: s_{k+1} = s_k + dt v / (1 - ey(s_k) / R) (v stays 1.2), then ey(s_k) of the line.
    s, expected = 1.0, []
    for _ in range(config.horizon):
        s += config.plan_dt_s * 1.2 / (1 - 0.1 * math.sin(2 * math.pi * s / track.length) / R)
        expected.append(0.1 * math.sin(2 * math.pi * s / track.length))
    steps = np.asarray(cost.x_ref_steps)
    assert steps[:, EY] == pytest.approx(expected, abs=2e-4)   # the line is tabulated every 2.6 cm
    assert steps[:, V] == pytest.approx(np.full(config.horizon, 1.2))
    assert steps[:, S] == pytest.approx(np.zeros(config.horizon))
    assert planner.speed_cap(x0, 2.0) == pytest.approx(1.2)
    plan = planner.plan(x0, np.array([[4.0, 0.0, 0.5, 0.0]]))   # another car half a lap ahead
    assert plan.used in ("converged", "accepted")


def test_unknown_line_is_named():
    from planning.config import PlannerConfigError
    from race.setup import RaceSetupError, RaceSpec

    with pytest.raises(PlannerConfigError, match=r"planner\.line: must be one of centre, racing, got 'fast'"):
        PlannerConfig(line="fast")
    with pytest.raises(RaceSetupError, match=r"^line: must be one of centre, racing"):
        RaceSpec(line="fast").load()
