"""`race --hil --link-protocol buzzracer-fhss` end to end (rendered camera -> detector -> estimator ->
planners -> FHSS frames over a pty -> emulated BuzzRacer box -> each simulated car's receiver), with
its link capture: every frame decodes with a good CRC, the first and last frames are neutral."""
from __future__ import annotations

import json

import pytest

from app.cli import main
from vehicles.link_capture import decode_capture, read_capture


def test_fhss_hil_race_and_its_capture(tmp_path, capsys):
    capture, js = tmp_path / "link.txt", tmp_path / "race.json"
    code = main(["race", "--hil", "--link-protocol", "buzzracer-fhss", "--link-capture", str(capture),
                 "--max-time", "2", "--out", str(tmp_path / "race.rrd"), "--json", str(js)])
    assert code == 0, capsys.readouterr()
    summary = json.loads(js.read_text())
    assert summary["end_reason"] == "time_limit"
    records = read_capture(capture)
    report = decode_capture(records, "buzzracer-fhss")
    assert report.bad_frames == 0 and report.bad["bytes_discarded"] == 0
    neutral = {m: (1500, 1500) for m in range(6)}
    assert report.frames[0].cars == neutral and report.frames[-1].cars == neutral
    # the cars were driven in between: throttle slots (1 = modem 0, 3 = modem 1) above neutral
    assert any(f.cars[0][1] > 1500 and f.cars[1][1] > 1500 for f in report.frames)
    tx = [r.t for r in records if r.direction == "tx"]
    # the sender's 100 frames/s (neutral() on a safety hold and stop() add a frame at once)
    gaps = sorted(b - a for a, b in zip(tx, tx[1:]))
    assert gaps[len(gaps) // 2] == pytest.approx(0.010, abs=0.001)
    assert any("BuzzRacer FHSS box" in line for _, line in report.box_text)


def test_pure_simulation_capture(tmp_path, capsys):
    """Without a serial port the capture holds the frame each control step would have sent, at the
    simulated time (30 Hz control), and a neutral frame when the race ends."""
    capture = tmp_path / "link.txt"
    assert main(["race", "--link-capture", str(capture), "--link-protocol", "buzzracer-fhss", "--max-time", "0.5",
                 "--out", str(tmp_path / "race.rrd")]) == 0
    capsys.readouterr()
    records = read_capture(capture)
    assert all(r.direction == "tx" for r in records)
    times = [r.t for r in records]
    steps = round(0.5 * 30)
    # the simulator keeps the 30 Hz control clock on its 1 ms physics grid
    assert times[:steps] == pytest.approx([k / 30 for k in range(steps)], abs=1e-3)
    report = decode_capture(records, "buzzracer-fhss")
    assert report.bad_frames == 0 and len(report.frames) == steps + 1
    assert report.frames[0].cars[0][1] > 1500  # throttle from the start
    assert report.frames[-1].cars == {m: (1500, 1500) for m in range(6)}
