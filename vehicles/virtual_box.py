"""A software stand-in for the radio transmitter box, on the far end of a pseudo-terminal.

``VirtualCarBox`` opens a pty pair on construction; ``path`` is the slave device that a
``SerialCarLink`` opens like a USB serial port. A reader thread decodes the byte stream
with ``FrameDecoder`` and keeps the commands in effect, applying the failsafes the real
box must have (docs/serial-protocol.md, "Transmitter box behaviour"): every car neutral
- at once on a corrupt stream (bytes that are not part of a valid frame), until the next
  valid frame;
- at once when the host hangs up (the last writer closes the device) or reading fails;
- when no valid frame has arrived for ``failsafe_timeout`` (100 ms).
A simulator reads ``commands_at(t)``; ``close()`` unplugs the device.

With ``protocol="buzzracer-fhss"`` it is the BuzzRacer FHSS box's firmware instead (vehicles/fhss.py):
its 0xAA 0x55 state machine, bad-CRC frames dropped silently, no corrupt or hang-up failsafe (the
firmware sees neither), every channel 1500 us after 100 ms without a valid frame, and free-form ASCII
debug text back to the host. Its commands are keyed by modem id (0..5, always all six) and carry the
pulses as ``vehicles.fhss.pulse_to_unit`` values (1500 us = 0): the car's receiver calibration turns
them into wheel angle and throttle.
"""
from __future__ import annotations

import bisect
import errno
import logging
import os
import select
import threading
import time
import tty
from collections import Counter, deque
from dataclasses import dataclass
from typing import Callable, Literal

from vehicles import fhss
from vehicles.protocol import MAX_CARS, NEUTRAL, CarCommand, DecodedFrame, DecoderStats, FrameDecoder

log = logging.getLogger(__name__)

_READ_SIZE = 4096
_FAILSAFE_LOG_LEN = 1024

FailsafeReason = Literal["timeout", "corrupt", "hangup", "read_error"]
FAILSAFE_REASONS: tuple[FailsafeReason, ...] = ("timeout", "corrupt", "hangup", "read_error")


@dataclass(frozen=True)
class ReceivedCommand:
    command: CarCommand
    t_received: float  # box clock (time.monotonic by default) when the frame was read
    seq: int  # sequence number of the frame that carried it


@dataclass(frozen=True)
class FailsafeEvent:
    """One transition from "commands in effect" to "every car neutral"."""

    t: float  # box clock when the box went neutral (for corrupt/hangup: the read that showed the fault)
    reason: FailsafeReason
    last_valid_t: float | None  # receive time of the last accepted frame before it
    detail: str  # e.g. "bad_crc 1, bytes_discarded 12" or the read error


@dataclass(frozen=True)
class BoxStats:
    frames_received: int  # valid frames acted on
    failsafe_events: int  # transitions from "receiving" to "failsafe neutral" (all reasons)
    failsafe_active: bool
    callback_errors: int  # exceptions raised by on_commands (logged, never fatal)
    decoder: DecoderStats | fhss.FhssParserStats  # rejected frames by reason (the protocol's decoder)
    failsafe_by_reason: dict[str, int]  # failsafe_events split by FailsafeReason (every reason present)
    line_errors: int  # reads that carried corrupt, truncated or stray bytes (whether or not receiving)
    hangups: int  # times the host closed the device (also while already neutral)
    coalesced_reads: int  # reads that carried more than one valid frame: the reader fell behind the sender


def _line_error_count(stats: DecoderStats) -> int:
    """Grows whenever the decoder rejects bytes as damaged: a corrupt or truncated frame or stray bytes.

    Stale frames (duplicate, out of order) are not counted: they passed the CRC, so the line is not
    damaged (a replayed or second sender is the timeout failsafe's business).
    """
    return stats.corrupt + stats.truncated + stats.bytes_discarded


class _OrderedDecoder(FrameDecoder):
    """FrameDecoder that notes the damage counter at each accepted frame, so that within one read
    the box knows whether damaged bytes came after the last valid frame (-> neutral) or before it."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.errors_at_accept: list[int] = []

    def _accept(self, frame_bytes: bytes) -> DecodedFrame | None:
        frame = super()._accept(frame_bytes)
        if frame is not None:
            self.errors_at_accept.append(_line_error_count(self.stats))
        return frame


class _FhssFirmware:
    """The FHSS box's parser behind the interface VirtualCarBox uses for its decoder (no inter-byte
    timeout, no sequence numbers: ``buffered`` is always 0, ``reset_sequence`` does nothing)."""

    gap_timeout = 0.0
    buffered = 0

    def __init__(self) -> None:
        self._parser = fhss.FhssParser()
        self.stats = self._parser.stats
        self.errors_at_accept: list[int] = []

    def feed(self, data, now=None) -> list[DecodedFrame]:
        frames = []
        for pulses in self._parser.feed(data):
            commands = {m: CarCommand(fhss.pulse_to_unit(pulses[fhss.steering_slot(m)]),
                                      fhss.pulse_to_unit(pulses[fhss.throttle_slot(m)])) for m in range(fhss.MAX_CARS)}
            frames.append(DecodedFrame(self._parser.stats.frames_ok % (1 << 16), commands))
            self.errors_at_accept.append(_line_error_count(self.stats))
        return frames

    def poll(self, now=None) -> list[DecodedFrame]:
        return []

    def flush(self) -> list[DecodedFrame]:
        return []

    def reset_sequence(self) -> None:
        pass


class CommandHistory:
    """What the box outputs over time: (t, complete command set) entries with ascending t, a frame's
    commands or a failsafe's neutral set. ``commands_at`` applies the silence failsafe, so it also
    answers for times after the last entry. Not thread-safe (VirtualCarBox locks around it)."""

    def __init__(self, failsafe_timeout: float, history_s: float = 5.0):
        self.failsafe_timeout = float(failsafe_timeout)
        self.history_s = float(history_s)
        self.known_cars: set[int] = set()
        # Parallel deques so commands_at can bisect the times.
        self._t: deque[float] = deque()
        self._commands: deque[dict[int, CarCommand]] = deque()

    def append(self, t: float, commands: dict[int, CarCommand]) -> None:
        self.known_cars |= commands.keys()
        self._t.append(t)
        self._commands.append(commands)
        while len(self._t) > 1 and t - self._t[0] > self.history_s:
            self._t.popleft()
            self._commands.popleft()

    def commands_at(self, t: float) -> dict[int, CarCommand]:
        """The last entry at or before ``t``, unless it is ``failsafe_timeout`` or more older than
        ``t`` (or there is none): then every car seen so far is neutral."""
        result = {car: NEUTRAL for car in self.known_cars}
        index = bisect.bisect_right(self._t, t) - 1
        if index >= 0 and t - self._t[index] < self.failsafe_timeout:
            result.update(self._commands[index])
        return result


class VirtualCarBox:
    """Pty-backed virtual transmitter box. Starts reading immediately; use as a context manager.

    ``on_commands(commands, t)`` is called from the reader thread with the complete
    command set (every car seen so far) after each accepted frame and once when a
    failsafe engages; ``on_failsafe(event)`` then too, after it. Both are called after the
    box's state (``latest``, ``stats``, ``failsafe_active``) shows the change, outside its lock,
    so a reader may see the new state a moment before the callback runs. ``clock`` must be monotonic; it timestamps received frames and is
    the time base of ``commands_at``. ``history_s`` seconds of frames are kept for it.
    ``max_cars`` is how many cars this box drives (its radio channels; default the protocol's maximum,
    16): a frame announcing more is damaged, and is known to be so from its header alone (a bit error
    in the car-count byte then trips the corrupt failsafe at once, not after the longer announced
    frame's worth of bytes).
    """

    def __init__(
        self,
        *,
        failsafe_timeout: float = 0.1,
        on_commands: Callable[[dict[int, CarCommand], float], None] | None = None,
        on_failsafe: Callable[[FailsafeEvent], None] | None = None,
        gap_timeout: float = 0.02,
        history_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        max_cars: int = MAX_CARS,
        protocol: str = "rd3g",
        chatter_every_s: float = 1.0,
    ):
        if not failsafe_timeout > 0:
            raise ValueError(f"failsafe_timeout must be > 0 seconds, got {failsafe_timeout!r}")
        if not 0 < gap_timeout < failsafe_timeout:
            raise ValueError(f"gap_timeout must be in (0, failsafe_timeout), got {gap_timeout!r}")
        if not history_s > failsafe_timeout:
            raise ValueError(f"history_s must exceed failsafe_timeout, got {history_s!r}")
        self.failsafe_timeout = float(failsafe_timeout)
        self.history_s = float(history_s)
        self.on_commands = on_commands
        self.on_failsafe = on_failsafe
        self._clock = clock
        if isinstance(max_cars, bool) or not isinstance(max_cars, int) or not 1 <= max_cars <= MAX_CARS:
            raise ValueError(f"max_cars must be an int in 1..{MAX_CARS} (cars the box drives), got {max_cars!r}")
        if protocol not in ("rd3g", "buzzracer-fhss"):
            raise ValueError(f"protocol must be rd3g or buzzracer-fhss, got {protocol!r}")
        self.protocol = protocol
        self._fhss = protocol == "buzzracer-fhss"
        self._decoder = _FhssFirmware() if self._fhss else _OrderedDecoder(
            gap_timeout=gap_timeout, clock=clock, max_cars=max_cars)
        self.chatter_every_s = float(chatter_every_s)
        self._next_chatter: float | None = None
        self._lock = threading.Lock()
        self._latest: dict[int, ReceivedCommand] = {}
        self._history = CommandHistory(failsafe_timeout, history_s)
        if self._fhss:  # the box drives all twelve channels from power-on
            self._history.known_cars = set(range(fhss.MAX_CARS))
        self._last_valid_t: float | None = None
        self._timed_out = False  # failsafe_timeout has passed since the last valid frame
        self._failsafe_active = True  # nothing received yet: cars are neutral
        self._failsafe_log: deque[FailsafeEvent] = deque(maxlen=_FAILSAFE_LOG_LEN)
        self._failsafe_counts: Counter[str] = Counter()
        self._frames_received = 0
        self._callback_errors = 0
        self._line_errors = 0
        self._hangups = 0
        self._coalesced_reads = 0
        self._closed = False

        self._master_fd, slave_fd = os.openpty()
        # Raw mode: no echo, no CR/LF translation, no signal characters - a byte pipe.
        tty.setraw(slave_fd)
        # Non-blocking: debug text that nobody reads is dropped, it never stalls the reader.
        os.set_blocking(self._master_fd, False)
        self.path = os.ttyname(slave_fd)
        # While no host is attached the box holds the slave open itself, so the master does not
        # report a hang-up. It lets go once bytes arrive: from then on "every writer closed the
        # device" shows as EIO on the master, which is the host hanging up.
        self._holder_fd: int | None = slave_fd
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name=f"VirtualCarBox({self.path})", daemon=True)
        if self._fhss:
            self._next_chatter = clock() + self.chatter_every_s
        self._thread.start()

    # ------------------------------------------------------------------ public API
    def commands_at(self, t: float) -> dict[int, CarCommand]:
        """Commands in effect at time ``t`` (box clock) for every car seen so far.

        That is the box's output after the last event at or before ``t`` (an accepted frame or
        a failsafe), unless the last frame is ``failsafe_timeout`` or more older than ``t``
        (or there is none): then every car is neutral.
        """
        with self._lock:
            return self._history.commands_at(t)

    def current_commands(self) -> dict[int, CarCommand]:
        return self.commands_at(self._clock())

    def latest(self) -> dict[int, ReceivedCommand]:
        """Last received command per car with its receive time (ignores the failsafe)."""
        with self._lock:
            return dict(self._latest)

    def failsafe_log(self) -> list[FailsafeEvent]:
        """The failsafe events, oldest first (the last 1024)."""
        with self._lock:
            return list(self._failsafe_log)

    @property
    def failsafe_active(self) -> bool:
        with self._lock:
            return self._failsafe_active

    @property
    def stats(self) -> BoxStats:
        with self._lock:
            return BoxStats(
                frames_received=self._frames_received,
                failsafe_events=sum(self._failsafe_counts.values()),
                failsafe_active=self._failsafe_active,
                callback_errors=self._callback_errors,
                decoder=self._decoder.stats.copy(),
                failsafe_by_reason={reason: self._failsafe_counts[reason] for reason in FAILSAFE_REASONS},
                line_errors=self._line_errors,
                hangups=self._hangups,
                coalesced_reads=self._coalesced_reads,
            )

    def close(self) -> None:
        """Stop the reader and close the pty: to the link this is the device vanishing."""
        if self._closed:
            return
        self._closed = True
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass
        self._thread.join(timeout=2.0)
        if self._thread.is_alive():
            log.error("reader thread of %s did not stop in time", self.path)
        for fd in (self._master_fd, self._holder_fd, self._wake_r, self._wake_w):
            if fd is None:
                continue
            try:
                os.close(fd)
            except OSError:
                pass
        self._holder_fd = None

    def __enter__(self) -> "VirtualCarBox":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # ------------------------------------------------------------------ reader thread
    def _say(self, text: str) -> None:
        """FHSS firmware debug text to the host (dropped if the host does not read it)."""
        try:
            os.write(self._master_fd, (text + "\r\n").encode("ascii"))
        except OSError:
            pass

    def _chatter(self, now: float) -> None:
        if self._next_chatter is None or now < self._next_chatter:
            return
        self._next_chatter = now + self.chatter_every_s
        stats = self._decoder.stats
        self._say(f"frames {self._frames_received} crc_err {stats.corrupt} skipped {stats.bytes_discarded}")

    def _run(self) -> None:
        while True:
            readable, _, _ = select.select([self._master_fd, self._wake_r], [], [], self._wait_timeout())
            if self._wake_r in readable:
                return
            now = self._clock()
            if self._master_fd not in readable:
                self._process(b"", now)
            else:
                try:
                    data = os.read(self._master_fd, _READ_SIZE)
                except OSError as exc:
                    if exc.errno in (errno.EAGAIN, errno.EINTR):
                        continue
                    if exc.errno != errno.EIO:  # EIO is the pty's "no writer left"
                        self._engage(now, "read_error", f"{type(exc).__name__}: {exc}")
                        log.error("reading %s failed: %s; reader stops", self.path, exc)
                        return
                    data = b""
                if not data:  # EIO on Linux, end of file elsewhere: the host hung up
                    if not self._hang_up(now):
                        return
                    continue
                self._release_holder()
                self._process(data, now)
            self._check_timeout(self._clock())
            self._chatter(self._clock())

    def _release_holder(self) -> None:
        if self._holder_fd is not None:
            os.close(self._holder_fd)
            self._holder_fd = None
            if self._fhss:  # a host attached (opening the port, pyserial flushed what was there before)
                self._say(f"BuzzRacer FHSS box (emulated): {fhss.MAX_CARS} modems, failsafe "
                          f"{1e3 * self.failsafe_timeout:.0f} ms")

    def _hang_up(self, now: float) -> bool:
        """Every writer closed the device: neutral at once, then wait for the next host.
        Returns False if the device cannot be held open again (the reader must stop)."""
        with self._lock:
            frames = self._decoder.flush()  # a partial frame left behind is truncated
            self._decoder.errors_at_accept.clear()
            self._hangups += 1
        for frame in frames:
            self._apply(frame, now)
        if not self._fhss:  # the FHSS firmware cannot see the host go: its timeout acts
            self._engage(now, "hangup", "host closed the serial device")
        with self._lock:
            # A new host is a new sender: accept its first frame whatever its sequence number.
            self._decoder.reset_sequence()
        # Hold the line again, or the master keeps reporting the hang-up (a busy loop).
        try:
            self._holder_fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY)
            tty.setraw(self._holder_fd)
        except OSError as exc:
            log.error("%s: cannot reopen after the hang-up (%s); reader stops", self.path, exc)
            return False
        return True

    def _process(self, data: bytes, now: float) -> None:
        with self._lock:
            errors_before = _line_error_count(self._decoder.stats)
            frames = self._decoder.feed(data, now) if data else self._decoder.poll(now)
            errors_after = _line_error_count(self._decoder.stats)
            errors_at_accept = self._decoder.errors_at_accept
            self._decoder.errors_at_accept = []
            if len(frames) > 1:
                self._coalesced_reads += 1
            if errors_after > errors_before:
                self._line_errors += 1
            stats = self._decoder.stats
        for frame in frames:
            self._apply(frame, now)
        # Damage after the last valid frame of this read (or with no valid frame): the stream
        # is corrupt now, whatever the last valid frame said.
        last_good = errors_at_accept[-1] if errors_at_accept else errors_before
        if errors_after > last_good and not self._fhss:  # the FHSS firmware drops bad frames silently
            self._engage(now, "corrupt", f"corrupt {stats.corrupt}, truncated {stats.truncated}, "
                                         f"bytes discarded {stats.bytes_discarded} so far")

    def _wait_timeout(self) -> float | None:
        """Sleep until data, the failsafe deadline or the decoder's inter-byte timeout."""
        now = self._clock()
        deadlines = []
        with self._lock:
            if not self._timed_out and self._last_valid_t is not None:
                deadlines.append(self._last_valid_t + self.failsafe_timeout)
            if self._decoder.buffered:
                # Small slack so the decoder sees the gap as strictly exceeded.
                deadlines.append(now + self._decoder.gap_timeout + 1e-3)
            if self._next_chatter is not None:
                deadlines.append(self._next_chatter)
        return max(0.0, min(deadlines) - now) if deadlines else None

    def _apply(self, frame: DecodedFrame, t: float) -> None:
        with self._lock:
            # A frame is the complete command set: a known car it omits is commanded neutral.
            known = self._history.known_cars | frame.commands.keys()
            commands = {car: frame.commands.get(car, NEUTRAL) for car in known}
            self._latest = {car: ReceivedCommand(cmd, t, frame.seq) for car, cmd in commands.items()}
            self._history.append(t, commands)
            self._last_valid_t = t
            self._timed_out = False
            if self._failsafe_active and self._failsafe_log:
                log.info("%s: valid frames again, failsafe released", self.path)
            self._failsafe_active = False
            self._frames_received += 1
        self._notify(dict(commands), t)

    def _engage(self, now: float, reason: FailsafeReason, detail: str) -> None:
        """Every car neutral from ``now``; a failsafe event if commands were in effect."""
        with self._lock:
            if self._failsafe_active:
                return
            self._failsafe_active = True
            neutral = {car: NEUTRAL for car in self._history.known_cars}
            self._history.append(now, neutral)
            event = FailsafeEvent(now, reason, self._last_valid_t, detail)
            self._failsafe_log.append(event)
            self._failsafe_counts[reason] += 1
        log.warning("%s: failsafe (%s: %s): all cars neutral", self.path, reason, detail)
        if self._fhss:
            self._say(f"failsafe ({reason}): all channels {fhss.NEUTRAL_US} us")
        self._notify(dict(neutral), now)
        if self.on_failsafe is not None:
            try:
                self.on_failsafe(event)
            except Exception:
                log.exception("on_failsafe callback raised")
                with self._lock:
                    self._callback_errors += 1

    def _check_timeout(self, now: float) -> None:
        with self._lock:
            if self._timed_out or self._last_valid_t is None:
                return
            silence = now - self._last_valid_t
            if silence < self.failsafe_timeout:
                return
            self._timed_out = True
            # The sender may have restarted with a new sequence; accept whatever comes next.
            # Also when already neutral for another reason (a corrupt stream that went on).
            self._decoder.reset_sequence()
        self._engage(now, "timeout", f"no valid frame for {1e3 * silence:.0f} ms")

    def _notify(self, commands: dict[int, CarCommand], t: float) -> None:
        if self.on_commands is None:
            return
        try:
            self.on_commands(commands, t)
        except Exception:
            log.exception("on_commands callback raised")
            with self._lock:
                self._callback_errors += 1
