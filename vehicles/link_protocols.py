"""The frame encoders a ``SerialCarLink`` can speak, by name (the one list of protocol names).

* ``rd3g``: this project's frame (vehicles/protocol.py): version, sequence number, CRC-16, any car
  ids; decoded by ``vehicles.virtual_box.VirtualCarBox`` (simulation and HIL).
* ``buzzracer-fhss``: the BuzzRacer transmitter box (vehicles/fhss.py): 12 servo pulses, CRC-8; the
  default on hardware (docs/serial-protocol.md says why).
"""
from __future__ import annotations

from typing import Mapping, Protocol, Sequence

from vehicles.fhss import FhssEncoder, ServoCalibration
from vehicles.protocol import CarCommand, Rd3gEncoder

PROTOCOLS = ("rd3g", "buzzracer-fhss")
HARDWARE_DEFAULT = "buzzracer-fhss"
HIL_DEFAULT = "rd3g"


class FrameEncoder(Protocol):
    name: str
    max_cars: int
    max_frame_len: int             # bytes, for the rate the baud rate allows
    max_rate_hz: float | None      # the receiver's own cap on frames per second (None: none)

    def check_car_id(self, car_id: object) -> int:
        """The id, or ProtocolError naming it if this receiver cannot drive it."""

    def limit(self, car_id: int, command: CarCommand) -> tuple[CarCommand, int]:
        """The command within the car's limits and how many values were clamped."""

    def encode(self, seq: int, commands: Mapping[int, CarCommand]) -> bytes:
        """One frame carrying ``commands`` (ids checked, values limited); ``seq`` counts frames."""


class UnknownProtocolError(ValueError):
    pass


def check_protocol(name: str, field: str = "--link-protocol") -> str:
    if name not in PROTOCOLS:
        raise UnknownProtocolError(f"{field}: unknown protocol {name!r}; expected one of {', '.join(PROTOCOLS)}")
    return name


def make_encoder(name: str, calibrations: Sequence[ServoCalibration] = ()) -> FrameEncoder:
    """The encoder for protocol ``name``; ``calibrations`` (one per car) are needed by buzzracer-fhss."""
    check_protocol(name)
    if name == "buzzracer-fhss":
        return FhssEncoder(calibrations)
    return Rd3gEncoder()
