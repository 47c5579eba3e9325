"""The loop stops a race whose cars have been held neutral too long (`--stop-after-hold`,
LoopConfig.stop_after_hold_s; docs/race-stack.md), instead of waiting for the time limit (HIL seed 16
of the loop bench sat 58 s with both cars lost)."""
from __future__ import annotations

import pytest

from race.config import LoopConfig, LoopConfigError
from test_loop_support import load_json, run_cli

HOLD_S = 0.5
PERIOD = 1 / 60
MARGIN = 0.1  # scheduling slack on a shared machine


def test_stop_after_hold_is_validated():
    with pytest.raises(LoopConfigError, match="stop_after_hold_s"):
        LoopConfig(stop_after_hold_s=0.0)
    with pytest.raises(SystemExit, match="--stop-after-hold must be positive"):
        run_cli(["race", "--hil", "--stop-after-hold", "-1"])


@pytest.fixture(scope="module")
def occluded_race(tmp_path_factory):
    d = tmp_path_factory.mktemp("hold")
    out, js = d / "hil.rrd", d / "hil.json"
    # both markers covered from 0.3 s for far longer than the race may sit neutral
    code = run_cli(["race", "--hil", "--seed", "2", "--max-time", "10", "--fault", "occlude@0.3+30",
                    "--stop-after-hold", str(HOLD_S), "--out", str(out), "--json", str(js)])
    return code, load_json(js)


def test_race_stops_after_the_hold_limit(occluded_race):
    code, s = occluded_race
    assert code == 1  # stopped, like a fault: not a finished race
    assert s["end_reason"] == "held_neutral"
    assert s["events"].get("stop") == 1
    assert s["race_time_s"] < 0.3 + 0.25 + HOLD_S + 1.0  # nowhere near the 10 s limit


def test_stop_comes_hold_limit_after_the_hold_began(occluded_race):
    from race.review import events
    from race.recording import load_recording

    _, s = occluded_race
    evs = events(load_recording(s["recording"]))
    stop = next(e for e in evs if e["kind"] == "stop")
    assert "held neutral" in stop["text"] and "lost" in stop["text"]
    # the unbroken stretch of holds: the first fault after the last "racing again" before the stop
    resumed = [e["time_s"] for e in evs if e["kind"] == "recovered" and "racing again" in e["text"]
               and e["time_s"] < stop["time_s"]]
    start = min(e["time_s"] for e in evs if e["kind"] == "fault" and e["time_s"] >= max(resumed, default=0.0))
    assert HOLD_S <= stop["time_s"] - start <= HOLD_S + 2 * PERIOD + MARGIN
