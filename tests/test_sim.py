"""Simulator tests on analytic geometries (ring and straight), so every expectation has an
exact reference independent of tracks/."""

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from sim.collision import footprint_corners, rectangles_overlap
from planning.pursuit import PurePursuitController
from sim.effects import SimEffects, SimEffectsError
from sim.race import LapBookkeeper
from sim.simulator import Simulator
from vehicles.params import CarParams


class RingTrack:
    """Centre line: circle of radius R, driven counter-clockwise, s = 0 at (R, 0)."""

    def __init__(self, radius=1.0, half_width=0.25):
        self.radius, self.half_width = radius, half_width
        self.length = 2 * math.pi * radius

    def to_frenet(self, x, y, heading=None):
        angle = np.mod(np.arctan2(y, x), 2 * np.pi)
        ey = self.radius - np.hypot(x, y)  # left of the direction of travel is positive
        epsi = None if heading is None else np.mod(np.asarray(heading) - angle - np.pi / 2 + np.pi, 2 * np.pi) - np.pi
        return self.radius * angle, ey, epsi

    def position(self, s):
        a = np.asarray(s) / self.radius
        return np.stack([self.radius * np.cos(a), self.radius * np.sin(a)], axis=-1)

    def heading(self, s):
        return np.asarray(s) / self.radius + np.pi / 2

    def curvature(self, s):
        return np.full(np.shape(s), 1.0 / self.radius)

    def is_inside(self, x, y, margin=0.0):
        return np.abs(np.hypot(x, y) - self.radius) <= self.half_width - margin

    def limit_excess_frenet(self, s, ey):
        return np.abs(ey) - self.half_width


class StraightTrack:
    """A long straight along +x, |y| <= half_width; s = x (a 'lap' is the whole length)."""

    def __init__(self, length=100.0, half_width=0.3):
        self.length, self.half_width = length, half_width

    def to_frenet(self, x, y, heading=None):
        return np.mod(x, self.length), np.asarray(y), None if heading is None else np.asarray(heading)

    def is_inside(self, x, y, margin=0.0):
        return np.abs(y) <= self.half_width - margin

    def limit_excess_frenet(self, s, ey):
        return np.abs(ey) - self.half_width


P = CarParams()
L = P.geometry.wheelbase_m


def feedforward(speed, p=P):
    lon = p.longitudinal
    return (lon.rolling_resistance_n + lon.drag_n_per_mps2 * speed**2) / (
        lon.motor_force_n - lon.motor_speed_loss_n_per_mps * speed)


def run_constant(sim, command, duration, dt=0.02):
    log = []
    for _ in range(round(duration / dt)):
        sim.step([command] * sim.n_cars, dt)
        log.append((sim.time, sim.state(0)))
    return log


# ---------------------------------------------------------------- physics references
@pytest.mark.parametrize("extra_drag", [0.0, 0.02])
def test_coasting_matches_the_1d_rolling_and_drag_ode(extra_drag):
    lon, m = P.longitudinal, P.inertia.mass_kg
    sim = Simulator(StraightTrack(), [P], effects=SimEffects(extra_drag_n_per_mps2=extra_drag))
    v0 = 2.5
    sim.reset([[0, 0, 0, v0, 0, 0]])
    log = run_constant(sim, [0.0, 0.0], 1.5, dt=0.05)
    cd = lon.drag_n_per_mps2 + extra_drag

    def rhs(_t, v):
        return [(-lon.rolling_resistance_n * np.tanh(v[0] / lon.rolling_smoothing_speed_mps) - cd * v[0] * abs(v[0])) / m]

    times = np.array([t for t, _ in log])
    ref = solve_ivp(rhs, (0, times[-1]), [v0], t_eval=times, rtol=1e-10, atol=1e-12).y[0]
    sim_v = np.array([x[3] for _, x in log])
    np.testing.assert_allclose(sim_v, ref, rtol=1e-6, atol=1e-7)
    # And the closed form of dv/dt = -a - b v^2 (valid while v >> smoothing speed).
    a, b = lon.rolling_resistance_n / m, cd / m
    closed = np.sqrt(a / b) * np.tan(np.arctan(v0 * np.sqrt(b / a)) - np.sqrt(a * b) * times)
    np.testing.assert_allclose(sim_v, closed, rtol=1e-5)
    assert all(abs(x[1]) < 1e-12 and abs(x[2]) < 1e-12 for _, x in log)


def _fit_circle(xy):
    # Algebraic (Kasa) least-squares circle fit: x^2 + y^2 = 2ax + 2by + c.
    A = np.column_stack([2 * xy[:, 0], 2 * xy[:, 1], np.ones(len(xy))])
    sol = np.linalg.lstsq(A, (xy**2).sum(axis=1), rcond=None)[0]
    return math.sqrt(sol[2] + sol[0] ** 2 + sol[1] ** 2)


def _rear_axle_radius(sim, steering, speed, duration=4.0):
    sim.reset([[0, 0, 0, speed, 0, 0]], initial_inputs=[[feedforward(speed), 0.0]])
    log = run_constant(sim, [feedforward(speed), steering], duration)
    tail = [x for t, x in log if t > duration / 2]
    lr = P.geometry.lr_m
    rear = np.array([[x[0] - lr * math.cos(x[2]), x[1] - lr * math.sin(x[2])] for x in tail])
    return _fit_circle(rear), np.mean([x[3] for x in tail])


@pytest.mark.parametrize("speed", [0.25, 0.5])
@pytest.mark.parametrize("steering", [0.15, 0.35])
def test_low_speed_steady_cornering_has_the_kinematic_radius(speed, steering):
    sim = Simulator(StraightTrack(half_width=100.0), [P])
    radius, _ = _rear_axle_radius(sim, steering, speed)
    assert radius == pytest.approx(L / math.tan(steering), rel=0.03)


def test_cornering_at_speed_understeers_as_the_linear_bicycle_model_predicts():
    # R = (L + K v^2) / delta with the understeer gradient K = m (lr/Cf - lf/Cr) / L.
    m, lf, lr, g = P.inertia.mass_kg, P.geometry.lf_m, P.geometry.lr_m, 9.81
    cf = P.front_tire.b * P.front_tire.c * P.front_tire.d * m * g * lr / L
    cr = P.rear_tire.b * P.rear_tire.c * P.rear_tire.d * m * g * lf / L
    K = m * (lr / cf - lf / cr) / L
    sim = Simulator(StraightTrack(half_width=100.0), [P])
    delta = 0.04
    radius, speed = _rear_axle_radius(sim, delta, 2.0, duration=3.0)
    assert radius == pytest.approx((L + K * speed**2) / delta, rel=0.03)
    assert radius > 1.1 * L / math.tan(delta)


# ---------------------------------------------------------------- collisions
def _polygons_intersect(pa, pb):
    """Independent reference: convex polygons intersect iff an edge pair crosses or one
    contains a vertex of the other."""
    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def segments_cross(p1, p2, q1, q2):
        d1, d2 = cross(q1, q2, p1), cross(q1, q2, p2)
        d3, d4 = cross(p1, p2, q1), cross(p1, p2, q2)
        return (d1 * d2 <= 0) and (d3 * d4 <= 0)

    def contains(poly, pt):
        signs = [cross(poly[k], poly[(k + 1) % 4], pt) for k in range(4)]
        return all(s >= 0 for s in signs) or all(s <= 0 for s in signs)

    for k in range(4):
        for m in range(4):
            if segments_cross(pa[k], pa[(k + 1) % 4], pb[m], pb[(m + 1) % 4]):
                return True
    return contains(pa, pb[0]) or contains(pb, pa[0])


def test_rectangle_overlap_known_cases():
    unit = [1.0, 1.0]
    s2 = math.sqrt(2)
    # A 45-degree square's vertex pokes into an axis-aligned square, or just misses it.
    assert rectangles_overlap([0, 0], 0.0, unit, [1 + s2 - 1e-3, 0], math.pi / 4, unit)
    assert not rectangles_overlap([0, 0], 0.0, unit, [1 + s2 + 1e-3, 0], math.pi / 4, unit)
    # Thin crossing bars (a plus sign) overlap although no vertex is inside the other.
    assert rectangles_overlap([0, 0], 0.0, [2.0, 0.1], [0, 0], math.pi / 2, [2.0, 0.1])
    # Two long thin rotated bars whose bounding boxes overlap but which are parallel and apart.
    assert not rectangles_overlap([0, 0], math.pi / 4, [2.0, 0.1], [0.3, -0.3], math.pi / 4, [2.0, 0.1])
    # Side by side with a 1 mm gap, and touching.
    assert not rectangles_overlap([0, 0], 0.0, [0.08, 0.035], [0, 0.071], 0.0, [0.08, 0.035])
    assert rectangles_overlap([0, 0], 0.0, [0.08, 0.035], [0, 0.07], 0.0, [0.08, 0.035])


def test_rectangle_overlap_agrees_with_polygon_reference_on_random_pairs():
    rng = np.random.default_rng(3)
    n = 2000
    ca, cb = rng.uniform(-0.2, 0.2, (n, 2)), rng.uniform(-0.2, 0.2, (n, 2))
    ha, hb = rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi, np.pi, n)
    halfa, halfb = rng.uniform(0.01, 0.12, (n, 2)), rng.uniform(0.01, 0.12, (n, 2))
    sat = rectangles_overlap(ca, ha, halfa, cb, hb, halfb)
    pa = footprint_corners(ca[:, 0], ca[:, 1], ha, 2 * halfa[:, 0], 2 * halfa[:, 1])
    pb = footprint_corners(cb[:, 0], cb[:, 1], hb, 2 * halfb[:, 0], 2 * halfb[:, 1])
    ref = np.array([_polygons_intersect(pa[i], pb[i]) for i in range(n)])
    assert 0.2 < ref.mean() < 0.8
    np.testing.assert_array_equal(sat, ref)


def test_collision_event_when_a_car_drives_into_a_stopped_one():
    track = StraightTrack()
    sim = Simulator(track, [P, P], check_dt=0.001)
    gap = 0.30  # centre to centre; bodies are 0.16 m long, so contact after 0.14 m
    sim.reset([[0, 0, 0, 1.0, 0, 0], [gap, 0, 0, 0, 0, 0]])
    hits = []
    t = 0.0
    while not hits and t < 1.0:
        hits = [e for e in sim.step([[feedforward(1.0), 0], [0, 0]], 0.001) if e.kind == "collision"]
        t = sim.time
    assert hits and (hits[0].car, hits[0].other) == (0, 1)
    travelled = sim.state(0)[0]
    assert travelled == pytest.approx(gap - P.geometry.footprint_length_m, abs=2e-3)
    assert sim.race_status().collisions == 1
    assert sim.race_status().min_center_distance_m == pytest.approx(gap - travelled, abs=2e-3)


def test_cars_side_by_side_do_not_collide_until_they_touch():
    sim = Simulator(StraightTrack(), [P, P])
    w = P.geometry.footprint_width_m
    sim.reset([[0, -w / 2 - 0.002, 0, 1, 0, 0], [0, w / 2 + 0.002, 0, 1, 0, 0]])
    run_constant(sim, [feedforward(1.0), 0.0], 0.5)
    assert sim.race_status().collisions == 0
    sim.reset([[0, -w / 2 + 0.001, 0, 1, 0, 0], [0, w / 2 - 0.001, 0, 1, 0, 0]])
    assert sim.race_status().collisions == 1 and sim.events[0].time == 0.0


# ---------------------------------------------------------------- track limits
def test_off_track_when_a_corner_crosses_the_outer_edge():
    track = RingTrack(radius=1.0, half_width=0.25)
    sim = Simulator(track, [P], check_dt=0.001)
    # Start on the centre line heading along the tangent and drive straight: the car drifts
    # outward, and the outer front corner leaves the ring at an analytically known y.
    sim.reset([[1.0, 0, math.pi / 2, 1.0, 0, 0]])
    hl, hw = P.geometry.footprint_length_m / 2, P.geometry.footprint_width_m / 2
    y_exit = math.sqrt((1.0 + 0.25) ** 2 - (1.0 + hw) ** 2) - hl
    events = []
    while not events:
        events = [e for e in sim.step([[feedforward(1.0), 0.0]], 0.001) if e.kind == "off_track"]
    assert sim.state(0)[1] == pytest.approx(y_exit, abs=2e-3)
    assert sim.race_status().off_track == (True,)
    assert sim.race_status().off_track_count == (1,)


# ---------------------------------------------------------------- laps and races
def test_lap_bookkeeper_interpolates_crossings_and_ignores_back_and_forth():
    book = LapBookkeeper(track_length=10.0, laps_to_win=2, initial_s=np.array([1.0, 9.0]))
    # Car 0 starts past the line (already racing); car 1 is on the grid behind it.
    events = []
    for k in range(1, 301):
        t = 0.1 * k
        events += book.update(t, np.array([1.0 + 0.5 * t, 9.0 + 0.4 * t]))
    laps = [(e.car, round(e.time, 9), round(e.lap_time, 9)) for e in events if e.kind == "lap"]
    # Car 0 crosses s = 10 at t = 18, then every 20 s; car 1 leaves the grid at t = 2.5 and
    # then needs 25 s per lap.
    assert laps == [(0, 18.0, 18.0), (1, 27.5, 25.0)]
    assert list(book.laps) == [1, 1]

    back = LapBookkeeper(track_length=10.0, laps_to_win=1, initial_s=np.array([9.5]))
    seq = [9.9, 0.1, 9.9, 0.2, 0.5]  # leave grid, back over the line, forward again
    for k, s in enumerate(seq):
        assert back.update(float(k + 1), np.array([s])) == []
    assert list(back.laps) == [0]


def test_race_on_a_ring_with_the_reference_controller():
    track = RingTrack(radius=0.8, half_width=0.25)
    sim = Simulator(track, [P, P], laps_to_win=2, seed=0)
    # Car 1 starts a car length behind car 0, both at rest on the centre line.
    ang = -0.3
    sim.reset([[0.8, 0.0, math.pi / 2, 0, 0, 0],
               [0.8 * math.cos(ang), 0.8 * math.sin(ang), math.pi / 2 + ang, 0, 0, 0]])
    controllers = [PurePursuitController(track, P, target_speed_mps=1.2) for _ in range(2)]
    dt = 1 / 30
    while sim.race_status().finish_times[1] is None and sim.time < 20:
        sim.step([c.command(sim.state(i), dt) for i, c in enumerate(controllers)], dt)
    status = sim.race_status()
    assert status.winner == 0 and status.finish_order == (0, 1)
    assert status.collisions == 0 and status.off_track_count == (0, 0)
    # The second lap is a flying lap at the reference speed.
    for lap_times in status.lap_times:
        assert lap_times[1] == pytest.approx(track.length / 1.2, rel=0.05)
    assert status.min_center_distance_m > 0.15


# ---------------------------------------------------------------- effects, limits, determinism
def _run_with_noise(seed, effects):
    sim = Simulator(RingTrack(), [P, P], effects=effects, seed=seed)
    sim.reset([[1.0, 0, math.pi / 2, 1.0, 0, 1.0], [0, 1.0, math.pi, 1.0, 0, 1.0]])
    out = []
    for k in range(30):
        sim.step([[0.3, 0.1], [0.4, 0.08]], 1 / 30)
        out.append([sim.states, [dataclasses.astuple(sim.measure(i)) for i in range(2)]])
    return out, sim.events


def test_deterministic_given_seed():
    noisy = SimEffects(position_noise_m=0.003, heading_noise_rad=0.01)
    a, ev_a = _run_with_noise(5, noisy)
    b, ev_b = _run_with_noise(5, noisy)
    c, _ = _run_with_noise(6, noisy)
    for (sa, ma), (sb, mb), (sc, mc) in zip(a, b, c):
        np.testing.assert_array_equal(sa, sb)
        assert ma == mb
        np.testing.assert_array_equal(sa, sc)  # physics does not depend on the noise seed
        assert ma != mc
    assert ev_a == ev_b


def test_measurement_noise_has_the_configured_spread():
    sim = Simulator(StraightTrack(), [P], effects=SimEffects(position_noise_m=0.004, heading_noise_rad=0.02), seed=1)
    sim.reset([[1.0, 0.1, 3.1, 0, 0, 0]])
    meas = np.array([dataclasses.astuple(sim.measure(0))[1:4] for _ in range(4000)])
    err = meas - np.array([1.0, 0.1, 3.1])
    err[:, 2] = np.mod(err[:, 2] + np.pi, 2 * np.pi) - np.pi
    assert np.std(err[:, 0]) == pytest.approx(0.004, rel=0.05)
    assert np.std(err[:, 1]) == pytest.approx(0.004, rel=0.05)
    assert np.std(err[:, 2]) == pytest.approx(0.02, rel=0.05)
    assert np.all(np.abs(meas[:, 2]) <= np.pi)
    clean = Simulator(StraightTrack(), [P])
    clean.reset([[1.0, 0.1, 3.1, 0, 0, 0]])
    m = clean.measure(0)
    assert (m.x, m.y, m.t) == (1.0, 0.1, 0.0) and m.heading == pytest.approx(3.1, abs=1e-12)


@pytest.mark.parametrize("delay", [0.0, 0.05, 0.12])
def test_steering_delay_shifts_the_response_by_the_delay(delay):
    sim = Simulator(StraightTrack(), [P], effects=SimEffects(steering_delay_s=delay))
    sim.reset([[0, 0, 0, 1.0, 0, 0]], initial_inputs=[[feedforward(1.0), 0.0]])
    sim.step([[feedforward(1.0), 0.0]], 0.1)  # the step is commanded at t = 0.1 s
    onset = None
    for _ in range(300):
        sim.step([[feedforward(1.0), 0.3]], 0.001)
        if onset is None and abs(sim.state(0)[5]) > 1e-9:
            onset = sim.time
    # The yaw rate starts in the first physics step after the command reaches the servo.
    assert onset == pytest.approx(0.1 + delay + 0.001, abs=1e-9)
    assert sim.applied_inputs(0)[1] == pytest.approx(0.3)


def test_throttle_delay_shifts_the_acceleration():
    sim = Simulator(StraightTrack(), [P], effects=SimEffects(throttle_delay_s=0.07))
    sim.reset([[0, 0, 0, 0, 0, 0]])
    speeds = []
    for _ in range(100):
        sim.step([[1.0, 0.0]], 0.001)
        speeds.append(sim.state(0)[3])
    assert max(speeds[:70]) == 0.0 and speeds[71] > 0.0


def test_actuator_limits_and_rate_limits():
    sim = Simulator(StraightTrack(), [P])
    sim.reset([[0, 0, 0, 1.0, 0, 0]])
    a = P.actuators
    sim.step([[5.0, 1.0]], 0.01)
    # After 10 ms the servo has slewed 10 ms * rate, the ESC 10 ms * its rate.
    np.testing.assert_allclose(sim.applied_inputs(0), [0.01 * a.throttle_rate_limit_per_s,
                                                        0.01 * a.steering_rate_limit_radps])
    sim.step([[5.0, 1.0]], 0.5)
    np.testing.assert_allclose(sim.applied_inputs(0), [a.throttle_max, a.max_steering_rad])


@pytest.mark.parametrize("offset, gain, command", [(0.05, 1.0, 0.0), (0.0, 0.5, 0.3), (-0.02, 1.3, 0.2)])
def test_steering_offset_and_gain_change_the_turning_radius(offset, gain, command):
    sim = Simulator(StraightTrack(half_width=100.0), [P],
                    effects=SimEffects(steering_offset_rad=offset, steering_gain=gain))
    radius, _ = _rear_axle_radius(sim, command, 0.5)
    assert radius == pytest.approx(L / abs(math.tan(gain * command + offset)), rel=0.03)


def test_grip_scale_lowers_the_cornering_limit():
    def lateral_accel(grip):
        sim = Simulator(StraightTrack(half_width=100.0), [P], effects=SimEffects(grip_scale=grip))
        sim.reset([[0, 0, 0, 2.0, 0, 0]], initial_inputs=[[0.6, 0.0]])
        log = run_constant(sim, [0.6, P.actuators.max_steering_rad], 3.0)
        tail = np.array([x for t, x in log if t > 2.0])
        return float(np.mean(np.hypot(tail[:, 3], tail[:, 4]) * np.abs(tail[:, 5])))

    full, half = lateral_accel(1.0), lateral_accel(0.5)
    g = 9.81
    peak_full = g * (P.front_tire.d * P.geometry.lr_m + P.rear_tire.d * P.geometry.lf_m) / L
    assert full <= peak_full * 1.02
    assert half <= 0.5 * peak_full * 1.02
    assert half < 0.75 * full


def test_batched_physics_matches_per_car_physics():
    cars = [P, dataclasses.replace(P, inertia=dataclasses.replace(P.inertia, mass_kg=0.2)), P]
    start = [[0, 0, 0, 1.0, 0, 0], [0, 1, 0.5, 2.0, 0.1, 0.5], [0, -1, -0.2, 0.1, 0, 0]]
    results = []
    for threshold in (0, 8):
        sim = Simulator(StraightTrack(half_width=100.0), cars, batch_threshold=threshold)
        sim.reset(start)
        for k in range(20):
            sim.step([[0.5, 0.2], [0.3, -0.1], [1.0, 0.4]], 0.02)
        results.append(sim.states)
    np.testing.assert_allclose(results[0], results[1], rtol=1e-12, atol=1e-12)


def test_control_clock_does_not_drift_with_30_hz_on_1_ms_physics():
    sim = Simulator(StraightTrack(), [P])
    sim.reset([[0, 0, 0, 0, 0, 0]])
    for _ in range(300):
        sim.step([[0, 0]], 1 / 30)
    assert sim.time == pytest.approx(10.0, abs=1e-12)


def test_bad_inputs_name_the_field():
    with pytest.raises(SimEffectsError, match="SimEffects.steering_gain"):
        SimEffects(steering_gain=0.0)
    with pytest.raises(SimEffectsError, match="SimEffects.position_noise_m"):
        SimEffects(position_noise_m=-1.0)
    sim = Simulator(StraightTrack(), [P, P])
    with pytest.raises(RuntimeError, match="before reset"):
        sim.step([[0, 0], [0, 0]], 0.01)
    with pytest.raises(ValueError, match="initial_states"):
        sim.reset([[0, 0, 0, 0, 0, 0]])
    sim.reset(np.zeros((2, 6)) + [[0, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0]])
    with pytest.raises(ValueError, match="commands"):
        sim.step([[0, 0]], 0.01)
    with pytest.raises(ValueError, match="commands: non-finite command for car 1"):
        sim.step([[0, 0], [np.nan, 0]], 0.01)
    with pytest.raises(ValueError, match="dt_control"):
        sim.step([[0, 0], [0, 0]], 0.0)
    with pytest.raises(ValueError, match="check_dt"):
        Simulator(StraightTrack(), [P], check_dt=0.0015)
    with pytest.raises(ValueError, match="effects"):
        Simulator(StraightTrack(), [P, P], effects=[SimEffects()])
    with pytest.raises(IndexError):
        sim.state(2)
