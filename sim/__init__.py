"""Multi-car race simulator (see docs/simulator.md)."""

from sim.effects import SimEffects, SimEffectsError
from sim.race import RaceStatus, SimEvent
from sim.simulator import PoseMeasurement, Simulator

__all__ = [
    "PoseMeasurement",
    "RaceStatus",
    "SimEffects",
    "SimEffectsError",
    "SimEvent",
    "Simulator",
]
