"""What defines a race, in one place: the roster (race.roster), the typed set-up with its defaults (the
`race` command's defaults, docs/racing.md) and the seeded standing start (single file or the grid).

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
from planning.config import PlannerConfigError
from planning.reference import planner_racing_line
from planning.frenet import lateral_half_extent
from race.roster import MAX_SPEED_MPS, RosterCar, RosterError, make_roster, two_car_roster
from sim.effects import SimEffects, SimEffectsError, parse_effects, sim_effects
from sim.race import OFF_TRACK_ALLOWANCE_CAR_LENGTHS
from tracks import TrackFormatError, load_track
from tracks.io import UnknownTrackError
from vehicles.params import CarParams, CarParamsError, load_car_params

OPPONENTS = ("mpc", "pursuit")
STARTS = ("front", "rear")
# single_file: the two-car race's start (RaceSetup.start says which car is in front); roster / random:
# the grid of rows of two (grid_states), slots in roster order (RosterCar.start_slot) or shuffled.
GRIDS = ("single_file", "roster", "random")
# first: the race ends when the first car finishes (the two-car race); all: when every car has
# finished (a fleet race: finishing order and unfinished cars), or at max_time_s either way.
FINISHES = ("first", "all")
CONTROL_HZ = 30.0                # planning (control) rate of the race's planners
# How the two cars of the paper's experiment differ in speed (docs/racing.md, "Two speed models"):
# limits: the slower car has a lower hard top speed, both cars start at rest (the default);
# preference: the authors' code (BuzzRacer car_racing.h): one hard top speed for both, soft speed
# references 1.0 + 0.1 i m/s in the cost (the faster car 1.1, the slower 1.0), rolling start at them.
SPEED_MODELS = ("limits", "preference")
PREFERENCE_REFERENCE_MPS = (1.1, 1.0)    # (faster, slower) car's speed reference and start speed


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
    # The two-car race's (rd3g, opponent) speed references in their costs (None: their top speeds) and
    # speeds at the start (m/s, along the heading); the preference speed model sets both.
    reference_speeds_mps: tuple[float | None, float | None] = (None, None)
    start_speeds_mps: tuple[float, float] = (0.0, 0.0)
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
    # The cars (race.roster.make_roster); None: the two-car roster of `opponent` and the two top speeds.
    roster: tuple[RosterCar, ...] | None = None
    car_files: tuple[CarParams, ...] | None = None  # per roster car (its planner and simulated car); None: `car`
    grid: str = "single_file"
    finish: str = "first"
    grid_row_gap_car_lengths: tuple[float, float] = (1.9, 2.1)  # grid rows centre to centre: about one car length free
    grid_lane_ey_m: float = 0.15        # a row's two cars at ey = +-grid_lane_ey_m ...
    grid_jitter_m: float = 0.01         # ... each jittered uniformly by up to this along and across the track
    planner_threads: int = 2            # threads planning the cars of one step (race.planning.RacePlanners)
    # Progress made off the track does not count (sim.race, docs/racing.md "Off track"): of what a car
    # gains between leaving and rejoining the track, this much (in its footprint lengths) still counts.
    off_track_allowance_car_lengths: float = OFF_TRACK_ALLOWANCE_CAR_LENGTHS

    def __post_init__(self) -> None:
        if self.grid not in GRIDS:
            raise RaceSetupError("grid", f"must be one of {GRIDS}, got {self.grid!r}")
        if self.finish not in FINISHES:
            raise RaceSetupError("finish", f"must be one of {FINISHES}, got {self.finish!r}")
        if self.opponent not in OPPONENTS:
            raise RaceSetupError("opponent", f"must be one of {OPPONENTS}, got {self.opponent!r}")
        if self.start not in STARTS:
            raise RaceSetupError("start", f"must be one of {STARTS}, got {self.start!r}")
        if not isinstance(self.sim_effects, SimEffects):
            raise RaceSetupError("sim_effects", f"must be a SimEffects, got {type(self.sim_effects).__name__}")
        if isinstance(self.laps, bool) or not isinstance(self.laps, int) or self.laps < 1:
            raise RaceSetupError("laps", f"must be an integer >= 1, got {self.laps!r}")
        if isinstance(self.planner_threads, bool) or not isinstance(self.planner_threads, int) or self.planner_threads < 1:
            raise RaceSetupError("planner_threads", f"must be an integer >= 1, got {self.planner_threads!r}")
        if self.max_time_s is None:
            object.__setattr__(self, "max_time_s", default_max_time_s(self.laps))
        allowance = self.off_track_allowance_car_lengths
        if isinstance(allowance, bool) or not (isinstance(allowance, (int, float)) and math.isfinite(allowance)
                                               and allowance >= 0):
            raise RaceSetupError("off_track_allowance_car_lengths", f"must be a number >= 0, got {allowance!r}")
        for name in ("rd3g_top_speed_mps", "opponent_top_speed_mps", "control_period_s", "max_time_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise RaceSetupError(name, f"must be a positive number, got {v!r}")
            if name.endswith("speed_mps") and v > MAX_SPEED_MPS:
                raise RaceSetupError(name, f"must be at most {MAX_SPEED_MPS:g} m/s, got {v!r}")
        try:
            cars = self.cars
        except RosterError as exc:
            raise RaceSetupError("roster", str(exc)) from None
        if self.grid == "single_file" and len(cars) != 2:
            raise RaceSetupError("grid", f"single_file is the two-car start; {len(cars)} cars need roster or random")
        if self.car_files is not None and len(self.car_files) != len(cars):
            raise RaceSetupError("car_files", f"one car file per car: {len(cars)} cars, {len(self.car_files)} files")

    @property
    def cars(self) -> tuple[RosterCar, ...]:
        """The race's roster (``roster``, or the two-car one: ``rd3g`` and ``opponent``)."""
        if self.roster is not None:
            return make_roster(self.roster)
        return two_car_roster(self.opponent, self.rd3g_top_speed_mps, self.opponent_top_speed_mps,
                              reference_speeds_mps=self.reference_speeds_mps, start_speeds_mps=self.start_speeds_mps)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cars)

    def racing_line(self):
        """The racing line the planners follow (planner.line "racing"; that of the fastest car's top
        speed and car file, for the recording), else None."""
        if self.planner.line != "racing":
            return None
        i = max(range(len(self.cars)), key=lambda k: self.cars[k].top_speed_mps)
        return planner_racing_line(self.track, self.car_file(i), self.cars[i].top_speed_mps, self.planner)

    def car_file(self, i: int) -> CarParams:
        """The car file of roster car i (its planner's model; the simulated car unless sim_car is set)."""
        return self.car if self.car_files is None else self.car_files[i]

    def sim_car_file(self, i: int) -> CarParams:
        return self.car_file(i) if self.sim_car is None else self.sim_car


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
    # A fleet race (race.roster): the parsed --cars or --roster (None: the two-car race of `opponent`);
    # its grid (None: "roster"; the two-car race keeps its single-file start unless a grid is named).
    roster: tuple[RosterCar, ...] | None = None
    grid: str | None = None
    game_players: int = PlannerConfig.game_players  # players of an RD3G car's game (0: every car in reach)
    speed_model: str = "limits"         # SPEED_MODELS; the faster car is the one with the higher top speed given
    planner_threads: int = RaceSetup.planner_threads
    line: str = PlannerConfig.line      # the planners' reference: planning.config.LINES
    lateral_clearance_m: float = PlannerConfig.lateral_clearance_m  # side-by-side distance of the collision constraint

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
        if raceline != 0.0 and self.line != "centre":
            raise RaceSetupError("raceline_ey_m", f"a constant lateral reference ({raceline:g} m) applies to line "
                                                  f"'centre' only, the planners race line {self.line!r} (--line centre)")
        try:
            planner = PlannerConfig(raceline_ey_m=raceline, game_players=self.game_players, line=self.line,
                                    lateral_clearance_m=self.lateral_clearance_m)
        except PlannerConfigError as exc:
            name = str(exc).split(":")[0].removeprefix("planner.")
            raise RaceSetupError(name, str(exc).removeprefix(f"planner.{name}: ")) from None
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
        speeds = self._speeds()
        fleet = {}
        if self.roster is not None:
            fleet = dict(roster=self.roster, finish="all", grid=self.grid or "roster",
                         car_files=self._car_files(car, track, need))
        elif self.grid is not None:
            fleet = dict(grid=self.grid)
        return RaceSetup(track=track, car=car, seed=self.seed, laps=self.laps, opponent=self.opponent,
                         start=self.start, control_period_s=1.0 / self.control_hz,
                         max_time_s=self.max_time_s, sim_car=sim_car, sim_effects=effects,
                         planner=planner, planner_threads=self.planner_threads, **speeds, **fleet)

    def _speeds(self) -> dict:
        """The two cars' RaceSetup speed fields under ``speed_model``. preference: both cars get the
        higher of the two top speeds as their hard limit; the car given the higher top speed (RD3G on a
        tie) gets the higher PREFERENCE_REFERENCE_MPS as speed reference and start speed."""
        if self.speed_model not in SPEED_MODELS:
            raise RaceSetupError("speed_model", f"must be one of {', '.join(SPEED_MODELS)}, got {self.speed_model!r}")
        tops = dict(rd3g_top_speed_mps=self.rd3g_top_speed_mps, opponent_top_speed_mps=self.opponent_top_speed_mps)
        if self.speed_model == "limits":
            return tops
        if self.roster is not None:
            raise RaceSetupError("speed_model", "preference is the two-car experiment's speed model; "
                                                "a fleet race sets speeds per car")
        top = max(self.rd3g_top_speed_mps, self.opponent_top_speed_mps)
        faster, slower = PREFERENCE_REFERENCE_MPS
        refs = (faster, slower) if self.rd3g_top_speed_mps >= self.opponent_top_speed_mps else (slower, faster)
        return dict(rd3g_top_speed_mps=top, opponent_top_speed_mps=top, reference_speeds_mps=refs,
                    start_speeds_mps=refs)

    def _car_files(self, car: CarParams, track, need: float) -> tuple[CarParams, ...] | None:
        """Each roster car's car file (None: every car uses `car`). One footprint for every car: the
        referee's gap and the planners' collision distance assume it (RaceSetupError naming the car)."""
        if all(c.car_params is None for c in self.roster):
            return None
        files = []
        for c in self.roster:
            if c.car_params is None:
                files.append(car)
                continue
            try:
                files.append(load_car_params(c.car_params))
            except CarParamsError as exc:
                raise RaceSetupError("roster", f"car {c.name}: car_params: {exc}") from None
            if files[-1].geometry != car.geometry:
                raise RaceSetupError("roster", f"car {c.name}: car_params: {c.car_params}: geometry differs from "
                                               f"{self.car_params}'s; every car of a race has one footprint")
        return tuple(files)


def start_states(setup: RaceSetup) -> np.ndarray:
    """Seeded start, rows [x, y, heading, vx, vy, yaw_rate] in roster order, every car at its
    ``start_speed_mps`` (at rest unless set) and aligned with the track: the two-car single file (``grid = "single_file"``: the front car just
    after the line, the other about one car length of free space, 2 +- 0.25 car lengths centre to
    centre, behind along the track, each at a random lateral offset; ``start`` says which is in front)
    or the grid (grid_states)."""
    if setup.grid != "single_file":
        return grid_states(setup)
    rng = np.random.default_rng(setup.seed)
    tr = setup.track
    s_front = rng.uniform(*setup.start_s_m)
    gap = rng.uniform(*setup.start_gap_car_lengths) * setup.car.geometry.footprint_length_m
    ey = rng.uniform(-setup.start_ey_m, setup.start_ey_m, size=2)
    s = np.array([s_front, s_front - gap]) if setup.start == "front" else np.array([s_front - gap, s_front])
    s = np.mod(s, tr.length)
    x, y, heading = tr.to_cartesian(s, ey, np.zeros(2))
    return np.column_stack([x, y, heading, [c.start_speed_mps for c in setup.cars], np.zeros((2, 2))])


def grid_slots(setup: RaceSetup) -> np.ndarray:
    """Each roster car's grid slot: its ``start_slot`` (``grid = "roster"``) or a seeded shuffle of
    the slots (``grid = "random"``, drawn from the race's seed)."""
    slots = np.array([c.start_slot for c in setup.cars])
    if setup.grid == "random":
        slots = np.random.default_rng([setup.seed, 1]).permutation(len(slots))
    return slots


def grid_frenet(setup: RaceSetup) -> tuple[np.ndarray, np.ndarray]:
    """(s, ey) of every roster car on the grid: rows of two, the front row's s drawn from start_s_m;
    slot k in row k // 2, on the left (ey = +grid_lane_ey_m) for even k and the right for odd k; row
    r is r row gaps (grid_row_gap_car_lengths car lengths centre to centre, drawn once per race)
    behind the front row; each car jittered by up to grid_jitter_m along and across the track."""
    rng = np.random.default_rng(setup.seed)
    n = len(setup.cars)
    s_front = rng.uniform(*setup.start_s_m)
    row_gap = rng.uniform(*setup.grid_row_gap_car_lengths) * setup.car.geometry.footprint_length_m
    jitter = rng.uniform(-setup.grid_jitter_m, setup.grid_jitter_m, size=(n, 2))
    slots = grid_slots(setup)
    s = s_front - (slots // 2) * row_gap + jitter[:, 0]
    ey = np.where(slots % 2 == 0, setup.grid_lane_ey_m, -setup.grid_lane_ey_m) + jitter[:, 1]
    return np.mod(s, setup.track.length), ey


def grid_states(setup: RaceSetup) -> np.ndarray:
    """The grid (grid_frenet) as start states [x, y, heading, start speed, 0, 0], roster order."""
    s, ey = grid_frenet(setup)
    x, y, heading = setup.track.to_cartesian(s, ey, np.zeros(len(s)))
    return np.column_stack([x, y, heading, [c.start_speed_mps for c in setup.cars], np.zeros((len(s), 2))])
