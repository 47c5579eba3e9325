"""`python -m app calibrate` end to end on a rendered frame."""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import app.cli
from tracking.calibration import load_calibration, load_fixed_markers, save_intrinsics, Intrinsics
from sim.camera import SyntheticCamera, overhead_camera

FIXED_FILE = Path(__file__).resolve().parents[1] / "tracking" / "data" / "oval_fixed_markers.json"


@pytest.fixture(autouse=True)
def with_calibrate_command(monkeypatch):
    if "app.commands.calibrate" not in app.cli.COMMAND_MODULES:
        monkeypatch.setattr(app.cli, "COMMAND_MODULES", app.cli.COMMAND_MODULES + ["app.commands.calibrate"])


@pytest.fixture(scope="module")
def arena_png(tmp_path_factory):
    camera = overhead_camera()
    synth = SyntheticCamera(camera, fixed_markers=list(load_fixed_markers(FIXED_FILE).markers.values()))
    path = tmp_path_factory.mktemp("cal") / "arena.png"
    cv2.imwrite(str(path), synth.render([], 0.0).image)
    return camera, path


def test_calibrate_from_image_with_intrinsics(arena_png, tmp_path, capsys):
    camera, png = arena_png
    intr = tmp_path / "intr.json"
    save_intrinsics(intr, Intrinsics(camera.camera_matrix, np.zeros(5), camera.image_size))
    out = tmp_path / "cal.json"
    code = app.cli.main(["calibrate", "--image", str(png), "--fixed-markers", str(FIXED_FILE),
                         "--intrinsics", str(intr), "--out", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    assert "reprojection error: rms" in text and "markers used: [40, 41, 42, 43, 44, 45, 46, 47, 48]" in text
    cal = load_calibration(out)
    assert np.linalg.norm(cal.camera.position - camera.position) < 0.005
    assert cal.reprojection_rms_px < 0.2
    assert json.loads(out.read_text())["intrinsics_source"] == "file"


def test_calibrate_without_intrinsics(arena_png, tmp_path):
    camera, png = arena_png
    out = tmp_path / "cal.json"
    assert app.cli.main(["calibrate", "--image", str(png), "--fixed-markers", str(FIXED_FILE), "--out", str(out)]) == 0
    cal = load_calibration(out)
    assert cal.intrinsics_source == "estimated"
    assert cal.camera.camera_matrix[0, 0] == pytest.approx(camera.camera_matrix[0, 0], rel=0.01)


def test_bad_inputs_exit_2_naming_the_field(arena_png, tmp_path, capsys):
    _, png = arena_png
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"markers": {"40": {"x": 0.1, "y": 0.1}}}))
    args = ["calibrate", "--image", str(png), "--out", str(tmp_path / "o.json")]
    assert app.cli.main(args + ["--fixed-markers", str(bad)]) == 2
    assert "markers['40'].size: missing" in capsys.readouterr().err
    assert app.cli.main(["calibrate", "--image", str(tmp_path / "none.png"), "--fixed-markers", str(FIXED_FILE),
                         "--out", str(tmp_path / "o.json")]) == 2
    assert "--image" in capsys.readouterr().err
    intr = tmp_path / "intr.json"
    intr.write_text(json.dumps({"image_width": 1280, "image_height": 800, "camera_matrix": [[1, 0], [0, 1]],
                                "dist_coeffs": []}))
    assert app.cli.main(args + ["--fixed-markers", str(FIXED_FILE), "--intrinsics", str(intr)]) == 2
    assert "camera_matrix: expected shape (3, 3)" in capsys.readouterr().err
    assert app.cli.main(["calibrate", "--camera", "/nonexistent/stream.mjpg", "--fixed-markers", str(FIXED_FILE),
                         "--out", str(tmp_path / "o.json")]) == 2
    assert "--camera: cannot open" in capsys.readouterr().err


def test_intrinsics_from_opencv_yaml(arena_png, tmp_path):
    camera, png = arena_png
    yml = tmp_path / "intr.yml"
    fs = cv2.FileStorage(str(yml), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", camera.image_size[0])
    fs.write("image_height", camera.image_size[1])
    fs.write("camera_matrix", camera.camera_matrix)
    fs.write("distortion_coefficients", np.zeros((5, 1)))
    fs.release()
    out = tmp_path / "cal.json"
    assert app.cli.main(["calibrate", "--image", str(png), "--fixed-markers", str(FIXED_FILE),
                         "--intrinsics", str(yml), "--out", str(out)]) == 0
    assert np.linalg.norm(load_calibration(out).camera.position - camera.position) < 0.005
