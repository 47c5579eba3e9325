"""The reference controller on the real oval from tracks/."""

import math

import numpy as np
import pytest

from planning import PurePursuitController
from sim import SimEffects, Simulator
from vehicles.params import load_car_params

tracks = pytest.importorskip("tracks")
load_track = getattr(tracks, "load_track", None)
if load_track is None:  # pragma: no cover - only while tracks/ is being written
    pytest.skip("tracks.load_track not available yet", allow_module_level=True)


def _start_state(track, s, speed=0.0):
    xy = np.asarray(track.position(np.array([s])), dtype=float).reshape(2)
    heading = float(np.asarray(track.heading(np.array([s]))).reshape(-1)[0])
    return [xy[0], xy[1], heading, speed, 0.0, 0.0]


@pytest.mark.parametrize("target_speed", [1.0, 2.0])
def test_pure_pursuit_completes_a_lap_of_the_oval_on_track(target_speed):
    track = load_track("oval")
    car = load_car_params("buzzracer")
    sim = Simulator(track, [car], laps_to_win=1)
    # Start a little before the line so the lap is a full, timed one.
    sim.reset([_start_state(track, track.length - 0.3)])
    ctrl = PurePursuitController(track, car, target_speed_mps=target_speed)
    dt = 1 / 30
    while sim.race_status().winner is None and sim.time < 3 * track.length / target_speed + 5:
        sim.step([ctrl.command(sim.state(0), dt)], dt)
    status = sim.race_status()
    assert status.winner == 0
    assert status.off_track_count == (0,)
    # No faster than the target speed allows, and not crawling either.
    assert track.length / target_speed * 0.95 < status.lap_times[0][0] < 2.0 * track.length / target_speed


def test_pure_pursuit_tolerates_an_unknown_steering_offset_and_delay():
    track = load_track("oval")
    car = load_car_params("buzzracer")
    sim = Simulator(track, [car], effects=SimEffects(steering_offset_rad=0.04, steering_delay_s=0.03))
    sim.reset([_start_state(track, 0.0)])
    ctrl = PurePursuitController(track, car, target_speed_mps=1.2)
    dt = 1 / 30
    while sim.race_status().laps[0] < 1 and sim.time < 30:
        sim.step([ctrl.command(sim.state(0), dt)], dt)
    assert sim.race_status().laps[0] == 1
    assert sim.race_status().off_track_count == (0,)
    assert math.isfinite(sim.race_status().lap_times[0][0])
