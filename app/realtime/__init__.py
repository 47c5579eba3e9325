"""The real-time race stack (docs/race-stack.md): a fixed-rate loop frame -> detect -> estimate ->
plan -> command -> telemetry with a deadline monitor and safety holds, run against the
hardware-in-the-loop world (``--hil``) or real hardware (``--camera/--serial/--calibration``)."""
from .config import FaultSpec, LoopConfig, StageBudgets, parse_fault
from .loop import CarBinding, DeadlineMonitor, LoopError, LoopOutcome, RaceLoop

__all__ = ["CarBinding", "DeadlineMonitor", "FaultSpec", "LoopConfig", "LoopError", "LoopOutcome", "RaceLoop",
           "StageBudgets", "parse_fault"]
