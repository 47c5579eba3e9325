"""The race loop's feed on motion capture (race.world.Feed): each poll's newest mocap frame
(tracking.mocap.MocapFrame, where a camera frame would be) and the source's fault events (kind ``mocap``).

On hardware the feed is the mocap source alone. In HIL (``race --hil --mocap``) it also passes on the
simulated world's packets (events, winner, serial reports) and the simulator's truth of the mocap frame's
own snapshot, matched by frame number (the world streams snapshot k over NatNet as frame k and sends its
truth through its pipe). Matching by number holds whatever the network and scheduling delays; a frame
whose truth has not arrived is passed on without one (no tracking-error sample).
"""
from __future__ import annotations

import collections
import time

from race.world import WorldPacket

# Truths kept for frames still on their way (snapshots arrive at the mocap rate, at most a few hundred per
# second; the loop reads a frame within a tick of its arrival).
TRUTHS_KEPT = 256


class MocapFeed:
    """``source``: tracking.natnet.NatNetSource (``read()``, ``events()``, ``close()``); ``world``: the HIL
    world (None on hardware). With a world the feed is that world to the loop (race.world.World: ``go``,
    ``observe`` and ``close`` go to it), its frames replaced by the mocap source's."""

    def __init__(self, source, world=None, wait_step_s: float = 0.001) -> None:
        self.source, self.world, self.wait_step_s = source, world, wait_step_s
        self._truths: collections.OrderedDict = collections.OrderedDict()  # frame number -> (truth, t_race)
        self.truth_matched = 0
        self.truth_missing = 0

    def poll(self, timeout: float = 0.0) -> WorldPacket:
        deadline = time.monotonic() + timeout
        frame = self.source.read()
        while frame is None and time.monotonic() < deadline:
            time.sleep(self.wait_step_s)
            frame = self.source.read()
        packet = self.world.poll(0.0) if self.world is not None else WorldPacket()
        packet.events.extend((None, "mocap", text) for _, text in self.source.events())
        if self.world is None:
            packet.frame = frame
            return packet
        for index, truth, t_race in packet.truths:
            self._truths[index] = (truth, t_race)
            while len(self._truths) > TRUTHS_KEPT:
                self._truths.popitem(last=False)
        packet.frame, packet.truth, packet.t_race, packet.truths = frame, None, None, []
        if frame is not None:
            match = self._truths.get(frame.index)
            if match is not None:
                packet.truth, packet.t_race = match
                self.truth_matched += 1
            else:
                self.truth_missing += 1
        return packet

    def go(self, t_go: float) -> None:
        self.world.go(t_go)

    def observe(self, t_race: float, states: dict) -> WorldPacket:
        return self.world.observe(t_race, states)

    def close(self):
        """Close the source, then the world; the world's summary (None on hardware)."""
        self.source.close()
        return self.world.close() if self.world is not None else None
