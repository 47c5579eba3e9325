"""race.mocap_feed.MocapFeed in HIL: each mocap frame is paired with the truth of its own snapshot (by frame
number), whatever order the world's pipe and the mocap stream deliver them in; a frame whose truth has not
arrived gets none."""
from __future__ import annotations

import numpy as np

from race.mocap_feed import TRUTHS_KEPT, MocapFeed
from race.world import WorldPacket
from tracking.mocap import MocapFrame


class ScriptedSource:
    """A mocap source that yields the given frames, one per read."""

    def __init__(self, frames):
        self.frames = list(frames)

    def read(self):
        return self.frames.pop(0) if self.frames else None

    def events(self):
        return []

    def close(self):
        pass


class ScriptedWorld:
    """A HIL world whose polls deliver the given snapshot indices' truths (state row = [index, 0, ...])."""

    def __init__(self, deliveries):
        self.deliveries = list(deliveries)

    def poll(self, timeout=0.0):
        indices = self.deliveries.pop(0) if self.deliveries else []
        truths = [(k, np.full((2, 6), float(k)), 0.01 * k) for k in indices]
        newest = truths[-1] if truths else None
        return WorldPacket(truth=None if newest is None else newest[1], t_race=None if newest is None else newest[2],
                           truths=truths)


def _frame(index):
    return MocapFrame(t_capture_s=0.0, index=index, bodies={})


def test_each_frame_gets_its_own_snapshots_truth():
    # Poll 1: snapshots 0-2 arrived, the stream's newest frame is 1 (not the newest truth, 2).
    # Poll 2: nothing new from the world; frame 2 arrives (its truth came in poll 1).
    # Poll 3: frame 5 arrives before its truth: no truth, counted missing.
    feed = MocapFeed(ScriptedSource([_frame(1), _frame(2), _frame(5)]), ScriptedWorld([[0, 1, 2], [], [3, 4]]))
    got = [feed.poll() for _ in range(3)]
    assert got[0].truth[0, 0] == 1.0 and got[0].t_race == 0.01
    assert got[1].truth[0, 0] == 2.0 and got[1].t_race == 0.02
    assert got[2].truth is None and got[2].t_race is None
    assert (feed.truth_matched, feed.truth_missing) == (2, 1)
    assert all(p.truths == [] for p in got)  # consumed by the feed, not passed on to the loop


def test_old_truths_are_let_go():
    feed = MocapFeed(ScriptedSource([None, _frame(0), _frame(TRUTHS_KEPT + 9)]),
                     ScriptedWorld([list(range(TRUTHS_KEPT + 10))]))
    feed.poll()
    assert feed.poll().truth is None  # snapshot 0's truth was dropped: more than TRUTHS_KEPT came after it
    assert feed.poll().truth[0, 0] == TRUTHS_KEPT + 9
