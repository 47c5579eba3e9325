"""When FrameDecoder reports a damaged frame, and that resynchronisation after it loses no valid frame.

The transmitter box's `corrupt` failsafe acts on the first read in which the decoder reports damage
(docs/serial-protocol.md, "Transmitter box behaviour"), so a damaged frame must be reported as soon as
its bytes can be known to be wrong, never held back while later bytes are awaited.

Reference: frames are made by the protocol's encoder from known commands; a frame with one flipped bit
is damaged (CRC-16 detects every 1-bit error), every other frame must come out of the decoder once, in
order, with its commands. When a damaged frame can first be known to be wrong follows from the byte
layout alone (`earliest_chunk`). "Reported" means a rejection counter or the discarded-byte count grew,
the box's definition of line damage.
"""
from __future__ import annotations

import os
import random
import time

import pytest

from vehicles.protocol import (
    CAR_RECORD_LEN,
    CRC_LEN,
    HEADER_LEN,
    MAX_CARS,
    CarCommand,
    DecoderStats,
    FrameDecoder,
    encode_frame,
)
from vehicles.virtual_box import VirtualCarBox

QUANTUM = 0.5 / 32767  # encoder rounding


def commands_for(seq: int) -> dict[int, CarCommand]:
    """Two cars whose commands differ per frame, so a frame decoded in the wrong place shows."""
    return {3: CarCommand(0.001 * seq, 0.4), 8: CarCommand(-0.2, 0.3 - 0.001 * seq)}


def frame(seq: int) -> bytes:
    return encode_frame(seq, commands_for(seq))


FRAME_LEN = HEADER_LEN + 2 * CAR_RECORD_LEN + CRC_LEN  # 18: every frame here carries two cars


def damage(stats: DecoderStats) -> int:
    return stats.corrupt + stats.truncated + stats.bytes_discarded


def flipped(data: bytes, position: int, bit: int) -> bytes:
    out = bytearray(data)
    out[position] ^= 1 << bit
    return bytes(out)


def assert_decoded_as_encoded(decoded, expected_seqs):
    assert [f.seq for f in decoded] == expected_seqs
    for f in decoded:
        reference = commands_for(f.seq)
        assert f.commands.keys() == reference.keys()
        for car, command in reference.items():
            assert f.commands[car].steering == pytest.approx(command.steering, abs=QUANTUM)
            assert f.commands[car].throttle == pytest.approx(command.throttle, abs=QUANTUM)


def earliest_chunk(position: int, bit: int, max_cars: int) -> int:
    """First frame-sized chunk after which the damage can be known, from the layout: 0 = the damaged
    frame's own bytes, 1 = also the next frame's. Only a car count raised to a value the receiver
    allows (2 < count <= max_cars) looks plausible in the header; the frame is then known to be wrong
    when the next frame's header shows where it really ended (or its announced length's CRC fails)."""
    if position != 5:
        return 0  # sync destroyed (stray bytes), version wrong, or sequence number: CRC fails at 18 bytes
    count = 2 ^ (1 << bit)
    return 1 if 2 < count <= max_cars else 0


HEADER_BITS = [(position, bit) for position in range(HEADER_LEN) for bit in range(8)]


@pytest.mark.parametrize("max_cars", [MAX_CARS, 2])
@pytest.mark.parametrize("position,bit", HEADER_BITS)
def test_header_bit_flip_reported_by_the_next_frame_and_the_following_frames_decoded(position, bit, max_cars):
    """One read per frame, as the box reads a sender's frames."""
    decoder = FrameDecoder(max_cars=max_cars)
    assert_decoded_as_encoded(decoder.feed(frame(9), now=0.0), [9])
    chunks = [flipped(frame(10), position, bit), frame(11), frame(12)]
    reported_at = None
    decoded = []
    for index, chunk in enumerate(chunks):
        out = decoder.feed(chunk, now=0.0)
        decoded += out
        if reported_at is None and damage(decoder.stats):
            reported_at = index
        # No valid frame waits for anything: it comes out of the read that completes it.
        assert [f.seq for f in out] == ([] if index == 0 else [10 + index])
    assert reported_at == earliest_chunk(position, bit, max_cars)
    assert_decoded_as_encoded(decoded, [11, 12])
    stats = decoder.stats
    assert stats.frames_missed == 1 and stats.stale == 0 and decoder.buffered == 0


@pytest.mark.parametrize("max_cars", [MAX_CARS, 2])
@pytest.mark.parametrize("position,bit", HEADER_BITS)
def test_header_bit_flip_fed_byte_by_byte(position, bit, max_cars):
    """Byte by byte (a box decoding as bytes arrive): reported no later than the last byte of the chunk
    in which the damage can be known, and each valid frame out on its own last byte."""
    decoder = FrameDecoder(max_cars=max_cars)
    decoder.feed(frame(9), now=0.0)
    stream = flipped(frame(10), position, bit) + frame(11) + frame(12)
    decoded_at: dict[int, int] = {}
    reported_at = None
    for offset in range(len(stream)):
        for f in decoder.feed(stream[offset:offset + 1], now=0.0):
            decoded_at[f.seq] = offset
        if reported_at is None and damage(decoder.stats):
            reported_at = offset
    deadline = (earliest_chunk(position, bit, max_cars) + 1) * FRAME_LEN - 1
    assert reported_at is not None and reported_at <= deadline
    assert decoded_at == {11: 2 * FRAME_LEN - 1, 12: 3 * FRAME_LEN - 1}


def _damaged_crc(seq: int) -> bytes:
    return flipped(frame(seq), FRAME_LEN - 1, 0)


def test_count_raised_in_a_burst_reported_at_once_when_the_receiver_knows_its_cars():
    """The HIL fault race's case: the relay flips bits in every frame for 0.4 s; its first damaged read
    (two frames, seed 4) raises the first frame's car count from 2 to 10 (byte 5, bit 3), and no valid
    frame follows. A box driving 2 cars knows from byte 5; a receiver allowing 16 cars learns it only
    when the 58 announced bytes are in, two reads (17 ms at 120 Hz) later."""
    burst = [flipped(frame(10), 5, 3) + _damaged_crc(11)] + [_damaged_crc(seq) for seq in range(12, 16)]
    announced = HEADER_LEN + 10 * CAR_RECORD_LEN + CRC_LEN
    for max_cars, expected_read in ((2, 0), (MAX_CARS, 2)):
        decoder = FrameDecoder(max_cars=max_cars)
        decoder.feed(frame(9), now=0.0)
        received = 0
        for index, chunk in enumerate(burst):
            assert decoder.feed(chunk, now=0.0) == []
            received += len(chunk)
            if damage(decoder.stats):
                break
        assert index == expected_read, max_cars
        if max_cars == MAX_CARS:
            assert received - len(chunk) < announced <= received


def test_bad_crc_reported_when_its_announced_length_is_in_not_when_a_later_candidate_completes():
    """A 2-car frame whose count was raised to 10 is followed by damaged frames, the third of which
    announces 16 cars (88 bytes). Once the first frame's 58 announced bytes are in, it is known to be
    wrong; the candidate starting inside it that is still incomplete must not hold the report back
    (it did: the decoder waited for that candidate to complete, 84 bytes later, to pick a counter)."""
    long_claim = bytearray(_damaged_crc(14))
    long_claim[5] = MAX_CARS
    stream = flipped(frame(10), 5, 3) + _damaged_crc(11) + _damaged_crc(12) + bytes(long_claim)
    announced = HEADER_LEN + 10 * CAR_RECORD_LEN + CRC_LEN  # 58
    assert 3 * FRAME_LEN < announced < 3 * FRAME_LEN + HEADER_LEN + MAX_CARS * CAR_RECORD_LEN + CRC_LEN
    decoder = FrameDecoder()
    decoder.feed(frame(9), now=0.0)
    for offset in range(len(stream)):
        decoder.feed(stream[offset:offset + 1], now=0.0)
        assert bool(damage(decoder.stats)) == (offset >= announced - 1), offset


def test_frame_cut_short_is_reported_before_the_frame_that_cut_it_is_complete():
    """10 bytes of frame 10, then frame 11: at 18 bytes frame 10's CRC fails, with frame 11's header
    inside it: cut short. Reported at once; frame 11 still decoded when its own bytes are in."""
    decoder = FrameDecoder()
    decoder.feed(frame(9), now=0.0)
    cut, following = frame(10)[:10], frame(11)
    assert decoder.feed(cut + following[:8], now=0.0) == []
    assert decoder.stats.truncated == 1 and decoder.stats.corrupt == 0
    assert_decoded_as_encoded(decoder.feed(following[8:], now=0.0), [11])


class _DamageAtAccept(FrameDecoder):
    """Notes the damage reported so far at each accepted frame (as the box does to order a read)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.damage_at: dict[int, int] = {}

    def _accept(self, frame_bytes):
        accepted = super()._accept(frame_bytes)
        if accepted is not None:
            self.damage_at[accepted.seq] = damage(self.stats)
        return accepted


@pytest.mark.parametrize("max_cars", [MAX_CARS, 2])
def test_random_bit_flips_random_chunks_no_valid_frame_lost_seeded(max_cars):
    """Seeded fuzz: a quarter of the frames get one flipped bit anywhere, the stream arrives in random
    chunks. Exactly the intact frames come out, in order, with their commands, and damage between two
    intact frames has been reported when the second one comes out."""
    rng = random.Random(20261121 + max_cars)
    stream, intact = b"", []
    for seq in range(400):
        data = frame(seq)
        if rng.random() < 0.25:
            data = flipped(data, rng.randrange(len(data)), rng.randrange(8))
        else:
            intact.append(seq)
        stream += data
    decoder = _DamageAtAccept(max_cars=max_cars)
    decoded, offset = [], 0
    while offset < len(stream):
        size = rng.randint(1, 40)
        decoded += decoder.feed(stream[offset:offset + size], now=0.0)
        offset += size
    decoded += decoder.flush()
    assert_decoded_as_encoded(decoded, intact)
    previous = None
    for seq in intact:
        if previous is not None and seq != previous + 1:  # damaged frames in between
            assert decoder.damage_at[seq] > decoder.damage_at[previous], (previous, seq)
        previous = seq
    assert decoder.stats.stale == 0


def test_virtual_box_driving_two_cars_goes_neutral_on_the_first_damaged_read():
    """End to end on the pty: the burst's first read (count 2 -> 10, then a damaged frame) alone trips
    the corrupt failsafe of a box that drives two cars; the 100 ms silence timer has not run out."""
    driving = commands_for(9)
    with VirtualCarBox(max_cars=2) as box:
        fd = os.open(box.path, os.O_WRONLY | os.O_NOCTTY)
        try:
            os.write(fd, frame(9))
            deadline = time.monotonic() + 3.0
            while box.stats.frames_received < 1 and time.monotonic() < deadline:
                time.sleep(0.005)
            assert box.stats.frames_received == 1
            t_valid = box.latest()[3].t_received
            os.write(fd, flipped(frame(10), 5, 3) + _damaged_crc(11))
            deadline = time.monotonic() + 1.0
            while not box.failsafe_active and time.monotonic() < deadline:
                time.sleep(0.005)
            [event] = box.failsafe_log()
            assert event.reason == "corrupt" and event.last_valid_t == t_valid
            assert event.t < t_valid + box.failsafe_timeout
            assert box.stats.decoder.bad_length >= 1
            assert set(box.commands_at(event.t)) == set(driving)
            assert all(c.is_neutral for c in box.commands_at(event.t).values())
        finally:
            os.close(fd)


@pytest.mark.parametrize("max_cars", [0, 17, -1, True, 2.0])
def test_bad_max_cars_is_a_clear_error(max_cars):
    with pytest.raises(ValueError, match="max_cars"):
        FrameDecoder(max_cars=max_cars)
    with pytest.raises(ValueError, match="max_cars"):
        VirtualCarBox(max_cars=max_cars)
