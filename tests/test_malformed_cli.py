"""Malformed versions of the project's real files through the command line (app/malformed_cli.py):
every case exits 2 naming the file and the field / row / byte, with no traceback, hang or partial output,
or is a file the format allows. A short seeded sample per format here; the long run is
`python -m app bench malformed` (docs/file-formats.md). The exact messages of what it found are
written out by hand below."""
from __future__ import annotations

import json
import random

import pytest

from app import malformed_cli as mc

ROOT = mc.ROOT


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return mc.make_seeds(tmp_path_factory.mktemp("seeds"))


@pytest.mark.parametrize("name", list(mc.FORMATS))
def test_sampled_mutations_of_real_files(name, seeds, tmp_path):
    rng = random.Random(f"ci-{name}")
    cases = mc.cases_for(mc.FORMATS[name], seeds.files[name], 6, rng)
    # Mostly mutations that can never be valid (each must be rejected), and a few that may be valid.
    strict = [c for c in cases if c.must_reject]
    loose = [c for c in cases if not c.must_reject]
    sample = rng.sample(strict, min(3, len(strict))) + rng.sample(loose, min(1, len(loose)))
    assert sample
    for i, case in enumerate(sample):
        outcome, why = mc.run_case(case, seeds, tmp_path / str(i))
        assert outcome != "failure", f"{case.mutation}: {why}"
        if case.must_reject:
            assert outcome == "rejected"


def _edit(data: bytes, path: tuple, value) -> bytes:
    doc = json.loads(data)
    c = doc
    for k in path[:-1]:
        c = c[k]
    c[path[-1]] = value
    return json.dumps(doc).encode()


def _rejected(seeds, tmp_path, name: str, data: bytes) -> str:
    fmt = mc.FORMATS[name]
    tmp_path.mkdir()
    infile = tmp_path / f"in{fmt.suffix}"
    infile.write_bytes(data)
    out = tmp_path / "out"
    out.mkdir()
    code, stdout, err = mc.run_cli(fmt.argv(infile, out, seeds), out, 120)
    assert code == 2 and "Traceback" not in err, (code, err)
    assert not [p for p in out.iterdir() if not p.name.startswith(".std")]
    return err.strip()


def test_what_the_family_found(seeds, tmp_path):
    # A 2**64 motor loss passed `>= 0` and blew up the simulation with "to_frenet: x and y must be finite".
    car = seeds.files["car"].replace(b"motor_speed_loss_n_per_mps = 0.282", b"motor_speed_loss_n_per_mps = 18446744073709551616")
    assert car != seeds.files["car"]
    err = _rejected(seeds, tmp_path / "car", "car", car)
    assert "in.toml: longitudinal.motor_speed_loss_n_per_mps: must be finite and within +-1e+06" in err
    # A 2**64 m marker made calibrate say "the camera is below the track", naming no file.
    err = _rejected(seeds, tmp_path / "fm", "fixed_markers", _edit(seeds.files["fixed_markers"], ("markers", "44", "size"), 2**64))
    assert "in.json: markers['44'].size: must be within +-10" in err
    # A 1e308 distortion coefficient made OpenCV's pose solver assert (a cv2.error traceback).
    err = _rejected(seeds, tmp_path / "k", "intrinsics", _edit(seeds.files["intrinsics"], ("dist_coeffs", 3), 1e308))
    assert "in.json: dist_coeffs: each must be within +-10000" in err
    # format_version true was taken for 1 (True == 1 in Python).
    err = _rejected(seeds, tmp_path / "cal", "calibration", _edit(seeds.files["calibration"], ("format_version",), True))
    assert "in.json: format_version: expected 1, got True" in err


@pytest.mark.parametrize("name", ["roster", "cars_flag", "grid_flag"])
def test_every_hand_written_roster_case(name, seeds, tmp_path):
    """Duplicates, 1 or 7 cars, unknown planners/keys/car files, bad --cars and --grid values: exit 2
    naming the file or flag and the field (the roster's structural mutations are sampled above)."""
    fmt = mc.FORMATS[name]
    cases = mc._roster_cases(fmt, seeds.files[name]) if name == "roster" else mc.cases_for(fmt, seeds.files[name], 0, None)
    for i, case in enumerate(cases):
        outcome, why = mc.run_case(case, seeds, tmp_path / str(i))
        assert outcome == ("rejected" if case.must_reject else "accepted"), f"{case.mutation}: {why}"


def test_a_roster_car_file_that_does_not_exist_names_the_roster_file(seeds, tmp_path):
    # It named the car and the field but not the roster file it came from.
    roster = seeds.files["roster"].replace(b'planner = "mpc"', b'planner = "mpc"\ncar_params = "no_such_car"')
    err = _rejected(seeds, tmp_path / "r", "roster", roster)
    assert "--roster: " in err and "in.toml: car blue: car_params:" in err and "not found" in err
