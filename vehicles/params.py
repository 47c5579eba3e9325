"""Typed car parameters, loaded from and written back to TOML.

A car file (e.g. ``vehicles/buzzracer.toml``) has a ``name`` and one table per dataclass below;
a key missing inside a table falls back to the BuzzRacer 1/28-scale defaults documented in
docs/vehicles.md. A missing ``name`` or table (an empty or truncated file), unknown tables or keys
(with a "did you mean"), wrong types and out-of-range values raise :class:`CarParamsError` naming
the file and the field (``geometry.lf_m``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Callable

import cv2

import fileio
from fileio import unknown_key_message

VEHICLES_DIR = Path(__file__).resolve().parent
GRAVITY_MPS2 = 9.81
MAX_MAGNITUDE = 1e6  # every number in a car file (docs/vehicles.md)


class CarParamsError(fileio.InputFileError):
    """A car parameter file or value is invalid; the message names the field at fault."""


# Each field carries a validator in its metadata: check(value) -> error text or None.
def _positive(v: float) -> str | None:
    return None if v > 0 else "must be > 0"


def _non_negative(v: float) -> str | None:
    return None if v >= 0 else "must be >= 0"


def _between(lo: float, hi: float) -> Callable[[float], str | None]:
    def check(v: float) -> str | None:
        return None if lo <= v <= hi else f"must be in [{lo}, {hi}]"

    return check


def _any(_v: float) -> str | None:
    return None


def _num(default: float, check: Callable[[float], str | None] = _positive, doc: str = "") -> Any:
    return field(default=default, metadata={"check": check, "doc": doc})


def _int(default: int, check: Callable[[float], str | None] = _non_negative, doc: str = "") -> Any:
    return field(default=default, metadata={"check": check, "doc": doc, "int": True})


def _text(default: str, check: Callable[[str], str | None], doc: str = "") -> Any:
    return field(default=default, metadata={"check": check, "doc": doc, "text": True})


@dataclass(frozen=True)
class GeometryParams:
    lf_m: float = _num(0.04824, doc="centre of gravity to front axle")
    lr_m: float = _num(0.04176, doc="centre of gravity to rear axle")
    footprint_length_m: float = _num(0.16, doc="collision rectangle length (body outline)")
    footprint_width_m: float = _num(0.07, doc="collision rectangle width")
    footprint_offset_m: float = _num(0.0, _any, doc="collision rectangle centre ahead of the CG")

    @property
    def wheelbase_m(self) -> float:
        return self.lf_m + self.lr_m


@dataclass(frozen=True)
class InertiaParams:
    mass_kg: float = _num(0.1667)
    yaw_inertia_kgm2: float = _num(0.1667 * (0.15**2 + 0.10**2) / 12.0)


@dataclass(frozen=True)
class TireParams:
    """Simplified Pacejka magic formula F_y = D*F_z*sin(C*atan(B*a - E*(B*a - atan(B*a))))."""

    b: float = _num(2.3, doc="stiffness factor [1/rad]")
    c: float = _num(1.6, _between(0.1, 2.0), doc="shape factor")
    d: float = _num(1.1, doc="peak friction coefficient (peak force / normal load)")
    e: float = _num(0.0, _between(-10.0, 1.0), doc="curvature factor")


@dataclass(frozen=True)
class LongitudinalParams:
    """Drive force F = Cm1*u - Cm2*vx*|u| - Cr0*tanh(vx/v_s) - Cd*vx*|vx| (u = throttle in -1..1)."""

    motor_force_n: float = _num(1.0285, doc="Cm1: force at full throttle from standstill")
    motor_speed_loss_n_per_mps: float = _num(0.282, _non_negative, doc="Cm2: back-EMF loss per m/s")
    rolling_resistance_n: float = _num(0.034, _non_negative, doc="Cr0: rolling + drivetrain friction")
    drag_n_per_mps2: float = _num(6.5e-4, _non_negative, doc="Cd: aerodynamic drag, F = Cd*v^2")
    rolling_smoothing_speed_mps: float = _num(0.02, doc="v_s: tanh smoothing of sign(vx)")
    throttle_smoothing: float = _num(0.02, doc="eps in |u| ~ sqrt(u^2+eps^2)-eps")


@dataclass(frozen=True)
class ActuatorParams:
    max_steering_rad: float = _num(math.radians(27.0), _between(1e-3, 1.2))
    steering_rate_limit_radps: float = _num(10.5)
    throttle_min: float = _num(-1.0, _between(-1.0, 0.0))
    throttle_max: float = _num(1.0, _between(0.0, 1.0))
    throttle_rate_limit_per_s: float = _num(20.0)


@dataclass(frozen=True)
class SpeedControlParams:
    """A car whose command is a speed set-point (an F1/10 car's VESC speed controller) instead of a throttle:
    the longitudinal acceleration is gain * (set-point * corrections.speed_setpoint_gain - speed), limited
    to [-max_decel, max_accel] (the controller compensates friction and drag; the car file's motor law is
    not used). docs/sysid.md, "Speed set-point cars"."""

    gain_per_s: float = _num(0.0, _non_negative, doc="0: the car is driven by throttle (default); > 0: speed "
                                                    "set-point in m/s, 1 / time constant of the speed loop")
    max_accel_mps2: float = _num(5.0, doc="largest acceleration the speed loop commands")
    max_decel_mps2: float = _num(5.0, doc="largest deceleration the speed loop commands")
    max_setpoint_mps: float = _num(10.0, doc="set-points are clipped to +-this")

    @property
    def active(self) -> bool:
        return self.gain_per_s > 0.0


@dataclass(frozen=True)
class ModelParams:
    """Low-speed handling of the dynamic model (blend to a kinematic model)."""

    blend_speed_low_mps: float = _num(0.15, doc="below this vx the model is purely kinematic")
    blend_speed_high_mps: float = _num(0.35, doc="above this vx the model is purely dynamic")
    kinematic_relax_time_s: float = _num(0.02, doc="time constant pulling vy, r to kinematic values")


# The ArUco dictionary of the cars' markers: the simulated camera's (sim/camera.py) and the default of
# fixed-marker files and calibrations (tracking/calibration.py). An id it lacks is never detected.
MARKER_DICTIONARY = "DICT_4X4_50"


def aruco_dictionary_size(name: str) -> int | None:
    """Ids in OpenCV's predefined ArUco dictionary ``name`` (0 .. size - 1); None if OpenCV has none of that name."""
    value = getattr(cv2.aruco, name, None) if isinstance(name, str) and name.startswith("DICT_") else None
    return int(cv2.aruco.getPredefinedDictionary(value).bytesList.shape[0]) if isinstance(value, int) else None


def _aruco_dictionary(name: str) -> str | None:
    return None if aruco_dictionary_size(name) else f"must be an OpenCV ArUco dictionary name such as {MARKER_DICTIONARY!r}"


@dataclass(frozen=True)
class MarkerParams:
    aruco_id: int = _int(0, _between(0, 999), doc="within marker.dictionary's ids")
    height_m: float = _num(0.045, _non_negative, doc="marker plane above the ground")
    size_m: float = _num(0.055, doc="side of the printed ArUco marker (outer black border)")
    dictionary: str = _text(MARKER_DICTIONARY, _aruco_dictionary,
                            doc="ArUco dictionary of the printed marker; the track's fixed markers use the same")
    # Where the marker is glued: its centre relative to the car's reference point (the CG) in the car's frame,
    # and its turn against the car's heading; the tracker subtracts them. A few mm and 1-2 degrees are usual.
    offset_forward_m: float = _num(0.0, _between(-0.2, 0.2), doc="marker centre ahead of the reference point")
    offset_left_m: float = _num(0.0, _between(-0.2, 0.2), doc="marker centre left of the reference point")
    yaw_rad: float = _num(0.0, _between(-0.5, 0.5), doc="marker turned counter-clockwise against the car")


@dataclass(frozen=True)
class Corrections:
    """Deviations of the real car from the nominal model, filled in by model identification.

    All neutral by default. Wheel angle = steering_gain * command + steering_offset_rad.
    """

    steering_delay_s: float = _num(0.0, _between(0.0, 1.0))
    throttle_delay_s: float = _num(0.0, _between(0.0, 1.0))
    steering_offset_rad: float = _num(0.0, _between(-0.3, 0.3))
    steering_gain: float = _num(1.0, _between(0.2, 5.0))
    extra_drag_n_per_mps2: float = _num(0.0, _between(-1.0, 10.0), doc="added to Cd")
    tire_grip_scale: float = _num(1.0, _between(0.05, 5.0), doc="multiplies D of both axles")
    # ---- model identification, beyond the nominal model (docs/sysid.md, "Candidates") ----
    steering_backlash_rad: float = _num(
        0.0, _between(0.0, 0.3), doc="play of the steering linkage: servo travel lost when the command reverses")
    steering_gain_asymmetry: float = _num(
        0.0, _between(-0.5, 0.5), doc="a: gain * (1 + a) for left (positive) servo angles, * (1 - a) for right")
    motor_force_drift_per_s: float = _num(
        0.0, _between(-0.01, 0.01), doc="motor force scale 1 - rate * t (t: s since the log/race start)")
    throttle_gain: float = _num(
        1.0, _between(0.2, 5.0), doc="throttle cars: the motor sees gain * sign(u) * max(|u| - dead band, 0)")
    throttle_dead_band: float = _num(0.0, _between(0.0, 0.5), doc="throttle cars: |throttle| below this does nothing")
    throttle_curvature: float = _num(
        0.0, _between(-1.0, 1.0),
        doc="throttle cars: c in the map's shape x (1 + c (x - 1)), x = max(|u| - dead band, 0); full scale unchanged")
    speed_setpoint_gain: float = _num(
        1.0, _between(0.2, 5.0), doc="speed set-point cars: speed reached per commanded m/s")
    speed_response_scale: float = _num(
        1.0, _between(0.05, 20.0), doc="speed set-point cars: multiplies speed_control.gain_per_s")
    # ---- end of model identification fields ----


# ---- model identification: fitted terms of an effect without a name (docs/sysid.md, "other") ----
# Added to d(speed)/dt (accel_*, m/s^2 per unit of the term) and d(heading)/dt (yaw_rate_*, rad/s per
# unit) as functions of speed v, throttle u and wheel angle d; vehicles.extra_terms evaluates them.
def _coef(doc: str) -> Any:
    return _num(0.0, _any, doc=doc)


@dataclass(frozen=True)
class OtherTermsParams:
    accel_1: float = _coef("constant")
    accel_v: float = _coef("v")
    accel_v_absv: float = _coef("v|v|")
    accel_u: float = _coef("u")
    accel_u_v: float = _coef("u*v")
    accel_d: float = _coef("d")
    accel_d_v: float = _coef("d*v")
    accel_d_v2: float = _coef("d*v^2")
    accel_d_absd_v: float = _coef("d|d|*v")
    accel_d2_v2: float = _coef("d^2*v^2")
    yaw_rate_1: float = _coef("constant")
    yaw_rate_v: float = _coef("v")
    yaw_rate_v_absv: float = _coef("v|v|")
    yaw_rate_u: float = _coef("u")
    yaw_rate_u_v: float = _coef("u*v")
    yaw_rate_d: float = _coef("d")
    yaw_rate_d_v: float = _coef("d*v")
    yaw_rate_d_v2: float = _coef("d*v^2")
    yaw_rate_d_absd_v: float = _coef("d|d|*v")
    yaw_rate_d2_v2: float = _coef("d^2*v^2")

    @property
    def active(self) -> bool:
        return any(getattr(self, f.name) != 0.0 for f in fields(self))


MIN_MOTOR_FORCE_SCALE = 0.2  # a drifting motor never drops below this fraction of its force


def motor_force_scale(drift_per_s: float, elapsed_s):
    """Motor force factor after ``elapsed_s`` of a battery drifting at ``drift_per_s`` (float or array)."""
    scale = 1.0 - drift_per_s * elapsed_s
    return max(MIN_MOTOR_FORCE_SCALE, scale) if isinstance(scale, float) else scale.clip(MIN_MOTOR_FORCE_SCALE, None)
# ---- end of model identification terms ----


# ---- radio link calibration (BuzzRacer FHSS box, vehicles/fhss.py; docs/vehicles.md "Radio calibration")
def _optional(check: Callable[[float], str | None], doc: str, is_int: bool = False) -> Any:
    """A field that may be absent from the file (None): the doc says what stands in for it."""
    return field(default=None, metadata={"check": check, "doc": doc, "int": is_int, "optional": True})


def _pulse(default: int, doc: str) -> Any:
    return _int(default, _between(1000, 2000), doc=doc)


@dataclass(frozen=True)
class RadioParams:
    """How this car's receiver maps pulse widths (us) to steering angle and throttle, and which
    transmitter slot drives it. Pulses at the two ends may be in either order (servo direction,
    reversed throttle channel); each neutral pulse must lie strictly between its two ends."""

    modem_id: int | None = _optional(_between(0, 5), "FHSS box radio: slots 2m (steering), 2m+1 (throttle)", True)
    steering_left_max_rad: float | None = _optional(
        _between(1e-3, 1.2), "full left wheel angle (absent: actuators.max_steering_rad)")
    steering_right_max_rad: float | None = _optional(
        _between(1e-3, 1.2), "full right wheel angle (absent: actuators.max_steering_rad)")
    steering_left_us: int = _pulse(1100, "pulse at full left")
    steering_neutral_us: int = _pulse(1500, "pulse at straight ahead")
    steering_right_us: int = _pulse(2000, "pulse at full right")
    throttle_forward_us: int = _pulse(1900, "pulse at throttle +1")
    throttle_neutral_us: int = _pulse(1500, "pulse at throttle 0")
    throttle_reverse_us: int = _pulse(1100, "pulse at throttle -1 (brake/reverse)")


def _check_radio(radio: RadioParams, source: str) -> None:
    for channel, low_end, high_end in (("steering", "left", "right"), ("throttle", "forward", "reverse")):
        a, n, b = (getattr(radio, f"{channel}_{k}_us") for k in (low_end, "neutral", high_end))
        if not (min(a, b) < n < max(a, b)):
            raise CarParamsError(f"{source}: radio.{channel}_neutral_us: must lie strictly between "
                                 f"radio.{channel}_{low_end}_us ({a}) and radio.{channel}_{high_end}_us ({b}), got {n}")
# ---- end radio link calibration


@dataclass(frozen=True)
class MocapParams:
    """The car's rigid body in a motion-capture system (OptiTrack Motive, `race --mocap`): its streaming id
    and where its pivot sits on the car, which the mocap tracker subtracts (docs/tracking.md)."""

    rigid_body_id: int | None = _optional(_between(0, 2**31 - 1), "Motive's streaming id of the car's rigid body", True)
    offset_forward_m: float = _num(0.0, _between(-0.2, 0.2), doc="rigid-body pivot ahead of the reference point")
    offset_left_m: float = _num(0.0, _between(-0.2, 0.2), doc="rigid-body pivot left of the reference point")
    yaw_rad: float = _num(0.0, _between(-math.pi, math.pi), doc="rigid body's +x axis counter-clockwise against the car")


@dataclass(frozen=True)
class CarParams:
    name: str = "buzzracer"
    geometry: GeometryParams = field(default_factory=GeometryParams)
    inertia: InertiaParams = field(default_factory=InertiaParams)
    front_tire: TireParams = field(default_factory=TireParams)
    rear_tire: TireParams = field(default_factory=lambda: TireParams(d=1.265))
    longitudinal: LongitudinalParams = field(default_factory=LongitudinalParams)
    actuators: ActuatorParams = field(default_factory=ActuatorParams)
    model: ModelParams = field(default_factory=ModelParams)
    marker: MarkerParams = field(default_factory=MarkerParams)
    corrections: Corrections = field(default_factory=Corrections)
    speed_control: SpeedControlParams = field(default_factory=SpeedControlParams,
                                              metadata={"optional_in_file": True})
    # transmitter calibration (BuzzRacer FHSS box) and model identification; both optional in a car file
    # (added after the first car files were written)
    radio: RadioParams = field(default_factory=RadioParams, metadata={"optional_in_file": True})
    other_terms: OtherTermsParams = field(default_factory=OtherTermsParams, metadata={"optional_in_file": True})
    mocap: MocapParams = field(default_factory=MocapParams, metadata={"optional_in_file": True})

    def __post_init__(self) -> None:
        _check_cross_fields(self, source="CarParams")


_SECTION_TYPES = {
    "geometry": GeometryParams,
    "inertia": InertiaParams,
    "front_tire": TireParams,
    "rear_tire": TireParams,
    "longitudinal": LongitudinalParams,
    "actuators": ActuatorParams,
    "model": ModelParams,
    "marker": MarkerParams,
    "corrections": Corrections,
    "speed_control": SpeedControlParams,
    "radio": RadioParams,
    "other_terms": OtherTermsParams,  # model identification
    "mocap": MocapParams,
}


def _check_cross_fields(p: CarParams, source: str) -> None:
    if p.model.blend_speed_high_mps <= p.model.blend_speed_low_mps:
        raise CarParamsError(
            f"{source}: model.blend_speed_high_mps must exceed model.blend_speed_low_mps "
            f"({p.model.blend_speed_high_mps} <= {p.model.blend_speed_low_mps})"
        )
    if p.actuators.throttle_max <= p.actuators.throttle_min:
        raise CarParamsError(f"{source}: actuators.throttle_max must exceed actuators.throttle_min")
    for sec, obj in _sections_of(p):
        for f in fields(obj):
            _validate_value(source, f"{sec}.{f.name}", f, getattr(obj, f.name))
    g = p.geometry
    front, rear = g.footprint_offset_m + 0.5 * g.footprint_length_m, g.footprint_offset_m - 0.5 * g.footprint_length_m
    if g.lf_m > front or -g.lr_m < rear:  # an axle outside the body: lengths in different units, or swapped
        raise CarParamsError(
            f"{source}: geometry: the axles (lf_m {g.lf_m}, lr_m {g.lr_m} from the CG) must lie inside the body "
            f"outline (footprint_length_m {g.footprint_length_m} centred {g.footprint_offset_m} ahead of the CG)")
    _check_radio(p.radio, source)
    ids = aruco_dictionary_size(p.marker.dictionary)  # each valid alone; a marker its dictionary lacks is never seen
    if not p.marker.aruco_id < ids:
        raise CarParamsError(f"{source}: marker.aruco_id: {p.marker.aruco_id} is not an id of marker.dictionary "
                             f"{p.marker.dictionary} (ids 0..{ids - 1})")


def _sections_of(p: CarParams) -> list[tuple[str, Any]]:
    return [(name, getattr(p, name)) for name in _SECTION_TYPES]


def _validate_value(source: str, key: str, f: dataclasses.Field, value: Any) -> Any:
    is_int = f.metadata.get("int", False)
    if value is None and f.metadata.get("optional"):
        return None
    if f.metadata.get("text"):  # a name (the marker's dictionary): a string the field's check accepts
        problem = None if isinstance(value, str) else "must be a string"
        problem = problem or f.metadata["check"](value)
        if problem:
            raise CarParamsError(f"{source}: {key}: {problem}, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        kind = "an integer" if is_int else "a number"
        raise CarParamsError(f"{source}: {key}: must be {kind}, got {value!r}")
    if is_int and not isinstance(value, int):
        raise CarParamsError(f"{source}: {key}: must be an integer, got {value!r}")
    if abs(value) > MAX_MAGNITUDE or not math.isfinite(value):  # (math.isfinite overflows on a huge int)
        # Far beyond any model car: a 2**64 motor loss passed the range checks and blew up the simulation.
        raise CarParamsError(f"{source}: {key}: must be finite and within +-{MAX_MAGNITUDE:g}, got {value!r}")
    problem = f.metadata["check"](value)
    if problem:
        raise CarParamsError(f"{source}: {key}: {problem}, got {value!r}")
    return value if is_int else float(value)


def car_params_from_dict(data: dict[str, Any], source: str = "<dict>") -> CarParams:
    """Build CarParams from a parsed TOML mapping; missing fields take the defaults."""
    if not isinstance(data, dict):
        raise CarParamsError(f"{source}: expected a table of car parameters, got {type(data).__name__}")
    for key in data:
        if key not in _SECTION_TYPES and key != "name":
            raise CarParamsError(f"{source}: {key}: {unknown_key_message(key, ['name', *_SECTION_TYPES])}")
    name = data.get("name", CarParams.name)
    if not isinstance(name, str) or not name:
        raise CarParamsError(f"{source}: name: must be a non-empty string, got {name!r}")
    defaults = CarParams()
    sections: dict[str, Any] = {}
    for sec, cls in _SECTION_TYPES.items():
        raw = data.get(sec, {})
        if not isinstance(raw, dict):
            raise CarParamsError(f"{source}: {sec}: must be a table, got {raw!r}")
        known = {f.name: f for f in fields(cls)}
        for key in raw:
            if key not in known:
                raise CarParamsError(f"{source}: {sec}.{key}: {unknown_key_message(key, known)}")
        values = {k: _validate_value(source, f"{sec}.{k}", known[k], v) for k, v in raw.items()}
        sections[sec] = dataclasses.replace(getattr(defaults, sec), **values)
    try:
        return CarParams(name=name, **sections)
    except CarParamsError as exc:
        raise CarParamsError(str(exc).replace("CarParams", source, 1)) from None


def resolve_car_path(path_or_name: str | Path) -> Path:
    """A bare name ("buzzracer") means vehicles/<name>.toml; anything else is a path."""
    text = str(path_or_name)
    if "/" not in text and "\\" not in text and not text.endswith(".toml"):
        return VEHICLES_DIR / f"{text}.toml"
    return Path(text)


MAX_FILE_BYTES = 2**20
MAX_LINE = 4096


def load_car_params(path_or_name: str | Path) -> CarParams:
    """A car file must name the car and have every table (keys inside a table may be left out): an
    empty file, or one cut short, is an error rather than a car on default parameters."""
    path = resolve_car_path(path_or_name)
    data = fileio.load_toml(path, "car parameter file", max_bytes=MAX_FILE_BYTES, max_line=MAX_LINE,
                            error=CarParamsError)
    if not data:
        raise CarParamsError(f"{path}: empty car parameter file (expected name and tables {', '.join(_SECTION_TYPES)})")
    params = car_params_from_dict(data, source=str(path))
    missing = [k for k in ("name", *_SECTION_TYPES) if k not in data and not _optional_in_file(k)]
    if missing:
        raise CarParamsError(f"{path}: {missing[0]}: missing (a car file has name and every table: "
                             f"{', '.join(_SECTION_TYPES)}; is the file cut short?)")
    return params


def _optional_in_file(key: str) -> bool:
    """Tables added after car files were first written carry metadata {"optional_in_file": True}, so
    older files stay valid."""
    f = next((f for f in fields(CarParams) if f.name == key), None)
    return f is not None and f.metadata.get("optional_in_file", False)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)  # shortest string that round-trips exactly
    if isinstance(v, str):
        escaped = v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
        return f'"{escaped}"'
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_car_params(params: CarParams) -> str:
    """TOML text for params; load_car_params of it gives back an equal CarParams."""
    lines = [f"name = {_toml_value(params.name)}"]
    for sec, obj in _sections_of(params):
        lines.append("")
        lines.append(f"[{sec}]")
        for f in fields(obj):
            doc = f.metadata.get("doc")
            comment = f"  # {doc}" if doc else ""
            if getattr(obj, f.name) is None:  # an optional field left out (TOML has no null)
                lines.append(f"# {f.name} = (not set){comment}")
                continue
            lines.append(f"{f.name} = {_toml_value(getattr(obj, f.name))}{comment}")
    return "\n".join(lines) + "\n"


def save_car_params(params: CarParams, path: str | Path) -> Path:
    return fileio.atomic_write_text(path, dump_car_params(params))
