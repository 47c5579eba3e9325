"""Judgements of the pre-race hardware check (``python -m app check``, docs/race-stack.md): does the
calibration still fit the fixed markers, and did a commanded car (and only it) move as told."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# A car "moved" when its marker moved this much between two still measurements: well above the
# tracker's noise on a car at rest (sub-millimetre in HIL, a few mm on a real camera), well below the
# few centimetres a short throttle pulse gives.
MOVED_M = 0.01
STILL_M = 0.005


@dataclass(frozen=True)
class FixedMarkerFit:
    seen: list[int]
    missing: list[int]
    rms_px: float        # detected vs projected corners (centres for markers without a surveyed heading)
    max_px: float
    max_mm: float        # detected corners mapped onto the marker plane vs their surveyed positions


def fixed_marker_fit(camera, marker_set, detected: dict[int, np.ndarray]) -> FixedMarkerFit:
    """How well ``camera`` (tracking.geometry.PinholeCamera of the calibration) maps the surveyed fixed
    markers of ``marker_set`` onto the corners ``detected`` in a frame ({id: (4, 2) pixels})."""
    px_err: list[float] = []
    mm_err: list[float] = []
    seen, missing = [], []
    for marker_id, marker in sorted(marker_set.markers.items()):
        corners = detected.get(marker_id)
        if corners is None:
            missing.append(marker_id)
            continue
        seen.append(marker_id)
        if marker.heading_rad is not None:
            world = marker.corners()
            image = np.asarray(corners, float).reshape(4, 2)
        else:
            world = np.array([[marker.x, marker.y, marker.z]])
            image = np.asarray(corners, float).reshape(4, 2).mean(0, keepdims=True)
        px_err += np.linalg.norm(camera.project(world) - image, axis=1).tolist()
        on_plane = camera.pixels_to_plane(image, marker.z)
        mm_err += (1e3 * np.linalg.norm(on_plane[:, :2] - world[:, :2], axis=1)).tolist()
    if not px_err:
        return FixedMarkerFit(seen, missing, math.nan, math.nan, math.nan)
    return FixedMarkerFit(seen, missing, float(np.sqrt(np.mean(np.square(px_err)))), float(max(px_err)),
                          float(max(mm_err)))


@dataclass(frozen=True)
class Displacement:
    along_m: float     # along the car's heading at the start (forward positive)
    across_m: float    # to its left
    distance_m: float


def displacement(before: tuple[float, float, float], after: tuple[float, float, float]) -> Displacement:
    """Motion from pose ``before`` (x, y, heading) to ``after`` in the frame of ``before``."""
    dx, dy = after[0] - before[0], after[1] - before[1]
    c, s = math.cos(before[2]), math.sin(before[2])
    return Displacement(c * dx + s * dy, -s * dx + c * dy, math.hypot(dx, dy))


def judge_throttle_pulse(car: str, moves: dict[str, Displacement]) -> tuple[bool, str]:
    """After a short forward throttle pulse to ``car``: it must have moved forward along its heading by
    more than MOVED_M and every other car must have stayed within STILL_M. Returns (ok, what happened,
    naming the likely fault)."""
    own = moves[car]
    others = {name: d for name, d in moves.items() if name != car and d.distance_m > STILL_M}
    said = f"{car} moved {100 * own.along_m:+.1f} cm along its heading, {100 * own.across_m:+.1f} cm across"
    if others:
        other_text = ", ".join(f"{name} moved {100 * d.distance_m:.1f} cm" for name, d in others.items())
        if own.distance_m <= MOVED_M:
            return False, f"{said}; {other_text} instead: radio ids swapped ({car}'s commands drive another car)"
        return False, f"{said}; {other_text} too: another car listens to {car}'s radio id"
    if own.distance_m <= MOVED_M:
        return False, f"{said}: did not move (radio id wrong or receiver off, or throttle below the motor's dead band)"
    if own.along_m < -MOVED_M:
        return False, f"{said}: moved backwards: throttle channel reversed"
    if own.along_m < abs(own.across_m):
        return False, f"{said}: moved mostly sideways, not along its heading: marker mounted turned?"
    return True, said
