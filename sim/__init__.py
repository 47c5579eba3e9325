"""Multi-car race simulator (see docs/simulator.md)."""

from sim.controllers import PurePursuitController
from sim.effects import SimEffects, SimEffectsError
from sim.race import RaceStatus, SimEvent
from sim.simulator import PoseMeasurement, Simulator

__all__ = [
    "PoseMeasurement",
    "PurePursuitController",
    "RaceStatus",
    "SimEffects",
    "SimEffectsError",
    "SimEvent",
    "Simulator",
]
