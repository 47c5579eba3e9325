import dataclasses
import math

import pytest
from scipy.optimize import brentq

from vehicles.params import (
    CarParams,
    CarParamsError,
    Corrections,
    GRAVITY_MPS2,
    car_params_from_dict,
    dump_car_params,
    load_car_params,
    resolve_car_path,
    save_car_params,
)


def test_bare_name_loads_the_shipped_file_which_matches_the_documented_defaults():
    assert resolve_car_path("buzzracer").name == "buzzracer.toml"
    p = load_car_params("buzzracer")
    assert p == CarParams()
    assert p.geometry.wheelbase_m == pytest.approx(0.090)
    assert p.inertia.mass_kg == pytest.approx(0.167, abs=1e-3)
    assert math.degrees(p.actuators.max_steering_rad) == pytest.approx(27.0)
    assert p.corrections == Corrections()


def test_defaults_reproduce_the_published_performance_figures():
    p = CarParams()
    lon = p.longitudinal
    # Top speed: where the full-throttle drive force balances the resistances.
    def net(v):
        return lon.motor_force_n - lon.motor_speed_loss_n_per_mps * v - lon.rolling_resistance_n - lon.drag_n_per_mps2 * v * v

    assert brentq(net, 0.0, 20.0) == pytest.approx(3.5, abs=0.05)
    # Launch acceleration from the BuzzRacer throttle identification (6.17 m/s^2).
    assert lon.motor_force_n / p.inertia.mass_kg == pytest.approx(6.17, rel=0.01)
    # Cornering: the axle with less grip bounds lateral acceleration near 1 g.
    g_limit = min(p.front_tire.d, p.rear_tire.d)
    assert 0.9 <= g_limit <= 1.2
    assert GRAVITY_MPS2 == pytest.approx(9.81)


def test_round_trip_through_toml(tmp_path):
    p = CarParams(
        name='car "two"',
        geometry=dataclasses.replace(CarParams().geometry, lf_m=0.05, lr_m=0.043),
        marker=dataclasses.replace(CarParams().marker, aruco_id=7, height_m=0.05),
        corrections=Corrections(
            steering_delay_s=0.033, throttle_delay_s=0.07, steering_offset_rad=-0.0123456789012345,
            steering_gain=0.93, extra_drag_n_per_mps2=0.01, tire_grip_scale=0.8,
        ),
        rear_tire=dataclasses.replace(CarParams().rear_tire, e=-0.3),
    )
    path = save_car_params(p, tmp_path / "two.toml")
    assert load_car_params(path) == p
    assert load_car_params(str(path)) == p
    assert dump_car_params(load_car_params(path)) == path.read_text()


def test_missing_fields_take_defaults_and_integers_are_accepted_for_floats():
    p = car_params_from_dict({"inertia": {"mass_kg": 1}, "marker": {"aruco_id": 3}})
    assert p.inertia.mass_kg == 1.0 and isinstance(p.inertia.mass_kg, float)
    assert p.marker.aruco_id == 3
    assert p.geometry == CarParams().geometry


@pytest.mark.parametrize(
    "data, field",
    [
        ({"inertia": {"mass_kg": -0.1}}, "inertia.mass_kg"),
        ({"inertia": {"mass_kg": "heavy"}}, "inertia.mass_kg"),
        ({"inertia": {"mass_kg": True}}, "inertia.mass_kg"),
        ({"geometry": {"lf": 0.05}}, "geometry"),
        ({"geometry": {"lf_m": float("nan")}}, "geometry.lf_m"),
        ({"front_tire": {"c": 3.0}}, "front_tire.c"),
        ({"marker": {"aruco_id": 1.5}}, "marker.aruco_id"),
        ({"corrections": {"steering_gain": 0.0}}, "corrections.steering_gain"),
        ({"corrections": {"steering_delay_s": -0.01}}, "corrections.steering_delay_s"),
        ({"model": {"blend_speed_low_mps": 0.5, "blend_speed_high_mps": 0.4}}, "model.blend_speed_high_mps"),
        ({"actuators": {"throttle_min": 0.0, "throttle_max": 0.0}}, "actuators.throttle_max"),
        ({"tyres": {}}, "tyres"),
        ({"geometry": 3}, "geometry"),
        ({"name": ""}, "name"),
    ],
)
def test_validation_errors_name_the_field(data, field):
    with pytest.raises(CarParamsError) as err:
        car_params_from_dict(data, source="car.toml")
    assert field in str(err.value)
    assert "car.toml" in str(err.value)


def test_file_errors_name_the_file(tmp_path):
    with pytest.raises(CarParamsError, match="not found"):
        load_car_params(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[geometry\nlf_m = 1\n")
    with pytest.raises(CarParamsError, match="bad.toml: not valid TOML"):
        load_car_params(bad)
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("[inertia]\nyaw_inertia_kgm2 = 0\n")
    with pytest.raises(CarParamsError, match=r"wrong.toml: inertia.yaw_inertia_kgm2: must be > 0"):
        load_car_params(wrong)


def test_constructing_invalid_params_in_code_is_rejected_too():
    with pytest.raises(CarParamsError, match="inertia.mass_kg"):
        CarParams(inertia=dataclasses.replace(CarParams().inertia, mass_kg=0.0))
