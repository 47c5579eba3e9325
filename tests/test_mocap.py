"""Motion capture without hardware: rigid-body poses, the mocap-to-track fit, the calibration and survey files,
and the loopback Motive emulator (sim/natnet_emulator.py, written from the NatNet packet layout) decoded by
the NatNet client library (PyPI natnet) through tracking.natnet.NatNetSource, with its fault events."""
from __future__ import annotations

import json
import math
import socket
import struct
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tracking.mocap import (MocapCalibrationError, MocapCar, MocapFrame, MocapTracker, MocapTransform,
                            RigidBodySample, fit_transform, ground_pose, load_mocap_calibration, load_survey_points,
                            mocap_body, mocap_calibration_json)
from tracks.geometry import wrap_angle

natnet = pytest.importorskip("natnet")  # the optional `mocap` extra

from race.world import MonotonicClock  # noqa: E402
from sim.natnet_emulator import MotiveEmulator, frame_packet  # noqa: E402
from tracking.natnet import MocapError, NatNetSource, parse_natnet_url  # noqa: E402


@pytest.mark.parametrize("up_axis", ["y", "z"])
def test_ground_pose_of_a_tilted_body_against_scipy(up_axis):
    """The yaw of the body's +x axis projected on the ground plane, for bodies that are not level (a car
    on a bump), against scipy's rotation of the +x axis."""
    rng = np.random.default_rng(0)
    up = {"y": 1, "z": 2}[up_axis]
    for _ in range(50):
        yaw = rng.uniform(-math.pi, math.pi)
        tilt = Rotation.from_rotvec(rng.normal(0, 0.1, 3))
        about_up = Rotation.from_rotvec(np.eye(3)[up] * yaw)
        q = (about_up * tilt).as_quat()  # scipy: (x, y, z, w), NatNet's order
        forward = (about_up * tilt).apply([1.0, 0.0, 0.0])
        ref = math.atan2(-forward[2], forward[0]) if up_axis == "y" else math.atan2(forward[1], forward[0])
        pos = rng.normal(0, 2, 3)
        u, v, got = ground_pose(pos, q, up_axis)
        assert abs(wrap_angle(got - ref)) < 1e-9
        assert (u, v) == pytest.approx((pos[0], -pos[2]) if up_axis == "y" else (pos[0], pos[1]))
        # A level body: the yaw is the turn about the up axis (right-handed: counter-clockwise seen from above).
        assert abs(wrap_angle(ground_pose(pos, about_up.as_quat(), up_axis)[2] - yaw)) < 1e-9


@pytest.mark.parametrize("up_axis", ["y", "z"])
def test_mocap_body_is_the_inverse_of_ground_pose(up_axis):
    for u, v, yaw in [(1.2, -0.4, 0.3), (-2.0, 1.5, -2.9), (0.0, 0.0, math.pi - 1e-3)]:
        b = mocap_body(u, v, yaw, 0.05, up_axis)
        assert b.position[{"y": 1, "z": 2}[up_axis]] == 0.05
        got = ground_pose(b.position, b.rotation, up_axis)
        assert got[:2] == pytest.approx((u, v)) and abs(wrap_angle(got[2] - yaw)) < 1e-12


def test_transform_round_trip_and_heading():
    t = MocapTransform("y", 0.7, (2.5, 1.5), 1.01)
    x, y, h = t.to_track(0.3, -0.2, 0.1)
    # hand-worked: R(0.7) (0.3, -0.2) * 1.01 + (2.5, 1.5)
    c, s = math.cos(0.7), math.sin(0.7)
    assert (x, y) == pytest.approx((1.01 * (0.3 * c + 0.2 * s) + 2.5, 1.01 * (0.3 * s - 0.2 * c) + 1.5))
    assert h == pytest.approx(0.8)
    assert t.to_mocap(x, y, h) == pytest.approx((0.3, -0.2, 0.1))


@pytest.mark.parametrize("with_scale", [False, True])
def test_fit_recovers_a_known_transform(with_scale):
    rng = np.random.default_rng(3)
    true = MocapTransform("y", -1.1, (2.3, 1.7), 1.004 if with_scale else 1.0)
    track = rng.uniform([0, 0], [5, 3], (6, 2))
    noise = 0.0005
    uv = np.array([true.to_mocap(x, y, 0.0)[:2] for x, y in track]) + rng.normal(0, noise, (6, 2))
    fit = fit_transform(uv, track, "y", with_scale=with_scale)
    t = fit.transform
    assert abs(wrap_angle(t.rotation_rad - true.rotation_rad)) < 1e-3
    assert t.translation_m == pytest.approx(true.translation_m, abs=2e-3)
    assert t.scale == pytest.approx(true.scale, abs=5e-4)
    # residuals: the noise left after fitting 3 (4) parameters to 12 coordinates
    assert 0.2 * noise < fit.rms_m < 2 * noise
    exact = fit_transform(np.array([true.to_mocap(x, y, 0)[:2] for x, y in track]), track, with_scale=with_scale)
    assert exact.rms_m < 1e-9 and abs(wrap_angle(exact.transform.rotation_rad - true.rotation_rad)) < 1e-9


def test_fit_refuses_degenerate_points():
    with pytest.raises(ValueError, match="at least 2"):
        fit_transform([[0, 0]], [[1, 1]])
    with pytest.raises(ValueError, match="coincide"):
        fit_transform([[1, 1], [1, 1]], [[0, 0], [1, 0]])


def test_tracker_subtracts_the_pivot_offset_and_yaw():
    """A rigid body whose pivot is 30 mm ahead and 10 mm left of the reference point and whose +x axis is
    turned 0.2 rad: hand-worked pose of the reference point."""
    t = MocapTransform("z", 0.0, (0.0, 0.0))
    car = MocapCar(key=7, rigid_body_id=3, offset_forward_m=0.03, offset_left_m=0.01, yaw_rad=0.2)
    heading = 0.5
    ref = np.array([1.0, 2.0])
    pivot = ref + 0.03 * np.array([math.cos(heading), math.sin(heading)]) + 0.01 * np.array(
        [-math.sin(heading), math.cos(heading)])
    body = mocap_body(pivot[0], pivot[1], heading + 0.2, 0.05, "z")
    tracker = MocapTracker(t, [car, MocapCar(key=8, rigid_body_id=4)])
    det = tracker.process(MocapFrame(1.5, 10, {3: body, 4: RigidBodySample((0, 0, 0), (0, 0, 0, 1), tracked=False)}))
    m = det.cars[7]
    assert (m.x, m.y, m.heading, m.t_capture_s) == pytest.approx((1.0, 2.0, 0.5, 1.5))
    assert 8 not in det.cars and det.rejected == {8: "untracked"}
    assert tracker.process(MocapFrame(1.6, 11, {})).rejected == {7: "absent", 8: "absent"}


def test_calibration_file_round_trip_and_bad_fields(tmp_path):
    t = fit_transform([[0, 0], [1, 0], [0, 1]], [[2, 1], [2, 2], [1, 1]], "z").transform
    path = tmp_path / "mocap.json"
    path.write_text(json.dumps(mocap_calibration_json(t)))
    back = load_mocap_calibration(path)
    assert back == t and abs(back.rotation_rad - math.pi / 2) < 1e-12
    for change, field in [({"up_axis": "x"}, "up_axis"), ({"translation_m": [1.0]}, "translation_m"),
                          ({"rotation_rad": "1"}, "rotation_rad"), ({"scale": 0}, "scale"), ({"rotaton_rad": 0}, "rotaton_rad")]:
        bad = {**mocap_calibration_json(t), **change}
        path.write_text(json.dumps(bad))
        with pytest.raises(MocapCalibrationError, match=rf"{path}: {field}"):
            load_mocap_calibration(path)
    path.write_text('{"format": "rd3g-mocap-calibration"')
    with pytest.raises(MocapCalibrationError, match=str(path)):
        load_mocap_calibration(path)


def test_survey_points_file_errors_name_row_and_column(tmp_path):
    p = tmp_path / "points.csv"
    p.write_text("name,mocap_x,mocap_y,mocap_z,track_x,track_y\na,0,0,0,1,1\nb,1,0,0,2,1\nc,0,0,x,1,2\n")
    with pytest.raises(MocapCalibrationError, match=r"row 4, column mocap_z: not a number"):
        load_survey_points(p)
    p.write_text("mocap_x,mocap_y,mocap_z,track_x\n0,0,0,1\n")
    with pytest.raises(MocapCalibrationError, match=r"row 1: the header must have the columns"):
        load_survey_points(p)
    p.write_text("mocap_x,mocap_y,mocap_z,track_x,track_y\n0,0,0,1,1\n1,0,0,2,1\n")
    with pytest.raises(MocapCalibrationError, match=r"2 point\(s\); at least 3"):
        load_survey_points(p)


def test_mocap_calibrate_command_recovers_the_transform(tmp_path, capsys):
    """Markers on 5 surveyed points as Motive (Y-up) would report them, 0.3 mm noise: the command's transform
    against the one that made them; a bad row is exit 2 naming file, row and column."""
    from app.cli import main

    true = MocapTransform("y", 0.35, (2.5, 1.5))
    rng = np.random.default_rng(1)
    rows = ["name,mocap_x,mocap_y,mocap_z,track_x,track_y"]
    for i, (x, y) in enumerate([(0.2, 0.2), (4.8, 0.2), (4.8, 2.8), (0.2, 2.8), (2.5, 1.5)]):
        u, v, _ = true.to_mocap(x, y, 0.0)
        b = mocap_body(u + rng.normal(0, 3e-4), v + rng.normal(0, 3e-4), 0.0, 0.012)
        rows.append(f"p{i},{b.position[0]:.5f},{b.position[1]:.5f},{b.position[2]:.5f},{x},{y}")
    points, out = tmp_path / "points.csv", tmp_path / "mocap.json"
    points.write_text("\n".join(rows) + "\n")
    assert main(["mocap-calibrate", str(points), "--out", str(out)]) == 0
    got = load_mocap_calibration(out)
    assert abs(got.rotation_rad - 0.35) < 5e-4 and got.translation_m == pytest.approx((2.5, 1.5), abs=1e-3)
    assert got.residual_rms_m < 1e-3 and got.points == 5
    assert "residual rms" in capsys.readouterr().out
    points.write_text("\n".join(rows[:3] + ["p9,1,2,nan,3,4"] + rows[3:]) + "\n")
    assert main(["mocap-calibrate", str(points), "--out", str(tmp_path / "other.json")]) == 2
    assert f"{points}: row 4, column mocap_z" in capsys.readouterr().err
    assert not (tmp_path / "other.json").exists()


def test_natnet_url():
    a = parse_natnet_url("natnet://192.168.1.20")
    assert (a.host, a.command_port) == ("192.168.1.20", 1510)
    assert parse_natnet_url("natnet://127.0.0.1:4000").command_port == 4000
    assert parse_natnet_url("natnet://10.0.0.2?multicast=239.255.42.99").multicast_group == "239.255.42.99"
    for bad in ("udp://1.2.3.4", "natnet://", "natnet://h:70000", "natnet://h/x", "192.168.1.20", "natnet://h?x=1",
                "natnet://h?multicast=10.0.0.1", "natnet://h?multicast="):
        with pytest.raises(MocapError, match="natnet://|multicast"):
            parse_natnet_url(bad)


def _bodies(poses, tracked=()):
    out = []
    for rid, (u, v, yaw) in poses.items():
        b = mocap_body(u, v, yaw, 0.05)
        out.append((rid, b.position, b.rotation, rid not in tracked, 0.0002))
    return out


@pytest.mark.parametrize("version", [(2, 9), (3, 1), (4, 1)])
def test_emulator_frames_decode_in_the_client_library(version):
    """The emulator's packets against the client library at three NatNet versions: every field the race
    uses comes back (float32 positions, quaternion, tracking flag, frame number, timestamp)."""
    em = MotiveEmulator(version=version)
    source = NatNetSource(parse_natnet_url(f"natnet://127.0.0.1:{em.port}"), MonotonicClock())
    try:
        assert f"NatNet {version[0]}.{version[1]}" in source.server
        poses = {3: (1.25, -0.5, 0.3), 11: (-2.0, 0.75, -2.5)}
        em.send_frame(41, 12.5, [(3, *_bodies(poses)[0][1:]), (11, *_bodies(poses, tracked=(11,))[1][1:])])
        deadline = time.monotonic() + 2
        frame = None
        while frame is None and time.monotonic() < deadline:
            frame = source.read()
            time.sleep(0.002)
        assert frame is not None and frame.index == 41
        assert set(frame.bodies) == {3, 11}
        assert frame.bodies[3].tracked and not frame.bodies[11].tracked
        for rid, (u, v, yaw) in poses.items():
            got = ground_pose(frame.bodies[rid].position, frame.bodies[rid].rotation)
            assert got[:2] == pytest.approx((u, v), abs=1e-6) and abs(wrap_angle(got[2] - yaw)) < 1e-6
    finally:
        source.close()
        em.close()


def _port_pair() -> int:
    """A free UDP port whose successor is free too (Motive's command and data ports)."""
    for _ in range(50):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as a, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b:
            a.bind(("127.0.0.1", 0))
            port = a.getsockname()[1]
            try:
                b.bind(("", port + 1))
            except OSError:
                continue
            return port
    pytest.skip("no free pair of UDP ports")


def test_multicast_stream_decodes():
    """Motive's default transmission: the frames go to the multicast group on the data port."""
    group = "239.255.42.99"
    em = MotiveEmulator(port=_port_pair(), multicast_group=group)
    try:
        source = NatNetSource(parse_natnet_url(f"natnet://127.0.0.1:{em.port}?multicast={group}"), MonotonicClock())
    except MocapError as exc:
        em.close()
        pytest.skip(f"multicast on the loopback interface not available here: {exc}")
    try:
        frame = None
        for i in range(100):
            em.send_frame(i, i / 120, _bodies({4: (0.5, -0.25, 1.0)}))
            time.sleep(0.005)
            frame = source.read() or frame
            if frame is not None:
                break
        assert frame is not None, "no multicast frame received"
        got = ground_pose(frame.bodies[4].position, frame.bodies[4].rotation)
        assert got[:2] == pytest.approx((0.5, -0.25), abs=1e-6) and abs(got[2] - 1.0) < 1e-6
    finally:
        source.close()
        em.close()


def test_frame_layout_by_hand():
    """NatNet 3.1 frame with one rigid body, packed by hand from the layout (not by the emulator's code)."""
    body = struct.pack("<i", 5) + struct.pack("<ii", 0, 0)  # frame 5, no marker sets, no unlabeled markers
    body += struct.pack("<i", 1) + struct.pack("<i3f4ffh", 2, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0, 0.5, 1)
    body += struct.pack("<iiii", 0, 0, 0, 0)  # skeletons, labeled markers, force plates, devices
    body += struct.pack("<IIdQQQh", 0, 0, 1.25, 12_500_000, 12_500_000, 12_500_000, 0)
    expected = struct.pack("<HH", 7, len(body)) + body
    assert frame_packet((3, 1), 5, 1.25, [(2, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), True, 0.5)]) == expected


def test_frame_times_follow_motive_stamps_not_arrival_jitter():
    """Frames sent 1/120 s apart by Motive's stamp but with 0-6 ms of extra delay each: a frame's time is its
    stamp plus the smallest arrival delay so far (never growing), so the jitter that arrival times carry is
    gone from the frames' times."""
    em = MotiveEmulator()
    source = NatNetSource(parse_natnet_url(f"natnet://127.0.0.1:{em.port}"), MonotonicClock(), poll_s=0.0005)
    try:
        rng = np.random.default_rng(5)
        rows = []  # (stamp, frame time, time read)
        t0 = time.monotonic()
        for i in range(40):
            stamp = 100.0 + i / 120
            target = t0 + i / 120 + rng.uniform(0, 0.006)
            while time.monotonic() < target:
                time.sleep(0.0005)
            em.send_frame(i, stamp, _bodies({1: (0.0, 0.0, 0.0)}))
            deadline = time.monotonic() + 0.05
            frame = None
            while frame is None and time.monotonic() < deadline:
                frame = source.read()
                time.sleep(0.0002)
            if frame is not None:
                rows.append((100.0 + frame.index / 120, frame.t_capture_s, time.monotonic()))
        stamp, t, read = np.array(rows).T
        assert len(stamp) >= 30
        offset = t - stamp
        assert np.all(np.diff(offset) <= 1e-9)  # the running minimum of the arrival delays
        late = slice(len(stamp) // 2, None)
        assert np.std(offset[late]) < max(0.5 * np.std((read - stamp)[late]), 2e-4)
    finally:
        source.close()
        em.close()


def test_stall_and_server_gone_are_events_not_exceptions():
    em = MotiveEmulator()
    source = NatNetSource(parse_natnet_url(f"natnet://127.0.0.1:{em.port}"), MonotonicClock(), stall_after_s=0.1)
    try:
        for i in range(5):
            em.send_frame(i, i / 120, _bodies({1: (0.0, 0.0, 0.0)}))
            time.sleep(1 / 120)
        em.stall()
        time.sleep(0.3)
        texts = [t for _, t in source.events()]
        assert any("no frame for" in t for t in texts)
        em.resume()
        em.send_frame(9, 0.1, _bodies({1: (0.0, 0.0, 0.0)}))
        time.sleep(0.1)
        assert any("resumed" in t for _, t in source.events())
        em.close()  # the server goes away: the client's keep-alives are refused
        time.sleep(0.4)
        texts = [t for _, t in source.events()]
        assert any("no frame for" in t for t in texts)
        assert source._thread.is_alive()  # the receive thread survives the refused datagrams
    finally:
        source.close()


def test_unreachable_server_is_an_error_at_start():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # a port nobody answers on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    with pytest.raises(MocapError, match=rf"natnet://127.0.0.1:{port}"):
        NatNetSource(parse_natnet_url(f"natnet://127.0.0.1:{port}"), MonotonicClock(), connect_timeout_s=0.5)
    assert time.monotonic() - t0 < 3.0


def test_race_refuses_a_rigid_body_id_twice_and_a_bad_calibration(tmp_path, capsys):
    """Exit 2 naming the file, car and field, before any world process or socket opens."""
    from app.cli import main

    roster = tmp_path / "roster.toml"
    roster.write_text('[[car]]\nname = "a"\nplanner = "rd3g"\nrigid_body_id = 3\n'
                      '[[car]]\nname = "b"\nplanner = "mpc"\nrigid_body_id = 3\n')
    assert main(["race", "--hil", "--mocap", "natnet://127.0.0.1", "--roster", str(roster), "--rt-priority", "0",
                 "--out", str(tmp_path / "r.rrd")]) == 2
    assert f"{roster}: car b: rigid_body_id: 3 is also car a's" in capsys.readouterr().err
    cal = tmp_path / "mocap.json"
    cal.write_text(json.dumps({**mocap_calibration_json(MocapTransform()), "up_axis": "up"}))
    assert main(["race", "--hil", "--mocap", "natnet://127.0.0.1", "--mocap-calibration", str(cal),
                 "--rt-priority", "0", "--out", str(tmp_path / "r.rrd")]) == 2
    assert f"--mocap-calibration: {cal}: up_axis: expected one of 'y', 'z'" in capsys.readouterr().err
    assert not (tmp_path / "r.rrd").exists()
    assert main(["race", "--mocap", "natnet://127.0.0.1", "--serial", "/dev/null", "--rt-priority", "0",
                 "--out", str(tmp_path / "r.rrd")]) == 2
    assert "--mocap on hardware needs --mocap-calibration" in capsys.readouterr().err


def test_car_file_rigid_body_ids(tmp_path):
    """The car file's [mocap] rigid_body_id when the roster gives none; the same id on two cars is refused."""
    import dataclasses

    from app.cli import UserError
    from app.realtime.mocap import mocap_cars
    from race.loop import CarBinding
    from race.setup import RaceSpec
    from vehicles.params import MocapParams, load_car_params, save_car_params

    car = load_car_params("buzzracer")
    path = tmp_path / "car.toml"
    save_car_params(dataclasses.replace(car, mocap=MocapParams(rigid_body_id=12, offset_forward_m=0.02)), path)
    setup = RaceSpec(car_params=str(path)).load()
    bindings = [CarBinding(c.name, i, i) for i, c in enumerate(setup.cars)]
    with pytest.raises(UserError, match="car opponent: car file mocap.rigid_body_id: 12 is also car rd3g's"):
        mocap_cars(setup, bindings, hil=True)
    roster = tmp_path / "roster.toml"
    roster.write_text(f'[[car]]\nname = "a"\nplanner = "rd3g"\ncar_params = "{path}"\n'
                      f'[[car]]\nname = "b"\nplanner = "mpc"\ncar_params = "{path}"\nrigid_body_id = 4\n')
    from race.roster import load_roster

    setup = RaceSpec(roster=load_roster(roster)).load()
    got = mocap_cars(setup, [CarBinding(c.name, i, i) for i, c in enumerate(setup.cars)], hil=False)
    assert [(m.rigid_body_id, m.offset_forward_m) for m in got] == [(12, 0.02), (4, 0.02)]
