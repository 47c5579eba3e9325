"""The BuzzRacer FHSS frame (vehicles/fhss.py) against independent references: the CRC-8/SMBUS check value,
CRCs by polynomial long division over GF(2), frames written out by hand from the frame layout, and the
firmware's parser rules."""
import math
import struct

import pytest

from vehicles import fhss
from vehicles.fhss import FhssEncoder, FhssParser, ServoCalibration, crc8_smbus, encode_pulses
from vehicles.link_protocols import PROTOCOLS, check_protocol, make_encoder
from vehicles.protocol import CarCommand, ProtocolError


def crc_by_division(data: bytes) -> int:
    """CRC with init 0, no reflection, no final xor is the remainder of M(x) * x^8 divided by
    x^8 + x^2 + x + 1 (0x107) over GF(2): long division on a Python int."""
    m = int.from_bytes(data, "big") << 8
    while m.bit_length() >= 9:
        m ^= 0x107 << (m.bit_length() - 9)
    return m


def test_crc8_check_value():
    assert crc8_smbus(b"123456789") == 0xF4  # the catalogued check value of CRC-8/SMBUS
    assert crc_by_division(b"123456789") == 0xF4


@pytest.mark.parametrize("data", [b"", b"\x00", b"\xff", b"\xaa\x55", bytes(range(24)), b"\x80" * 24])
def test_crc8_matches_long_division(data):
    assert crc8_smbus(data) == crc_by_division(data)


# 1500 us = 0x05DC -> "dc 05" (little-endian); 1100 = 0x044C -> "4c 04"; 1900 = 0x076C -> "6c 07";
# full right of a car whose right limit (29.8 deg) is beyond the command's full scale (27 deg):
# 1500 + 500 * 27 / 29.8 = 1953.02 -> 1953 = 0x07A1 -> "a1 07". Car m: steering in slot 2m, throttle in
# slot 2m+1, so car 0 is payload bytes 0-3 and car 5 bytes 20-23. CRC bytes: crc_by_division.
N = "dc05"
HAND_FRAMES = {
    "neutral": (None, None, "aa55" + N * 12 + "3f"),
    "car0_full_left": (0, CarCommand(1.0, 0.0), "aa55" + "4c04" + N * 11 + "91"),
    "car5_full_left": (5, CarCommand(1.0, 0.0), "aa55" + N * 10 + "4c04" + N + "02"),
    "car0_full_right": (0, CarCommand(-1.0, 0.0), "aa55" + "a107" + N * 11 + "ce"),
    "car5_full_right": (5, CarCommand(-1.0, 0.0), "aa55" + N * 10 + "a107" + N + "25"),
    "car0_full_throttle": (0, CarCommand(0.0, 1.0), "aa55" + N + "6c07" + N * 10 + "22"),
    "car5_full_throttle": (5, CarCommand(0.0, 1.0), "aa55" + N * 11 + "6c07" + "7e"),
    "car0_full_brake": (0, CarCommand(0.0, -1.0), "aa55" + N + "4c04" + N * 10 + "1f"),
    "car5_full_brake": (5, CarCommand(0.0, -1.0), "aa55" + N * 11 + "4c04" + "d9"),
}


def paper_car(modem_id: int) -> ServoCalibration:
    """23.2 deg left, 29.8 deg right (the issue's example), commands scaled to 27 deg, default pulses."""
    return ServoCalibration(modem_id, math.radians(27.0), math.radians(23.2), math.radians(29.8))


@pytest.mark.parametrize("name", sorted(HAND_FRAMES))
def test_frames_worked_out_by_hand(name):
    car, command, hex_frame = HAND_FRAMES[name]
    expected = bytes.fromhex(hex_frame)
    assert len(expected) == 27
    assert expected[-1] == crc_by_division(expected[2:-1])  # the hand CRC byte, independently
    encoder = FhssEncoder([paper_car(0), paper_car(5)])
    commands = {} if car is None else {car: command}
    assert encoder.encode(0, commands) == expected
    # the neutral command of either car gives the all-neutral frame too
    assert encoder.encode(7, {0: CarCommand(), 5: CarCommand()}) == bytes.fromhex(HAND_FRAMES["neutral"][2])


def test_full_left_is_clamped_and_counted():
    cal = paper_car(0)
    limited, n = cal.clamp(CarCommand(1.0, 0.0))  # 27 deg asked, 23.2 deg possible
    assert n == 1 and limited.steering == pytest.approx(23.2 / 27.0)
    assert cal.clamp(CarCommand(-1.0, 0.5)) == (CarCommand(-1.0, 0.5), 0)  # 27 deg right is within 29.8
    assert cal.clamp(CarCommand(0.0, 1.5))[1] == 1


def test_pulse_map_is_piecewise_linear_through_neutral():
    cal = paper_car(0)
    # half the left range: 1500 + (1100 - 1500) / 2 = 1300; a quarter of the right range: 1500 + 500 / 4 = 1625
    half_left = CarCommand(math.radians(11.6) / math.radians(27.0), 0.0)
    quarter_right = CarCommand(-math.radians(29.8 / 4) / math.radians(27.0), 0.0)
    assert cal.pulses(half_left)[0] == 1300
    assert cal.pulses(quarter_right)[0] == 1625
    assert cal.pulses(CarCommand(0.0, 0.5)) == (1500, 1700)
    assert cal.pulses(CarCommand(0.0, -0.25)) == (1500, 1400)
    # the receiver side inverts it
    assert cal.steering_rad(1300) == pytest.approx(math.radians(11.6))
    assert cal.steering_rad(1625) == pytest.approx(-math.radians(29.8 / 4))
    assert cal.steering_rad(900) == pytest.approx(math.radians(23.2))  # beyond the end: the servo's stop
    assert cal.throttle(1700) == pytest.approx(0.5) and cal.throttle(1400) == pytest.approx(-0.25)


def test_reversed_throttle_channel():
    cal = ServoCalibration(2, 0.47, 0.4, 0.4, throttle_forward_us=1100, throttle_reverse_us=1900)
    assert cal.pulses(CarCommand(0.0, 1.0)) == (1500, 1100)
    assert cal.pulses(CarCommand(0.0, -1.0)) == (1500, 1900)
    assert cal.throttle(1100) == pytest.approx(1.0)


def test_parser_resync_and_silent_drops():
    good = bytes.fromhex(HAND_FRAMES["car0_full_left"][2])
    neutral = bytes.fromhex(HAND_FRAMES["neutral"][2])
    bad = bytearray(good)
    bad[10] ^= 0x01  # one bit in the payload
    parser = FhssParser()
    # AA AA 55: the second AA is the header (resynchronisation), junk before is skipped
    stream = b"\x13\x37\xaa" + good + bytes(bad) + b"hello" + neutral
    frames = []
    for i in range(0, len(stream), 5):  # split anywhere
        frames += parser.feed(stream[i:i + 5])
    assert [f[0] for f in frames] == [1100, 1500]
    assert all(len(f) == 12 for f in frames)
    assert parser.stats.frames_ok == 2 and parser.stats.bad_crc == 1
    assert parser.stats.bytes_discarded == 3 + 5


def test_parser_offsets_name_where_frames_start():
    good = bytes.fromhex(HAND_FRAMES["neutral"][2])
    frames, offsets = FhssParser().feed_with_offsets(b"xy" + good + good)
    assert offsets == [2, 29] and len(frames) == 2


def test_encoder_rejects_bad_configuration():
    with pytest.raises(ProtocolError, match="7 cars on an FHSS box"):
        FhssEncoder([paper_car(m % 6) for m in range(7)])
    with pytest.raises(ProtocolError, match="two cars with modem id 3"):
        FhssEncoder([paper_car(3), paper_car(3)])
    with pytest.raises(ProtocolError, match="modem id 6"):
        FhssEncoder([paper_car(6)])
    encoder = FhssEncoder([paper_car(1)])
    with pytest.raises(ProtocolError, match="modem id 2 has no calibration"):
        encoder.encode(0, {2: CarCommand()})
    with pytest.raises(ProtocolError, match="NaN"):
        encoder.encode(0, {1: CarCommand(float("nan"), 0.0)})
    with pytest.raises(ProtocolError, match="slot 3: pulse 2001"):
        encode_pulses([1500] * 3 + [2001] + [1500] * 8)


def test_registry_lists_both_protocols():
    assert PROTOCOLS == ("rd3g", "buzzracer-fhss")
    with pytest.raises(ValueError, match="unknown protocol 'sbus'"):
        check_protocol("sbus")
    assert make_encoder("buzzracer-fhss", [paper_car(0)]).max_rate_hz == fhss.MAX_RATE_HZ
    # the rd3g encoder is this project's frame: sync A5 5A, version 1, sequence, count
    frame = make_encoder("rd3g").encode(0x1234, {2: CarCommand(0.0, 0.5)})
    assert frame[:6] == bytes.fromhex("a55a01341201")
    assert struct.unpack_from("<Bhh", frame, 6) == (2, 0, 16384)
