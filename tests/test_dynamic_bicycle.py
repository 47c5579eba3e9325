import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import fsolve

from vehicles.dynamic_bicycle import (
    ModelCoefficients,
    derivative,
    derivative_one,
    jacobians,
    pacejka,
)
from vehicles.params import GRAVITY_MPS2, CarParams, Corrections


def _random_points(rng, n, vx_range):
    states = np.column_stack([
        rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(-4, 4, n),
        rng.uniform(*vx_range, n), rng.uniform(-0.4, 0.4, n), rng.uniform(-6, 6, n),
    ])
    inputs = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-0.47, 0.47, n)])
    return states, inputs


def _finite_difference(state, u, params, h=1e-6):
    A = np.zeros(state.shape[:-1] + (6, 6))
    B = np.zeros(state.shape[:-1] + (6, 2))
    for j in range(6):
        e = np.zeros(6)
        e[j] = h
        A[..., j] = (derivative(state + e, u, params) - derivative(state - e, u, params)) / (2 * h)
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        B[..., j] = (derivative(state, u + e, params) - derivative(state, u - e, params)) / (2 * h)
    return A, B


TUNED = dataclasses.replace(
    CarParams(),
    front_tire=dataclasses.replace(CarParams().front_tire, e=-0.5),
    rear_tire=dataclasses.replace(CarParams().rear_tire, e=0.4),
    corrections=Corrections(steering_offset_rad=0.02, steering_gain=0.9, extra_drag_n_per_mps2=0.01,
                            tire_grip_scale=0.8),
)


@pytest.mark.parametrize("params", [CarParams(), TUNED], ids=["default", "with_corrections"])
@pytest.mark.parametrize("vx_range", [(-0.5, 0.14), (0.16, 0.34), (0.4, 3.5)], ids=["kinematic", "blend", "dynamic"])
def test_analytic_jacobians_match_finite_differences(params, vx_range):
    rng = np.random.default_rng(1)
    states, inputs = _random_points(rng, 300, vx_range)
    # The vx ranges avoid the blend edges, where the clamps make f only once differentiable.
    fx, A, B = jacobians(states, inputs, params)
    A_fd, B_fd = _finite_difference(states, inputs, params)
    np.testing.assert_allclose(fx, derivative(states, inputs, params))
    np.testing.assert_allclose(A, A_fd, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(B, B_fd, rtol=1e-5, atol=1e-4)


def test_batched_cars_with_different_parameters():
    rng = np.random.default_rng(2)
    cars = [CarParams(), TUNED, dataclasses.replace(CarParams(), inertia=dataclasses.replace(
        CarParams().inertia, mass_kg=0.2, yaw_inertia_kgm2=6e-4))]
    states, inputs = _random_points(rng, 3, (0.5, 3.0))
    k = ModelCoefficients.from_params(cars)
    fx, A, B = jacobians(states, inputs, k)
    for i, car in enumerate(cars):
        fi, Ai, Bi = jacobians(states[i], inputs[i], car)
        np.testing.assert_allclose(fx[i], fi)
        np.testing.assert_allclose(A[i], Ai)
        np.testing.assert_allclose(B[i], Bi)
        one = derivative_one(states[i].tolist(), inputs[i].tolist(), ModelCoefficients.from_params(car))
        np.testing.assert_allclose(one, fi, rtol=1e-12, atol=1e-12)
    # A batch of samples for one car, e.g. a horizon: (T, n_cars, 6) broadcasts against (n_cars,).
    many = np.broadcast_to(states, (5, 3, 6))
    np.testing.assert_allclose(derivative(many, np.broadcast_to(inputs, (5, 3, 2)), k)[4], fx)


def test_pacejka_slope_and_peak():
    slip = np.linspace(-1.2, 1.2, 2001)
    b, c, peak, e = 2.3, 1.6, 1.7, -0.4
    force, slope = pacejka(slip, b, c, peak, e)
    np.testing.assert_allclose(slope[1:-1], np.gradient(force, slip)[1:-1], rtol=1e-3, atol=1e-3)
    # The magic formula peaks at exactly D where C*atan(phi) = pi/2.
    assert force.max() == pytest.approx(peak, rel=1e-5)
    assert slope[1000] == pytest.approx(b * c * peak)  # cornering stiffness BCD at zero slip


def test_straight_line_motion_and_drive_force_signs():
    p = CarParams()
    lon = p.longitudinal
    state = np.array([0.0, 0.0, 0.3, 2.0, 0.0, 0.0])
    xdot = derivative(state, np.array([1.0, 0.0]), p)
    assert xdot[0] == pytest.approx(2.0 * math.cos(0.3)) and xdot[1] == pytest.approx(2.0 * math.sin(0.3))
    eps = lon.throttle_smoothing
    expected = (lon.motor_force_n - lon.motor_speed_loss_n_per_mps * 2.0 * (math.hypot(1.0, eps) - eps)
                - lon.rolling_resistance_n * math.tanh(2.0 / lon.rolling_smoothing_speed_mps)
                - lon.drag_n_per_mps2 * 4.0) / p.inertia.mass_kg
    assert xdot[3] == pytest.approx(expected)
    assert xdot[4] == pytest.approx(0.0) and xdot[5] == pytest.approx(0.0)
    # At standstill with no throttle nothing moves (rolling resistance does not push backwards).
    assert np.allclose(derivative(np.zeros(6), np.zeros(2), p), 0.0)


def test_linear_steady_state_cornering_matches_the_understeer_gradient_formula():
    """Small steering at moderate speed: yaw rate r = v*delta / (L + K*v^2) with the linear
    bicycle model's understeer gradient K = m*(lr/Cf - lf/Cr)/L and Cf = B*C*D*F_zf."""
    p = CarParams()
    m, lf, lr = p.inertia.mass_kg, p.geometry.lf_m, p.geometry.lr_m
    L = lf + lr
    cf = p.front_tire.b * p.front_tire.c * p.front_tire.d * m * GRAVITY_MPS2 * lr / L
    cr = p.rear_tire.b * p.rear_tire.c * p.rear_tire.d * m * GRAVITY_MPS2 * lf / L
    K = m * (lr / cf - lf / cr) / L
    for v in (0.8, 1.5, 2.5):
        delta = 0.01

        def residual(z):
            vy, r, throttle = z
            return derivative(np.array([0, 0, 0, v, vy, r]), np.array([throttle, delta]), p)[3:]

        vy, r, _ = fsolve(residual, [0.0, v * delta / L, 0.1], xtol=1e-13)
        assert r == pytest.approx(v * delta / (L + K * v * v), rel=0.01)


def test_kinematic_regime_follows_no_slip_yaw_rate():
    p = CarParams()
    L = p.geometry.wheelbase_m
    vx, delta = 0.1, 0.3
    r_kin = vx * math.tan(delta) / L
    steady = np.array([0, 0, 0, vx, p.geometry.lr_m * r_kin, r_kin])
    xdot = derivative(steady, np.array([0.0, delta]), p)
    assert xdot[4] == pytest.approx(0.0, abs=1e-12) and xdot[5] == pytest.approx(0.0, abs=1e-12)
    # Reversing is handled by the kinematic part: the yaw rate flips sign with vx.
    rev = derivative(np.array([0, 0, 0, -0.3, 0, 0]), np.array([0.0, delta]), p)
    assert rev[5] < 0


def test_bad_shapes_are_rejected():
    with pytest.raises(ValueError, match="state"):
        derivative(np.zeros(5), np.zeros(2), CarParams())
    with pytest.raises(ValueError, match="u"):
        derivative(np.zeros(6), np.zeros(3), CarParams())
