"""`python -m app mocap-calibrate POINTS.csv --out FILE [--up-axis y|z] [--scale]`: the mocap-to-track
transform from a few surveyed points (docs/tracking.md, "Motion capture"; file format:
docs/file-formats.md, "Mocap calibration file")."""
from __future__ import annotations

import json

import numpy as np

from app.cli import UserError
from fileio import atomic_write_text, check_output_path
from tracking.mocap import UP_AXES, MocapCalibrationError, fit_transform, ground_pose, load_survey_points, \
    mocap_calibration_json

# A surveyed point off by more than this after the fit is reported (a typo, a point read off the wrong marker).
WARN_RESIDUAL_M = 0.005


def register(sub):
    p = sub.add_parser(
        "mocap-calibrate", help="mocap-to-track transform from surveyed points (for race --mocap)",
        description="Fit the 2-D rigid transform (with --scale: similarity) that takes the ground-plane "
                    "positions Motive reports for markers on surveyed track points to those points; print "
                    "each point's residual and write the calibration file race --mocap-calibration reads.")
    p.add_argument("points", metavar="POINTS.csv",
                   help="CSV with columns mocap_x,mocap_y,mocap_z (Motive, metres),track_x,track_y (metres) "
                        "and optionally name; at least 3 points")
    p.add_argument("--out", required=True, help="mocap calibration JSON to write")
    p.add_argument("--up-axis", choices=UP_AXES, default="y",
                   help="Motive's up axis as streamed (default y, Motive's default)")
    p.add_argument("--scale", action="store_true",
                   help="fit a scale too (a mocap system calibrated with a wrong wand length); default rigid")
    p.set_defaults(func=run)


def run(args) -> int:
    check_output_path(args.out)
    try:
        points = load_survey_points(args.points)
    except FileNotFoundError:
        raise UserError(f"{args.points}: file not found") from None
    except MocapCalibrationError as exc:
        raise UserError(str(exc)) from None
    unit = np.array([ground_pose(p, (0.0, 0.0, 0.0, 1.0), args.up_axis)[:2] for p in points.mocap_xyz])
    try:
        fit = fit_transform(unit, points.track_xy, args.up_axis, with_scale=args.scale)
    except ValueError as exc:
        raise UserError(f"{args.points}: {exc}") from None
    t = fit.transform
    print(f"mocap-calibrate: {len(unit)} points, up axis {args.up_axis}: rotation {np.degrees(t.rotation_rad):.3f} deg, "
          f"translation ({t.translation_m[0]:.4f}, {t.translation_m[1]:.4f}) m, scale {t.scale:.6f}")
    for name, row, r in zip(points.names, points.rows, fit.residuals_m):
        flag = "  <- check this point" if r > WARN_RESIDUAL_M else ""
        print(f"  {name:12s} (row {row}): residual {1e3 * r:.2f} mm{flag}")
    print(f"residual rms {1e3 * fit.rms_m:.2f} mm, max {1e3 * float(fit.residuals_m.max()):.2f} mm")
    atomic_write_text(args.out, json.dumps(mocap_calibration_json(t), indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0
