"""Tests for vehicles/protocol.py: frame layout, CRC, scaling, and the streaming decoder.

References are independent of the code under test: the CRC is checked against the
catalogue check value and a bit-by-bit implementation of the polynomial definition;
frames are built by hand with struct from the byte table in docs/serial-protocol.md.
"""
from __future__ import annotations

import math
import random
import struct

import pytest

from vehicles.protocol import (
    MAX_CARS,
    NEUTRAL,
    SYNC,
    CarCommand,
    FrameDecoder,
    ProtocolError,
    crc16_ccitt_false,
    encode_frame,
    seq_is_newer,
)


def reference_crc16_ccitt_false(data: bytes) -> int:
    """Bitwise CRC straight from the definition: poly 0x1021, init 0xFFFF, MSB first."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def hand_built_frame(seq: int, cars: list[tuple[int, int, int]], version: int = 1, n_cars: int | None = None) -> bytes:
    """Frame from the documented byte table, with raw int16 values."""
    body = struct.pack("<BHB", version, seq, len(cars) if n_cars is None else n_cars)
    for car_id, steering, throttle in cars:
        body += struct.pack("<Bhh", car_id, steering, throttle)
    return b"\xa5\x5a" + body + struct.pack("<H", reference_crc16_ccitt_false(body))


def frame(seq: int, throttle: float = 0.25) -> bytes:
    return encode_frame(seq, {1: CarCommand(0.1, throttle), 4: CarCommand(-0.3, 0.0)})


def seqs(frames) -> list[int]:
    return [f.seq for f in frames]


# ---------------------------------------------------------------------------- CRC
def test_crc_check_value():
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert reference_crc16_ccitt_false(b"123456789") == 0x29B1


def test_crc_matches_bitwise_reference_on_random_data():
    rng = random.Random(1)
    for length in list(range(0, 20)) + [100, 257]:
        data = bytes(rng.randrange(256) for _ in range(length))
        assert crc16_ccitt_false(data) == reference_crc16_ccitt_false(data)


# ---------------------------------------------------------------------------- encoder
def test_encoded_bytes_match_documented_layout():
    encoded = encode_frame(0x1234, {7: CarCommand(1.0, -1.0), 2: CarCommand(0.0, 0.5)})
    # Cars in ascending id order; 0.5 * 32767 = 16383.5 rounds half away from zero to 16384.
    assert encoded == hand_built_frame(0x1234, [(2, 0, 16384), (7, 32767, -32767)])
    assert encoded[:2] == SYNC and len(encoded) == 6 + 2 * 5 + 2


def test_round_trip_random_commands_within_quantisation():
    rng = random.Random(7)
    decoder = FrameDecoder()
    for seq in range(200):
        commands = {car: CarCommand(rng.uniform(-1, 1), rng.uniform(-1, 1))
                    for car in rng.sample(range(256), rng.randint(0, MAX_CARS))}
        (decoded,) = decoder.feed(encode_frame(seq, commands))
        assert decoded.seq == seq
        assert decoded.commands.keys() == commands.keys()
        for car, command in commands.items():
            assert decoded.commands[car].steering == pytest.approx(command.steering, abs=0.5 / 32767)
            assert decoded.commands[car].throttle == pytest.approx(command.throttle, abs=0.5 / 32767)
    assert decoder.stats.rejected == 0


def test_neutral_and_full_scale_are_exact():
    (decoded,) = FrameDecoder().feed(encode_frame(0, {0: NEUTRAL, 1: CarCommand(1.0, -1.0)}))
    assert decoded.commands[0] == CarCommand(0.0, 0.0) and decoded.commands[0].is_neutral
    assert decoded.commands[1] == CarCommand(1.0, -1.0)


def test_out_of_range_values_are_clamped():
    assert encode_frame(3, {5: CarCommand(1.7, -40.0)}) == hand_built_frame(3, [(5, 32767, -32767)])


def test_raw_minus_32768_decodes_to_minus_one():
    (decoded,) = FrameDecoder().feed(hand_built_frame(0, [(1, -32768, 0)]))
    assert decoded.commands[1].steering == -1.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("field", ["steering", "throttle"])
def test_encoder_rejects_non_finite_naming_car_and_field(bad, field):
    command = CarCommand(**{"steering": 0.0, "throttle": 0.0, field: bad})
    with pytest.raises(ValueError, match=rf"car 3 {field}"):
        encode_frame(0, {1: NEUTRAL, 3: command})


@pytest.mark.parametrize("car_id", [-1, 256, True, "1", 1.0])
def test_encoder_rejects_bad_car_ids(car_id):
    with pytest.raises(ProtocolError, match="car id"):
        encode_frame(0, {car_id: NEUTRAL})


def test_encoder_rejects_bad_seq_and_too_many_cars():
    with pytest.raises(ProtocolError, match="sequence"):
        encode_frame(65536, {})
    with pytest.raises(ProtocolError, match="sequence"):
        encode_frame(-1, {})
    with pytest.raises(ProtocolError, match=f"at most {MAX_CARS}"):
        encode_frame(0, {car: NEUTRAL for car in range(MAX_CARS + 1)})


def test_empty_and_full_frames_round_trip():
    decoder = FrameDecoder()
    full = {car: CarCommand(0.5, -0.5) for car in range(100, 100 + MAX_CARS)}
    decoded = decoder.feed(encode_frame(0, {}) + encode_frame(1, full))
    assert [f.commands.keys() for f in decoded] == [set(), full.keys()]


# ---------------------------------------------------------------------------- resync and chunking
def test_garbage_without_sync_is_discarded_and_counted():
    rng = random.Random(3)
    garbage = bytes(rng.choice([b for b in range(256) if b != 0xA5]) for _ in range(500))
    decoder = FrameDecoder()
    assert seqs(decoder.feed(garbage + frame(1) + garbage + frame(2))) == [1, 2]
    assert decoder.stats.bytes_discarded == 2 * len(garbage)
    assert decoder.stats.rejected == 0


@pytest.mark.parametrize("prefix", [b"\xa5", b"\xa5\xa5", b"\x5a", b"\xa5\x5a", b"\xa5\x5a\x01", b"\x00\xa5\x5a\x01\x07",
                                    b"\xa5\x5a\x01\x07\x00\x10\x22"])
def test_partial_headers_before_a_frame_never_hide_it(prefix):
    decoder = FrameDecoder()
    assert seqs(decoder.feed(prefix + frame(42))) == [42]
    assert decoder.stats.corrupt == 0


def test_split_chunks_of_every_size():
    stream = b"".join(frame(seq, throttle=seq / 10) for seq in range(5))
    for size in range(1, len(stream) + 1):
        decoder = FrameDecoder()
        decoded = []
        for offset in range(0, len(stream), size):
            decoded += decoder.feed(stream[offset:offset + size], now=0.0)
        assert seqs(decoded) == list(range(5)), f"chunk size {size}"
        assert [f.commands[1].throttle for f in decoded] == pytest.approx([s / 10 for s in range(5)], abs=1e-4)
        assert decoder.stats.rejected == 0 and decoder.stats.bytes_discarded == 0


def test_random_garbage_between_frames_seeded_fuzz():
    rng = random.Random(11)
    no_sync_start = [b for b in range(256) if b != 0xA5]
    stream, expected = b"", []
    for seq in range(300):
        stream += bytes(rng.choice(no_sync_start) for _ in range(rng.randint(0, 12)))
        stream += frame(seq)
        expected.append(seq)
    decoder = FrameDecoder()
    decoded, offset = [], 0
    while offset < len(stream):
        size = rng.randint(1, 40)
        decoded += decoder.feed(stream[offset:offset + size], now=0.0)
        offset += size
    assert seqs(decoded) == expected
    assert decoder.stats.rejected == 0


# ---------------------------------------------------------------------------- corruption
def test_every_single_bit_flip_is_rejected_and_counted():
    before, target, after = frame(9), frame(10, throttle=0.75), frame(11)
    # Precondition for exact counts: no sync pattern inside the frames except their headers,
    # and none can be created by one flip (else the flipped frame could resync mid-frame).
    assert (before + target + after).count(SYNC) == 3
    for position in range(len(target)):
        for bit in range(8):
            flipped = bytearray(target)
            flipped[position] ^= 1 << bit
            assert (before + flipped + after).count(SYNC) <= 3
            decoder = FrameDecoder()
            decoded = decoder.feed(before + bytes(flipped) + after, now=0.0)
            where = f"byte {position} bit {bit}"
            assert seqs(decoded) == [9, 11], where
            stats = decoder.stats
            assert stats.frames_missed == 1, where
            assert stats.truncated == 0 and stats.stale == 0, where
            if position < 2:
                # Sync header destroyed: the frame is never recognised, its bytes are skipped.
                assert stats.corrupt == 0 and stats.bytes_discarded == len(target), where
            else:
                assert stats.corrupt == 1, where
                if position == 2:
                    assert stats.bad_version == 1, where
                elif position == 5:
                    assert stats.bad_length + stats.bad_crc == 1, where
                else:
                    assert stats.bad_crc == 1, where


def test_car_count_raised_by_noise_is_bad_length_not_truncated():
    target = bytearray(frame(10))
    target[5] = 3  # 2 cars on the wire, header claims 3
    decoder = FrameDecoder()
    assert seqs(decoder.feed(bytes(target) + frame(11), now=0.0)) == [11]
    assert decoder.stats.bad_length == 1 and decoder.stats.truncated == 0


def test_car_count_above_maximum_is_bad_length():
    decoder = FrameDecoder()
    decoder.feed(hand_built_frame(1, [], n_cars=MAX_CARS + 1) + frame(2), now=0.0)
    assert decoder.stats.bad_length == 1


def test_other_version_with_valid_crc_is_rejected():
    decoder = FrameDecoder()
    assert seqs(decoder.feed(hand_built_frame(5, [(1, 100, 100)], version=2) + frame(6))) == [6]
    assert decoder.stats.bad_version == 1


def test_duplicate_car_id_is_bad_payload():
    decoder = FrameDecoder()
    assert decoder.feed(hand_built_frame(5, [(1, 100, 100), (1, 0, 0)])) == []
    assert decoder.stats.bad_payload == 1 and decoder.stats.corrupt == 1


# ---------------------------------------------------------------------------- truncation
def test_frame_cut_short_by_next_header_at_every_length():
    target = frame(10, throttle=0.9)
    for cut in range(2, len(target)):
        decoder = FrameDecoder()
        decoded = decoder.feed(frame(9) + target[:cut] + frame(11), now=0.0)
        assert seqs(decoded) == [9, 11], f"cut at {cut}"
        assert decoder.stats.truncated == 1 and decoder.stats.corrupt == 0, f"cut at {cut}"


def test_frame_cut_short_is_detected_before_its_declared_length_arrives():
    long_frame = encode_frame(10, {car: CarCommand(0.2, 0.2) for car in range(MAX_CARS)})
    decoder = FrameDecoder()
    # 12 bytes of an 88-byte frame, then a complete short frame: it must come out now,
    # not after another 70 bytes (that would be several frame periods of latency).
    assert seqs(decoder.feed(long_frame[:12] + frame(11), now=0.0)) == [11]
    assert decoder.stats.truncated == 1 and decoder.buffered == 0


def test_partial_frame_dropped_after_inter_byte_timeout():
    decoder = FrameDecoder(gap_timeout=0.05)
    target = frame(10)
    assert decoder.feed(target[:9], now=0.0) == []
    assert decoder.poll(now=0.04) == [] and decoder.buffered == 9
    assert decoder.poll(now=0.06) == []
    assert decoder.stats.truncated == 1 and decoder.buffered == 0
    # The late remainder is headerless garbage; the next whole frame decodes normally.
    assert seqs(decoder.feed(target[9:] + frame(11), now=0.07)) == [11]
    # Discarded: the dropped partial after its first byte (decoding resumes there) + the remainder.
    assert decoder.stats.bytes_discarded == (9 - 1) + (len(target) - 9)


def test_late_remainder_after_gap_does_not_complete_the_old_frame():
    decoder = FrameDecoder(gap_timeout=0.05)
    target = frame(10)
    decoder.feed(target[:9], now=0.0)
    assert decoder.feed(target[9:], now=1.0) == []
    assert decoder.stats.truncated == 1 and decoder.stats.frames_ok == 0


def test_flush_counts_partial_frame_as_truncated():
    decoder = FrameDecoder()
    decoder.feed(frame(1)[:-1], now=0.0)
    assert decoder.flush() == [] and decoder.stats.truncated == 1


# ---------------------------------------------------------------------------- sequence numbers
def test_duplicates_and_out_of_order_frames_are_rejected():
    decoder = FrameDecoder()
    decoded = decoder.feed(b"".join(frame(s) for s in [5, 5, 6, 4, 7, 6, 8]))
    assert seqs(decoded) == [5, 6, 7, 8]
    assert decoder.stats.duplicate == 1 and decoder.stats.out_of_order == 2
    assert decoder.stats.frames_missed == 0


def test_sequence_wraps_around():
    decoder = FrameDecoder()
    decoded = decoder.feed(b"".join(frame(s) for s in [65533, 65534, 65535, 0, 1, 65535, 3]))
    assert seqs(decoded) == [65533, 65534, 65535, 0, 1, 3]
    assert decoder.stats.out_of_order == 1 and decoder.stats.frames_missed == 1


def test_seq_is_newer_matches_signed_difference():
    rng = random.Random(5)
    pairs = [(rng.randrange(65536), rng.randrange(65536)) for _ in range(5000)]
    pairs += [(0, 65535), (65535, 0), (100, 100), (32867, 100), (32868, 100), (99, 100)]
    for seq, last in pairs:
        signed_diff = (seq - last + 32768) % 65536 - 32768  # int16 reinterpretation
        assert seq_is_newer(seq, last) == (signed_diff > 0), (seq, last)


def test_reset_sequence_accepts_a_restarted_sender():
    decoder = FrameDecoder()
    decoder.feed(frame(1000))
    assert decoder.feed(frame(0)) == [] and decoder.stats.out_of_order == 1
    decoder.reset_sequence()
    assert seqs(decoder.feed(frame(0))) == [0]
