"""A software stand-in for the radio transmitter box, on the far end of a pseudo-terminal.

``VirtualCarBox`` opens a pty pair on construction; ``path`` is the slave device that a
``SerialCarLink`` opens like a USB serial port. A reader thread decodes the byte stream
with ``FrameDecoder`` and keeps the commands in effect, applying the same failsafe the
real box must have: no valid frame for ``failsafe_timeout`` (100 ms) -> every car neutral.
A simulator reads ``commands_at(t)``; ``close()`` unplugs the device.
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
from collections import deque
from dataclasses import dataclass
from typing import Callable

from vehicles.protocol import NEUTRAL, CarCommand, DecodedFrame, DecoderStats, FrameDecoder

log = logging.getLogger(__name__)

_READ_SIZE = 4096


@dataclass(frozen=True)
class ReceivedCommand:
    command: CarCommand
    t_received: float  # box clock (time.monotonic by default) when the frame was read
    seq: int  # sequence number of the frame that carried it


@dataclass(frozen=True)
class BoxStats:
    frames_received: int  # valid frames acted on
    failsafe_events: int  # transitions from "receiving" to "failsafe neutral"
    failsafe_active: bool
    callback_errors: int  # exceptions raised by on_commands (logged, never fatal)
    decoder: DecoderStats  # rejected frames by reason


class VirtualCarBox:
    """Pty-backed virtual transmitter box. Starts reading immediately; use as a context manager.

    ``on_commands(commands, t)`` is called from the reader thread with the complete
    command set (every car seen so far) after each accepted frame and once when the
    failsafe engages. ``clock`` must be monotonic; it timestamps received frames and is
    the time base of ``commands_at``. ``history_s`` seconds of frames are kept for it.
    """

    def __init__(
        self,
        *,
        failsafe_timeout: float = 0.1,
        on_commands: Callable[[dict[int, CarCommand], float], None] | None = None,
        gap_timeout: float = 0.02,
        history_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
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
        self._clock = clock
        self._decoder = FrameDecoder(gap_timeout=gap_timeout, clock=clock)
        self._lock = threading.Lock()
        self._known_cars: set[int] = set()
        self._latest: dict[int, ReceivedCommand] = {}
        # Parallel arrays (times ascending) so commands_at can bisect.
        self._history_t: deque[float] = deque()
        self._history_cmds: deque[dict[int, CarCommand]] = deque()
        self._last_valid_t: float | None = None
        self._failsafe_active = True  # nothing received yet: cars are neutral
        self._failsafe_events = 0
        self._frames_received = 0
        self._callback_errors = 0
        self._closed = False

        self._master_fd, self._slave_fd = os.openpty()
        # Raw mode: no echo, no CR/LF translation, no signal characters - a byte pipe.
        tty.setraw(self._slave_fd)
        self.path = os.ttyname(self._slave_fd)
        # The box keeps the slave open itself so reads never fail while no link is attached.
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name=f"VirtualCarBox({self.path})", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ public API
    def commands_at(self, t: float) -> dict[int, CarCommand]:
        """Commands in effect at time ``t`` (box clock) for every car seen so far.

        That is the last accepted frame received at or before ``t``, unless it is older
        than ``failsafe_timeout`` (or there is none): then every car is neutral.
        """
        with self._lock:
            result = {car: NEUTRAL for car in self._known_cars}
            index = bisect.bisect_right(self._history_t, t) - 1
            if index >= 0 and t - self._history_t[index] < self.failsafe_timeout:
                result.update(self._history_cmds[index])
            return result

    def current_commands(self) -> dict[int, CarCommand]:
        return self.commands_at(self._clock())

    def latest(self) -> dict[int, ReceivedCommand]:
        """Last received command per car with its receive time (ignores the failsafe)."""
        with self._lock:
            return dict(self._latest)

    @property
    def failsafe_active(self) -> bool:
        with self._lock:
            return self._failsafe_active

    @property
    def stats(self) -> BoxStats:
        with self._lock:
            return BoxStats(
                frames_received=self._frames_received,
                failsafe_events=self._failsafe_events,
                failsafe_active=self._failsafe_active,
                callback_errors=self._callback_errors,
                decoder=self._decoder.stats.copy(),
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
        for fd in (self._master_fd, self._slave_fd, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> "VirtualCarBox":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # ------------------------------------------------------------------ reader thread
    def _run(self) -> None:
        while True:
            readable, _, _ = select.select([self._master_fd, self._wake_r], [], [], self._wait_timeout())
            if self._wake_r in readable:
                return
            now = self._clock()
            data = b""
            if self._master_fd in readable:
                try:
                    data = os.read(self._master_fd, _READ_SIZE)
                except OSError as exc:
                    if exc.errno not in (errno.EAGAIN, errno.EINTR):
                        log.error("reading %s failed: %s; reader stops", self.path, exc)
                        return
                else:
                    if not data:  # EOF would make select report readable forever
                        log.error("%s: end of file on pty master; reader stops", self.path)
                        return
            with self._lock:
                frames = self._decoder.feed(data, now) if data else self._decoder.poll(now)
            for frame in frames:
                self._apply(frame, now)
            self._check_failsafe(self._clock())

    def _wait_timeout(self) -> float | None:
        """Sleep until data, the failsafe deadline or the decoder's inter-byte timeout."""
        now = self._clock()
        deadlines = []
        with self._lock:
            if not self._failsafe_active and self._last_valid_t is not None:
                deadlines.append(self._last_valid_t + self.failsafe_timeout)
            if self._decoder.buffered:
                # Small slack so the decoder sees the gap as strictly exceeded.
                deadlines.append(now + self._decoder.gap_timeout + 1e-3)
        return max(0.0, min(deadlines) - now) if deadlines else None

    def _apply(self, frame: DecodedFrame, t: float) -> None:
        with self._lock:
            self._known_cars |= frame.commands.keys()
            # A frame is the complete command set: a known car it omits is commanded neutral.
            commands = {car: frame.commands.get(car, NEUTRAL) for car in self._known_cars}
            self._latest = {car: ReceivedCommand(cmd, t, frame.seq) for car, cmd in commands.items()}
            self._history_t.append(t)
            self._history_cmds.append(commands)
            while len(self._history_t) > 1 and t - self._history_t[0] > self.history_s:
                self._history_t.popleft()
                self._history_cmds.popleft()
            self._last_valid_t = t
            if self._failsafe_active and self._failsafe_events:
                log.info("%s: valid frames again, failsafe released", self.path)
            self._failsafe_active = False
            self._frames_received += 1
        self._notify(dict(commands), t)

    def _check_failsafe(self, now: float) -> None:
        with self._lock:
            if self._failsafe_active or self._last_valid_t is None:
                return
            if now - self._last_valid_t < self.failsafe_timeout:
                return
            self._failsafe_active = True
            self._failsafe_events += 1
            # The sender may have restarted with a new sequence; accept whatever comes next.
            self._decoder.reset_sequence()
            neutral = {car: NEUTRAL for car in self._known_cars}
            silence = now - self._last_valid_t
        log.warning("%s: no valid frame for %.0f ms, failsafe: all cars neutral", self.path, 1e3 * silence)
        self._notify(neutral, now)

    def _notify(self, commands: dict[int, CarCommand], t: float) -> None:
        if self.on_commands is None:
            return
        try:
            self.on_commands(commands, t)
        except Exception:
            log.exception("on_commands callback raised")
            with self._lock:
                self._callback_errors += 1
