"""The BuzzRacer FHSS transmitter box's serial frame, its firmware's parser, and the servo calibration.

The box (an Arduino with A7105 FHSS radio modules, one per car) reads, at 115200 baud by default::

    offset  size  field
    0       2     sync 0xAA 0x55
    2       24    12 servo pulse widths, u16 little-endian, microseconds (1000..2000, 1500 neutral)
    26      1     CRC-8/SMBUS (poly 0x07, init 0, no reflection, no final xor) over bytes 2..25

The car with modem id m (0..5) listens to slot 2m (steering) and slot 2m+1 (throttle). There is no
length, version or sequence field; the box answers only with free-form ASCII debug text. Its
firmware waits for 0xAA then 0x55 (0xAA 0xAA resynchronises), reads payload and CRC, drops a frame
with a bad CRC silently and sets every channel to 1500 us when no valid frame came for 100 ms
(docs/serial-protocol.md, "BuzzRacer FHSS box").
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Mapping, Sequence

from vehicles.protocol import CarCommand, ProtocolError, check_command_value

SYNC = b"\xaa\x55"
CHANNELS = 12
MAX_CARS = CHANNELS // 2  # modem ids 0..5
PAYLOAD_LEN = 2 * CHANNELS
FRAME_LEN = len(SYNC) + PAYLOAD_LEN + 1  # 27
NEUTRAL_US = 1500
PULSE_MIN_US = 1000
PULSE_MAX_US = 2000
MAX_RATE_HZ = 100.0  # the reference host's cap; the firmware's radio cycle is built for it

_PAYLOAD = struct.Struct(f"<{CHANNELS}H")


def _crc8_table(poly: int) -> bytes:
    table = bytearray(256)
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table[byte] = crc
    return bytes(table)


_CRC8_TABLE = _crc8_table(0x07)


def crc8_smbus(data: bytes | bytearray | memoryview) -> int:
    """CRC-8/SMBUS: poly 0x07, init 0x00, no reflection, no final xor (check value of b"123456789": 0xF4)."""
    crc = 0
    for byte in bytes(data):
        crc = _CRC8_TABLE[crc ^ byte]
    return crc


def steering_slot(modem_id: int) -> int:
    return 2 * modem_id


def throttle_slot(modem_id: int) -> int:
    return 2 * modem_id + 1


def check_modem_id(modem_id: object) -> int:
    if isinstance(modem_id, bool) or not isinstance(modem_id, int) or not 0 <= modem_id < MAX_CARS:
        raise ProtocolError(f"modem id {modem_id!r} must be an int in 0..{MAX_CARS - 1} (FHSS box slots)")
    return modem_id


def encode_pulses(pulses: Sequence[int]) -> bytes:
    """One 27-byte frame from 12 pulse widths (us, 1000..2000)."""
    if len(pulses) != CHANNELS:
        raise ProtocolError(f"an FHSS frame carries {CHANNELS} pulse widths, got {len(pulses)}")
    for slot, us in enumerate(pulses):
        if isinstance(us, bool) or not isinstance(us, int) or not PULSE_MIN_US <= us <= PULSE_MAX_US:
            raise ProtocolError(f"slot {slot}: pulse {us!r} us outside {PULSE_MIN_US}..{PULSE_MAX_US}")
    payload = _PAYLOAD.pack(*pulses)
    return SYNC + payload + bytes((crc8_smbus(payload),))


def decode_payload(payload: bytes | bytearray | memoryview) -> tuple[int, ...]:
    return _PAYLOAD.unpack(bytes(payload))


@dataclass
class FhssParserStats:
    frames_ok: int = 0
    bad_crc: int = 0  # dropped silently by the firmware
    bytes_discarded: int = 0  # bytes outside any frame (hunting for 0xAA 0x55)

    @property
    def corrupt(self) -> int:
        return self.bad_crc

    @property
    def truncated(self) -> int:
        return 0  # the firmware has no inter-byte timeout: a cut frame is completed by later bytes

    def copy(self) -> "FhssParserStats":
        return FhssParserStats(self.frames_ok, self.bad_crc, self.bytes_discarded)


_WAIT_AA, _WAIT_55, _PAYLOAD_STATE, _CRC_STATE = range(4)


class FhssParser:
    """The box firmware's byte-by-byte state machine: wait for 0xAA, then 0x55 (another 0xAA keeps
    waiting for 0x55, anything else starts over), collect 24 payload bytes and the CRC byte, return
    the 12 pulse widths of a frame whose CRC matches; a bad CRC is dropped silently (counted).

    ``feed_with_offsets`` also gives, per frame, the stream offset of its first sync byte, and with
    ``keep_bad_offsets`` the offsets of the frames dropped for a bad CRC are kept in ``bad_offsets``, so
    a capture reader can name where a frame started."""

    def __init__(self, keep_bad_offsets: bool = False) -> None:
        self.stats = FhssParserStats()
        self._state = _WAIT_AA
        self._buf = bytearray()
        self._offset = 0  # bytes fed so far
        self._frame_start = 0
        self.keep_bad_offsets = keep_bad_offsets
        self.bad_offsets: list[int] = []

    @property
    def in_frame(self) -> bool:
        """A frame has started (sync seen) but is not complete."""
        return self._state != _WAIT_AA

    @property
    def frame_offset(self) -> int | None:
        """Stream offset of the first sync byte of the frame being read (None between frames)."""
        return self._frame_start if self.in_frame else None

    def feed(self, data: bytes | bytearray | memoryview) -> list[tuple[int, ...]]:
        frames, _ = self.feed_with_offsets(data)
        return frames

    def feed_with_offsets(self, data) -> tuple[list[tuple[int, ...]], list[int]]:
        frames: list[tuple[int, ...]] = []
        offsets: list[int] = []
        for byte in bytes(data):
            state = self._state
            if state == _WAIT_AA:
                if byte == 0xAA:
                    self._state = _WAIT_55
                    self._frame_start = self._offset
                else:
                    self.stats.bytes_discarded += 1
            elif state == _WAIT_55:
                if byte == 0x55:
                    self._state = _PAYLOAD_STATE
                    self._buf.clear()
                elif byte == 0xAA:  # resynchronise: this 0xAA may be the real header
                    self.stats.bytes_discarded += 1
                    self._frame_start = self._offset
                else:
                    self.stats.bytes_discarded += 2
                    self._state = _WAIT_AA
            elif state == _PAYLOAD_STATE:
                self._buf.append(byte)
                if len(self._buf) == PAYLOAD_LEN:
                    self._state = _CRC_STATE
            else:
                self._state = _WAIT_AA
                if crc8_smbus(self._buf) == byte:
                    self.stats.frames_ok += 1
                    frames.append(decode_payload(self._buf))
                    offsets.append(self._frame_start)
                else:
                    self.stats.bad_crc += 1
                    if self.keep_bad_offsets:
                        self.bad_offsets.append(self._frame_start)
            self._offset += 1
        return frames, offsets


def pulse_to_unit(us: float) -> float:
    """A channel's pulse as the box-level value the HIL world carries in a CarCommand: (us - 1500) / 500,
    so the failsafe's 1500 us is exactly CarCommand neutral."""
    return (us - NEUTRAL_US) / (PULSE_MAX_US - NEUTRAL_US)


def unit_to_pulse(value: float) -> float:
    return NEUTRAL_US + value * (PULSE_MAX_US - NEUTRAL_US)


@dataclass(frozen=True)
class ServoCalibration:
    """One car's receiver: command -> pulse widths and back (piecewise linear through the neutral pulse).

    Steering angles are radians, positive = left (the model's convention); a ``CarCommand.steering``
    of 1 means ``steering_full_scale_rad`` (the car's ``actuators.max_steering_rad``). The steering
    range is [-right_max_rad, +left_max_rad]; throttle [-1, 1]. Pulses at the two ends may be in either
    order (servo direction, reversed throttle channel); the neutral pulse lies strictly between them.
    """

    modem_id: int
    steering_full_scale_rad: float
    left_max_rad: float
    right_max_rad: float
    steering_left_us: int = 1100
    steering_neutral_us: int = NEUTRAL_US
    steering_right_us: int = 2000
    throttle_forward_us: int = 1900
    throttle_neutral_us: int = NEUTRAL_US
    throttle_reverse_us: int = 1100

    def clamp(self, command: CarCommand) -> tuple[CarCommand, int]:
        """The command within this car's limits, and how many of its two values were clamped."""
        steering = command.steering * self.steering_full_scale_rad
        clamped = 0
        if steering > self.left_max_rad:
            steering, clamped = self.left_max_rad, clamped + 1
        elif steering < -self.right_max_rad:
            steering, clamped = -self.right_max_rad, clamped + 1
        throttle = command.throttle
        if abs(throttle) > 1.0:
            throttle, clamped = math.copysign(1.0, throttle), clamped + 1
        if not clamped:
            return command, 0
        return CarCommand(steering / self.steering_full_scale_rad, throttle), clamped

    def pulses(self, command: CarCommand) -> tuple[int, int]:
        """(steering us, throttle us) of a command already within limits (``clamp``), rounded to 1 us."""
        angle = command.steering * self.steering_full_scale_rad
        if angle >= 0:
            steer = self.steering_neutral_us + (self.steering_left_us - self.steering_neutral_us) * angle / self.left_max_rad
        else:
            steer = self.steering_neutral_us + (self.steering_right_us - self.steering_neutral_us) * -angle / self.right_max_rad
        t = command.throttle
        end = self.throttle_forward_us if t >= 0 else self.throttle_reverse_us
        throttle = self.throttle_neutral_us + (end - self.throttle_neutral_us) * abs(t)
        return _round_half_up(steer), _round_half_up(throttle)

    def steering_rad(self, us: float) -> float:
        """The wheel angle this car's servo takes at pulse ``us`` (clamped to its range)."""
        return _inverse(us, self.steering_neutral_us, self.steering_left_us, self.left_max_rad,
                        self.steering_right_us, self.right_max_rad)

    def throttle(self, us: float) -> float:
        """The throttle this car's speed controller applies at pulse ``us`` (clamped to [-1, 1])."""
        return _inverse(us, self.throttle_neutral_us, self.throttle_forward_us, 1.0, self.throttle_reverse_us, 1.0)


def _round_half_up(x: float) -> int:
    return int(math.floor(x + 0.5))


def _inverse(us: float, neutral: float, pos_end: float, pos_max: float, neg_end: float, neg_max: float) -> float:
    """Value at pulse ``us`` on the piecewise-linear map neutral -> 0, pos_end -> +pos_max, neg_end -> -neg_max."""
    if (us - neutral) * (pos_end - neutral) > 0:
        return pos_max * min(1.0, (us - neutral) / (pos_end - neutral))
    if (us - neutral) * (neg_end - neutral) > 0:
        return -neg_max * min(1.0, (us - neutral) / (neg_end - neutral))
    return 0.0


class FhssEncoder:
    """Frame encoder for ``SerialCarLink``: car ids are modem ids (0..5), each with its calibration."""

    name = "buzzracer-fhss"
    max_cars = MAX_CARS
    max_frame_len = FRAME_LEN
    max_rate_hz = MAX_RATE_HZ

    def __init__(self, cars: Mapping[int, ServoCalibration] | Sequence[ServoCalibration]):
        items = list(cars.values()) if isinstance(cars, Mapping) else list(cars)
        if len(items) > MAX_CARS:
            raise ProtocolError(f"{len(items)} cars on an FHSS box, at most {MAX_CARS} (modem ids 0..{MAX_CARS - 1})")
        self.cars: dict[int, ServoCalibration] = {}
        for cal in items:
            check_modem_id(cal.modem_id)
            if cal.modem_id in self.cars:
                raise ProtocolError(f"two cars with modem id {cal.modem_id}")
            self.cars[cal.modem_id] = cal

    def check_car_id(self, car_id: object) -> int:
        check_modem_id(car_id)
        if car_id not in self.cars:
            raise ProtocolError(f"car with modem id {car_id} has no calibration (configured: {sorted(self.cars)})")
        return car_id  # type: ignore[return-value]

    def limit(self, car_id: int, command: CarCommand) -> tuple[CarCommand, int]:
        return self.cars[car_id].clamp(command)

    def encode(self, seq: int, commands: Mapping[int, CarCommand]) -> bytes:
        """A frame with every car of ``commands`` (limited with ``limit``); other slots neutral (1500 us)."""
        del seq  # the box has no sequence field
        pulses = [NEUTRAL_US] * CHANNELS
        for car_id, command in commands.items():
            cal = self.cars[self.check_car_id(car_id)]
            for name in ("steering", "throttle"):
                check_command_value(car_id, name, getattr(command, name))
            command, _ = cal.clamp(command)
            pulses[steering_slot(car_id)], pulses[throttle_slot(car_id)] = cal.pulses(command)
        return encode_pulses(pulses)


def servo_calibration(car, modem_id: int | None = None, steering_full_scale_rad: float | None = None
                      ) -> ServoCalibration:
    """The ServoCalibration of a car file (``vehicles.params.CarParams``): its ``[radio]`` section, with
    ``modem_id`` given here or in the file (ProtocolError naming the car if neither has one). A steering
    command of 1 means ``steering_full_scale_rad`` (default: the car's ``actuators.max_steering_rad``)."""
    radio = car.radio
    modem = radio.modem_id if modem_id is None else modem_id
    if modem is None:
        raise ProtocolError(f"car {car.name!r}: radio.modem_id is not set (the FHSS box slot that drives it)")
    own = car.actuators.max_steering_rad
    return ServoCalibration(
        modem_id=check_modem_id(modem),
        steering_full_scale_rad=own if steering_full_scale_rad is None else steering_full_scale_rad,
        left_max_rad=own if radio.steering_left_max_rad is None else radio.steering_left_max_rad,
        right_max_rad=own if radio.steering_right_max_rad is None else radio.steering_right_max_rad,
        steering_left_us=radio.steering_left_us, steering_neutral_us=radio.steering_neutral_us,
        steering_right_us=radio.steering_right_us, throttle_forward_us=radio.throttle_forward_us,
        throttle_neutral_us=radio.throttle_neutral_us, throttle_reverse_us=radio.throttle_reverse_us)
