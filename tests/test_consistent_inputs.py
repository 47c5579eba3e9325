"""Values each valid alone but inconsistent together are refused at load, naming the file and the field
(exit 2 on the command line): bounds with no feasible value, one state for both collision coordinates, a
car marker its ArUco dictionary lacks, a marker id given twice or worn by a car and a fixed marker, a
camera whose principal point lies outside its image."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from test_strict_loaders import BASE, _cli

ROOT = Path(__file__).resolve().parent.parent

PROBLEM = BASE  # a 2-car kinematic bicycle game


# (changes to agents[0] or the collision block, the message after "FILE: ")
PROBLEM_CASES = [
    ({"agents": {"u_min": [3, 3], "u_max": [3, 0.5]}},
     "agents[0].u_min must be below agents[0].u_max in every component (component 0: 3 >= 3)"),
    ({"agents": {"u_min": [-1, 1], "u_max": [1, 0.5]}},
     "agents[0].u_min must be below agents[0].u_max in every component (component 1: 1 >= 0.5)"),
    ({"agents": {"x_min": [-9, -9, 5, -9], "x_max": [9, 9, 4, 9]}},
     "agents[0].x_min must be below agents[0].x_max in every component (component 2: 5 >= 4)"),
    ({"agents": {"u_min": [float("inf"), -1]}}, "agents[0].u_min[0] must be below +inf"),
    ({"agents": {"x_ref": [0, 1, 2]}}, "agents[0].cost.x_ref"),
    ({"collision": {"pos_x": 1, "pos_y": 1}}, "collision.pos_x and collision.pos_y must be different states, got 1 for both"),
]


@pytest.mark.parametrize("change, message", PROBLEM_CASES, ids=[m[:50] for _, m in PROBLEM_CASES])
def test_problem_bounds_and_indices_that_admit_nothing(tmp_path, capsys, change, message):
    doc = copy.deepcopy(PROBLEM)
    for key, value in change.get("agents", {}).items():
        (doc["agents"][0]["cost"] if key == "x_ref" else doc["agents"][0])[key] = value
    doc["collision"].update(change.get("collision", {}))
    f = tmp_path / "p.json"
    f.write_text(json.dumps(doc))
    code, err = _cli(["solve", f, "--out", tmp_path / "r.json"], capsys)
    assert code == 2 and err.startswith(f"error: {f}: {message}"), err
    assert "\n" not in err and not (tmp_path / "r.json").exists()


def test_car_marker_outside_its_dictionary(tmp_path, capsys):
    from vehicles.params import CarParamsError, load_car_params

    shipped = (ROOT / "vehicles" / "buzzracer.toml").read_text()
    assert "aruco_id = 0\n" in shipped and "dictionary" not in shipped  # the default DICT_4X4_50: ids 0..49
    f = tmp_path / "car300.toml"
    message = f"{f}: marker.aruco_id: 300 is not an id of marker.dictionary DICT_4X4_50 (ids 0..49)"
    f.write_text(shipped.replace("aruco_id = 0\n", "aruco_id = 300\n"))
    with pytest.raises(CarParamsError) as info:
        load_car_params(f)
    assert str(info.value) == message
    for argv in (["race", "--car-params", f, "--out", tmp_path / "r.rrd"], ["check", "--hil", "--car-params", f]):
        code, err = _cli(argv, capsys)
        assert code == 2 and message in err, (argv, err)
    assert not (tmp_path / "r.rrd").exists()
    for marker, ok in (("aruco_id = 49", True), ("aruco_id = 50", False),
                       ('aruco_id = 99\ndictionary = "DICT_4X4_100"', True),
                       ('aruco_id = 100\ndictionary = "DICT_4X4_100"', False)):
        f.write_text(shipped.replace("aruco_id = 0\n", marker + "\n"))
        if ok:
            assert load_car_params(f).marker.aruco_id == int(marker.split()[2])
        else:
            with pytest.raises(CarParamsError, match=r"marker.aruco_id: .* \(ids 0..(49|99)\)"):
                load_car_params(f)


def test_fixed_marker_given_twice(tmp_path):
    from tracking.calibration import CalibrationError, load_fixed_markers

    f = tmp_path / "m.json"
    f.write_text(json.dumps({"markers": {"40": {"x": 0, "y": 0, "size": 0.1}, "040": {"x": 5, "y": 5, "size": 0.1}}}))
    with pytest.raises(CalibrationError, match=r"m.json: markers\['040'\]: marker id 40 appears twice \(also as '40'\)"):
        load_fixed_markers(f)


def _camera():
    from tracking.geometry import PinholeCamera

    return PinholeCamera(np.array([[900.0, 0, 640], [0, 900, 360], [0, 0, 1]]), np.zeros(5), np.diag([1.0, -1, -1]),
                         np.array([-2.5, 1.5, 3.0]), (1280, 720))


def test_principal_point_outside_the_image(tmp_path):
    from tracking.calibration import CalibrationError, load_intrinsics

    f = tmp_path / "k.json"
    for k, message in (([[900, 0, 1500], [0, 900, 360], [0, 0, 1]], r"principal point x \(1500 px\) .*image_width = 1280"),
                       ([[900, 0, 640], [0, 900, -3], [0, 0, 1]], r"principal point y \(-3 px\) .*image_height = 720")):
        f.write_text(json.dumps({"image_width": 1280, "image_height": 720, "camera_matrix": k, "dist_coeffs": [0.0] * 5}))
        with pytest.raises(CalibrationError, match=f"k.json: camera_matrix: {message}"):
            load_intrinsics(f)
    f.write_text(json.dumps({"image_width": 1280, "image_height": 720, "camera_matrix": _camera().camera_matrix.tolist(),
                             "dist_coeffs": [0.0] * 5}))
    assert load_intrinsics(f).image_size == (1280, 720)


def test_calibration_marker_error_given_twice(tmp_path):
    from tracking.calibration import CalibrationError, CameraCalibration, load_calibration, save_calibration

    path = tmp_path / "cal.json"
    save_calibration(path, CameraCalibration(_camera(), marker_errors_px={40: 0.25}, reprojection_rms_px=0.25,
                                             reprojection_max_px=0.5))
    data = json.loads(path.read_text())
    data["marker_errors_px"] = {"40": 0.25, "0040": 3.0}
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"cal.json: marker_errors_px: marker id 40 appears twice \('0040', '40'\)"):
        load_calibration(path)
    data["marker_errors_px"] = {"40": 0.25}
    data["markers_missing"] = [41, 40]
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"cal.json: markers_missing: marker id 40 is also in marker_errors_px"):
        load_calibration(path)
    data["markers_missing"] = [41]
    path.write_text(json.dumps(data))
    assert load_calibration(path).markers_missing == [41]


def test_a_car_wearing_a_fixed_marker_id(tmp_path):
    from tracking.calibration import CameraCalibration
    from tracking.markers import ArucoTracker

    cal = CameraCalibration(_camera())
    with pytest.raises(ValueError, match=r"car_ids: marker id 41 is also a fixed marker of the track \(fixed ids 40, 41\)"):
        ArucoTracker(cal, 0.055, car_ids=[0, 41], fixed_ids=[40, 41])
    assert ArucoTracker(cal, 0.055, car_ids=[0, 1], fixed_ids=[40, 41]).fixed_ids == {40, 41}
