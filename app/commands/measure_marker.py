"""`python -m app measure-marker LOG.csv [--car ID] [--car-params CAR.toml] [--out CAR_OUT.toml]`: where a car's
marker is glued (offset and yaw), from slow circles at two steering angles (tracking.marker_offset;
docs/tracking.md, "Measuring the marker offset")."""
from __future__ import annotations

import dataclasses
import math

from app.cli import UserError
from fileio import atomic_write_text, check_output_path
from sysid.log import LogFormatError, read_log
from tracking.marker_offset import MarkerOffsetError, circles_from_poses, marker_offset
from vehicles.params import CarParamsError, dump_car_params, load_car_params


def register(sub) -> None:
    p = sub.add_parser(
        "measure-marker", help="the marker's offset and yaw on a car, from slow circles driven in front of the camera",
        description="Reads a drive log (t,car,x,y,heading,throttle,steering: `track --link-capture` of a video "
                    "tracked with no marker offset, e.g. --markers ID) of the car driving slow circles at two or more "
                    "steady steering angles (one left, one right, half a turn each at least) and fits where its "
                    "marker sits: marker.offset_forward_m, offset_left_m and yaw_rad of the car file.")
    p.add_argument("log", metavar="LOG.csv", help="drive log: tracked marker poses and the steering (wheel angle, rad)")
    p.add_argument("--car", type=int, help="car (marker id) in the log (default: the only one)")
    p.add_argument("--car-params", default="buzzracer", help="car file: its wheelbase and CG (default buzzracer)")
    p.add_argument("--out", help="write the car file with the measured marker fields (TOML)")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.out:
        check_output_path(args.out)
    try:
        car = load_car_params(args.car_params)
    except (CarParamsError, FileNotFoundError) as exc:
        raise UserError(f"--car-params: {exc}") from None
    try:
        log = read_log(args.log)
    except (LogFormatError, FileNotFoundError) as exc:
        raise UserError(str(exc)) from None
    car_id = args.car
    if car_id is None:
        if len(log.cars) > 1:
            raise UserError(f"{args.log}: the log has cars {log.cars}; choose one with --car")
        car_id = log.cars[0]
    pick = log.car == car_id
    if not pick.any():
        raise UserError(f"{args.log}: no rows of car {car_id} (cars in the log: {log.cars})")
    geometry = car.geometry
    try:
        result = marker_offset(circles_from_poses(log.t[pick], log.x[pick], log.y[pick], log.heading[pick],
                                                  log.steering[pick], geometry.lf_m, geometry.lr_m))
    except MarkerOffsetError as exc:
        raise UserError(f"{args.log}: car {car_id}: {exc}") from None
    for c in result.circles:
        print(f"circle at steering {c.steering_rad:+.3f} rad: {c.poses} poses over {math.degrees(c.arc_rad):.0f} deg, "
              f"marker path radius {c.radius_m:.3f} m (rms {1e3 * c.rms_m:.2f} mm)")
    print(f"marker.offset_forward_m = {result.offset_forward_m:.4f}")
    print(f"marker.offset_left_m = {result.offset_left_m:.4f}")
    print(f"marker.yaw_rad = {result.yaw_rad:.4f}  ({math.degrees(result.yaw_rad):.2f} deg)")
    if len(result.circles) > 2:
        print(f"fit residual over {len(result.circles)} circles: {1e3 * result.residual_m:.2f} mm")
    if args.out:
        marker = dataclasses.replace(car.marker, offset_forward_m=round(result.offset_forward_m, 5),
                                     offset_left_m=round(result.offset_left_m, 5), yaw_rad=round(result.yaw_rad, 5))
        try:
            text = dump_car_params(dataclasses.replace(car, marker=marker))
        except (CarParamsError, ValueError) as exc:  # an offset outside the car file's bounds
            raise UserError(f"--out: the measured marker does not make a valid car file: {exc}") from None
        atomic_write_text(args.out, text)
        print(f"wrote {args.out}")
    return 0
