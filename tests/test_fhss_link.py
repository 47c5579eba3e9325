"""SerialCarLink with the FHSS encoder -> pseudo-terminal -> VirtualCarBox emulating the BuzzRacer firmware,
and the link capture (its file, its reader, link-decode)."""
from __future__ import annotations

import math
import os
import time

import pytest

from app.cli import main
from vehicles import fhss
from vehicles.fhss import FhssEncoder, ServoCalibration, unit_to_pulse
from vehicles.link_capture import CaptureError, LinkCapture, decode_capture, read_capture
from vehicles.protocol import CarCommand
from vehicles.serial_link import SerialCarLink
from vehicles.virtual_box import VirtualCarBox


def wait_until(predicate, timeout: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def cars():
    return [ServoCalibration(0, math.radians(27), math.radians(23.2), math.radians(29.8)),
            ServoCalibration(5, math.radians(27), math.radians(27), math.radians(27))]


def pulses(box, modem_id):
    c = box.current_commands()[modem_id]
    return round(unit_to_pulse(c.steering)), round(unit_to_pulse(c.throttle))


def test_commands_reach_the_emulated_box_as_pulses(tmp_path):
    with VirtualCarBox(protocol="buzzracer-fhss", chatter_every_s=0.05) as box:
        capture = LinkCapture(tmp_path / "cap.txt")
        link = SerialCarLink(box.path, rate_hz=100, car_ids=[0, 5], encoder=FhssEncoder(cars()),
                             capture=capture, handle_signals=False)
        with link:
            link.set_commands({0: CarCommand(1.0, 0.5), 5: CarCommand(-1.0, -0.25)})
            assert wait_until(lambda: pulses(box, 0) == (1100, 1700) and pulses(box, 5) == (2000, 1400))
            assert set(box.current_commands()) == set(range(6))  # the box drives all six slots
            assert pulses(box, 3) == (1500, 1500)
            assert link.stats.clamped_values == 1  # 27 deg left asked of a car that turns 23.2
            assert wait_until(lambda: link.stats.bytes_received > 0)  # the box's text was read
        capture.close()
        assert wait_until(lambda: box.latest()[0].command == CarCommand(0.0, 0.0))  # the last frame: neutral
    records = read_capture(tmp_path / "cap.txt")
    report = decode_capture(records, "buzzracer-fhss")
    assert report.bad_frames == 0 and len(report.frames) == sum(r.direction == "tx" for r in records)
    assert report.frames[0].cars[0] == (1500, 1500) and report.frames[-1].cars == {m: (1500, 1500) for m in range(6)}
    assert any("BuzzRacer FHSS box" in line for _, line in report.box_text)
    assert all(r.t >= 0 for r in records) and records == sorted(records, key=lambda r: r.t)


def test_failsafe_after_100_ms_of_silence_and_silent_crc_drops():
    with VirtualCarBox(protocol="buzzracer-fhss") as box:
        master, slave = box, os.open(box.path, os.O_RDWR | os.O_NOCTTY)
        try:
            encoder = FhssEncoder(cars())
            good = encoder.encode(0, {0: CarCommand(0.0, 1.0)})
            os.write(slave, good)
            assert wait_until(lambda: pulses(box, 0) == (1500, 1900))
            t_last = box.latest()[0].t_received
            bad = bytearray(encoder.encode(0, {0: CarCommand(0.0, -1.0)}))
            bad[5] ^= 0x10
            os.write(slave, bytes(bad))  # dropped silently: no failsafe, the last good command holds
            assert wait_until(lambda: box.stats.decoder.bad_crc == 1)
            assert pulses(box, 0) == (1500, 1900) and not box.failsafe_active
            assert wait_until(lambda: box.failsafe_active, timeout=1.0)
            event = box.failsafe_log()[-1]
            assert event.reason == "timeout"
            assert 0.1 <= event.t - t_last < 0.2  # its 100 ms, plus the reader's wake-up
            assert box.commands_at(t_last + 0.1001)[0] == CarCommand(0.0, 0.0)  # 1500 us from 100 ms on
            assert box.commands_at(t_last + 0.099)[0] == CarCommand(0.0, pulse_unit(1900))
        finally:
            os.close(slave)
        del master


def pulse_unit(us):
    return fhss.pulse_to_unit(us)


def test_rate_cap_and_car_ids():
    with pytest.raises(ValueError, match="buzzracer-fhss receiver's 100 frames/s"):
        SerialCarLink("loop://", rate_hz=120, encoder=FhssEncoder(cars()))
    with pytest.raises(ValueError, match="modem id 2 has no calibration"):
        SerialCarLink("loop://", rate_hz=100, car_ids=[2], encoder=FhssEncoder(cars()))


def test_capture_reader_names_the_fault(tmp_path):
    path = tmp_path / "cap.txt"
    path.write_text("0.000100 tx aa55\n0.010000 rx 6f6b0d0a\n")
    assert [r.direction for r in read_capture(path)] == ["tx", "rx"]
    path.write_text("0.000100 tx aa55\n0.0100")  # cut short
    with pytest.raises(CaptureError, match=r"line 2 \(byte offset 17\) is cut short"):
        read_capture(path)
    path.write_text("0.000100 tx aa55\nhello world\n")
    with pytest.raises(CaptureError, match=r"line 2 \(byte offset 17\) is not a capture line"):
        read_capture(path)
    path.write_text("0.000100 tx AA55\n")  # upper case is not the format
    with pytest.raises(CaptureError, match="line 1"):
        read_capture(path)


def test_link_decode_counts_bad_frames(tmp_path, capsys):
    encoder = FhssEncoder(cars())
    good = encoder.encode(0, {5: CarCommand(0.0, 1.0)}).hex()
    bad = bytearray(encoder.encode(0, {}))
    bad[-1] ^= 0xFF
    path = tmp_path / "cap.txt"
    path.write_text(f"0.010000 tx {good}\n0.020000 tx {bytes(bad).hex()}\n0.030000 tx {good[:20]}\n"
                    f"0.031000 tx {good[20:]}\n0.032000 rx 626f780d0a\n")
    assert main(["link-decode", str(path), "--protocol", "buzzracer-fhss"]) == 1
    out = capsys.readouterr().out
    assert "m5 1500/1900" in out and "0.031000" in out and "box: box" in out
    assert "2 good frames, 1 bad (bad_crc 1)" in out
    assert "0.020000  BAD frame starting at tx byte offset 27" in out
    path.write_text(f"0.010000 tx {good}\n")
    assert main(["link-decode", str(path), "--protocol", "buzzracer-fhss"]) == 0
    assert main(["link-decode", str(path), "--protocol", "sbus"]) == 2
    assert "unknown protocol 'sbus'" in capsys.readouterr().err
    path.write_text("not a capture\n")
    assert main(["link-decode", str(path)]) == 2
    assert "line 1 (byte offset 0)" in capsys.readouterr().err


def test_unplugged_box_is_neutral_within_its_100_ms():
    """The USB device vanishes (the HIL relay closes): the link faults, and the box, which sees only
    silence, commands 1500 us no later than 100 ms after the unplug."""
    from race.hil import SerialRelay

    with VirtualCarBox(protocol="buzzracer-fhss") as box:
        relay = SerialRelay(box.path, frame_len=fhss.FRAME_LEN)
        link = SerialCarLink(relay.path, rate_hz=100, car_ids=[0], encoder=FhssEncoder(cars()[:1]),
                             handle_signals=False)
        try:
            with link:
                link.set_commands({0: CarCommand(0.0, 0.5)})
                assert wait_until(lambda: pulses(box, 0) == (1500, 1700))
                t_unplug = time.monotonic()
                relay.close()
                assert link.wait_fault(2.0)
                assert wait_until(lambda: box.failsafe_active, timeout=2.0)
        finally:
            relay.close()
        event = box.failsafe_log()[-1]
        assert event.reason == "timeout" and event.last_valid_t <= t_unplug
        assert box.commands_at(t_unplug + 0.1)[0] == CarCommand(0.0, 0.0)
        assert box.commands_at(event.last_valid_t + 0.099)[0].throttle == pytest.approx(fhss.pulse_to_unit(1700))
