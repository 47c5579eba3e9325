"""The roster: the cars of one race, defined once (docs/racing.md, "Fleet races"; file format:
docs/file-formats.md, "Roster file").

A roster is a tuple of :class:`RosterCar` (2 to :data:`MAX_CARS`), each with its name, planner
(:data:`PLANNERS`), car file, ArUco marker id, radio id (FHSS modem id), top speed, start slot and, for
motion capture, its rigid-body id. It
comes from ``--cars rd3g,mpc,mpc`` (:func:`parse_cars`: names are the planner plus the car's 1-based
index, ``rd3g1``, ``mpc2``), from ``--roster FILE.toml`` (:func:`load_roster`: one ``[[car]]`` table
per car) or, without either flag, from the two-car race's options (:func:`two_car_roster`: ``rd3g``
and ``opponent``). :func:`make_roster` fills in the defaults and checks the whole roster; a fault is
a :class:`RosterError` naming the car and the field.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

from fileio import FieldSpec, InputFileError, ListOf, Number, String, Table, load_toml, table_from_dataclass, validate

PLANNERS = ("rd3g", "mpc", "pursuit", "human")
MIN_CARS, MAX_CARS = 2, 6
# Top speeds (m/s) by planner when the roster gives none: RaceSetup's defaults of the two-car race
# (RD3G 2.0, the opponent 1.8).
# Every speed of a car (top, reference, start): far above a 1/28 car's few m/s; a planner's grids grow
# with it (--rd3g-speed 1e6 hung the race, a roster's 1e308 overflowed an array).
MAX_SPEED_MPS = 20.0
DEFAULT_TOP_SPEED_MPS = {"rd3g": 2.0, "mpc": 1.8, "pursuit": 1.8, "human": 1.8}


class RosterError(ValueError):
    """A roster value is invalid: ``car`` names the car (or its 1-based index), ``field`` the field."""

    def __init__(self, car: str, field_name: str, message: str) -> None:
        super().__init__(f"car {car}: {field_name}: {message}")
        self.car, self.field, self.message = car, field_name, message


class RosterFileError(InputFileError):
    """A roster file cannot be read or does not follow the format (the message names file and field)."""


@dataclass(frozen=True)
class RosterCar:
    """One car of a race. ``None`` fields take their default in :func:`make_roster`: marker id, radio
    id and start slot the smallest one no other car has (in roster order: 0, 1, 2, ... when none is
    given), top speed by planner (DEFAULT_TOP_SPEED_MPS), car file = the race's ``--car-params``."""

    name: str
    planner: str
    car_params: str | None = None      # car file (name or path)
    marker_id: int | None = None       # ArUco id on the roof
    radio_id: int | None = None        # id in the serial protocol (FHSS modem id)
    top_speed_mps: float | None = None
    start_slot: int | None = None      # 0 = pole; slots 2r and 2r + 1 make grid row r
    # The speed reference of its planner's cost (None: the top speed) and its speed at the start (m/s):
    # the authors' "preference" speed model (race.setup.SPEED_MODELS, docs/racing.md).
    reference_speed_mps: float | None = None
    start_speed_mps: float = 0.0
    # Motive's streaming id of its rigid body (`race --mocap`; None: the car file's mocap.rigid_body_id)
    rigid_body_id: int | None = None

    @property
    def solves(self) -> bool:
        """Its planner is a solve (RD3G, MPC), timed per plan."""
        return self.planner in ("rd3g", "mpc")


def _integer(car: str, name: str, v, lo: int = 0, hi: int = 2**31 - 1) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise RosterError(car, name, f"must be an integer in [{lo}, {hi}], got {v!r}")


def make_roster(cars, max_cars: int = MAX_CARS) -> tuple[RosterCar, ...]:
    """The checked roster with every default filled in (RosterCar doc): 2 to ``max_cars`` cars, known
    planners, unique names, marker ids, radio ids and start slots, slots below the number of cars."""
    cars = list(cars)
    if not MIN_CARS <= len(cars) <= max_cars:
        raise RosterError("-", "cars", f"a race has {MIN_CARS} to {max_cars} cars, got {len(cars)}")
    out = []
    for i, c in enumerate(cars):
        label = c.name if isinstance(c.name, str) and c.name else str(i + 1)
        if not isinstance(c.name, str) or not c.name or not c.name.replace("_", "").isalnum() or not c.name.isascii():
            raise RosterError(label, "name", f"must be a non-empty name of letters, digits and _, got {c.name!r}")
        if c.planner not in PLANNERS:
            raise RosterError(label, "planner", f"must be one of {', '.join(PLANNERS)}, got {c.planner!r}")
        if c.car_params is not None and (not isinstance(c.car_params, str) or not c.car_params.strip()):
            raise RosterError(label, "car_params", f"must be a car file name or path, got {c.car_params!r}")
        speed = DEFAULT_TOP_SPEED_MPS[c.planner] if c.top_speed_mps is None else c.top_speed_mps
        if isinstance(speed, bool) or not isinstance(speed, (int, float)) or not 0 < speed <= MAX_SPEED_MPS:
            raise RosterError(label, "top_speed_mps", f"must be a number in (0, {MAX_SPEED_MPS:g}] m/s, got {speed!r}")
        ref, v0 = c.reference_speed_mps, c.start_speed_mps
        if ref is not None and (isinstance(ref, bool) or not isinstance(ref, (int, float))
                                or not 0 < ref <= MAX_SPEED_MPS):
            raise RosterError(label, "reference_speed_mps", f"must be a number in (0, {MAX_SPEED_MPS:g}] m/s, got {ref!r}")
        if isinstance(v0, bool) or not isinstance(v0, (int, float)) or not 0 <= v0 <= MAX_SPEED_MPS:
            raise RosterError(label, "start_speed_mps", f"must be a number in [0, {MAX_SPEED_MPS:g}] m/s, got {v0!r}")
        if c.rigid_body_id is not None:
            _integer(label, "rigid_body_id", c.rigid_body_id)
        out.append(dataclasses.replace(c, top_speed_mps=float(speed)))
    for f, hi in (("marker_id", 999), ("radio_id", 255), ("start_slot", len(cars) - 1)):
        taken = {getattr(c, f) for c in out}
        free = (v for v in itertools.count() if v not in taken)
        out = [c if getattr(c, f) is not None else dataclasses.replace(c, **{f: next(free)}) for c in out]
        for c in out:
            _integer(c.name, f, getattr(c, f), 0, hi)
    for f in ("name", "marker_id", "radio_id", "start_slot", "rigid_body_id"):
        seen: dict = {}
        for c in out:
            v = getattr(c, f)
            if v is None:  # a rigid-body id left to the car file
                continue
            if v in seen:
                raise RosterError(c.name, f, f"{v!r} is also car {seen[v]}'s; each car needs its own")
            seen[v] = c.name
    return tuple(out)


def parse_cars(text: str, flag: str = "--cars") -> tuple[RosterCar, ...]:
    """``rd3g,mpc,mpc,pursuit`` -> the roster (names: planner + 1-based index, ``rd3g1, mpc2, ...``)."""
    planners = [p.strip() for p in str(text).split(",")]
    cars = []
    for i, p in enumerate(planners):
        if p not in PLANNERS:
            raise RosterError(str(i + 1), "planner", f"{flag} {text!r}: must be one of {', '.join(PLANNERS)}, got {p!r}")
        cars.append(RosterCar(name=f"{p}{i + 1}", planner=p))
    return make_roster(cars)


def two_car_roster(opponent: str, rd3g_top_speed_mps: float, opponent_top_speed_mps: float,
                   car_params: str | None = None, reference_speeds_mps=(None, None),
                   start_speeds_mps=(0.0, 0.0)) -> tuple[RosterCar, ...]:
    """The two-car race without a roster flag: ``rd3g`` (RD3G, id 0) and ``opponent`` (id 1); the
    speed references and start speeds in that order."""
    return make_roster([RosterCar("rd3g", "rd3g", car_params, 0, 0, rd3g_top_speed_mps, 0,
                                  reference_speeds_mps[0], start_speeds_mps[0]),
                        RosterCar("opponent", opponent, car_params, 1, 1, opponent_top_speed_mps, 1,
                                  reference_speeds_mps[1], start_speeds_mps[1])])


def _schema() -> Table:
    car = table_from_dataclass(RosterCar, overrides={
        "name": String(nonempty=True, max_len=32), "planner": String(choices=PLANNERS),
        "car_params": String(nonempty=True), "marker_id": Number(integer=True, ge=0, le=999),
        "radio_id": Number(integer=True, ge=0, le=255), "top_speed_mps": Number(gt=0, le=MAX_SPEED_MPS),
        "start_slot": Number(integer=True, ge=0, le=MAX_CARS - 1), "reference_speed_mps": Number(gt=0, le=MAX_SPEED_MPS),
        "start_speed_mps": Number(ge=0, le=MAX_SPEED_MPS),
        "rigid_body_id": Number(integer=True, ge=0, le=2**31 - 1)})
    return Table({"car": FieldSpec(ListOf(car, min_len=MIN_CARS, max_len=MAX_CARS))}, "roster")


ROSTER_SCHEMA = _schema()


def load_roster(path) -> tuple[RosterCar, ...]:
    """A roster file (TOML, one ``[[car]]`` table per car): RosterFileError naming the file, the car
    (``car[2]`` or its name) and the field on any fault."""
    data = load_toml(path, "roster file", error=RosterFileError)
    d = validate(data, ROSTER_SCHEMA, str(path), RosterFileError)
    try:
        return make_roster(RosterCar(**c) for c in d["car"])
    except RosterError as exc:
        raise RosterFileError(f"{path}: {exc}") from None
