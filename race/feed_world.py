"""A world without its own simulator (real hardware: the camera feed, app.realtime.hardware.CameraFeed)
behind the loop's World interface (race.world): laps, contacts and the winner are judged by the one
referee (race.referee.Referee) from the loop's perceived states (off-track excursions too, with the
simulator's rule that progress made off the track does not count), and those states are the world's
best knowledge of where the cars are (recorded as their positions)."""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from race.referee import Referee
from race.world import Feed, WorldPacket, WorldSummary


class FeedWorld:
    """``feed``: polled for the readings; ``states_at(t_abs)``: the perceived states of every car at a
    clock time (the referee's start positions at the go)."""

    def __init__(self, feed: Feed, setup, names, states_at: Callable[[float], dict]) -> None:
        self.feed, self.setup, self.names = feed, setup, list(names)
        self.states_at = states_at
        self.referee = Referee(setup.track, setup.car, self.names, setup.laps,
                               off_track_allowance_car_lengths=setup.off_track_allowance_car_lengths)
        self.t_go: float | None = None
        self._t_race = 0.0

    def poll(self, timeout: float = 0.0) -> WorldPacket:
        return self.feed.poll(timeout)

    def go(self, t_go: float) -> None:
        self.t_go = t_go
        at_go = self.states_at(t_go)
        self.referee.observe(0.0, np.array([at_go[name] for name in self.names]))

    def observe(self, t_race: float, states: dict) -> WorldPacket:
        """Referee the perceived states (every car's, else nothing is judged); the answer carries them
        as the cars' positions (NaN rows for cars without a state), the referee's events and the winner
        once the race is decided (RaceSetup.finish)."""
        self._t_race = t_race
        truth = np.array([states.get(name, np.full(6, np.nan)) for name in self.names], dtype=float)
        answer = WorldPacket(truth=truth, t_race=t_race)
        if len(states) == len(self.names):
            for ev in self.referee.observe(t_race, truth):
                entry = self.referee.log_entry(ev)
                if entry is not None:
                    answer.events.append((t_race, *entry))
            ref = self.referee
            if ref.winner is not None and (self.setup.finish == "first" or ref.all_finished):
                answer.winner = ref.winner
        return answer

    def close(self) -> WorldSummary:
        if hasattr(self.feed, "close"):
            self.feed.close()
        ref = self.referee
        order = ref.finish_order
        decided = ref.winner is not None and (self.setup.finish == "first" or ref.all_finished)
        return WorldSummary(winner=ref.winner if decided else None, lap_times_s=ref.lap_times_s,
                            min_gap_m=ref.min_gap_m if math.isfinite(ref.min_gap_m) else None,
                            collisions=list(ref.collisions), race_time_s=self._t_race, finish_order=order,
                            results=ref.results(order, ref.lap_times_s, self.setup.laps),
                            off_track=dict(ref.off_track))
