"""Steering linkage beyond gain and offset: play (backlash) and left/right gain asymmetry.

servo angle s (after the servo's delay, limits and rate limit) -> play of width b -> linkage
angle w -> asymmetric scaling -> wheel angle = gain * scaled + offset (docs/vehicles.md). The play
operator holds w while |s - w| <= b/2 and drags it along otherwise, so a reversing command must
cross the dead band b before the wheels move. Float and numpy inputs alike.
"""

from __future__ import annotations

import numpy as np


def play(previous, servo, backlash: float):
    """Linkage angle after the servo moved to ``servo`` (previous linkage angle ``previous``)."""
    half = 0.5 * backlash
    if isinstance(servo, float) and isinstance(previous, float):
        return min(max(previous, servo - half), servo + half)
    return np.clip(previous, servo - half, servo + half)


def asymmetric(angle, asymmetry: float):
    """angle * (1 + a) for left (positive) angles, angle * (1 - a) for right ones."""
    if isinstance(angle, float):
        return angle * (1.0 + asymmetry) if angle >= 0.0 else angle * (1.0 - asymmetry)
    return angle * (1.0 + asymmetry * np.sign(angle))


def inverse_asymmetric(scaled, asymmetry: float):
    """The angle whose :func:`asymmetric` image is ``scaled`` (signs agree since |a| < 1)."""
    if isinstance(scaled, float):
        return scaled / (1.0 + asymmetry) if scaled >= 0.0 else scaled / (1.0 - asymmetry)
    return scaled / (1.0 + asymmetry * np.sign(scaled))
