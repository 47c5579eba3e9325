"""`race --mocap natnet://SERVER[:PORT]`: the loop's parts for motion-capture input (docs/tracking.md,
"Motion capture"): the NatNet source, the mocap tracker (rigid body -> car pose through the mocap
calibration) and the feed, on hardware (`--serial`) or in HIL (`--hil`, a loopback Motive server in the
world process streams the simulator's poses)."""
from __future__ import annotations

import dataclasses
import math
from urllib.parse import urlsplit

from app.cli import UserError
from race.hil import HilWorld, MocapSpec, WorldSpec
from race.mocap_feed import MocapFeed
from race.world import MonotonicClock
from tracking.estimator import MultiCarEstimator
from tracking.mocap import MocapCalibrationError, MocapCar, MocapTracker, MocapTransform, load_mocap_calibration
from tracking.natnet import MocapError, NatNetAddress, NatNetSource, parse_natnet_url

# The HIL world's Motive frame, as a lab might have it: Y-up, its origin near the arena's centre, turned against
# the track. The world always streams through it; the loop maps back with it, or with --mocap-calibration
# (estimated, e.g. by mocap-calibrate from tracking/data/hil_mocap_survey.csv: its error then shows).
HIL_TRANSFORM = MocapTransform(up_axis="y", rotation_rad=0.35, translation_m=(2.5, 1.5))


def add_mocap_arguments(g) -> None:
    g.add_argument("--mocap", default=None, metavar="natnet://SERVER[:PORT][?multicast=GROUP]",
                   help="car poses from OptiTrack Motive over NatNet instead of a camera (PORT = Motive's command port, "
                        "default 1510; unicast unless ?multicast=GROUP, e.g. 239.255.42.99); with --hil a loopback "
                        "Motive server streams the simulator's poses, unicast (PORT 0 or none: a free port). "
                        "Needs pip install .[mocap]")
    g.add_argument("--mocap-calibration", default=None, metavar="FILE",
                   help="mocap-to-track transform (python -m app mocap-calibrate); required on hardware")
    g.add_argument("--mocap-latency-ms", type=float, default=0.0, metavar="MS",
                   help="Motive's exposure-to-arrival delay, subtracted from frame times (Motive's latency readout)")


def _transform(args, required: bool) -> MocapTransform:
    if args.mocap_calibration is None:
        if required:
            raise UserError("--mocap on hardware needs --mocap-calibration FILE (python -m app mocap-calibrate)")
        return HIL_TRANSFORM
    try:
        return load_mocap_calibration(args.mocap_calibration)
    except FileNotFoundError:
        raise UserError(f"--mocap-calibration: {args.mocap_calibration}: file not found") from None
    except MocapCalibrationError as exc:
        raise UserError(f"--mocap-calibration: {exc}") from None


def mocap_cars(setup, cars, hil: bool) -> list[MocapCar]:
    """Each car's rigid body: the roster's rigid_body_id, else its car file's mocap.rigid_body_id, else
    (HIL only) its 1-based roster position, Motive's first ids. UserError naming the car and field."""
    out, seen = [], {}
    for i, (c, binding) in enumerate(zip(setup.cars, cars)):
        m = setup.car_file(i).mocap
        rb = c.rigid_body_id if c.rigid_body_id is not None else m.rigid_body_id
        field = "rigid_body_id" if c.rigid_body_id is not None else "car file mocap.rigid_body_id"
        if rb is None:
            if not hil:
                raise UserError(f"car {c.name}: rigid_body_id: not set (give it in the roster or the car file's "
                                f"[mocap] table: Motive's streaming id of the car's rigid body)")
            rb, field = i + 1, "rigid_body_id (HIL default)"
        if rb in seen:
            raise UserError(f"car {c.name}: {field}: {rb} is also car {seen[rb]}'s; each car needs its own")
        seen[rb] = c.name
        out.append(MocapCar(binding.marker_id, rb, m.offset_forward_m, m.offset_left_m, m.yaw_rad))
    return out


def _address(args) -> NatNetAddress:
    if not math.isfinite(args.mocap_latency_ms) or not 0 <= args.mocap_latency_ms <= 500:
        raise UserError(f"--mocap-latency-ms must be in [0, 500] ms, got {args.mocap_latency_ms}")
    try:
        return parse_natnet_url(args.mocap)
    except MocapError as exc:
        raise UserError(f"--mocap: {exc}") from None


def _source(args, address: NatNetAddress) -> NatNetSource:
    try:
        return NatNetSource(address, MonotonicClock(), latency_s=args.mocap_latency_ms / 1e3)
    except MocapError as exc:
        raise UserError(f"--mocap: {exc}") from None


def open_mocap_hil(args, world_fields: dict, setup, cars):
    """(world, feed, tracker, estimator, serial path, note) of a HIL race on mocap input."""
    address = _address(args)
    if address.host not in ("127.0.0.1", "localhost") or address.multicast_group is not None:
        raise UserError(f"--mocap {args.mocap}: with --hil the Motive server is a loopback unicast one: "
                        f"natnet://127.0.0.1[:PORT]")
    transform = _transform(args, required=False)
    mcars = mocap_cars(setup, cars, hil=True)
    port = urlsplit(args.mocap).port or 0
    spec = WorldSpec(**world_fields, mocap=MocapSpec(tuple(c.rigid_body_id for c in mcars), HIL_TRANSFORM, port=port))
    world = HilWorld(spec)
    try:
        source = _source(args, dataclasses.replace(address, command_port=world.info["mocap_port"]))
    except Exception:
        world.close()
        raise
    note = (f"mocap: NatNet from {source.server} on port {world.info['mocap_port']}, rigid bodies "
            + ", ".join(f"{b.name} {m.rigid_body_id}" for b, m in zip(cars, mcars)))
    feed = MocapFeed(source, world)  # the loop's world: the HIL world with the mocap source's frames
    return feed, feed, MocapTracker(transform, mcars), MultiCarEstimator(), world.serial_path, note


def open_mocap_hardware(args, setup, cars):
    """(feed, tracker, estimator, note) on a real Motive server."""
    address = _address(args)
    transform = _transform(args, required=True)
    mcars = mocap_cars(setup, cars, hil=False)
    source = _source(args, address)
    note = (f"mocap: NatNet from {source.server} at {address.url}, rigid bodies "
            + ", ".join(f"{b.name} {m.rigid_body_id}" for b, m in zip(cars, mcars)))
    return MocapFeed(source), MocapTracker(transform, mcars), MultiCarEstimator(), note
