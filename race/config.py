"""Parameters of the real-time race loop and the fault-injection schedule (docs/race-stack.md)."""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field, fields

STAGES = ("frame", "detect", "estimate", "plan", "command", "telemetry")

FAULT_KINDS = {
    # kind: (where it is injected, needs a duration)
    "occlude": ("camera", True),          # the cars' markers are not visible
    "serial_corrupt": ("serial", True),   # bit errors on the serial line (half the bytes hit)
    "serial_vanish": ("serial", False),   # the serial device disappears (EIO on write), permanent
    "solver_fail": ("planner", True),     # every planning call raises
    "nan_state": ("estimator", False),    # the estimator's state of a car becomes NaN
    "mocap_stall": ("mocap", True),       # HIL --mocap: the Motive emulator sends no frame
    "mocap_down": ("mocap", False),       # HIL --mocap: the Motive emulator goes away, permanent
}


class LoopConfigError(ValueError):
    """A loop parameter or fault specification is invalid; the message names the field."""


@dataclass(frozen=True)
class StageBudgets:
    """Per-stage time budgets (ms). A stage over budget is counted (stats, not an event); the
    tick as a whole must issue its command within one period (the deadline)."""

    frame: float = 1.5
    detect: float = 10.0
    estimate: float = 1.5
    plan: float = 1.0
    command: float = 1.0
    telemetry: float = 1.5


# Fields that may be 0: the simulated world's lock-step timing (no delay, no linger).
_MAY_BE_ZERO = ("plan_ticks", "command_delay_s", "linger_s")


@dataclass(frozen=True)
class LoopConfig:
    rate_hz: float = 60.0            # loop ticks per second
    plan_hz: float = 30.0            # planning jobs per second (asynchronous, latest plan applied)
    link_hz: float = 120.0           # serial frames per second (SerialCarLink sender)
    # A plan made at tick k is applied at tick k + plan_ticks (a late plan: at the first tick after it is
    # done), so every plan acts after the same, known delay whatever its solve time. Applied as soon as
    # done, plans acted 17 ms early or on time depending on the solve. 0: the plan of tick k's
    # observation is applied at tick k (the simulated world's lock-step timing, race.simulation).
    plan_ticks: int = 2
    # From a tick's scheduled start until the cars act on the command that tick sends: the loop's stages
    # before the command, the link's 120 Hz cadence, relay and box (HIL; on hardware add the radio and
    # the servo). Measured in HIL by `command_lag_ms` (docs/race-stack.md, "Latency, measured per plan"):
    # with 15 ms the cars got the commands 3-5 ms after t_plan (median of 20 races, two runs).
    command_delay_s: float = 0.019
    max_plan_age_s: float = 0.15     # an older plan is a planner fault (neutral)
    lost_search_every: int = 6       # full-frame marker search every n frames while a car is lost
    serial_quiet_s: float = 0.3      # HIL: corrupt-frame counter unchanged this long = stream healthy again
    acquire_timeout_s: float = 10.0  # pre-race: time to find every car
    linger_s: float = 0.3            # HIL: keep reading the world's events this long after the race (0: stop at once)
    stop_after_hold_s: float = 3.0   # cars held neutral (any safety hold) this long without a break: stop the race
    acquire_measurements: int = 5    # pre-race: accepted measurements per car before the start
    image_log_every: int = 6         # log every n-th camera frame (downsampled) to the recording
    image_downscale: int = 4
    # A plan in which a car's planner failed (race.planning, one policy: plan_step gives that car its
    # fallback plan with the error): True holds every car neutral until a good plan arrives (real cars,
    # where any fault sends neutral first); False applies the plan, fallback included, and logs a
    # ``planner_error`` event (the simulated race: it measures the planners, and a hold would also
    # stop the other car). A job that produced no plan at all is a hold either way.
    hold_on_planner_error: bool = True
    budgets: StageBudgets = field(default_factory=StageBudgets)

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type == "bool":
                if not isinstance(v, bool):
                    raise LoopConfigError(f"{f.name}: must be true or false, got {v!r}")
                continue
            if f.name == "budgets":
                for b in fields(v):
                    bv = getattr(v, b.name)
                    if not (isinstance(bv, (int, float)) and math.isfinite(bv) and bv > 0):
                        raise LoopConfigError(f"budgets.{b.name}: must be a positive number of ms, got {bv!r}")
                continue
            lowest = 0 if f.name in _MAY_BE_ZERO else 1
            if f.type == "int":
                if isinstance(v, bool) or not isinstance(v, int) or v < lowest:
                    raise LoopConfigError(f"{f.name}: must be an integer >= {lowest}, got {v!r}")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 or (v == 0 and lowest):
                raise LoopConfigError(f"{f.name}: must be a {'non-negative' if not lowest else 'positive'} number, got {v!r}")
        if self.plan_hz > self.rate_hz:
            raise LoopConfigError(f"plan_hz: must not exceed rate_hz ({self.rate_hz}), got {self.plan_hz}")

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def plan_latency_s(self) -> float:
        """From a planning job's tick to when its plan's command acts on the cars: the instant the
        states are predicted to (t_plan)."""
        return self.plan_ticks * self.period_s + self.command_delay_s

    @property
    def plan_every(self) -> int:
        """Loop ticks per planning job."""
        return max(1, round(self.rate_hz / self.plan_hz))


@dataclass(frozen=True)
class FaultSpec:
    """One injected fault: `kind` (FAULT_KINDS) from race time `start_s` for `duration_s` seconds
    (0 for instantaneous/permanent kinds), on car `car` (a roster name, checked against the race's
    roster by :func:`check_fault_cars`) or every car (None)."""

    kind: str
    start_s: float
    duration_s: float = 0.0
    car: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise LoopConfigError(f"fault kind: must be one of {sorted(FAULT_KINDS)}, got {self.kind!r}")
        if not (math.isfinite(self.start_s) and self.start_s >= 0):
            raise LoopConfigError(f"fault {self.kind}: start must be a time >= 0 s, got {self.start_s!r}")
        needs_duration = FAULT_KINDS[self.kind][1]
        if needs_duration and not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise LoopConfigError(f"fault {self.kind}: needs a duration > 0 s (KIND@START+DURATION)")
        if not needs_duration and self.duration_s:
            raise LoopConfigError(f"fault {self.kind}: takes no duration")

    def active(self, t: float) -> bool:
        return self.start_s <= t < self.start_s + self.duration_s

    def applies_to(self, car: str) -> bool:
        return self.car is None or self.car == car


_FAULT_RE = re.compile(r"^(?P<kind>[a-z_]+)@(?P<start>[0-9.]+)(\+(?P<dur>[0-9.]+))?(:(?P<car>[a-z0-9_]+))?$")


def parse_fault(text: str) -> FaultSpec:
    """`KIND@START[+DURATION][:CAR]`, e.g. `occlude@2+1:opponent`, `serial_vanish@3`."""
    m = _FAULT_RE.match(text.strip())
    if not m:
        raise LoopConfigError(f"--fault {text!r}: expected KIND@START[+DURATION][:CAR], e.g. occlude@2+1:opponent")
    try:
        start = float(m["start"])
        duration = float(m["dur"]) if m["dur"] else 0.0
    except ValueError:
        raise LoopConfigError(f"--fault {text!r}: START and DURATION must be numbers (s)") from None
    return FaultSpec(m["kind"], start, duration, m["car"])


def check_fault_cars(faults, names) -> None:
    """Every fault's car is one of the race's cars ``names`` (LoopConfigError naming the fault)."""
    for f in faults:
        if f.car is not None and f.car not in names:
            raise LoopConfigError(f"fault {f.kind}: car must be one of {', '.join(names)}, got {f.car!r}")


def lower_realtime_priority(by: int) -> None:
    """In a thread running under SCHED_FIFO (``--rt-priority``), drop this thread's priority by
    `by` (at least 1), so the loop thread keeps precedence over helpers; no-op otherwise."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_FIFO:
            return
        prio = os.sched_getparam(0).sched_priority
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(max(1, prio - by)))
    except (AttributeError, OSError):
        pass
