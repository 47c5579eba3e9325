"""`race --hil --link-protocol buzzracer-fhss` end to end (rendered camera -> detector -> estimator ->
planners -> FHSS frames over a pty -> emulated BuzzRacer box -> each simulated car's receiver), with
its link capture: every frame decodes with a good CRC, the first and last frames are neutral."""
from __future__ import annotations

import json

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
    # at most 100 frames/s: no two frames closer than a period, give or take the sender's scheduling
    assert len(tx) <= 100 * (tx[-1] - tx[0]) + 2
    assert any("BuzzRacer FHSS box" in line for _, line in report.box_text)
