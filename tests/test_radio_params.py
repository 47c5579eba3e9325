"""The [radio] section of car files: the FHSS box calibration (typed, validated, written back)."""
import dataclasses
import math

import pytest

from vehicles.fhss import servo_calibration
from vehicles.params import CarParams, CarParamsError, car_params_from_dict, dump_car_params, load_car_params
from vehicles.protocol import CarCommand, ProtocolError


def test_defaults_leave_modem_id_unset(tmp_path):
    car = load_car_params("buzzracer")
    assert car.radio.modem_id is None
    with pytest.raises(ProtocolError, match="radio.modem_id is not set"):
        servo_calibration(car)
    # written back without a modem id, loads back equal
    path = tmp_path / "car.toml"
    path.write_text(dump_car_params(car))
    assert load_car_params(path) == car


def test_calibration_from_the_file(tmp_path):
    path = tmp_path / "red.toml"
    tables = "".join(f"[{f.name}]\n" for f in dataclasses.fields(CarParams) if f.name not in ("name", "radio"))
    path.write_text('name = "red"\n' + tables + "[radio]\nmodem_id = 5\nsteering_left_max_rad = 0.4049\nsteering_right_max_rad = 0.5201\n"
                    "throttle_forward_us = 1150\nthrottle_reverse_us = 1850\n")
    car = load_car_params(path)
    again = tmp_path / "again.toml"
    again.write_text(dump_car_params(car))
    assert load_car_params(again) == car
    cal = servo_calibration(car)
    assert cal.modem_id == 5 and cal.left_max_rad == 0.4049 and cal.right_max_rad == 0.5201
    assert cal.steering_full_scale_rad == car.actuators.max_steering_rad
    assert cal.pulses(CarCommand(0.0, 1.0)) == (1500, 1150)  # a reversed throttle channel is allowed


@pytest.mark.parametrize("radio, field", [
    ({"modem_id": 6}, "radio.modem_id"),
    ({"modem_id": 1.0}, "radio.modem_id"),
    ({"steering_left_us": 990}, "radio.steering_left_us"),
    ({"throttle_forward_us": 2100}, "radio.throttle_forward_us"),
    ({"steering_neutral_us": 2000}, "radio.steering_neutral_us"),  # at an end: not between left and right
    ({"throttle_neutral_us": 1000}, "radio.throttle_neutral_us"),
    ({"steering_right_max_rad": 0.0}, "radio.steering_right_max_rad"),
    ({"pulse": 1500}, "radio.pulse: unknown key"),
])
def test_bad_radio_values_name_the_field(radio, field):
    with pytest.raises(CarParamsError, match=field.replace(".", r"\.")):
        car_params_from_dict({"radio": radio}, source="cars/x.toml")


def test_angles_default_to_the_actuator_limit():
    car = car_params_from_dict({"radio": {"modem_id": 0}})
    cal = servo_calibration(car)
    assert cal.left_max_rad == cal.right_max_rad == car.actuators.max_steering_rad == pytest.approx(math.radians(27))
