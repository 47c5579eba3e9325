"""Short property-based fuzz runs (hypothesis) of every loader, the rd3g frame decoder and the solver's
Python API. Long campaigns: `python -m app bench fuzz --target NAME --examples 100000` (docs/benchmarks.md).
A failure prints the shrunk input and hypothesis' @reproduce_failure blob."""
from __future__ import annotations

import json

import pytest
from hypothesis import HealthCheck, given, settings

from bench import fuzz

SHORT = settings(max_examples=100, deadline=None, database=None, print_blob=True,
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@pytest.mark.parametrize("name", sorted(fuzz.TARGETS))
def test_fuzz_target(name):
    target = fuzz.TARGETS[name]

    @SHORT
    @given(target.strategy())
    def run(data: bytes) -> None:
        target.run(data)  # raises FuzzFailure on anything but "accepted" or the format's own error

    run()


def test_unmutated_seeds_are_accepted():
    """The seed documents are valid files: the fuzz starts from inputs the loaders accept."""
    for name, seeds, render in (("problem", fuzz.problem_seeds(), fuzz._json_bytes), ("car", fuzz.car_seeds(), fuzz.toml_bytes),
                                ("track", fuzz.track_seeds(), fuzz._json_bytes),
                                ("fixed_markers", fuzz.fixed_marker_seeds(), fuzz._json_bytes),
                                ("intrinsics", fuzz.intrinsics_seeds(), fuzz._json_bytes),
                                ("calibration", fuzz.calibration_seeds(), fuzz._json_bytes)):
        for seed in seeds:
            assert fuzz.TARGETS[name].run(render(seed)) == "accepted", name
    assert fuzz.TARGETS["sysid_csv"].run(fuzz.csv_seed()) == "accepted"
    assert fuzz.TARGETS["link_capture"].run(fuzz.capture_seed()) == "accepted"


def test_decoder_reference_finds_hand_built_frames():
    """The decoder property's reference parser against a frame assembled byte by byte from
    docs/serial-protocol.md (CRC-16/CCITT-FALSE of 0x01 0x02 0x00 0x00 is worked out by binascii)."""
    import binascii
    import struct

    body = bytes([1]) + struct.pack("<H", 2) + bytes([1]) + struct.pack("<Bhh", 7, 32767, -32767)
    frame = b"\xa5\x5a" + body + struct.pack("<H", binascii.crc_hqx(body, 0xFFFF))
    stream = b"\x00\xa5" + frame + b"\xa5\x5a\x01"
    assert fuzz._reference_frames(stream) == {2: (2, {7: (32767, -32767)})}
    assert fuzz.run_decoder(stream, chunks=[1]) == "accepted"


def test_fuzz_failure_is_reported_with_a_reproducer(tmp_path):
    """A campaign counts a failing input and writes it where --replay reads it."""
    broken = fuzz.Target("broken", lambda: fuzz.csv_inputs(), lambda data: (_ for _ in ()).throw(fuzz.FuzzFailure("boom")),
                         ".csv")
    fuzz.TARGETS["broken"] = broken
    try:
        report = fuzz.campaign("broken", 5, 0, tmp_path, progress=False)
    finally:
        del fuzz.TARGETS["broken"]
    assert report["counts"] == {"failure": 5}
    path, message = report["failures"][0].split(": ", 1)
    assert path == str(tmp_path / "broken-failure-0.csv") and message == "boom"
    assert (tmp_path / "broken-failure-4.csv").is_file()


def test_solver_api_fuzz_in_a_subprocess(tmp_path):
    """Random shapes, NaN/inf and extreme values through solver_cpp.solve in a child process: a native
    crash would be caught there and reported with the pickled input (`python -m app bench fuzz --replay`)."""
    report = fuzz.fuzz_solver(60, seed=1, timeout_s=300, workdir=tmp_path)
    counts = report["counts"]
    assert sum(counts.values()) == 60 and "failure" not in counts
    assert counts.get("rejected", 0) > 0 and any(k.startswith("accepted") for k in counts), json.dumps(counts)
