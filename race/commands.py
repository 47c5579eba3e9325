"""The one mapping between a planner's physical command and the serial link's normalised command.

Planners command [throttle in [-1, 1], steering angle in rad] (planning.CommandMapper: the inverse
longitudinal model gives the throttle); the protocol carries both normalised to [-1, 1]
(vehicles.protocol.CarCommand), steering as a fraction of the car file's ``max_steering_rad``. The loop
maps one way when it sends, the HIL world the other way when it drives the simulated cars."""
from __future__ import annotations

from vehicles.params import CarParams
from vehicles.protocol import CarCommand


def link_command(car: CarParams, throttle: float, steering_rad: float) -> CarCommand:
    """Physical -> normalised (values outside [-1, 1] are left for the protocol to reject)."""
    return CarCommand(steering=steering_rad / car.actuators.max_steering_rad, throttle=throttle)


def physical_command(car: CarParams, command: CarCommand) -> tuple[float, float]:
    """Normalised -> (throttle, steering angle rad)."""
    return command.throttle, command.steering * car.actuators.max_steering_rad
