"""The loop's one command history (race.command_history): what the loop writes is what the estimator
(CarEKF.accel_input) and the planners (PlanJob.in_flight) read, checked on hand-worked logs."""
from __future__ import annotations

import numpy as np

from race.command_history import KEEP_S, CommandHistory
from race.planning import PlanJob


def close(got, expected) -> bool:
    return len(got) == len(expected) and np.allclose(np.array(got, dtype=float), np.array(expected, dtype=float))


def test_a_new_entry_only_when_the_control_changes():
    h = CommandHistory()
    h.record("a", 1.00, (1.0, 0.1))
    h.record("a", 1.02, (1.0, 0.1))  # same control: still acting since 1.00
    h.record("a", 1.04, (2.0, 0.1))
    assert close(h.between("a", 1.0, 1.1), [(0.04, 1.0, 0.1), (0.06, 2.0, 0.1)])


def test_no_model_control_empties_the_car_history():
    h = CommandHistory()
    h.record("p", 1.0, (1.0, 0.0))
    h.record("p", 1.1, None)  # e.g. pure pursuit: nothing to predict with
    assert h.has("p") and not h.covers("p", 1.05) and h.between("p", 1.0, 2.0) == []
    assert not h.has("other")


def test_history_keeps_one_second():
    h = CommandHistory()
    for k in range(100):
        h.record("a", 0.1 * k, (float(k), 0.0))
    t_last = 9.9
    # the entry acting at t_last - KEEP_S is kept (it covers the start of the window), older ones dropped
    assert h.covers("a", t_last - KEEP_S) and not h.covers("a", t_last - KEEP_S - 0.1 - 1e-9)


def test_accel_input_gives_the_accelerations_of_the_window():
    h = CommandHistory()
    h.record("a", 0.0, (0.5, 0.2))
    h.record("a", 0.3, (-1.0, 0.2))
    accel = h.accel_input("a")
    assert close(accel(0.1, 0.5), [(0.2, 0.5), (0.2, -1.0)])
    h.record("a", 0.4, (2.0, 0.0))  # the estimator reads the live history
    assert close(accel(0.1, 0.5), [(0.2, 0.5), (0.1, -1.0), (0.1, 2.0)])


def test_snapshot_is_not_changed_by_later_records():
    h = CommandHistory()
    h.record("a", 0.0, (0.5, 0.0))
    snap = h.snapshot()
    h.record("a", 0.1, (1.5, 0.0))
    assert close(snap.between("a", 0.0, 0.2), [(0.2, 0.5, 0.0)])
    assert close(h.between("a", 0.0, 0.2), [(0.1, 0.5, 0.0), (0.1, 1.5, 0.0)])


def test_plan_job_in_flight_from_the_last_measured_pose():
    h = CommandHistory()
    h.record("a", 1.00, (1.0, 0.1))
    h.record("a", 1.05, (2.0, 0.2))
    state = np.arange(6.0)
    job = PlanJob(3, 1.10, {}, measured={"a": (1.02, state), "b": (1.02, state), "c": (0.90, state)},
                  commands=h.snapshot())
    got_state, segments = job.in_flight("a")
    np.testing.assert_array_equal(got_state, state)
    assert close(segments, [(0.03, 1.0, 0.1), (0.05, 2.0, 0.2)])
    assert job.in_flight("b") is None  # no command history (not commanded)
    h.record("c", 1.00, (1.0, 0.0))
    job = PlanJob(3, 1.10, {}, measured={"c": (0.90, state)}, commands=h.snapshot())
    assert job.in_flight("c") is None  # the pose is older than the history
    job = PlanJob(3, 1.10, {}, measured={"a": (1.10, state)}, commands=h.snapshot())
    assert job.in_flight("a") is None  # measured at t_plan: nothing in flight
    job = PlanJob(3, 1.10, {}, measured={"a": (1.02, np.full(6, np.nan))}, commands=h.snapshot())
    assert job.in_flight("a") is None
