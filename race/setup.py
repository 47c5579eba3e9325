"""What defines a race, in one place: the cars' names, the typed set-up with its defaults (the `race`
command's defaults, docs/racing.md) and the seeded standing start.

* :class:`RaceSetup` -- loaded objects (track, car files) and numbers; every mode (simulation, HIL,
  hardware), `batch`, `sysid-closed-loop` and the benches race one of these.
* :class:`RaceSpec` -- the same race named as on the command line (track and car files by name or
  path, the control rate in Hz, hidden simulator effects as text); :meth:`RaceSpec.load` reads the
  files and returns the RaceSetup or raises :class:`RaceSetupError` naming the field at fault.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from planning import PlannerConfig
from planning.frenet import lateral_half_extent
from sim.effects import SimEffects, SimEffectsError, parse_effects, sim_effects
from tracks import TrackFormatError, load_track
from tracks.io import UnknownTrackError
from vehicles.params import CarParams, CarParamsError, load_car_params

CAR_NAMES = ("rd3g", "opponent")  # car 0 is ours (RD3G), car 1 the opponent
OPPONENTS = ("mpc", "pursuit")
STARTS = ("front", "rear")
CONTROL_HZ = 30.0                # planning (control) rate of the race's planners


def default_max_time_s(laps: int) -> float:
    """A race not won by then is "unfinished": 30 s per lap plus 30 s."""
    return 30.0 * laps + 30.0


class RaceSetupError(ValueError):
    """A race set-up value is invalid: ``field`` names it (a RaceSetup or RaceSpec field), ``message``
    says what is wrong; str() is "field: message"."""

    def __init__(self, field_name: str, message: str) -> None:
        super().__init__(f"{field_name}: {message}")
        self.field = field_name
        self.message = message


@dataclass(frozen=True)
class RaceSetup:
    """Everything that defines one race. Speeds are the planners' top speeds (m/s)."""

    track: object
    car: CarParams                      # both cars' planners (and, by default, the simulated cars) use this file
    seed: int = 0
    laps: int = 1
    opponent: str = "mpc"               # "mpc" or "pursuit"
    start: str = "rear"                 # where our car starts: "front" or "rear"
    rd3g_top_speed_mps: float = 2.0
    opponent_top_speed_mps: float = 1.8
    control_period_s: float = 1.0 / CONTROL_HZ
    physics_dt_s: float = 0.001
    max_time_s: float | None = None     # None: default_max_time_s(laps)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    start_s_m: tuple[float, float] = (0.25, 0.45)   # front car's start s range (just after the line)
    start_gap_car_lengths: tuple[float, float] = (1.75, 2.25)  # centre-to-centre along the track: about one car length of free space
    start_ey_m: float = 0.12            # |ey| of each car at the start, uniform in [-start_ey_m, start_ey_m]
    # The physical cars in the simulator, when they differ from what the planners believe (closing the
    # model-identification loop, docs/sysid.md): sim_car (default: car) plus hidden sim_effects, both cars.
    sim_car: CarParams | None = None
    sim_effects: SimEffects = field(default_factory=SimEffects)

    def __post_init__(self) -> None:
        if self.opponent not in OPPONENTS:
            raise RaceSetupError("opponent", f"must be one of {OPPONENTS}, got {self.opponent!r}")
        if self.start not in STARTS:
            raise RaceSetupError("start", f"must be one of {STARTS}, got {self.start!r}")
        if not isinstance(self.sim_effects, SimEffects):
            raise RaceSetupError("sim_effects", f"must be a SimEffects, got {type(self.sim_effects).__name__}")
        if isinstance(self.laps, bool) or not isinstance(self.laps, int) or self.laps < 1:
            raise RaceSetupError("laps", f"must be an integer >= 1, got {self.laps!r}")
        if self.max_time_s is None:
            object.__setattr__(self, "max_time_s", default_max_time_s(self.laps))
        for name in ("rd3g_top_speed_mps", "opponent_top_speed_mps", "control_period_s", "max_time_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise RaceSetupError(name, f"must be a positive number, got {v!r}")


@dataclass(frozen=True)
class RaceSpec:
    """A race as the user names it; the defaults are RaceSetup's (and the planner's raceline)."""

    track: str = "oval"                 # track name or file
    car_params: str = "buzzracer"       # car file (name or path) of both cars' planners
    seed: int = RaceSetup.seed
    laps: int = RaceSetup.laps
    opponent: str = RaceSetup.opponent
    start: str = RaceSetup.start
    rd3g_top_speed_mps: float = RaceSetup.rd3g_top_speed_mps
    opponent_top_speed_mps: float = RaceSetup.opponent_top_speed_mps
    control_hz: float = CONTROL_HZ
    raceline_ey_m: float = PlannerConfig.raceline_ey_m
    max_time_s: float | None = None     # None: default_max_time_s(laps)
    sim_car_params: str | None = None   # car file the simulator runs (default: car_params)
    sim_effects: str = ""               # hidden simulator effects, "name=value,..." (sim.effects.GENERATOR_EFFECTS)

    def load(self) -> RaceSetup:
        """Read the files and build the RaceSetup; RaceSetupError names the field at fault."""
        try:
            track = load_track(self.track)
        except (UnknownTrackError, TrackFormatError) as exc:
            raise RaceSetupError("track", str(exc)) from None
        try:
            car = load_car_params(self.car_params)
        except CarParamsError as exc:
            raise RaceSetupError("car_params", str(exc)) from None
        if not (isinstance(self.control_hz, (int, float)) and self.control_hz > 0 and math.isfinite(self.control_hz)):
            raise RaceSetupError("control_hz", f"must be positive, got {self.control_hz}")
        raceline = self.raceline_ey_m
        if not math.isfinite(raceline) or abs(raceline) >= track.min_width / 2:
            raise RaceSetupError("raceline_ey_m", f"must be a finite offset inside the track "
                                                  f"(|M| < {track.min_width / 2:g} m), got {raceline}")
        planner = PlannerConfig(raceline_ey_m=raceline)
        # Before any output is opened: the planner refuses a car wider than the track in its first plan.
        need = lateral_half_extent(car.geometry, planner.heading_allowance_rad) + planner.track_margin_m
        if need >= track.min_width / 2:
            raise RaceSetupError("car_params", f"{self.car_params}: geometry.footprint_width_m/length_m/offset_m: the "
                                               f"car needs {need:.3f} m either side of its path, track {track.name!r} "
                                               f"offers {track.min_width / 2:.3f} m")
        sim_car = None
        if self.sim_car_params:
            try:
                sim_car = load_car_params(self.sim_car_params)
            except CarParamsError as exc:
                raise RaceSetupError("sim_car_params", str(exc)) from None
        try:
            effects = (sim_effects(parse_effects(self.sim_effects, flag=None), 0.0, 0.0) if self.sim_effects.strip()
                       else SimEffects())
        except (SimEffectsError, ValueError) as exc:
            raise RaceSetupError("sim_effects", str(exc)) from None
        return RaceSetup(track=track, car=car, seed=self.seed, laps=self.laps, opponent=self.opponent,
                         start=self.start, rd3g_top_speed_mps=self.rd3g_top_speed_mps,
                         opponent_top_speed_mps=self.opponent_top_speed_mps, control_period_s=1.0 / self.control_hz,
                         max_time_s=self.max_time_s, sim_car=sim_car, sim_effects=effects,
                         planner=planner)


def start_states(setup: RaceSetup) -> np.ndarray:
    """Seeded standing start: the front car just after the line, the other about one car
    lengths of free space (2 +- 0.25 car lengths centre to centre) behind along the track, each at a random lateral offset, aligned with
    the track, at rest. Rows: [x, y, heading, vx, vy, yaw_rate] for (rd3g, opponent)."""
    rng = np.random.default_rng(setup.seed)
    tr = setup.track
    s_front = rng.uniform(*setup.start_s_m)
    gap = rng.uniform(*setup.start_gap_car_lengths) * setup.car.geometry.footprint_length_m
    ey = rng.uniform(-setup.start_ey_m, setup.start_ey_m, size=2)
    s = np.array([s_front, s_front - gap]) if setup.start == "front" else np.array([s_front - gap, s_front])
    s = np.mod(s, tr.length)
    x, y, heading = tr.to_cartesian(s, ey, np.zeros(2))
    return np.column_stack([x, y, heading, np.zeros((2, 3))])
