"""A text record of every byte between the race computer and the transmitter box.

One line per write or read: the time in seconds since the capture's origin (the start of the race
command), ``tx`` (to the box) or ``rx`` (from the box), and the bytes as lowercase hex without
separators::

    12.345678 tx aa55dc05dc05...

``LinkCapture`` writes it (thread-safe; ``SerialCarLink(capture=...)`` records every frame and every
read); ``read_capture`` parses it, naming the line and byte offset of anything that is not a capture
line (docs/serial-protocol.md, "Link capture").
"""
from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

import fileio
from vehicles import fhss
from vehicles.link_protocols import check_protocol
from vehicles.protocol import CarCommand, FrameDecoder, ProtocolError

Direction = Literal["tx", "rx"]
_LINE = re.compile(rb"^(-?[0-9]+\.[0-9]+) (tx|rx) ((?:[0-9a-f]{2})+)$")


class CaptureError(fileio.InputFileError):
    """A capture file that is not one, or was cut short; the message names line and byte offset."""


@dataclass(frozen=True)
class CaptureRecord:
    t: float             # s since the capture's origin
    direction: Direction
    data: bytes
    line: int            # 1-based line number in the file


class LinkCapture:
    """Appends capture lines to ``path``. ``origin`` (clock time of t = 0) defaults to now."""

    def __init__(self, path: str | Path, clock: Callable[[], float] = time.monotonic, origin: float | None = None):
        self.path = Path(path)
        self._clock = clock
        self.origin = clock() if origin is None else float(origin)
        self._lock = threading.Lock()
        fileio.check_output_path(self.path)  # a regular file (a link to one) or new; written as it goes, not renamed
        self._file = self.path.open("w", encoding="ascii")
        self.lines = 0

    def record(self, direction: Direction, data: bytes, t: float | None = None) -> None:
        """One line; ``t`` (s since the origin) defaults to the clock's now."""
        if not data:
            return
        t = self._clock() - self.origin if t is None else t
        with self._lock:
            if self._file.closed:
                return
            self._file.write(f"{t:.6f} {direction} {bytes(data).hex()}\n")
            self.lines += 1

    def flush(self) -> None:
        with self._lock:
            if not self._file.closed:
                self._file.flush()

    def close(self) -> None:
        with self._lock:
            self._file.close()

    def __enter__(self) -> "LinkCapture":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


class SimulatedLink:
    """The frames a transmitter would have been sent in a pure simulation (no serial port): each control
    step's commands ((throttle, steering rad) per car), encoded as the link would, recorded as ``tx`` at
    the simulated time. ``radio_ids`` per car index; ``steering_full_scale_rad`` is a steering command
    of 1 (the link's normalisation)."""

    def __init__(self, capture: LinkCapture, encoder, radio_ids, steering_full_scale_rad: float):
        self.capture, self.encoder = capture, encoder
        self.radio_ids = list(radio_ids)
        self.full_scale = float(steering_full_scale_rad)
        self.frames = 0

    def send(self, t: float, commands) -> None:
        cars = {}
        for radio_id, (throttle, steering) in zip(self.radio_ids, commands):
            command = CarCommand(max(-1.0, min(1.0, float(steering) / self.full_scale)), max(-1.0, min(1.0, float(throttle))))
            cars[radio_id] = self.encoder.limit(radio_id, command)[0]
        try:
            frame = self.encoder.encode(self.frames % (1 << 16), cars)
        except ProtocolError:  # a non-finite command: the real link would not send it either
            return
        self.capture.record("tx", frame, t=t)
        self.frames += 1

    def neutral(self, t: float) -> None:
        self.send(t, [(0.0, 0.0)] * len(self.radio_ids))


def read_capture(path: str | Path) -> list[CaptureRecord]:
    """Every line of a capture file, or CaptureError naming the first bad line and its byte offset
    (a last line without its newline means the file was cut short)."""
    path = Path(path)
    raw = fileio.read_bytes(path, "capture file", error=CaptureError)  # a FIFO or device is an error, not a hang
    records: list[CaptureRecord] = []
    offset = 0
    for number, line in enumerate(raw.split(b"\n"), start=1):
        end = offset + len(line)
        if end == len(raw):  # after the last newline
            if line:
                raise CaptureError(f"{path}: line {number} (byte offset {offset}) is cut short: no newline at the end "
                                   f"of the file (truncated capture?)")
            break
        match = _LINE.match(line)
        if match is None:
            raise CaptureError(f"{path}: line {number} (byte offset {offset}) is not a capture line "
                               f"'<seconds> tx|rx <lowercase hex>': {line[:60]!r}")
        records.append(CaptureRecord(float(match[1]), match[2].decode(), bytes.fromhex(match[3].decode()), number))
        offset = end + 1
    if not records:
        raise CaptureError(f"{path}: empty, not a capture")
    return records


@dataclass(frozen=True)
class CapturedFrame:
    t: float                         # time of the write that completed it
    offset: int                      # byte offset of its first byte in the tx stream
    # per car id: (steering, throttle): pulses in us (buzzracer-fhss, every modem id 0..5) or
    # normalised values (rd3g)
    cars: dict[int, tuple[float, float]]
    seq: int | None = None           # rd3g only


@dataclass
class CaptureDecode:
    protocol: str
    frames: list[CapturedFrame]
    bad: dict[str, int]              # rejected frames and bytes by reason
    box_text: list[tuple[float, str]]  # (t, line) of what the box sent back
    bad_at: list[tuple[float, int]] = field(default_factory=list)  # (t, tx byte offset) of bad frames, where known
    tx_bytes: int = 0
    rx_bytes: int = 0

    @property
    def bad_frames(self) -> int:
        return sum(v for k, v in self.bad.items() if k != "bytes_discarded")


def decode_capture(records: list[CaptureRecord], protocol: str) -> CaptureDecode:
    """The frames in a capture's tx bytes (decoded as the receiver would) and the box's text lines."""
    check_protocol(protocol, "--protocol")
    frames: list[CapturedFrame] = []
    text: list[tuple[float, str]] = []
    pending = b""
    tx = rx = 0
    if protocol == "buzzracer-fhss":
        parser = fhss.FhssParser(keep_bad_offsets=True)
        bad_at: list[tuple[float, int]] = []
        for rec in records:
            if rec.direction == "rx":
                rx += len(rec.data)
                pending = _text_lines(pending + rec.data, rec.t, text)
                continue
            tx += len(rec.data)
            seen_bad = len(parser.bad_offsets)
            pulses_list, offsets = parser.feed_with_offsets(rec.data)
            bad_at += [(rec.t, offset) for offset in parser.bad_offsets[seen_bad:]]
            for pulses, offset in zip(pulses_list, offsets):
                cars = {m: (pulses[fhss.steering_slot(m)], pulses[fhss.throttle_slot(m)]) for m in range(fhss.MAX_CARS)}
                frames.append(CapturedFrame(rec.t, offset, cars))
        bad = {"bad_crc": parser.stats.bad_crc, "incomplete_at_end": int(parser.in_frame),
               "bytes_discarded": parser.stats.bytes_discarded}
        if parser.in_frame:
            bad_at.append((records[-1].t, parser.frame_offset))
    else:
        decoder = FrameDecoder(gap_timeout=1e9)  # a capture has no inter-byte timing to trust
        for rec in records:
            if rec.direction == "rx":
                rx += len(rec.data)
                pending = _text_lines(pending + rec.data, rec.t, text)
                continue
            for frame in decoder.feed(rec.data, now=rec.t):
                frames.append(CapturedFrame(rec.t, -1, {c: (v.steering, v.throttle) for c, v in frame.commands.items()},
                                            frame.seq))
            tx += len(rec.data)
        for frame in decoder.flush():
            frames.append(CapturedFrame(records[-1].t, -1, {c: (v.steering, v.throttle)
                                                            for c, v in frame.commands.items()}, frame.seq))
        st = decoder.stats
        bad = {"bad_crc": st.bad_crc, "bad_version": st.bad_version, "bad_length": st.bad_length,
               "bad_payload": st.bad_payload, "truncated": st.truncated, "duplicate": st.duplicate,
               "out_of_order": st.out_of_order, "bytes_discarded": st.bytes_discarded}
    if pending.strip():
        text.append((records[-1].t, pending.decode("ascii", "replace").strip()))
    return CaptureDecode(protocol, frames, bad, text, bad_at if protocol == "buzzracer-fhss" else [], tx, rx)


def _text_lines(buf: bytes, t: float, out: list[tuple[float, str]]) -> bytes:
    *lines, rest = buf.split(b"\n")
    for line in lines:
        if line.strip():
            out.append((t, line.decode("ascii", "replace").strip()))
    return rest
