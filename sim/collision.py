"""Car footprints as oriented rectangles and their overlap test (separating-axis theorem)."""

from __future__ import annotations

import numpy as np


def footprint_centers(x, y, heading, offset) -> np.ndarray:
    """Rectangle centres (..., 2): the CG moved ``offset`` metres along the heading."""
    x, y, heading = np.asarray(x, float), np.asarray(y, float), np.asarray(heading, float)
    return np.stack([x + offset * np.cos(heading), y + offset * np.sin(heading)], axis=-1)


def footprint_corners(x, y, heading, length, width, offset=0.0) -> np.ndarray:
    """Corners (..., 4, 2) in order front-left, front-right, rear-right, rear-left."""
    heading = np.asarray(heading, float)
    c = footprint_centers(x, y, heading, offset)
    fwd = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    left = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
    hl = np.asarray(length, float)[..., None] / 2.0
    hw = np.asarray(width, float)[..., None] / 2.0
    signs = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, -1.0], [-1.0, 1.0]])
    return (
        c[..., None, :]
        + signs[:, 0, None] * (hl * fwd)[..., None, :]
        + signs[:, 1, None] * (hw * left)[..., None, :]
    )


def rectangles_overlap(center_a, heading_a, half_a, center_b, heading_b, half_b) -> np.ndarray:
    """True where rectangle A and rectangle B intersect (touching counts as overlap).

    centers (..., 2), headings (...), half extents (..., 2) = (half length, half width); all
    broadcast together. Two convex shapes are disjoint iff some edge normal of either separates
    their projections; a rectangle has only two distinct edge normals, so four axes suffice.
    """
    center_a, center_b = np.asarray(center_a, float), np.asarray(center_b, float)
    half_a, half_b = np.asarray(half_a, float), np.asarray(half_b, float)
    ha, hb = np.asarray(heading_a, float), np.asarray(heading_b, float)
    axes_a = np.stack([np.stack([np.cos(ha), np.sin(ha)], -1), np.stack([-np.sin(ha), np.cos(ha)], -1)], -2)
    axes_b = np.stack([np.stack([np.cos(hb), np.sin(hb)], -1), np.stack([-np.sin(hb), np.cos(hb)], -1)], -2)
    axes = np.concatenate(np.broadcast_arrays(axes_a, axes_b), axis=-2)  # (..., 4, 2)
    d = center_b - center_a
    dist = np.abs(np.einsum("...kj,...j->...k", axes, d))
    # Projection radius of a rectangle onto axis n: sum over its own axes of half * |axis . n|.
    radius_a = np.einsum("...kj,...j->...k", np.abs(np.einsum("...kj,...mj->...km", axes, axes_a)), half_a)
    radius_b = np.einsum("...kj,...j->...k", np.abs(np.einsum("...kj,...mj->...km", axes, axes_b)), half_b)
    return np.all(dist <= radius_a + radius_b, axis=-1)
