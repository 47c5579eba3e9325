"""Bad link configuration on the command line: exit code 2 naming the flag, the car file's field or the
id at fault, before any world, camera or serial port is opened (so no frame is ever sent)."""
from __future__ import annotations

import dataclasses

import pytest

from app.cli import main
from vehicles.params import CarParams


@pytest.fixture
def nothing_opens(monkeypatch):
    """Fail the test if the race or check gets as far as opening the HIL world or a serial link."""
    import race.hil as hil
    import vehicles.serial_link as serial_link

    def refuse(*args, **kwargs):
        raise AssertionError("opened before the configuration was valid")

    monkeypatch.setattr(hil.HilWorld, "__init__", refuse)
    monkeypatch.setattr(serial_link.SerialCarLink, "start", refuse)


def car_file(tmp_path, name, radio: str) -> str:
    path = tmp_path / f"{name}.toml"
    # a car file has every table (the loader rejects one cut short); empty tables take the defaults
    tables = "".join(f"[{f.name}]\n" for f in dataclasses.fields(CarParams) if f.name not in ("name", "radio"))
    path.write_text(f'name = "{name}"\n{tables}[radio]\n{radio}\n')
    return str(path)


@pytest.mark.parametrize("command", ["race", "check"])
def test_unknown_protocol(command, capsys, nothing_opens):
    assert main([command, "--hil", "--link-protocol", "sbus"]) == 2
    assert "--link-protocol: unknown protocol 'sbus'; expected one of rd3g, buzzracer-fhss" in capsys.readouterr().err


def test_car_without_modem_id(tmp_path, capsys, nothing_opens):
    files = f"{car_file(tmp_path, 'red', 'modem_id = 0')},{car_file(tmp_path, 'blue', 'throttle_neutral_us = 1500')}"
    assert main(["race", "--hil", "--link-protocol", "buzzracer-fhss", "--car-files", files]) == 2
    err = capsys.readouterr().err
    assert "blue.toml: radio.modem_id is not set (car opponent" in err


def test_two_cars_with_one_modem_id(tmp_path, capsys, nothing_opens):
    files = f"{car_file(tmp_path, 'red', 'modem_id = 2')},{car_file(tmp_path, 'blue', 'modem_id = 2')}"
    assert main(["check", "--hil", "--link-protocol", "buzzracer-fhss", "--car-files", files]) == 2
    assert "both cars have radio.modem_id 2" in capsys.readouterr().err


def test_modem_id_beyond_the_box(capsys, nothing_opens):
    assert main(["race", "--hil", "--link-protocol", "buzzracer-fhss", "--radio-ids", "0,6"]) == 2
    assert "modem id 6 must be an int in 0..5" in capsys.readouterr().err


@pytest.mark.parametrize("radio, field", [
    ("modem_id = 0\nsteering_left_us = 900", "radio.steering_left_us: must be in [1000, 2000]"),
    ("modem_id = 0\nthrottle_neutral_us = 1950", "radio.throttle_neutral_us: must lie strictly between"),
])
def test_pulse_limits(tmp_path, capsys, nothing_opens, radio, field):
    files = f"{car_file(tmp_path, 'red', radio)},{car_file(tmp_path, 'blue', 'modem_id = 1')}"
    assert main(["race", "--hil", "--link-protocol", "buzzracer-fhss", "--car-files", files]) == 2
    err = capsys.readouterr().err
    assert "--car-files:" in err and "red.toml" in err and field in err


def test_pure_simulation_checks_the_link_too(tmp_path, capsys):
    assert main(["race", "--link-capture", str(tmp_path / "x.txt"), "--link-protocol", "sbus"]) == 2
    assert "unknown protocol 'sbus'" in capsys.readouterr().err
    assert not (tmp_path / "x.txt").exists()
