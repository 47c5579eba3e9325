"""Damaged recordings: `review` and `sysid` say the file is truncated or corrupt, what is readable, and
exit 2 instead of summarising a part as if it were the race.

The recording is written with the rerun SDK alone (not the project's writers): scalar rows on the
``sim_time`` timeline from 0 to 4 s, flushed in batches so the file holds many chunks. The damage
is made by hand: the first 100 bytes, the first half, the 4-byte file header flipped, 256 bytes in
the middle flipped.
"""
from __future__ import annotations

import re

import numpy as np
import pytest

from recording.integrity import RecordingDamage, read_verified

DURATION_S = 4.0


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    import rerun as rr

    path = tmp_path_factory.mktemp("rrd") / "whole.rrd"
    rec = rr.RecordingStream("rd3g_race", recording_id="integrity")
    rec.save(str(path))
    rec.log("race/setup", rr.TextDocument('{"mode": "simulation", "track": "oval", "laps": 1}'), static=True)
    t = np.arange(0.0, DURATION_S + 1e-9, 0.01)
    for lo in range(0, len(t), 40):  # one send per 0.4 s of race: ten chunks per entity
        times = [rr.TimeColumn("sim_time", duration=t[lo:lo + 40])]
        for name in ("rd3g", "opponent"):
            rec.send_columns(f"cars/{name}/speed_mps", indexes=times,
                             columns=rr.Scalars.columns(scalars=np.sin(t[lo:lo + 40])))
            rec.send_columns(f"world/cars/{name}/position", indexes=times,
                             columns=rr.Points2D.columns(positions=np.column_stack([t[lo:lo + 40], t[lo:lo + 40]])))
        rec.flush()
    rec.disconnect()
    return path


def damaged(whole, tmp_path, how: str):
    data = bytearray(whole.read_bytes())
    if how == "first100":
        data = data[:100]
    elif how == "half":
        data = data[:len(data) // 2]
    elif how == "header":
        data[0:4] = bytes(b ^ 0xFF for b in data[0:4])
    elif how == "middle":
        mid = len(data) // 2
        data[mid:mid + 256] = bytes(b ^ 0xFF for b in data[mid:mid + 256])
    path = tmp_path / f"{how}.rrd"
    path.write_bytes(bytes(data))
    return path


def test_whole_recording_reads(whole):
    store, chunks = read_verified(whole)
    assert store.recording_id == "integrity" and len(chunks) > 20


@pytest.mark.parametrize("how, kind, some_readable", [
    ("first100", "truncated", False),
    ("half", "truncated", True),
    ("header", "corrupt", False),
    ("middle", "corrupt", True),
])
def test_damage_is_named_with_what_is_readable(whole, tmp_path, how, kind, some_readable):
    with pytest.raises(RecordingDamage) as info:
        read_verified(damaged(whole, tmp_path, how))
    err = info.value
    assert err.kind == kind and kind in str(err) and str(err.path) in str(err)
    assert err.readable is not None
    if some_readable:
        # part of the race before the damage, not all of it
        assert err.readable.chunks > 0 and 0.0 <= err.readable.t_first_s <= err.readable.t_last_s < DURATION_S
        assert re.search(r"sim_time 0\.00-\d\.\d\d s", str(err))
    else:
        assert err.readable.chunks == 0 and "nothing readable" in str(err)


@pytest.mark.parametrize("how", ["first100", "half", "header", "middle"])
@pytest.mark.parametrize("command", [["review", "--no-plots"], ["sysid"]])
def test_cli_exits_2_without_a_summary(whole, tmp_path, capsys, how, command):
    from app.cli import main

    path = damaged(whole, tmp_path, how)
    argv = [command[0], str(path), *command[1:]]
    if command[0] == "sysid":
        argv += ["--report", str(tmp_path / "report.md")]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert re.search(r"(truncated|corrupt) recording", err) and "readable before the damage" in err
    assert "minimum gap" not in out and "laps" not in out and not (tmp_path / "report.md").exists()
