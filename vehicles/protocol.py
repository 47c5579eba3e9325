"""Binary command protocol between the race computer and the cars' radio transmitter box.

One frame carries the complete command set for every car the transmitter drives
(byte layout, scaling and decoder rules: docs/serial-protocol.md)::

    offset  size  field
    0       2     sync header 0xA5 0x5A
    2       1     protocol version (1)
    3       2     sequence number, u16 little-endian, wraps 65535 -> 0
    5       1     number of cars N (0..MAX_CARS)
    6       5*N   per car: id u8, steering i16 LE, throttle i16 LE
    6+5N    2     CRC-16/CCITT-FALSE over bytes 2 .. 5+5N, u16 little-endian

``encode_frame`` builds a frame; ``FrameDecoder`` turns an arbitrary byte stream back
into frames, rejecting and counting everything it does not trust.
"""
from __future__ import annotations

import binascii
import math
import struct
import time
from dataclasses import dataclass
from typing import Callable, Mapping

SYNC = b"\xa5\x5a"
PROTOCOL_VERSION = 1
MAX_CARS = 16
HEADER_LEN = 6  # sync(2) + version(1) + seq(2) + n_cars(1)
CAR_RECORD_LEN = 5  # id(1) + steering(2) + throttle(2)
CRC_LEN = 2
MIN_FRAME_LEN = HEADER_LEN + CRC_LEN
MAX_FRAME_LEN = HEADER_LEN + CAR_RECORD_LEN * MAX_CARS + CRC_LEN
SEQ_MODULUS = 1 << 16
# Full scale is +-32767 so that 0 is exactly neutral and the scaling is symmetric;
# -32768 is never produced by the encoder and decodes to -1.0.
FULL_SCALE = 32767

_CAR_RECORD = struct.Struct("<Bhh")
_SEQ = struct.Struct("<H")
_CRC = struct.Struct("<H")

COMMAND_FIELDS = ("steering", "throttle")


class ProtocolError(ValueError):
    """A command that cannot be encoded (NaN or infinite value, bad car id, too many cars)."""


def crc16_ccitt_false(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor).

    ``binascii.crc_hqx`` is the CCITT CRC with a caller-chosen initial value, so with
    0xFFFF it is exactly this variant (check value for b"123456789" is 0x29B1).
    """
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True)
class CarCommand:
    """Normalised command for one car: both fields in [-1, 1], 0 is neutral.

    steering: -1 full left .. +1 full right (sign convention is the transmitter's channel
    direction; calibrate per car). throttle: -1 full brake/reverse .. +1 full throttle.
    """

    steering: float = 0.0
    throttle: float = 0.0

    @property
    def is_neutral(self) -> bool:
        return self.steering == 0.0 and self.throttle == 0.0


NEUTRAL = CarCommand(0.0, 0.0)


@dataclass(frozen=True)
class DecodedFrame:
    seq: int
    commands: dict[int, CarCommand]


def check_car_id(car_id: object) -> int:
    """Car ids are u8 on the wire; bool is rejected because True == 1 is almost always a bug."""
    if isinstance(car_id, bool) or not isinstance(car_id, int):
        raise ProtocolError(f"car id {car_id!r} must be an int in 0..255")
    if not 0 <= car_id <= 255:
        raise ProtocolError(f"car id {car_id} out of range 0..255")
    return car_id


def check_command_value(car_id: int, field_name: str, value: object) -> float:
    """Return ``value`` as a float, or raise ProtocolError naming car and field if it is not finite.

    Infinity is rejected like NaN: an infinite controller output means the controller
    diverged, and clamping it to full throttle would be the worst possible reaction.
    """
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ProtocolError(f"car {car_id} {field_name}: {value!r} is not a number") from None
    if math.isnan(number):
        raise ProtocolError(f"car {car_id} {field_name} is NaN")
    if math.isinf(number):
        raise ProtocolError(f"car {car_id} {field_name} is infinite ({number})")
    return number


def to_raw(value: float) -> int:
    """Normalised value -> int16: clamp to [-1, 1], scale by 32767, round half away from zero."""
    clamped = min(1.0, max(-1.0, value))
    scaled = clamped * FULL_SCALE
    return int(math.floor(scaled + 0.5)) if scaled >= 0 else -int(math.floor(-scaled + 0.5))


def from_raw(raw: int) -> float:
    return max(-FULL_SCALE, raw) / FULL_SCALE


def encode_frame(seq: int, commands: Mapping[int, CarCommand]) -> bytes:
    """Encode one frame. Values outside [-1, 1] are clamped; NaN/inf raise ProtocolError.

    Cars are written in ascending id order so equal command sets give identical bytes.
    A frame with no cars is valid and means "every car neutral".
    """
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq < SEQ_MODULUS:
        raise ProtocolError(f"sequence number {seq!r} must be an int in 0..65535")
    if len(commands) > MAX_CARS:
        raise ProtocolError(f"{len(commands)} cars in one frame, at most {MAX_CARS} allowed")
    body = bytearray()
    body.append(PROTOCOL_VERSION)
    body += _SEQ.pack(seq)
    body.append(len(commands))
    for car_id in sorted(check_car_id(car_id) for car_id in commands):
        command = commands[car_id]
        raws = [to_raw(check_command_value(car_id, name, getattr(command, name))) for name in COMMAND_FIELDS]
        body += _CAR_RECORD.pack(car_id, *raws)
    return SYNC + bytes(body) + _CRC.pack(crc16_ccitt_false(body))


def seq_is_newer(seq: int, last: int) -> bool:
    """Serial-number arithmetic (RFC 1982) on u16: newer if 0 < (seq - last) mod 2^16 < 2^15."""
    return 0 < (seq - last) % SEQ_MODULUS < SEQ_MODULUS // 2


@dataclass
class DecoderStats:
    """Counters kept by FrameDecoder. Every rejected frame increments exactly one counter."""

    frames_ok: int = 0  # frames yielded
    bad_crc: int = 0  # checksum mismatch
    bad_length: int = 0  # car count above the decoder's max_cars, or a length byte that disagrees with the frame
    bad_version: int = 0  # version byte is not PROTOCOL_VERSION
    bad_payload: int = 0  # CRC correct but contents invalid (same car id twice)
    truncated: int = 0  # cut short by the next frame's header or by the inter-byte timeout
    duplicate: int = 0  # sequence number equal to the last accepted one
    out_of_order: int = 0  # sequence number older than the last accepted one
    frames_missed: int = 0  # gaps in the accepted sequence numbers (frames never seen at all)
    # Bytes skipped while hunting for a sync header. After a rejection decoding resumes one
    # byte past the rejected header, so the rest of a rejected candidate is counted here too.
    bytes_discarded: int = 0

    @property
    def corrupt(self) -> int:
        return self.bad_crc + self.bad_length + self.bad_version + self.bad_payload

    @property
    def stale(self) -> int:
        return self.duplicate + self.out_of_order

    @property
    def rejected(self) -> int:
        return self.corrupt + self.truncated + self.stale

    def copy(self) -> "DecoderStats":
        return DecoderStats(**{name: getattr(self, name) for name in self.__dataclass_fields__})


# Result of looking at a candidate frame starting at some offset of the buffer.
_VALID = "valid"
_INCOMPLETE = "incomplete"
_BAD_VERSION = "bad_version"
_BAD_LENGTH = "bad_length"
_BAD_CRC = "bad_crc"


def _frame_status(buf: bytearray, start: int, max_cars: int = MAX_CARS) -> tuple[str, int]:
    """Classify the candidate at ``buf[start:]`` (which begins with SYNC). Returns (status, length).

    Each check is made as soon as its byte is in, so a candidate is known bad as early as its
    bytes allow: the version at 3 bytes, the car count at 6, the CRC at the announced length.
    """
    available = len(buf) - start
    if available < 3:
        return _INCOMPLETE, MIN_FRAME_LEN
    if buf[start + 2] != PROTOCOL_VERSION:
        return _BAD_VERSION, 0
    if available < HEADER_LEN:
        return _INCOMPLETE, MIN_FRAME_LEN
    n_cars = buf[start + 5]
    if n_cars > max_cars:
        return _BAD_LENGTH, 0
    length = HEADER_LEN + CAR_RECORD_LEN * n_cars + CRC_LEN
    if available < length:
        return _INCOMPLETE, length
    end = start + length
    (received_crc,) = _CRC.unpack_from(buf, end - CRC_LEN)
    if crc16_ccitt_false(memoryview(buf)[start + 2 : end - CRC_LEN]) != received_crc:
        return _BAD_CRC, length
    return _VALID, length


def _length_byte_was_corrupted(buf: bytearray, cut_at: int, max_cars: int = MAX_CARS) -> bool:
    """True if buf[0:cut_at] is a complete frame whose only fault is its car-count byte.

    Distinguishes "length byte hit by noise" (the bytes before the next header are a
    whole frame once the count is corrected) from "frame cut short" (they are not).
    """
    payload_len = cut_at - MIN_FRAME_LEN
    if payload_len < 0 or payload_len % CAR_RECORD_LEN or buf[2] != PROTOCOL_VERSION:
        return False
    true_count = payload_len // CAR_RECORD_LEN
    if true_count > max_cars or true_count == buf[5]:
        return False
    body = bytearray(buf[2:cut_at - CRC_LEN])
    body[3] = true_count
    return crc16_ccitt_false(body) == _CRC.unpack_from(buf, cut_at - CRC_LEN)[0]


class FrameDecoder:
    """Streaming decoder: feed it byte chunks of any size, get back trusted frames.

    Rules (docs/serial-protocol.md, "Decoder"):
    - bytes before a sync header are discarded (counted in ``bytes_discarded``);
    - a candidate is rejected as soon as its bytes prove it wrong: a wrong version (byte 2),
      a car count above ``max_cars`` (byte 5), a wrong CRC (once its announced length is in).
      It is never held back waiting for later bytes. Decoding resumes one byte after its sync
      header, so a valid frame hidden inside a rejected candidate's span is still found;
    - a rejected candidate whose span holds the header of a later frame that is valid or not
      yet complete was cut short (``truncated``), unless the bytes before that header are a
      whole frame with a corrupted car-count byte (``bad_length``);
    - a candidate still waiting for its announced length that holds a complete valid frame
      was cut short too (or had its car count raised by noise): it is rejected, and the
      later frame decoded, at once;
    - if a partial frame is buffered and no byte arrives for ``gap_timeout`` seconds,
      the partial frame is dropped as ``truncated``;
    - a frame whose sequence number is not newer than the last accepted one (u16 serial
      number arithmetic) is rejected as ``duplicate`` / ``out_of_order``.

    ``max_cars`` is the most cars a frame may carry for this receiver (default: the protocol's
    MAX_CARS). A transmitter box that drives N cars sets it to N: a car count above N is then
    known to be wrong at byte 5, instead of after the longer announced frame has arrived.
    """

    def __init__(self, gap_timeout: float = 0.05, clock: Callable[[], float] = time.monotonic,
                 max_cars: int = MAX_CARS):
        if not gap_timeout > 0:
            raise ValueError(f"gap_timeout must be > 0, got {gap_timeout!r}")
        if isinstance(max_cars, bool) or not isinstance(max_cars, int) or not 1 <= max_cars <= MAX_CARS:
            raise ValueError(f"max_cars must be an int in 1..{MAX_CARS}, got {max_cars!r}")
        self.gap_timeout = gap_timeout
        self.max_cars = max_cars
        self._clock = clock
        self._buf = bytearray()
        self._last_byte_time: float | None = None
        self._last_seq: int | None = None
        self.stats = DecoderStats()

    @property
    def last_seq(self) -> int | None:
        return self._last_seq

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def reset_sequence(self) -> None:
        """Accept the next frame whatever its sequence number (e.g. after the sender restarted)."""
        self._last_seq = None

    def feed(self, data: bytes | bytearray | memoryview, now: float | None = None) -> list[DecodedFrame]:
        """Add received bytes (``now`` = arrival time, default the clock) and return the new frames."""
        now = self._clock() if now is None else now
        frames = self._expire(now)
        if data:
            self._buf += data
            self._last_byte_time = now
            frames += self._process(final=False)
        return frames

    def poll(self, now: float | None = None) -> list[DecodedFrame]:
        """Apply the inter-byte timeout without new data; call this when a read times out."""
        return self._expire(self._clock() if now is None else now)

    def flush(self) -> list[DecodedFrame]:
        """End of stream: whatever is still buffered is final (partial frames count as truncated)."""
        frames = self._process(final=True)
        self._last_byte_time = None
        return frames

    def _expire(self, now: float) -> list[DecodedFrame]:
        if self._buf and self._last_byte_time is not None and now - self._last_byte_time > self.gap_timeout:
            return self.flush()
        return []

    def _discard(self, count: int, counted: bool = True) -> None:
        if counted:
            self.stats.bytes_discarded += count
        del self._buf[:count]

    def _count(self, reason: str) -> None:
        setattr(self.stats, reason, getattr(self.stats, reason) + 1)

    def _process(self, final: bool) -> list[DecodedFrame]:
        frames: list[DecodedFrame] = []
        buf = self._buf
        while buf:
            start = buf.find(SYNC)
            if start < 0:
                # Keep a trailing first sync byte: its partner may be in the next chunk.
                keep = 1 if (buf[-1] == SYNC[0] and not final) else 0
                self._discard(len(buf) - keep)
                break
            if start:
                self._discard(start)
            status, length = _frame_status(buf, 0, self.max_cars)
            if status == _VALID:
                frame = self._accept(bytes(buf[:length]))
                self._discard(length, counted=False)
                if frame is not None:
                    frames.append(frame)
                continue
            if status == _INCOMPLETE:
                # Not wrong yet, unless a complete valid frame starts inside it: then it was cut
                # short (or its count raised by noise), and that frame must not wait for it.
                cut_at = self._valid_frame_inside(len(buf))
                if cut_at is not None:
                    self._count("bad_length" if _length_byte_was_corrupted(buf, cut_at, self.max_cars)
                                else "truncated")
                    self._discard(cut_at, counted=False)
                    continue
                if not final:
                    break
                self._count("truncated")
            else:
                reason, cut_at = self._rejection_reason(status, length)
                self._count(reason)
                if cut_at is not None:  # the later header is where decoding goes on
                    self._discard(cut_at, counted=False)
                    continue
            # Resume right after this sync header's first byte: the span may hide a real frame.
            self._discard(1, counted=False)
        return frames

    def _valid_frame_inside(self, limit: int) -> int | None:
        """Offset (1 <= offset < limit) of the first complete valid frame inside the head candidate."""
        buf = self._buf
        pos = buf.find(SYNC, 1, limit + 1)
        while 0 < pos < limit:
            if _frame_status(buf, pos, self.max_cars)[0] == _VALID:
                return pos
            pos = buf.find(SYNC, pos + 1, limit + 1)
        return None

    def _rejection_reason(self, status: str, length: int) -> tuple[str, int | None]:
        """Counter for a head candidate known to be bad (bad version, count or CRC), and where decoding
        goes on (None: one byte past its header). Decided from the bytes already here, never by waiting
        for more, since the box reacts to the count: a later header inside its span (the announced
        length for a bad CRC; for a bad version or count the span is unknown, so only a header inside
        this one's header) whose frame is valid or still incomplete means it was cut short there,
        unless the bytes before that header are a whole frame with a corrupted car count."""
        buf = self._buf
        limit = length if status == _BAD_CRC else min(len(buf), HEADER_LEN)
        pos = buf.find(SYNC, 1, limit + 1)
        while 0 < pos < limit:
            if _length_byte_was_corrupted(buf, pos, self.max_cars):
                return "bad_length", pos
            if _frame_status(buf, pos, self.max_cars)[0] in (_VALID, _INCOMPLETE):
                return "truncated", pos
            pos = buf.find(SYNC, pos + 1, limit + 1)
        return status, None

    def _accept(self, frame_bytes: bytes) -> DecodedFrame | None:
        (seq,) = _SEQ.unpack_from(frame_bytes, 3)
        n_cars = frame_bytes[5]
        commands: dict[int, CarCommand] = {}
        for index in range(n_cars):
            car_id, steering, throttle = _CAR_RECORD.unpack_from(frame_bytes, HEADER_LEN + CAR_RECORD_LEN * index)
            if car_id in commands:
                self.stats.bad_payload += 1
                return None
            commands[car_id] = CarCommand(from_raw(steering), from_raw(throttle))
        if self._last_seq is not None:
            if seq == self._last_seq:
                self.stats.duplicate += 1
                return None
            if not seq_is_newer(seq, self._last_seq):
                self.stats.out_of_order += 1
                return None
            self.stats.frames_missed += (seq - self._last_seq) % SEQ_MODULUS - 1
        self._last_seq = seq
        self.stats.frames_ok += 1
        return DecodedFrame(seq, commands)


class Rd3gEncoder:
    """Frame encoder for ``SerialCarLink`` speaking this protocol: car ids 0..255, at most MAX_CARS per frame."""

    name = "rd3g"
    max_cars = MAX_CARS
    max_frame_len = MAX_FRAME_LEN
    max_rate_hz: float | None = None  # only the baud rate limits it

    def check_car_id(self, car_id: object) -> int:
        return check_car_id(car_id)

    def limit(self, car_id: int, command: CarCommand) -> tuple[CarCommand, int]:
        return command, 0  # [-1, 1] is the link's own limit

    def encode(self, seq: int, commands: Mapping[int, CarCommand]) -> bytes:
        return encode_frame(seq, commands)
