"""Perception is sensor-neutral (race.world.Perceiver, race.world.PoseSource): a pose source without
any image (a motion-capture stream at its own rate and times, here faked on the simulated clock) plugs
into race.perception.Perception and drives the race loop; a car it stops seeing holds every car
neutral like a lost marker. The world, link and planners are the fake-clock safety tests' fakes."""
from __future__ import annotations

import math

import numpy as np
import pytest

from race.command_history import CommandHistory
from race.config import LoopConfig
from race.loop import CarBinding, RaceLoop, SimulatedDeadlineMonitor
from race.perception import Perception
from race.planning import SyncPlanRunner
from race.setup import RaceSetup
from race.world import Observation, TimedPose
from test_loop_safety import LOST_AFTER_S, T0, Link, Planners, World, driving, events, neutral
from tracking.estimator import MultiCarEstimator
from tracks import load_track
from vehicles.params import load_car_params

RATE_HZ = 120.0     # the mocap stream's rate, not the loop's or a camera's
OFFSET_S = 0.0013   # its frames are not aligned with the loop's ticks
CARS = [CarBinding(f"car{i}", 10 + i, i) for i in range(4)]


class MocapPoses:
    """Timed poses per car from the stream's newest frame at the clock's time; no image, no regions.
    ``hidden[name] = (t0, t1)`` race times the car is not seen."""

    regions = False

    def __init__(self, world: World) -> None:
        self.world, self.hidden, self.readings = world, {}, 0
        self._last = -1

    def next_reading(self, packet) -> float | None:
        newest = math.floor((self.world.clock.now() - T0 - OFFSET_S) * RATE_HZ)
        if newest <= self._last:
            return None
        self._last = newest
        return T0 + OFFSET_S + newest / RATE_HZ

    def read(self, packet, predictions) -> Observation:
        t = T0 + OFFSET_S + self._last / RATE_HZ
        self.readings += 1
        poses = {}
        for i, c in enumerate(CARS):
            t0, t1 = self.hidden.get(c.name, (math.inf, math.inf))
            if not t0 <= self.world.race_time(t) < t1:
                poses[c.name] = TimedPose(t, *self.world.pose(i, t))
        return Observation(t, poses)


class Frameless(World):
    """The fake world without camera frames: packets carry nothing but time passing."""

    def poll(self, timeout: float = 0.0):
        packet = super().poll(timeout)
        packet.frame = None
        return packet


@pytest.fixture(scope="module")
def setup():
    return RaceSetup(track=load_track("oval"), car=load_car_params("buzzracer"), max_time_s=2.0)


def mocap_loop(setup):
    from race.world import SimulatedClock

    clock = SimulatedClock(T0)
    world = Frameless(clock, setup.track, len(CARS))
    source, link, commands = MocapPoses(world), Link(world), CommandHistory()
    perception = Perception(None, MultiCarEstimator(), CARS, LoopConfig().lost_search_every, commands=commands,
                            source=source)
    loop = RaceLoop(setup=setup, config=LoopConfig(), feed=world, link=link, planners=Planners(CARS), cars=CARS,
                    perception=perception, mode="hardware", clock=clock,
                    worker_factory=SyncPlanRunner, monitor_factory=SimulatedDeadlineMonitor)
    original = loop._cold_start

    def cold_start():
        original()
        world.t_go = loop.t_go

    loop._cold_start = cold_start
    assert loop.commands is commands  # the loop writes the history the perception's estimator reads
    return loop, world, source, link


def test_a_pose_source_without_images_drives_the_race(setup):
    loop, world, source, link = mocap_loop(setup)
    o = loop.run()
    assert o.reason == "time_limit" and not events(o, "fault")
    assert all(driving(c, 4) for t, c in link.sent if t > 0.1)
    # the newest reading at each tick (the stream runs at twice the loop's rate)
    assert o.ticks - 1 <= o.frames <= o.ticks and source.readings >= o.frames
    # the estimate at the last pose is where the fake world put the car then
    for i, c in enumerate(CARS):
        t, state = loop.perception.last_measurement(c.name)
        np.testing.assert_allclose(state[:2], world.pose(i, t)[:2], atol=0.01)


def test_a_car_the_source_stops_seeing_holds_every_car(setup):
    loop, world, source, link = mocap_loop(setup)
    source.hidden["car1"] = (1.0, 1.3)
    o = loop.run()
    (t_fault, text), *_ = events(o, "fault")
    assert "car car1 lost" in text
    assert 1.0 - 1 / RATE_HZ + LOST_AFTER_S < t_fault <= 1.0 + LOST_AFTER_S + 1 / 60 + 1e-9
    (t_back, text), *_ = events(o, "recovered")
    assert text.startswith("lost:car1 cleared") and 1.3 <= t_back < 1.3 + 2 / 60 + 1e-9
    held = [c for t, c in link.sent if t_fault - 1e-9 <= t < t_back - 1e-9]
    assert held and all(neutral(c, 4) for c in held)
