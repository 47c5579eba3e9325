"""Serial link to the cars' radio transmitter box: streams command frames at a fixed rate.

``SerialCarLink`` owns the port. A background thread sends the latest commands every
1/rate_hz seconds, encoded by a frame encoder (``vehicles.link_protocols``: this project's frame,
vehicles/protocol.py, or the BuzzRacer FHSS box's, vehicles/fhss.py; docs/serial-protocol.md). After
each frame it reads whatever the box sent back (ASCII debug text: logged, never waited for). Neutral
frames go out on start, on stop, on ``neutral()``, after a write failure, at interpreter
exit and on SIGINT/SIGTERM. A write failure (device unplugged, box gone, write timeout)
latches ``fault``, calls ``on_fault`` and stops the sender; the transmitter box's own
failsafe then keeps the cars neutral. Create a new link to reconnect.
"""
from __future__ import annotations

import atexit
import logging
import math
import os
import signal
import threading
import time
from dataclasses import dataclass, replace
from typing import Callable, Iterable, Mapping

import serial

from vehicles.link_capture import LinkCapture
from vehicles.protocol import (
    COMMAND_FIELDS,
    NEUTRAL,
    SEQ_MODULUS,
    CarCommand,
    ProtocolError,
    Rd3gEncoder,
    check_command_value,
)

log = logging.getLogger(__name__)

# 8N1 framing: 10 bits on the wire per byte.
_BITS_PER_BYTE = 10
_HANDLED_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_READ_MAX = 4096  # bytes of box text read per frame period


class SerialLinkError(OSError):
    """The serial port could not be opened."""


@dataclass(frozen=True)
class LinkStats:
    frames_sent: int = 0
    neutral_frames_sent: int = 0  # frames in which every car was neutral
    write_errors: int = 0
    clamped_values: int = 0  # command values clamped to the configured limits
    overruns: int = 0  # send ticks skipped because the sender fell behind
    last_seq: int | None = None  # sequence number of the last frame written (frame counter mod 2^16)
    bytes_received: int = 0  # bytes the box sent back (its debug text)
    last_error: str | None = None


class SerialCarLink:
    """Fixed-rate command stream to the transmitter box.

    ``port`` is anything ``serial.serial_for_url`` accepts: a device path (/dev/ttyUSB0,
    a pty slave such as VirtualCarBox.path) or a URL (loop://, socket://host:port).

    Keyword-only options: ``car_ids`` cars to command neutral from the first frame even
    before ``set_commands`` names them; ``max_abs_steering`` / ``max_abs_throttle`` limits
    in (0, 1] that commands are clamped to (counted in ``stats.clamped_values``);
    ``on_fault(exc)`` called once, from the sender thread, when the link faults;
    ``write_timeout`` seconds a write may block before it counts as a failure;
    ``handle_signals`` install SIGINT/SIGTERM handlers (main thread only) that send
    neutral and then chain to the previously installed handler; ``encoder`` the frame encoder
    (``vehicles.link_protocols.make_encoder``; default this project's frame), which also says which
    car ids the receiver drives, each car's limits and the receiver's frame-rate cap; ``capture``
    a ``LinkCapture`` that gets every byte written and read.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        rate_hz: float = 50.0,
        *,
        car_ids: Iterable[int] = (),
        max_abs_steering: float = 1.0,
        max_abs_throttle: float = 1.0,
        on_fault: Callable[[BaseException], None] | None = None,
        write_timeout: float = 0.1,
        handle_signals: bool = True,
        encoder=None,
        capture: LinkCapture | None = None,
    ):
        self.encoder = Rd3gEncoder() if encoder is None else encoder
        if isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0:
            raise ValueError(f"baudrate must be a positive int, got {baudrate!r}")
        if not (isinstance(rate_hz, (int, float)) and math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be a positive finite number, got {rate_hz!r}")
        # Worst case (the longest frame) must fit in one period, or frames queue up and latency grows.
        frame_len = self.encoder.max_frame_len
        max_rate = baudrate / (_BITS_PER_BYTE * frame_len)
        if rate_hz > max_rate:
            raise ValueError(
                f"rate_hz {rate_hz} too high for baudrate {baudrate}: a {frame_len}-byte frame "
                f"allows at most {max_rate:.1f} Hz")
        cap = self.encoder.max_rate_hz
        if cap is not None and rate_hz > cap:
            raise ValueError(f"rate_hz {rate_hz} above the {self.encoder.name} receiver's {cap:g} frames/s")
        for name, limit in (("max_abs_steering", max_abs_steering), ("max_abs_throttle", max_abs_throttle)):
            if not (isinstance(limit, (int, float)) and 0 < limit <= 1):
                raise ValueError(f"{name} must be in (0, 1], got {limit!r}")
        if not (isinstance(write_timeout, (int, float)) and write_timeout > 0):
            raise ValueError(f"write_timeout must be > 0 seconds, got {write_timeout!r}")
        self.port = port
        self.baudrate = baudrate
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self.write_timeout = float(write_timeout)
        self.on_fault = on_fault
        self._limits = {"steering": float(max_abs_steering), "throttle": float(max_abs_throttle)}
        self._handle_signals = handle_signals
        self.capture = capture
        self._rx_line = bytearray()  # the box's debug text up to the next newline
        self._paused = False

        self._state_lock = threading.Lock()  # commands and stats
        self._write_lock = threading.Lock()  # one frame at a time on the wire
        self._known_cars: set[int] = {self.encoder.check_car_id(c) for c in car_ids}
        if len(self._known_cars) > self.encoder.max_cars:
            raise ValueError(f"{len(self._known_cars)} car_ids given, at most {self.encoder.max_cars} allowed")
        self._commands: dict[int, CarCommand] = {c: NEUTRAL for c in self._known_cars}
        self._stats = LinkStats()
        self._seq = 0
        self._serial: serial.SerialBase | None = None
        self._thread: threading.Thread | None = None
        self._stop_event = threading.Event()
        self._fault_event = threading.Event()
        self._started = False
        self._stopped = False
        self._previous_handlers: dict[int, object] = {}

    # ------------------------------------------------------------------ public API
    def start(self) -> "SerialCarLink":
        """Open the port, send a neutral frame, start the sender thread."""
        if self._started:
            raise RuntimeError("SerialCarLink.start() called twice; create a new link to reconnect")
        self._started = True
        try:
            self._serial = serial.serial_for_url(
                self.port, baudrate=self.baudrate, timeout=0, write_timeout=self.write_timeout)
        except (serial.SerialException, OSError, ValueError) as exc:
            self._stopped = True
            raise SerialLinkError(f"cannot open serial port {self.port!r}: {exc}") from exc
        self._install_exit_hooks()
        self._write({c: NEUTRAL for c in self._known_cars})
        self._thread = threading.Thread(target=self._run, name=f"SerialCarLink({self.port})", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the sender, send a final neutral frame, close the port. Idempotent, never raises."""
        if not self._started or self._stopped:
            return
        self._stopped = True
        self._stop_event.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=max(1.0, 5 * self.period + self.write_timeout))
            if thread.is_alive():
                log.error("sender thread of %s did not stop in time", self.port)
        with self._state_lock:
            self._commands = {c: NEUTRAL for c in self._known_cars}
        if not self._fault_event.is_set():
            # Lock timeout: a signal handler may interrupt the main thread while it writes.
            self._write({c: NEUTRAL for c in self._known_cars}, lock_timeout=0.5)
        self._read_box()
        self._close_port()
        if self.capture is not None:
            self.capture.flush()
        self._remove_exit_hooks()

    def set_commands(self, commands: Mapping[int, CarCommand]) -> None:
        """Replace the command set. Cars known from earlier calls but absent here get neutral.

        Raises ProtocolError (a ValueError) naming car and field for NaN/inf values, bad ids
        or non-CarCommand entries; nothing is applied then. Values beyond the limits are
        clamped and counted.
        """
        validated: dict[int, CarCommand] = {}
        clamped = 0
        for car_id, command in commands.items():
            self.encoder.check_car_id(car_id)
            if not isinstance(command, CarCommand):
                raise ProtocolError(f"car {car_id}: expected CarCommand, got {type(command).__name__}")
            values = {}
            for name in COMMAND_FIELDS:
                value = check_command_value(car_id, name, getattr(command, name))
                limit = self._limits[name]
                if abs(value) > limit:
                    value = math.copysign(limit, value)
                    clamped += 1
                values[name] = value
            validated[car_id], n = self.encoder.limit(car_id, CarCommand(**values))
            clamped += n
        with self._state_lock:
            known = self._known_cars | validated.keys()
            if len(known) > self.encoder.max_cars:
                raise ProtocolError(f"{len(known)} cars commanded, at most {self.encoder.max_cars} allowed per frame")
            self._known_cars = known
            self._commands = {c: validated.get(c, NEUTRAL) for c in known}
            if clamped:
                self._stats = replace(self._stats, clamped_values=self._stats.clamped_values + clamped)

    def neutral(self) -> None:
        """Command every known car neutral and send that frame now (not at the next tick)."""
        with self._state_lock:
            self._commands = {c: NEUTRAL for c in self._known_cars}
        if self.running:
            self._write({c: NEUTRAL for c in self._known_cars})

    def pause_sending(self, paused: bool) -> None:
        """Stop (True) or resume (False) the periodic frames, e.g. to see the box's failsafe act;
        ``neutral()`` and ``stop()`` still send."""
        self._paused = bool(paused)

    @property
    def commands(self) -> dict[int, CarCommand]:
        with self._state_lock:
            return dict(self._commands)

    @property
    def stats(self) -> LinkStats:
        with self._state_lock:
            return self._stats

    @property
    def fault(self) -> bool:
        return self._fault_event.is_set()

    @property
    def last_error(self) -> str | None:
        return self.stats.last_error

    @property
    def running(self) -> bool:
        return self._started and not self._stopped and not self._fault_event.is_set()

    def wait_fault(self, timeout: float | None = None) -> bool:
        """Block until the link faults (True) or the timeout passes (False)."""
        return self._fault_event.wait(timeout)

    def __enter__(self) -> "SerialCarLink":
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.stop()

    # ------------------------------------------------------------------ sender
    def _run(self) -> None:
        next_tick = time.monotonic() + self.period
        while not self._stop_event.wait(max(0.0, next_tick - time.monotonic())):
            with self._state_lock:
                commands = dict(self._commands)
            if not self._paused and not self._write(commands):
                return
            self._read_box()
            next_tick += self.period
            now = time.monotonic()
            if next_tick < now:
                # Fell behind (machine busy): skip the missed ticks rather than bursting frames.
                missed = int((now - next_tick) / self.period) + 1
                next_tick += missed * self.period
                with self._state_lock:
                    self._stats = replace(self._stats, overruns=self._stats.overruns + missed)

    def _write(self, commands: dict[int, CarCommand], lock_timeout: float = -1) -> bool:
        """Encode and write one frame. Returns False if the link is (now) faulted."""
        if not self._write_lock.acquire(timeout=lock_timeout):
            log.warning("could not send frame on %s: writer busy", self.port)
            return True
        try:
            port = self._serial
            if self._fault_event.is_set() or port is None:
                return False
            seq = self._seq
            frame = self.encoder.encode(seq, commands)
            try:
                port.write(frame)
                if self.capture is not None:
                    self.capture.record("tx", frame)
            except (serial.SerialException, OSError, ValueError) as exc:
                # ValueError: pyserial raises it when the port was closed under us.
                self._fail(exc)
                return False
            self._seq = (seq + 1) % SEQ_MODULUS
            all_neutral = all(c.is_neutral for c in commands.values())
            with self._state_lock:
                s = self._stats
                self._stats = replace(s, frames_sent=s.frames_sent + 1, last_seq=seq,
                                      neutral_frames_sent=s.neutral_frames_sent + all_neutral)
            return True
        finally:
            self._write_lock.release()

    def _fail(self, exc: BaseException) -> None:
        """Called with the write lock held: latch the fault, try a last neutral, close, notify."""
        message = f"{type(exc).__name__}: {exc}"
        with self._state_lock:
            self._stats = replace(self._stats, write_errors=self._stats.write_errors + 1, last_error=message)
        if self._fault_event.is_set():
            return
        log.error("serial link %s failed: %s; sending neutral and stopping", self.port, message)
        port = self._serial
        if port is not None:
            try:  # the device may still accept a frame after e.g. a write timeout
                frame = self.encoder.encode(self._seq, {c: NEUTRAL for c in self._known_cars})
                port.write(frame)
                if self.capture is not None:
                    self.capture.record("tx", frame)
            except (serial.SerialException, OSError, ValueError):
                pass
        self._fault_event.set()
        self._stop_event.set()
        if self.on_fault is not None:
            try:
                self.on_fault(exc)
            except Exception:  # a broken callback must not hide the fault itself
                log.exception("on_fault callback of %s raised", self.port)

    def _read_box(self) -> None:
        """Take what the box sent back without waiting (timeout 0): capture it, log its text lines."""
        port = self._serial
        if port is None:
            return
        try:
            data = port.read(_READ_MAX)
        except (serial.SerialException, OSError, ValueError, TypeError):
            return  # the writer notices a gone device; reading is only diagnostics
        if not data:
            return
        if self.capture is not None:
            self.capture.record("rx", data)
        with self._state_lock:
            self._stats = replace(self._stats, bytes_received=self._stats.bytes_received + len(data))
        self._rx_line += data
        *lines, rest = self._rx_line.split(b"\n")
        self._rx_line = bytearray(rest[-_READ_MAX:])
        for line in lines:
            text = line.decode("ascii", "replace").strip()
            if text:
                log.info("box %s: %s", self.port, text)

    def _close_port(self) -> None:
        # Take the writer lock (bounded: a hung writer must not block shutdown) so no
        # frame is half-written when the port goes away.
        locked = self._write_lock.acquire(timeout=0.5)
        try:
            port, self._serial = self._serial, None
        finally:
            if locked:
                self._write_lock.release()
        if port is None:
            return
        try:
            if not self._fault_event.is_set():
                port.flush()  # let the final neutral frame leave before closing
        except (serial.SerialException, OSError, ValueError):
            pass
        try:
            port.close()
        except (serial.SerialException, OSError):
            pass

    # ------------------------------------------------------------------ exit hooks
    def _install_exit_hooks(self) -> None:
        atexit.register(self._atexit_stop)
        if not self._handle_signals or threading.current_thread() is not threading.main_thread():
            return
        for signum in _HANDLED_SIGNALS:
            self._previous_handlers[signum] = signal.getsignal(signum)
            signal.signal(signum, self._handle_signal)

    def _remove_exit_hooks(self) -> None:
        atexit.unregister(self._atexit_stop)
        if threading.current_thread() is not threading.main_thread():
            return  # signal.signal only works there; the handler chains harmlessly once stopped
        for signum, previous in self._previous_handlers.items():
            # Only undo our own handler: something installed after us stays in place.
            if signal.getsignal(signum) == self._handle_signal and previous is not None:
                signal.signal(signum, previous)

    def _atexit_stop(self) -> None:
        self.stop()

    def _handle_signal(self, signum: int, frame) -> None:
        log.warning("signal %s: sending neutral on %s", signal.Signals(signum).name, self.port)
        self.stop()
        previous = self._previous_handlers.get(signum)
        if callable(previous):
            previous(signum, frame)
        elif previous == signal.SIG_DFL:
            # Re-deliver with the default action so the exit status still says "killed by signal".
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
