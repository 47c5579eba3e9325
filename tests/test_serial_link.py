"""End-to-end tests: SerialCarLink -> pseudo-terminal -> VirtualCarBox.

Timing assertions are limited to the protocol's own timing (send rate, 100 ms failsafe)
and use generous margins: the test machine is shared and slow.
"""
from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from vehicles.protocol import NEUTRAL, CarCommand, FrameDecoder, encode_frame
from vehicles.serial_link import SerialCarLink, SerialLinkError
from vehicles.virtual_box import VirtualCarBox

REPO_ROOT = Path(__file__).resolve().parents[1]


def wait_until(predicate, timeout: float = 3.0, interval: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return predicate()


class Recorder:
    """Thread-safe log of VirtualCarBox.on_commands calls."""

    def __init__(self):
        self._lock = threading.Lock()
        self.calls: list[tuple[float, dict[int, CarCommand]]] = []

    def __call__(self, commands, t):
        with self._lock:
            self.calls.append((t, commands))

    def snapshot(self):
        with self._lock:
            return list(self.calls)

    def nth(self, n: int, timeout: float = 3.0):
        """The n-th call (1-based), waiting for it: the box updates its state, then calls back."""
        assert wait_until(lambda: len(self.snapshot()) >= n, timeout=timeout)
        return self.snapshot()[n - 1]


@pytest.fixture
def recorder():
    return Recorder()


@pytest.fixture
def box(recorder):
    with VirtualCarBox(on_commands=recorder) as virtual_box:
        yield virtual_box


@pytest.fixture
def raw_writer(box):
    """A second writer on the box's pty: injects bytes the way a misbehaving sender would."""
    fd = os.open(box.path, os.O_WRONLY | os.O_NOCTTY)
    yield fd
    os.close(fd)


def drained(box: VirtualCarBox, link: SerialCarLink) -> bool:
    """Every frame the link wrote has been accepted by the box."""
    return box.stats.frames_received == link.stats.frames_sent


# ---------------------------------------------------------------------------- input validation
def test_nan_and_inf_rejected_naming_car_and_field():
    link = SerialCarLink("loop://", handle_signals=False)
    link.set_commands({1: CarCommand(0.1, 0.2)})
    with pytest.raises(ValueError, match="car 3 steering is NaN"):
        link.set_commands({1: CarCommand(0.5, 0.5), 3: CarCommand(math.nan, 0.0)})
    with pytest.raises(ValueError, match="car 1 throttle is infinite"):
        link.set_commands({1: CarCommand(0.0, math.inf)})
    with pytest.raises(ValueError, match="car 2: expected CarCommand"):
        link.set_commands({2: (0.0, 0.0)})
    with pytest.raises(ValueError, match="car id 300"):
        link.set_commands({300: NEUTRAL})
    # A rejected call changes nothing.
    assert link.commands == {1: CarCommand(0.1, 0.2)}


def test_values_clamped_to_limits_and_counted():
    link = SerialCarLink("loop://", max_abs_throttle=0.5, handle_signals=False)
    link.set_commands({1: CarCommand(-2.0, 0.9), 2: CarCommand(0.3, -0.4)})
    assert link.commands == {1: CarCommand(-1.0, 0.5), 2: CarCommand(0.3, -0.4)}
    assert link.stats.clamped_values == 2


def test_cars_left_out_of_a_command_set_become_neutral():
    link = SerialCarLink("loop://", car_ids=[7], handle_signals=False)
    link.set_commands({1: CarCommand(0.1, 0.2), 2: CarCommand(0.3, 0.4)})
    link.set_commands({2: CarCommand(0.5, 0.6)})
    assert link.commands == {1: NEUTRAL, 2: CarCommand(0.5, 0.6), 7: NEUTRAL}


@pytest.mark.parametrize("kwargs, field", [
    ({"rate_hz": 0}, "rate_hz"), ({"rate_hz": math.nan}, "rate_hz"), ({"rate_hz": 1000}, "rate_hz"),
    ({"baudrate": 0}, "baudrate"), ({"max_abs_steering": 1.5}, "max_abs_steering"),
    ({"write_timeout": 0}, "write_timeout"),
])
def test_bad_constructor_arguments(kwargs, field):
    with pytest.raises(ValueError, match=field):
        SerialCarLink("loop://", **kwargs)


def test_unopenable_port_is_a_clear_error():
    with pytest.raises(SerialLinkError, match="/nonexistent/tty"):
        SerialCarLink("/nonexistent/tty", handle_signals=False).start()


# ---------------------------------------------------------------------------- loop:// transport
def test_loop_url_frames_decode_in_sequence(tmp_path):
    from vehicles.link_capture import LinkCapture, read_capture

    capture = LinkCapture(tmp_path / "link.txt")
    link = SerialCarLink("loop://", rate_hz=100, car_ids=[3], handle_signals=False, capture=capture)
    link.set_commands({3: CarCommand(0.25, 0.5)})
    with link:
        assert wait_until(lambda: link.stats.frames_sent >= 5)
    capture.close()
    # loop:// echoes writes back on the same port: the link reads them as the box's answer (rx).
    echoed = b"".join(r.data for r in read_capture(tmp_path / "link.txt") if r.direction == "rx")
    assert link.stats.bytes_received == len(echoed)
    decoded = FrameDecoder().feed(echoed)
    assert len(decoded) >= 5
    assert [f.seq for f in decoded] == list(range(len(decoded)))
    assert decoded[0].commands == {3: NEUTRAL}
    assert decoded[1].commands[3].throttle == pytest.approx(0.5, abs=1e-4)


# ---------------------------------------------------------------------------- link -> pty -> box
def test_neutral_on_start_and_stop(box, recorder):
    link = SerialCarLink(box.path, rate_hz=50, car_ids=[1, 2], handle_signals=False)
    with link:
        first_t, first = recorder.nth(1)
        assert first == {1: NEUTRAL, 2: NEUTRAL}
        link.set_commands({1: CarCommand(0.2, 0.6), 2: CarCommand(-0.2, 0.4)})
        assert wait_until(lambda: box.latest()[1].command.throttle > 0.5)
    assert wait_until(lambda: drained(box, link))
    # latest() ignores the failsafe, so this is the last frame the link sent: neutral.
    latest = box.latest()
    assert latest[1].command == NEUTRAL and latest[2].command == NEUTRAL
    assert latest[1].seq == link.stats.last_seq
    assert link.stats.neutral_frames_sent >= 2


def test_commands_arrive_in_order_at_the_configured_rate(box, recorder):
    rate_hz = 50.0
    link = SerialCarLink(box.path, rate_hz=rate_hz, car_ids=[1], handle_signals=False)
    throttles = [i / 10 for i in range(10)]
    with link:
        t_start = time.monotonic()
        for throttle in throttles:
            link.set_commands({1: CarCommand(0.0, throttle)})
            time.sleep(0.05)
        elapsed = time.monotonic() - t_start
    assert wait_until(lambda: drained(box, link))
    stats = box.stats.decoder
    assert stats.rejected == 0 and stats.frames_missed == 0
    assert stats.frames_ok == link.stats.frames_sent
    nonzero = [cmds[1].throttle for _, cmds in recorder.snapshot() if cmds[1].throttle > 0]
    # Every value received is one that was set, in the order set, and the last one arrived.
    assert nonzero == sorted(nonzero)
    assert set(round(v, 3) for v in nonzero) <= set(throttles)
    assert round(nonzero[-1], 3) == throttles[-1]
    # Rate: frames between start and stop, and their spacing at the box, match rate_hz.
    expected_frames = elapsed * rate_hz
    assert 0.6 * expected_frames <= link.stats.frames_sent <= 1.4 * expected_frames + 2
    times = sorted(t for t, _ in recorder.snapshot())
    intervals = sorted(b - a for a, b in zip(times, times[1:]))
    median = intervals[len(intervals) // 2]
    assert 0.6 / rate_hz <= median <= 1.4 / rate_hz


def test_neutral_sends_immediately(box):
    link = SerialCarLink(box.path, rate_hz=2, car_ids=[1], handle_signals=False)  # slow ticks
    with link:
        link.set_commands({1: CarCommand(0.0, 0.7)})
        assert wait_until(lambda: box.latest().get(1) and box.latest()[1].command.throttle > 0.6)
        link.neutral()
        # The next tick is up to 500 ms away, so seeing neutral within 200 ms means it was sent at once.
        assert wait_until(lambda: box.latest()[1].command == NEUTRAL, timeout=0.2)
        assert link.commands == {1: NEUTRAL}


def test_failsafe_neutral_after_sender_goes_silent(box, recorder, raw_writer):
    for seq in range(3):
        os.write(raw_writer, encode_frame(500 + seq, {4: CarCommand(0.3, 0.8)}))
        time.sleep(0.01)
    assert wait_until(lambda: box.stats.frames_received == 3)
    t_last = box.latest()[4].t_received
    assert wait_until(lambda: box.failsafe_active, timeout=2.0)
    assert box.stats.failsafe_events == 1 and box.failsafe_log()[0].reason == "timeout"
    t_failsafe, commands = recorder.nth(4)
    assert commands == {4: NEUTRAL}
    silence = t_failsafe - t_last
    assert 0.1 <= silence <= 0.1 + 0.15, silence
    # The simulator-facing view agrees, evaluated at exact times.
    assert box.commands_at(t_last + 0.05)[4].throttle == pytest.approx(0.8, abs=1e-4)
    assert box.commands_at(t_last + 0.101) == {4: NEUTRAL}
    assert box.commands_at(t_last - 1.0) == {4: NEUTRAL}  # before any frame
    # A restarted sender (sequence back at 0) is accepted after the failsafe.
    os.write(raw_writer, encode_frame(0, {4: CarCommand(0.0, 0.1)}))
    assert wait_until(lambda: not box.failsafe_active)
    assert box.latest()[4].command.throttle == pytest.approx(0.1, abs=1e-4)


def _frame_with_bad_crc(seq: int, commands) -> bytes:
    frame = bytearray(encode_frame(seq, commands))
    frame[-1] ^= 0x01  # CRC-16 detects every single-bit error
    return bytes(frame)


def test_corrupt_frame_makes_every_car_neutral_at_once_until_the_next_valid_frame(box, recorder, raw_writer):
    driving = {4: CarCommand(0.3, 0.8), 5: CarCommand(-0.2, 0.6)}
    os.write(raw_writer, encode_frame(100, driving))
    assert wait_until(lambda: box.stats.frames_received == 1)
    t_valid = box.latest()[4].t_received
    os.write(raw_writer, _frame_with_bad_crc(101, driving))
    assert wait_until(lambda: box.failsafe_active, timeout=1.0)
    [event] = box.failsafe_log()
    # Neutral on the read that carried the corrupt frame: the 100 ms silence timer cannot have run out
    # (the box stamps the read; it is after the valid frame and before the timeout would have fired).
    assert event.reason == "corrupt" and event.last_valid_t == t_valid
    assert t_valid < event.t < t_valid + 0.1
    t_neutral, commands = recorder.nth(2)
    assert t_neutral == event.t and commands == {4: NEUTRAL, 5: NEUTRAL}
    assert box.commands_at(event.t) == {4: NEUTRAL, 5: NEUTRAL}
    assert box.commands_at(event.t - 1e-6)[4].throttle == pytest.approx(0.8, abs=1e-4)  # frame in effect before
    stats = box.stats
    assert stats.decoder.bad_crc == 1 and stats.failsafe_by_reason == {
        "timeout": 0, "corrupt": 1, "hangup": 0, "read_error": 0}
    # More damage while neutral is not a new failsafe event.
    os.write(raw_writer, bytes(range(0x10, 0x30)))
    assert wait_until(lambda: box.stats.line_errors == 2)
    assert box.stats.failsafe_events == 1
    # The next valid frame (the sequence continues: a corrupt stream does not reset it) resumes commands.
    os.write(raw_writer, encode_frame(102, {4: CarCommand(0.0, 0.1)}))
    assert wait_until(lambda: not box.failsafe_active)
    t_resumed = box.latest()[4].t_received
    assert box.commands_at(t_resumed) == {4: CarCommand(0.0, pytest.approx(0.1, abs=1e-4)), 5: NEUTRAL}


def test_damage_after_the_last_valid_frame_of_a_read_wins(box, recorder, raw_writer):
    """Within one read the order of the bytes decides: valid-then-damaged is neutral,
    damaged-then-valid is the valid frame's commands."""
    go = {1: CarCommand(0.0, 0.5)}
    os.write(raw_writer, _frame_with_bad_crc(10, go) + encode_frame(11, go))
    assert wait_until(lambda: box.stats.frames_received == 1)
    assert not box.failsafe_active and box.stats.failsafe_events == 0
    os.write(raw_writer, encode_frame(12, go) + b"\x00\x13\x37")  # stray bytes after the frame
    assert wait_until(lambda: box.stats.frames_received == 2)
    assert wait_until(lambda: box.failsafe_active, timeout=1.0)
    [event] = box.failsafe_log()
    assert event.reason == "corrupt" and event.t == event.last_valid_t  # same read
    assert box.commands_at(event.t) == {1: NEUTRAL}


def test_stale_frames_are_not_a_corrupt_stream(box, raw_writer):
    go = {1: CarCommand(0.0, 0.5)}
    os.write(raw_writer, encode_frame(20, go))
    assert wait_until(lambda: box.stats.frames_received == 1)
    os.write(raw_writer, encode_frame(20, go) + encode_frame(19, go))  # duplicate, out of order
    assert wait_until(lambda: box.stats.decoder.stale == 2)
    assert box.stats.failsafe_events == 0 and box.stats.line_errors == 0


def test_host_hanging_up_makes_every_car_neutral_at_once(box, recorder):
    fd = os.open(box.path, os.O_WRONLY | os.O_NOCTTY)
    os.write(fd, encode_frame(7, {2: CarCommand(0.1, 0.9)}))
    assert wait_until(lambda: box.stats.frames_received == 1)
    t_valid = box.latest()[2].t_received
    t_closed = time.monotonic()
    os.close(fd)  # the only writer: the host closed the port (USB unplugged, process gone)
    assert wait_until(lambda: box.failsafe_active, timeout=1.0)
    [event] = box.failsafe_log()
    assert event.reason == "hangup" and event.last_valid_t == t_valid
    assert t_closed <= event.t < t_valid + 0.1  # before the silence timer could have fired
    assert box.commands_at(event.t) == {2: NEUTRAL}
    assert recorder.nth(2) == (event.t, {2: NEUTRAL})
    assert box.stats.hangups == 1
    # A new host (sequence back at 0) is accepted at once, and its hang-up is seen again.
    fd = os.open(box.path, os.O_WRONLY | os.O_NOCTTY)
    os.write(fd, encode_frame(0, {2: CarCommand(0.0, 0.2)}))
    assert wait_until(lambda: not box.failsafe_active)
    os.close(fd)
    assert wait_until(lambda: box.stats.hangups == 2 and box.failsafe_active, timeout=1.0)
    assert box.stats.failsafe_by_reason["hangup"] == 2 and box.stats.failsafe_by_reason["timeout"] == 0


def test_link_process_dying_is_a_hang_up_not_a_timeout(box, tmp_path):
    script = tmp_path / "child.py"
    script.write_text(CHILD_SCRIPT)
    child = subprocess.Popen([sys.executable, str(script), str(REPO_ROOT), box.path, "wait"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert wait_until(lambda: box.latest().get(1) and box.latest()[1].command.throttle > 0.5, timeout=10)
        child.kill()  # SIGKILL: no neutral frame, no stop(); the kernel closes the device
        child.wait(timeout=10)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert wait_until(lambda: box.failsafe_active, timeout=1.0)
    event = box.failsafe_log()[-1]
    assert event.reason == "hangup" and event.t - event.last_valid_t < 0.1


def test_link_stopping_without_neutral_is_caught_by_failsafe(box):
    link = SerialCarLink(box.path, rate_hz=50, handle_signals=False)
    link.set_commands({2: CarCommand(0.0, 0.5)})
    link.start()
    assert wait_until(lambda: box.latest().get(2) and box.latest()[2].command.throttle > 0.4)
    # Simulate a hung sender: stop the thread without the final neutral frame.
    link._stop_event.set()
    link._thread.join(timeout=2)
    t_stop = time.monotonic()
    assert wait_until(lambda: box.failsafe_active, timeout=2.0)
    assert box.current_commands() == {2: NEUTRAL}
    assert time.monotonic() - t_stop <= 0.1 + 0.3
    link.stop()


def test_injected_corrupt_bytes_are_counted_and_never_acted_on(box, recorder, raw_writer):
    link = SerialCarLink(box.path, rate_hz=50, car_ids=[1], handle_signals=False)
    dangerous = {1: CarCommand(1.0, 1.0)}
    with link:
        link.set_commands({1: CarCommand(0.0, 0.2)})
        time.sleep(0.05)
        # Sequence numbers far ahead: if any of these were accepted, the link's own frames
        # would be rejected as out of order afterwards.
        bad_crc = bytearray(encode_frame(30000, dangerous))
        bad_crc[-1] ^= 0x40
        flipped_payload = bytearray(encode_frame(30001, dangerous))
        flipped_payload[8] ^= 0x01
        wrong_version = bytearray(encode_frame(30002, dangerous))
        wrong_version[2] = 9
        truncated = encode_frame(30003, dangerous)[:9]
        garbage = bytes(range(0x60, 0xA0)) * 3  # contains no 0xA5
        for chunk in (bad_crc, garbage, flipped_payload, wrong_version, truncated):
            os.write(raw_writer, bytes(chunk))
            time.sleep(0.03)  # let the link's frames interleave
        time.sleep(0.05)
    assert wait_until(lambda: drained(box, link))
    stats = box.stats.decoder
    assert stats.bad_crc == 2
    assert stats.bad_version == 1
    assert stats.truncated == 1
    assert stats.stale == 0 and stats.frames_missed == 0
    assert stats.bytes_discarded >= len(garbage)
    assert all(cmds[1].throttle <= 0.2 + 1e-4 and cmds[1].steering == 0 for _, cmds in recorder.snapshot())


def test_device_vanishing_is_reported_as_fault(box):
    faults = []
    link = SerialCarLink(box.path, rate_hz=50, car_ids=[1], on_fault=faults.append, handle_signals=False)
    link.start()
    link.set_commands({1: CarCommand(0.0, 0.3)})
    assert wait_until(lambda: box.stats.frames_received >= 3)
    box.close()
    assert link.wait_fault(timeout=2.0)
    assert link.fault and not link.running
    assert len(faults) == 1 and isinstance(faults[0], OSError)
    stats = link.stats
    assert stats.write_errors >= 1 and "Input/output error" in stats.last_error
    # The app loop keeps calling the link after the fault: no exception, no resurrection.
    link.set_commands({1: CarCommand(0.0, 0.5)})
    link.neutral()
    link.stop()
    assert not link._thread.is_alive()
    assert link.stats.frames_sent == stats.frames_sent


# ---------------------------------------------------------------------------- exit hooks
def test_signal_handlers_installed_and_restored():
    before_int, before_term = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    link = SerialCarLink("loop://")
    with link:
        assert signal.getsignal(signal.SIGINT) == link._handle_signal
        assert signal.getsignal(signal.SIGTERM) == link._handle_signal
    assert signal.getsignal(signal.SIGINT) == before_int
    assert signal.getsignal(signal.SIGTERM) == before_term


CHILD_SCRIPT = textwrap.dedent("""
    import signal, sys, time
    # A shell's background job starts with SIGINT ignored; the test is about Python's default handler.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    sys.path.insert(0, sys.argv[1])
    from vehicles.protocol import CarCommand
    from vehicles.serial_link import SerialCarLink
    link = SerialCarLink(sys.argv[2], rate_hz=50)
    link.start()
    link.set_commands({1: CarCommand(0.1, 0.6)})
    if sys.argv[3] == "exit":
        time.sleep(0.3)
        sys.exit(0)  # no stop(): the atexit hook must send neutral
    time.sleep(30)  # killed by the test's signal long before this
""")


@pytest.mark.parametrize("how", ["SIGINT", "SIGTERM", "exit"])
def test_neutral_sent_when_process_is_interrupted_or_exits(box, tmp_path, how):
    script = tmp_path / "child.py"
    script.write_text(CHILD_SCRIPT)
    child = subprocess.Popen([sys.executable, str(script), str(REPO_ROOT), box.path, how],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert wait_until(lambda: box.latest().get(1) and box.latest()[1].command.throttle > 0.5, timeout=10)
        if how != "exit":
            child.send_signal(getattr(signal, how))
        _, stderr = child.communicate(timeout=10)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    if how == "SIGINT":
        assert "KeyboardInterrupt" in stderr  # chained to Python's default handler
    elif how == "SIGTERM":
        assert child.returncode == -signal.SIGTERM  # default action re-delivered
    else:
        assert child.returncode == 0, stderr
    # The last frame received (failsafe aside) is the neutral one sent on the way out.
    assert wait_until(lambda: box.latest()[1].command == NEUTRAL, timeout=1.0)
