"""The planners' constraints in tight turns (BuzzRacer tile track `full`, 0.3 m quarter turns) against
independent geometry: the collision separation on (s, ey) against the Cartesian distance of the same
points, and the track-limit bound on the inside of a turn against the radius the car turns at full lock."""
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
    cfg = PlannerConfig()
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
    constraint's separation |(a ds, dey)| says the cars are at least d_min apart, so are the points in the
    plane (track.to_cartesian); side by side (same s) the separation is the lateral gap, as in the plane,
    where the isotropic disc d_min / a asked for 1/a times more room."""
    p = _planner(full, car)
    s_turn = _turn_s(full)
    d_min = p.tm.collision_distance()
    rng = np.random.default_rng(0)
    checked = 0
    for s0 in s_turn + np.array([-0.4, -0.2, 0.0, 0.2]):
        low, high = p.ey_limits([s0])
        scale = p.tm.along_track_scale([s0])
        assert 0.2 <= scale < 0.5  # a real stretch: kappa ~ 3.3/m over the window
        s = s0 + rng.uniform(-0.3, 0.3, (5000, 2))
        ey = rng.uniform(low, high, (5000, 2))
        sep = frenet_separation(s[:, 0] - s[:, 1], ey[:, 0] - ey[:, 1], scale)
        x, y = full.to_cartesian(s, ey)
        cart = np.hypot(x[:, 0] - x[:, 1], y[:, 0] - y[:, 1])
        safe = sep >= d_min
        assert np.all(cart[safe] >= d_min - 1e-3), float(np.min(cart[safe]))
        checked += int(np.sum(safe))
        # Side by side: the separation is the lateral gap, which is the Cartesian distance.
        xs, ys = full.to_cartesian(np.full(2, s0), np.array([low, low + d_min]))
        assert float(frenet_separation(0.0, d_min, scale)) == pytest.approx(d_min)
        assert float(np.hypot(xs[1] - xs[0], ys[1] - ys[0])) == pytest.approx(d_min, abs=1e-6)
        assert d_min / scale > 2.0 * d_min  # what the isotropic disc asked for here
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
