"""The planners' constraints in tight turns (BuzzRacer tile track `full`, 0.3 m quarter turns) against
independent geometry: the collision separation on (s, ey) against the Cartesian distance of the same
points, and the track-limit bound on the inside of a turn against the radius the car turns at full lock."""
import math

import numpy as np
import pytest

from planning import CommandMapper, FrenetTrackModel, PlannerConfig, RacingPlanner
from planning.frenet import frenet_separation, min_turn_radius
from solver_cpp import KinematicBicycle
from tracks import load_track

PERIOD = 1.0 / 30.0


@pytest.fixture(scope="module")
def full():
    return load_track("buzzracer:full")


def _planner(track, car):
    cfg = PlannerConfig(line="centre")  # the constant-offset limits; a test sets a racing line where it needs one
    return RacingPlanner(FrenetTrackModel(track, car, cfg), CommandMapper(car, PERIOD, cfg.max_brake_mps2,
                                                                          cfg.steering_margin),
                         cfg, PERIOD, opponent_top_speed_mps=2.0)


def _turn_s(track) -> float:
    """Arc length of the middle of the first tight turn (|kappa| > 3/m)."""
    s = np.arange(0.0, track.length, 0.005)
    kappa = np.abs(track.curvature(s))
    first = int(np.argmax(kappa > 3.0))
    last = first + int(np.argmax(kappa[first:] < 3.0))
    return float(0.5 * (s[first] + s[last - 1]))


def test_separation_never_overstates_the_cartesian_distance_and_is_exact_across(full, car):
    """Pairs of points in and around a 0.3 m turn, both within the planner's ey limits: whenever the
    constraint's separation |(a ds, dey)| says the cars are at least d_min apart (the lateral clearance,
    0.25 m), the points in the plane (track.to_cartesian) are at least the footprint distance (0.195 m) apart;
    side by side (same s) the separation is the lateral gap, as in the plane, where the isotropic disc
    d_min / a asked for 1/a times more room."""
    p = _planner(full, car)
    s_turn = _turn_s(full)
    d_min, d_fp = p.tm.collision_distance(), p.tm.footprint_distance()
    assert d_min == 0.25 and d_fp == pytest.approx(0.195, abs=1e-3)
    rng = np.random.default_rng(0)
    checked = 0
    for s0 in s_turn + np.array([-0.4, -0.2, 0.0, 0.2]):
        low, high = p.ey_limits([s0])
        scale = p.tm.along_track_scale([s0])
        factor = scale * d_fp / d_min  # the curvature factor 1 - |kappa| ey_max
        assert 0.2 <= factor < 0.5  # a real stretch: kappa ~ 3.3/m over the window
        s = s0 + rng.uniform(-0.3, 0.3, (20000, 2))
        ey = rng.uniform(low, high, (20000, 2))
        sep = frenet_separation(s[:, 0] - s[:, 1], ey[:, 0] - ey[:, 1], scale)
        x, y = full.to_cartesian(s, ey)
        cart = np.hypot(x[:, 0] - x[:, 1], y[:, 0] - y[:, 1])
        safe = sep >= d_min
        assert np.all(cart[safe] >= d_fp - 1e-3), float(np.min(cart[safe]))
        checked += int(np.sum(safe))
        # Side by side: the separation is the lateral gap, which is the Cartesian distance.
        xs, ys = full.to_cartesian(np.full(2, s0), np.array([low, low + d_min]))
        assert float(frenet_separation(0.0, d_min, scale)) == pytest.approx(d_min)
        assert float(np.hypot(xs[1] - xs[0], ys[1] - ys[0])) == pytest.approx(d_min, abs=1e-6)
        assert d_fp / factor > 2.0 * d_fp  # what the isotropic footprint disc asked for here
    assert checked > 500


def test_inner_bound_keeps_the_cars_tightest_radius(full, car):
    """At every point of the track, the highest (lowest) ey a plan may take leaves a path radius on the
    inside of every left (right) turn in the planning window of at least the radius of the car's CG at the
    planner's steering limit, measured here from a Cartesian kinematic-bicycle rollout at full lock (the
    circle through three of its points); the nominal track-limit bound (0.205 m) did not: a 0.095 m path
    radius in the 0.3 m turns."""
    p = _planner(full, car)
    g = car.geometry
    radius = {}
    for side, delta in (("left", p.mapper.delta_max), ("right", p.mapper.delta_min)):
        model = KinematicBicycle(lf=g.lf_m, lr=g.lr_m).build(0.01)
        x = np.asarray(model.rollout(np.array([0.0, 0.0, 0.5, 0.0]), np.tile([0.0, delta], (200, 1))))
        a, b, c = x[0, :2], x[60, :2], x[120, :2]
        area2 = abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
        radius[side] = np.linalg.norm(b - a) * np.linalg.norm(c - b) * np.linalg.norm(a - c) / (2.0 * area2)
        assert min_turn_radius(g.lf_m, g.lr_m, delta) == pytest.approx(radius[side], rel=1e-3)
    assert p.tm.ey_bound([0.0]) > 1.0 / 3.33 - radius["left"] + 0.05  # the bound alone would allow less
    for s0 in np.arange(0.0, full.length, 0.05):
        low, high = p.ey_limits([s0])
        window = np.mod(p.tm.window([s0]), full.length)
        kappa = np.asarray(full.curvature(window))
        left, right = kappa[kappa > 1e-6], -kappa[kappa < -1e-6]
        if left.size:
            assert np.min(1.0 / left) - high >= radius["left"] * (1 - 1e-3)
        if right.size:
            assert np.min(1.0 / right) + low >= radius["right"] * (1 - 1e-3)
        assert -p.tm.ey_bound([s0]) <= low < high <= p.tm.ey_bound([s0])


def test_a_turn_tighter_than_the_car_is_an_error_naming_the_turn(car):
    """A planning window whose left and right turns leave no ey between their inner limits: a clear error."""
    p = _planner(load_track("buzzracer:full"), car)
    with pytest.raises(ValueError, match="too tight"):
        p.tm.ey_limits([0.0], 5.0, 5.0)


def test_a_racing_line_keeps_its_apex_within_the_limits(full, car):
    """Following a racing line, the limits never cut off the line's own offsets (plus line_margin_m) in the
    window, within the track-limit bound: a line that crosses a 0.3 m turn on a wide radius touches the
    inside at its apex, where a constant-offset path could not go. A line (written here) that dips to
    -0.17 m at the middle of a right turn and is 0 elsewhere: without it the inside of that turn is held
    at the constant-offset limit; with it the lower limit reaches the dip plus the margin."""
    from tracks.racing_line import RacingLine

    p = _planner(full, car)
    n = 2000
    s = np.arange(n) * full.length / n
    kappa = np.asarray(full.curvature(s))
    right = int(np.argmax(kappa < -3.0))
    apex = right + int(np.argmax(kappa[right:] > -3.0)) // 2
    ey = np.zeros(n)
    ey[apex - 5: apex + 5] = -0.17
    s0 = float(s[apex]) - 1.0
    low, _ = p.ey_limits([s0])
    assert low == pytest.approx(-(0.3 - min_turn_radius(car.geometry.lf_m, car.geometry.lr_m, p.mapper.delta_min)),
                                abs=1e-3)
    p.line = RacingLine(full.name, float(full.length), None, ey, np.full(n, 1.0), np.zeros(n), np.full(n, full.length / n))
    low_line, high_line = p.ey_limits([s0])
    bound = p.tm.ey_bound([s0])
    assert low_line == pytest.approx(max(-0.17 - p.config.line_margin_m, -bound))
    assert high_line <= bound


def test_path_curvature_is_the_inverse_of_the_cg_turn_radius():
    """Hand-worked: lf = lr = 0.05 m, tan(delta) = 0.2: beta = atan(0.05 * 0.2 / 0.1) = atan(0.1), sin(beta) / lr =
    (0.1 / sqrt(1.01)) / 0.05 = 1.990074 1/m, i.e. radius sqrt(0.05^2 + (0.1 / 0.2)^2) = 0.502494 m; signed with delta."""
    from planning.frenet import path_curvature

    delta = math.atan(0.2)
    assert path_curvature(delta, 0.05, 0.05) == pytest.approx(1.990074, abs=1e-6)
    assert path_curvature(-delta, 0.05, 0.05) == pytest.approx(-1.990074, abs=1e-6)
    assert min_turn_radius(0.05, 0.05, delta) == pytest.approx(math.hypot(0.05, 0.1 / 0.2), rel=1e-12)  # 0.502494
    assert path_curvature(0.0, 0.05, 0.05) == 0.0


def test_path_speed_bound_on_a_path_of_known_curvature():
    """Hand-worked: three segments at 2 m/s for 0.1 s each (0.2 m), the last a turn of curvature -4/m; lateral
    limit 4 m/s^2, braking 5 m/s^2. The turn allows sqrt(4 / 4) = 1 m/s; 0.2 m before it the car may be at
    sqrt(1 + 2 * 5 * 0.2) = sqrt(3) m/s, 0.4 m before it at sqrt(5) m/s. A straight path is not bounded, a
    constant curvature of 1/m gives sqrt(4) = 2 m/s everywhere."""
    from planning.reference import path_speed_bounds

    bounds = path_speed_bounds([2.0, 2.0, 2.0], [0.0, 0.0, -4.0], 0.1, 4.0, 5.0)
    np.testing.assert_allclose(bounds, [math.sqrt(5.0), math.sqrt(3.0), 1.0], rtol=1e-12)
    assert np.all(np.isinf(path_speed_bounds([2.0, 2.0], [0.0, 0.0], 0.1, 4.0, 5.0)))
    np.testing.assert_allclose(path_speed_bounds([1.0] * 4, [1.0] * 4, 0.1, 4.0, 5.0), 2.0)


def _entry_speeds(full, car, ey0: float, path_lateral_accel: float) -> list[tuple[float, float]]:
    """(s, v) of a car following the racing line alone (MPC planner, another car far ahead) in closed loop on
    the planning model, from 0.6 m before the right turn at s = 11.47 m of `full` at 1.95 m/s and offset ey0."""
    from planning import MPCOpponent

    cfg = PlannerConfig(line="racing", path_lateral_accel_mps2=path_lateral_accel)
    p = MPCOpponent(FrenetTrackModel(full, car, cfg), CommandMapper(car, PERIOD, cfg.max_brake_mps2, cfg.steering_margin),
                    cfg, PERIOD)
    model = p.tm.rollout_model(PERIOD)
    x, other = np.array([10.9, ey0, 1.95, 0.0]), np.array([16.9, 0.0, 0.5, 0.0])
    out = []
    for _ in range(30):
        x = np.asarray(model.rollout(x, np.asarray(p.plan(x, other).u[:1])))[1]
        other[0] += 0.5 * PERIOD
        out.append((float(x[0]), float(x[2])))
    return out


def test_a_car_entering_a_turn_off_the_line_slows(full, car):
    """The racing line takes this 0.3 m quarter turn at 1.9 m/s on a wide radius (0.8 m); a car 0.15 m outside
    the line turns on a tighter path, which the kinematic planning model drives at any speed. With the tyre-aware
    bound (path_lateral_accel_mps2 a, default 6 m/s^2) it slows in the turn to about the speed of its path, 0.1 m
    outside the centre line (radius 0.4 m: sqrt(a x 0.4) = 1.55 m/s, within 0.05 m/s: the bound acts one plan
    late), at least 0.05 m/s below the run without it (1e6 m/s^2: no bound), and not below that run before the
    turn."""
    def in_turn(run):
        return max(v for s, v in run if 11.6 <= s <= 11.95), min(v for s, v in run if 11.6 <= s <= 11.95)

    a = PlannerConfig().path_lateral_accel_mps2
    bounded, free = _entry_speeds(full, car, 0.15, a), _entry_speeds(full, car, 0.15, 1e6)
    assert in_turn(bounded)[1] < min(in_turn(free)[1] - 0.05, math.sqrt(a * 0.4) + 0.05)
    before = [vb - vf for (sb, vb), (sf, vf) in zip(bounded, free) if sb < 11.3]
    assert min(before) > -0.05


def test_a_fallback_does_not_steer_into_a_car_alongside(full, car):
    """Default car: footprint distance 0.195 m (along the track), lateral clearance 0.25 m (sideways). On a
    straight (kappa = 0: arc-length gaps are Cartesian), a car at ey = -0.19 m with another 0.1 m behind at
    ey = 0 (0.19 m to its left, inside 0.25 m): a fallback target of +0.15 m (across the other car) is held at
    the car's own offset, -0.19 m; with the other car 0.3 m to the left (ey = 0.11 m) it may go to
    0.11 - 0.25 = -0.14 m; a car 0.3 m behind (farther than 0.195 m along the track) or on the right does not
    hold it."""
    p = _planner(full, car)
    assert p.tm.footprint_distance() == pytest.approx(0.195, abs=1e-3) and p.tm.collision_distance() == 0.25
    s = np.arange(0.0, full.length, 0.01)
    straight = float(s[int(np.argmax(np.abs(full.curvature(s)) < 1e-9) + 20)])
    x0 = np.array([straight + 0.5, -0.19, 1.0, 0.0])
    assert abs(float(full.curvature(x0[0]))) < 1e-9
    assert p._clear_of_alongside(x0, 0.15, [(x0[0] - 0.1, 0.0)]) == pytest.approx(-0.19)
    assert p._clear_of_alongside(x0, 0.15, [(x0[0] - 0.1, 0.11)]) == pytest.approx(0.11 - 0.25)
    assert p._clear_of_alongside(x0, 0.15, [(x0[0] - 0.3, 0.0)]) == 0.15
    assert p._clear_of_alongside(x0, -0.1, [(x0[0], -0.4)]) == -0.1
    # In a right turn of radius 0.3 m (kappa = -3.33/m), our car at ey = +0.05 m: a car 0.35 m behind on the
    # inside (ey = -0.15 m, local scale 1 - kappa ey = 0.5: 0.175 m of arc there) is alongside, 0.2 m to the
    # right (closer than 0.25 m), so a target right of our offset is held there; on the outside (ey = +0.15 m,
    # scale 1.5; ours 1.17: 0.41 m) it is not alongside.
    right = _turn_s(full)
    assert float(full.curvature(right)) == pytest.approx(-1.0 / 0.3)
    xr = np.array([right, 0.05, 1.0, 0.0])
    assert p._clear_of_alongside(xr, -0.15, [(right - 0.35, -0.15)]) == pytest.approx(0.05)
    assert p._clear_of_alongside(xr, -0.15, [(right - 0.35, 0.15)]) == -0.15


def test_a_fallback_beside_a_car_holds_its_offset_along_the_track(full, car):
    """The fallback's steering (Stanley law: delta = atan(L kappa) - (epsi - epsi_ref) - atan(k (ey - ey_ref) / v))
    hand-worked on a straight (kappa = 0), k = fallback_lateral_gain = 2/s: our car at ey = -0.19 m, 1 m/s, heading
    0.2 rad to the left, tracking a plan at ey = -0.15 m with that heading (cutting across to the left). Alone (the
    other car 0.3 m behind, not alongside) the heading term is 0.2 - 0.2 = 0 and delta = atan(2 x 0.04 / 1) =
    +0.080 rad: on across. With a car alongside 0.19 m to its left (ey = 0, 0.1 m behind) the target is held at
    -0.19 m and the offset along the track (epsi_ref = 0): delta = -0.2 rad, steering away from that car."""
    p = _planner(full, car)
    c = p.config
    s = np.arange(0.0, full.length, 0.01)
    straight = float(s[int(np.argmax(np.abs(full.curvature(s)) < 1e-9) + 20)])
    x0 = np.array([straight + 0.5, -0.19, 1.0, 0.2])
    assert abs(float(full.curvature(x0[0]))) < 1e-9
    assert abs(p.mapper.delta_min) > 0.2 and p.mapper.delta_max > 0.2  # the expected steering is within the bounds
    assert c.fallback_lateral_gain == 2.0
    for other, delta in (((x0[0] - 0.3, 0.0), math.atan(0.08)), ((x0[0] - 0.1, 0.0), -0.2)):
        ref = np.tile([x0[0], -0.15, x0[2], x0[3]], (c.horizon + 1, 1))
        ref[:, 0] += np.arange(c.horizon + 1) * c.plan_dt_s * x0[2]
        p._reference, p._reference_age_s = ref, 0.0
        u = p._track_previous(x0, 0.205, u_all=np.zeros((1, c.horizon, 2)), others=[other])
        assert u[0, 0, 1] == pytest.approx(delta, abs=1e-9)


def test_lateral_clearance_widens_the_constraint_sideways_only(full, car):
    """Hand-worked from the car file: footprint radius hypot(L/2 + |offset|, W/2), footprint distance twice that
    plus collision_margin_m. With lateral_clearance_m = 0.25 the constraint's d_min is 0.25 m and the
    along-track scale grows by 0.25 / d_fp, so a gap purely along the track is safe from d_fp / (1 - |kappa|
    ey_max) on, as without it; lateral_clearance_m below d_fp (0 included) leaves the footprint distance."""
    g = car.geometry
    d_fp = 2.0 * math.hypot(0.5 * g.footprint_length_m + abs(g.footprint_offset_m), 0.5 * g.footprint_width_m) + 0.02
    s0 = _turn_s(full)
    scales = {}
    for lat in (0.0, 0.1, 0.25):
        cfg = PlannerConfig(lateral_clearance_m=lat)
        tm = FrenetTrackModel(full, car, cfg)
        assert tm.footprint_distance() == pytest.approx(d_fp, rel=1e-12)
        assert tm.collision_distance() == pytest.approx(max(d_fp, lat), rel=1e-12)
        scales[lat] = tm.along_track_scale([s0])
        # Along the track the boundary of |(a ds, 0)| >= d_min lies at the same ds for every clearance.
        ds = tm.collision_distance() / scales[lat]
        assert float(frenet_separation(ds, 0.0, scales[lat])) == pytest.approx(tm.collision_distance())
    assert scales[0.1] == scales[0.0]
    assert scales[0.25] == pytest.approx(scales[0.0] * 0.25 / d_fp, rel=1e-12)


def test_separation_ramp_opens_the_gap_at_the_recovery_rate_in_metres(full, car):
    """The ramp's rate in the constraint's measure |(a ds, dey)|, per m/s of recovery, is the measure over the
    Frenet distance |(ds, dey)|, at most 1. Hand-worked with the tile turn's scale: in line (dey = 0) it is a
    (0.3 m/s of measure would ask the rear car to drop back at 0.3 / a m/s); side by side (ds = 0) it is 1; at
    ds = 0.3 m, dey = 0.4 m and a = 0.5 it is hypot(0.15, 0.4) / 0.5 = 0.8544. Independent check: a gap that
    opens along its own direction at r m/s grows the measure at r times that rate (a finite difference)."""
    p = _planner(full, car)
    s0 = _turn_s(full)
    a = p.tm.along_track_scale([s0, s0 - 0.3], [0.15, 0.15])
    assert 0.3 < a < 0.5  # the tile turn stretches the along-track gap
    assert p.recovery_rate_factor(0.3, 0.0, a) == pytest.approx(a)
    assert p.recovery_rate_factor(-0.3, 0.0, a) == pytest.approx(a)
    assert p.recovery_rate_factor(0.0, 0.12, a) == pytest.approx(1.0)
    assert p.recovery_rate_factor(0.3, 0.4, 0.5) == pytest.approx(math.hypot(0.15, 0.4) / 0.5, rel=1e-12)
    assert p.recovery_rate_factor(0.3, 0.0, 1.2) == 1.0  # never faster than separation_recovery_mps
    assert p.recovery_rate_factor(0.0, 0.0, a) == 1.0
    r, dt = p.config.separation_recovery_mps, 1e-6
    for gap in ((0.3, 0.0), (0.2, 0.1), (0.05, 0.15), (-0.25, -0.05)):
        g = np.array(gap)
        opened = g + r * dt * g / np.linalg.norm(g)
        rate = (float(frenet_separation(*opened, a)) - float(frenet_separation(*g, a))) / dt
        assert rate == pytest.approx(r * p.recovery_rate_factor(*g, a), rel=1e-4)
    # In a plan: a pair 0.3 m apart in line in the turn is relaxed, and its distance grows at
    # separation_recovery_mps x a per second of measure (0.3 m/s of gap along the track) from k = 2 on.
    nominal = p.tm.collision_distance()
    steps = p._distance_steps(0.1, nominal, p.recovery_rate_factor(0.3, 0.0, a))
    k = np.arange(1, p.config.horizon + 1)
    assert np.allclose(steps, np.minimum(nominal, 0.1 + r * a * p.config.plan_dt_s * np.maximum(k - 2, 0)))
