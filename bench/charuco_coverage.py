"""Does calibrate-camera's reported uncertainty cover the real error? ``python -m app bench charuco``

Renders ``--trials`` sets of ``--views`` ChArUco views with known intrinsics (sim.charuco_views: OpenCV
alone, blur 0.6 px, noise 2 grey levels), calibrates each with tracking.charuco and prints, for fx, fy, cx,
cy, the largest relative error and the fraction of trials whose error lies within 1, 2 and 3 reported
standard deviations (a Gaussian gives 68, 95 and 99.7 %).
"""
from __future__ import annotations

import argparse

import numpy as np
from tqdm import tqdm

from sim.charuco_views import CAMERA_MATRIX, SIZE, BoardRenderer
from tracking.charuco import BoardDetector, CharucoBoardSpec, calibrate_intrinsics

SPEC = CharucoBoardSpec(7, 5, 0.03, 0.022, "DICT_4X4_50")
ENTRIES = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `python -m app bench charuco`."""
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--seed", type=int, default=100)


def run(args) -> int:
    if args.trials < 1 or args.views < 3:
        raise ValueError("--trials must be >= 1 and --views >= 3")
    render = BoardRenderer((SPEC.squares_x, SPEC.squares_y), SPEC.square_length_m, SPEC.marker_length_m, SPEC.dictionary)
    detector = BoardDetector(SPEC)
    z, rel = [], []
    for trial in tqdm(range(args.trials), desc="renderings", unit="set"):
        rng = np.random.default_rng(args.seed + trial)
        views = [detector.detect(render(r, t, rng=rng), f"v{i}") for i, (r, t) in enumerate(render.random_poses(args.views, rng))]
        result = calibrate_intrinsics(views, SIZE)
        k = result.intrinsics.camera_matrix
        error = np.array([k[e] - CAMERA_MATRIX[e] for e in ENTRIES.values()])
        z.append(np.abs(error) / np.array([result.std_px[name] for name in ENTRIES]))
        rel.append(np.abs(error) / np.array([CAMERA_MATRIX[e] for e in ENTRIES.values()]))
    z, rel = np.array(z), np.array(rel)
    print(f"{args.trials} renderings of {args.views} views ({SIZE[0]}x{SIZE[1]}, {SPEC.describe()})")
    print("param  max error %   within 1 / 2 / 3 std")
    for i, name in enumerate(ENTRIES):
        print(f"{name:5}  {100 * rel[:, i].max():10.3f}   " + " / ".join(f"{100 * np.mean(z[:, i] <= m):.0f} %" for m in (1, 2, 3)))
    return 0


if __name__ == "__main__":
    raise SystemExit("moved: python -m app bench charuco")
