"""EKF tests against analytic trajectories and finite differences."""
import math

import numpy as np
import pytest

from tracking.estimator import CarEKF, EstimatorConfig, MultiCarEstimator
from tracking.motion import ctrv_jacobian, ctrv_transition, slip_jacobian, slip_transition
from tracks.geometry import wrap_angle

RATE_HZ = 60.0


def numeric_jacobian(state, dt, eps=1e-6):
    jac = np.zeros((5, 5))
    for j in range(5):
        d = np.zeros(5)
        d[j] = eps
        jac[:, j] = (ctrv_transition(state + d, dt) - ctrv_transition(state - d, dt)) / (2 * eps)
    return jac


@pytest.mark.parametrize("yaw_rate", [0.0, 1e-5, 2e-3, 0.7, -2.5])
def test_jacobian_matches_finite_differences(yaw_rate):
    state = np.array([1.2, -0.4, 2.3, 1.7, yaw_rate])
    for dt in (1 / 60, 0.2):
        np.testing.assert_allclose(ctrv_jacobian(state, dt), numeric_jacobian(state, dt), atol=1e-7)
    # the estimator's model with sideslip
    slip_state = np.append(state, -0.04)
    for dt in (1 / 60, 0.2):
        numeric = np.zeros((6, 6))
        for j in range(6):
            d = np.zeros(6)
            d[j] = 1e-6
            numeric[:, j] = (slip_transition(slip_state + d, dt) - slip_transition(slip_state - d, dt)) / 2e-6
        np.testing.assert_allclose(slip_jacobian(slip_state, dt), numeric, atol=1e-7)


def test_slip_transition_matches_circle_geometry():
    # A car on a circle of radius R about (0, R), travelling along +x at the origin with its nose
    # turned beta off the direction of travel: after dt the position is on the circle, the heading
    # is still beta off the tangent.
    v, radius, dt, beta = 1.5, 0.8, 0.37, -0.05
    w = v / radius
    out = slip_transition(np.array([0.0, 0.0, -beta, v, w, beta]), dt)
    ang = w * dt
    np.testing.assert_allclose(out, [radius * math.sin(ang), radius * (1 - math.cos(ang)), ang - beta, v, w, beta],
                               atol=1e-12)


def test_transition_matches_circle_geometry():
    # Analytic circle: centre at (0, R) for a car at the origin heading +x turning left.
    v, radius, dt = 1.5, 0.8, 0.37
    w = v / radius
    out = ctrv_transition(np.array([0.0, 0.0, 0.0, v, w]), dt)
    ang = w * dt
    np.testing.assert_allclose(out[:3], [radius * math.sin(ang), radius * (1 - math.cos(ang)), ang], atol=1e-12)


def circle_measurements(v, radius, duration_s, rng, pos_std=0.002, head_std=math.radians(0.5), sideslip=0.0):
    """A car on a circle (analytic); its heading is ``sideslip`` off the direction of travel."""
    t = np.arange(0, duration_s, 1 / RATE_HZ)
    ang = v / radius * t
    x = 2.5 + radius * np.sin(ang)
    y = 1.5 - radius * np.cos(ang)
    heading = wrap_angle(ang - sideslip)
    noisy = np.column_stack([x + rng.normal(0, pos_std, t.size), y + rng.normal(0, pos_std, t.size),
                             heading + rng.normal(0, head_std, t.size)])
    return t, np.column_stack([x, y, heading]), noisy


@pytest.mark.parametrize("sideslip", [0.0, math.radians(-3.0)])
def test_circle_recovers_speed_and_yaw_rate(sideslip):
    rng = np.random.default_rng(0)
    v, radius = 1.8, 0.9
    t, truth, meas = circle_measurements(v, radius, 4.0, rng, sideslip=sideslip)
    # Low process noise: steady cornering (the defaults are tuned for racing manoeuvres).
    config = EstimatorConfig(position_std_m=0.002, heading_std_rad=math.radians(0.5), accel_noise=1.0,
                             yaw_accel_noise=1.0, sideslip_noise=0.05)
    ekf = CarEKF(config)
    speeds, yaw_rates, sideslips, filter_err, meas_err, ahead_err = [], [], [], [], [], []
    for ti, z, true_pose in zip(t, meas, truth):
        assert ekf.update(ti, *z).accepted  # heading wraps through +-pi several times
        speeds.append(ekf.x[3])
        yaw_rates.append(ekf.x[4])
        sideslips.append(ekf.x[5])
        filter_err.append(math.hypot(*(ekf.x[:2] - true_pose[:2])))
        meas_err.append(math.hypot(*(z[:2] - true_pose[:2])))
        ahead = ekf.predict_to(ti + 0.05)  # latency compensation: 50 ms ahead, on the analytic circle
        ang = v / radius * (ti + 0.05)
        ahead_err.append(math.hypot(ahead.x - (2.5 + radius * math.sin(ang)), ahead.y - (1.5 - radius * math.cos(ang))))
    tail = slice(len(t) // 2, None)
    assert abs(np.mean(speeds[tail]) - v) < 0.02
    assert abs(np.mean(yaw_rates[tail]) - v / radius) < 0.03
    assert abs(np.mean(sideslips[tail]) - sideslip) < math.radians(0.5)
    assert np.max(np.abs(np.array(speeds[tail]) - v)) < 0.3
    # the filtered positions beat the raw measurements (2 mm noise per axis)
    assert np.median(filter_err[tail]) < 0.7 * np.median(meas_err[tail])
    # 50 ms ahead within 5 mm (median); a filter that moves the car along its heading is 10 mm off with
    # the 3 degree sideslip (measured with the previous CTRV filter), 4 mm without.
    assert np.median(ahead_err[tail]) < 0.005


def straight_measurements(rng, v=1.2, heading=0.6, duration_s=3.0):
    t = np.arange(0, duration_s, 1 / RATE_HZ)
    x = 0.5 + v * t * math.cos(heading)
    y = 0.4 + v * t * math.sin(heading)
    meas = np.column_stack([x + rng.normal(0, 0.002, t.size), y + rng.normal(0, 0.002, t.size),
                            heading + rng.normal(0, math.radians(0.5), t.size)])
    return t, np.column_stack([x, y]), meas


def test_prediction_through_one_second_occlusion_on_straight():
    rng = np.random.default_rng(1)
    t, truth, meas = straight_measurements(rng)
    # Low process noise: the car drives straight at constant speed (the default is tuned for racing).
    config = EstimatorConfig(position_std_m=0.002, heading_std_rad=math.radians(0.5), accel_noise=0.3,
                             yaw_accel_noise=0.3)
    ekf = CarEKF(config)
    occluded = (t > 1.5) & (t <= 2.5)
    for ti, z in zip(t[t <= 1.5], meas[t <= 1.5]):
        ekf.update(ti, *z)
    snapshot = ekf.x.copy()
    for ti, xy in zip(t[occluded], truth[occluded]):
        state = ekf.predict_to(ti)
        err = np.array([state.x - xy[0], state.y - xy[1]])
        assert np.linalg.norm(err) < 0.01 + 0.06 * (ti - 1.5)  # 6 cm after 1 s at 1.2 m/s
        assert err @ np.linalg.solve(state.covariance[:2, :2], err) < 13.8  # inside the 99.9 % ellipse
    np.testing.assert_array_equal(ekf.x, snapshot)  # predict_to leaves the filter alone
    assert ekf.is_lost(t[occluded][-1])  # 1 s > default 0.5 s
    # After the gap the next measurement restarts the filter (counted as an initialisation).
    first_after = np.argmax(t > 2.5)
    assert ekf.update(t[first_after], *meas[first_after]).reason == "initialized"


def test_gating_rejects_injected_outlier():
    rng = np.random.default_rng(2)
    t, truth, meas = straight_measurements(rng, duration_s=1.0)
    ekf = CarEKF()
    for ti, z in zip(t[:40], meas[:40]):
        ekf.update(ti, *z)
    before = ekf.predict_to(t[40])
    result = ekf.update(t[40], meas[40, 0] + 0.25, meas[40, 1], meas[40, 2])
    assert not result.accepted and result.reason == "gated" and result.mahalanobis_sq > 16.27
    assert ekf.counts["gated"] == 1
    np.testing.assert_allclose(ekf.x, before.vector)  # rejected measurement changes nothing but time
    for ti, z in zip(t[41:], meas[41:]):
        assert ekf.update(ti, *z).accepted
    assert ekf.counts["gated"] == 1


def test_heading_outlier_across_wrap_is_accepted_when_close():
    ekf = CarEKF()
    ekf.update(0.0, 1.0, 1.0, math.pi - 0.01)
    result = ekf.update(1 / 60, 1.0, 1.0, -math.pi + 0.01)  # 0.02 rad apart across the wrap
    assert result.accepted
    assert abs(wrap_angle(ekf.x[2] - math.pi)) < 0.02


def test_nan_and_out_of_order_rejected_with_reason():
    ekf = CarEKF()
    assert ekf.update(0.0, float("nan"), 1.0, 0.0).reason == "nan"
    assert not ekf.initialized
    ekf.update(0.1, 1.0, 1.0, 0.0)
    assert ekf.update(0.2, 1.0, float("inf"), 0.0).reason == "nan"
    assert ekf.update(0.05, 1.0, 1.0, 0.0).reason == "out_of_order"
    assert ekf.counts["nan"] == 2 and ekf.counts["out_of_order"] == 1


def test_lost_after_configurable_timeout():
    ekf = CarEKF(EstimatorConfig(lost_after_s=0.2))
    ekf.update(0.0, 1.0, 1.0, 0.0)
    assert not ekf.is_lost(0.19)
    assert ekf.is_lost(0.21)
    multi = MultiCarEstimator(EstimatorConfig(lost_after_s=0.2))
    multi.update(0.0, [(3, 1.0, 1.0, 0.0), (5, 2.0, 1.0, 0.0)])
    multi.update(0.15, [(3, 1.0, 1.0, 0.0)])
    assert multi.lost_ids(0.3) == [5]
    assert set(multi.states_at(0.3)) == {3}
    assert set(multi.states_at(0.3, include_lost=True)) == {3, 5}


def test_config_validation_names_field():
    with pytest.raises(ValueError, match="lost_after_s"):
        EstimatorConfig(lost_after_s=-1)


def swerve_measurements(speed=2.0, wheelbase=0.09, rate_hz=RATE_HZ):
    """Exact poses of a kinematic bicycle at constant speed that swerves: steering +20 deg, then
    -20 deg reached at 8 rad/s, i.e. the yaw rate reverses from +8 to -8 rad/s in 0.09 s.
    Integrated with 0.1 ms Euler steps (the reference; independent of the CTRV model)."""
    dt_fine, t_end = 1e-4, 1.0
    x = y = heading = 0.0
    delta = math.radians(20)
    poses, t_samples, yaw_rates = [], [], []
    every = int(round(1 / (rate_hz * dt_fine)))
    for n in range(int(t_end / dt_fine)):
        t = n * dt_fine
        target = math.radians(20) if t < 0.4 else -math.radians(20)
        delta += float(np.clip(target - delta, -8.0 * dt_fine, 8.0 * dt_fine))
        if n % every == 0:
            t_samples.append(t)
            poses.append((x, y, float(wrap_angle(heading))))
            yaw_rates.append(speed * math.tan(delta) / wheelbase)
        x += speed * math.cos(heading) * dt_fine
        y += speed * math.sin(heading) * dt_fine
        heading += speed * math.tan(delta) / wheelbase * dt_fine
    return np.array(t_samples), np.array(poses), np.array(yaw_rates)


def test_swerve_is_reacquired_instead_of_lost():
    t, poses, yaw_rates = swerve_measurements()
    stiff = EstimatorConfig(yaw_accel_noise=2.0)  # a model that cannot follow the swerve
    never = CarEKF(EstimatorConfig(yaw_accel_noise=2.0, reacquire_after=10 ** 6))
    ekf = CarEKF(stiff)
    reasons = [ekf.update(ti, *z).reason for ti, z in zip(t, poses)]
    for ti, z in zip(t, poses):
        never.update(ti, *z)
    assert never.counts["gated"] >= 10  # without re-acquisition the swerve is gated until lost...
    assert ekf.counts["gated"] >= 2 and ekf.counts["reacquired"] >= 1
    # ...with it, no more than reacquire_after - 1 measurements in a row are rejected,
    run = longest = 0
    for r in reasons:
        run = run + 1 if r == "gated" else 0
        longest = max(longest, run)
    assert longest <= stiff.reacquire_after - 1
    assert not ekf.is_lost(t[-1])
    # and the filter ends on the true speed and yaw rate.
    assert abs(ekf.x[3] - 2.0) < 0.05
    assert abs(ekf.x[4] - yaw_rates[-1]) < 0.3


def test_outliers_that_disagree_are_never_reacquired():
    rng = np.random.default_rng(3)
    t, truth, meas = straight_measurements(rng, duration_s=1.0)
    ekf = CarEKF()
    for ti, z in zip(t[:30], meas[:30]):
        ekf.update(ti, *z)
    # Misreads scattered 0.3-1 m away, each far from the previous one: not one car's motion.
    for k in range(30, 40):
        jump = rng.uniform(0.3, 1.0) * np.array([math.cos(k), math.sin(k)])
        result = ekf.update(t[k], *(meas[k, :2] + jump), meas[k, 2])
        assert result.reason == "gated"
    assert ekf.counts["reacquired"] == 0
    assert ekf.update(t[40], *meas[40]).accepted  # the real car is still tracked


def test_car_moved_elsewhere_is_reacquired_before_lost():
    ekf = CarEKF()
    for k in range(30):
        ekf.update(k / RATE_HZ, 1.0 + 1.5 * k / RATE_HZ, 1.0, 0.0)
    # Picked up and put down 0.5 m aside, driving on at 1.5 m/s: three frames later it is tracked again.
    reasons = [ekf.update(k / RATE_HZ, 1.0 + 1.5 * k / RATE_HZ, 1.5, 0.0).reason for k in range(30, 34)]
    assert reasons[:2] == ["gated", "gated"] and reasons[2] == "reacquired" and reasons[3] == "accepted"
    assert abs(ekf.x[3] - 1.5) < 0.05 and abs(ekf.x[1] - 1.5) < 0.01


@pytest.mark.parametrize("known", [False, True])
def test_launch_with_known_acceleration(known):
    """A car launching at 5 m/s^2 along x from rest, measured exactly at 60 Hz from t = 0, with the
    acceleration known from t = 0.05 s. Analytic reference: v = a (t - 0.05), x = a (t - 0.05)^2 / 2.
    Without the input the random-walk speed lags; with it the filter follows."""
    a, t_on = 5.0, 0.05

    def accel(t0, t1):
        lo, hi = max(t0, t_on), t1
        return [(hi - lo, a)] if hi > lo else []

    ekf = CarEKF()
    if known:
        ekf.accel_input = accel
    speed_errors = []
    for k in range(25):
        t = k / 60.0
        x = 0.5 * a * max(t - t_on, 0.0) ** 2
        ekf.update(t, x, 0.0, 0.0)
        if t >= 0.25:
            speed_errors.append(ekf.predict_to(t).speed - a * (t - t_on))
    worst = max(abs(e) for e in speed_errors)
    if known:
        assert worst < 0.02
        ahead = ekf.predict_to(0.45)  # predicted 50 ms past the last measurement
        assert ahead.x == pytest.approx(0.5 * a * (0.45 - t_on) ** 2, abs=1e-3)
        assert ahead.speed == pytest.approx(a * (0.45 - t_on), abs=0.03)
    else:
        assert worst > 0.05
