"""Logged commands in the car's physical units (docs/sysid.md, "Command conventions").

A log's command columns are in a declared convention (``sysid.log.CommandUnits``): steering as a wheel
angle (rad), as the race link's normalised command, or as a receiver pulse width (us, e.g. from a link
capture); throttle as the normalised throttle, a pulse width, or a speed set-point (m/s, a car with a
speed controller). The mappings are the race stack's own: normalised commands through
``race.commands.physical_command`` (as the race link maps them), pulse widths through the car file's
``[radio]`` calibration (``vehicles.fhss.servo_calibration``, as the FHSS box drives the receiver).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from race.commands import physical_command
from sysid.log import CommandStream, CommandUnits, DriveLog, LogFormatError
from vehicles.fhss import servo_calibration
from vehicles.params import CarParams
from vehicles.protocol import CarCommand

PHYSICAL = CommandUnits(steering="rad", throttle="normalized")


def _convert(car: CarParams, units: CommandUnits, throttle: np.ndarray, steering: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    if units.steering == "normalized":
        _, steering = physical_command(car, CarCommand(steering=steering, throttle=0.0))
    elif units.steering == "us":
        cal = servo_calibration(car, modem_id=0)  # the slot does not enter the pulse mapping
        steering = np.vectorize(cal.steering_rad, otypes=[float])(steering)
    if units.throttle == "normalized":
        throttle, _ = physical_command(car, CarCommand(steering=0.0, throttle=throttle))
    elif units.throttle == "us":
        cal = servo_calibration(car, modem_id=0)
        throttle = np.vectorize(cal.throttle, otypes=[float])(throttle)
    return np.asarray(throttle, dtype=float), np.asarray(steering, dtype=float)


def to_physical(log: DriveLog, car: CarParams, car_source: str) -> DriveLog:
    """The log with steering in rad and throttle as the car's input (normalised throttle, or the speed
    set-point for a speed set-point car). A throttle log for a speed set-point car, or the reverse, is an
    error naming the log and the car file's field."""
    speed_car = car.speed_control.active
    if log.units.throttle == "speed" and not speed_car:
        raise LogFormatError(f"{log.source}: column throttle holds a speed set-point, but the car file {car_source} "
                             "drives by throttle (speed_control.gain_per_s = 0); use a speed set-point car file")
    if speed_car and log.units.throttle != "speed":
        raise LogFormatError(f"{log.source}: the car file {car_source} is a speed set-point car "
                             f"(speed_control.gain_per_s = {car.speed_control.gain_per_s}), but column throttle is "
                             f"declared {log.units.throttle}; declare --throttle-units speed")
    if log.units.steering == "rad" and log.units.throttle in ("normalized", "speed"):
        return log
    throttle, steering = _convert(car, log.units, log.throttle, log.steering)
    commands = log.commands
    if commands is not None:
        c_throttle, c_steering = _convert(car, log.units, commands.throttle, commands.steering)
        commands = CommandStream(commands.t, c_throttle, c_steering)
    units = CommandUnits(steering="rad", throttle="speed" if speed_car else "normalized")
    return dataclasses.replace(log, throttle=throttle, steering=steering, commands=commands, units=units)
