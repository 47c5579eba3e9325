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


def rectangle_poses(corners) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, 4, 2) corners in footprint order (front-left, front-right, rear-right, rear-left) ->
    centres (n, 2), headings (n,) rad, half extents (n, 2) = (half length, half width)."""
    corners = np.asarray(corners, float)
    centre = corners.mean(axis=1)
    front = 0.5 * (corners[:, 0] + corners[:, 1])
    rear = 0.5 * (corners[:, 2] + corners[:, 3])
    heading = np.arctan2(front[:, 1] - rear[:, 1], front[:, 0] - rear[:, 0])
    half = np.column_stack([0.5 * np.linalg.norm(front - rear, axis=1),
                            0.5 * np.linalg.norm(corners[:, 0] - corners[:, 1], axis=1)])
    return centre, heading, half


def rectangle_gap(a, b) -> np.ndarray:
    """Distance (m) between pairs of rectangles a[i], b[i] ((n, 4, 2) corners in footprint order), 0
    where they overlap. Overlap: no separating axis among the four edge directions (separating-axis
    theorem); distance: the closest corner-to-edge distance either way round (for disjoint convex
    polygons the closest points include a corner of one of them)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    axes = np.stack([a[:, 1] - a[:, 0], a[:, 3] - a[:, 0], b[:, 1] - b[:, 0], b[:, 3] - b[:, 0]], axis=1)  # (n, 4, 2)
    pa = np.einsum("nkd,ncd->nkc", axes, a)                   # corners projected on each axis (n, 4, 4)
    pb = np.einsum("nkd,ncd->nkc", axes, b)
    separated = (pa.max(axis=2) < pb.min(axis=2)) | (pb.max(axis=2) < pa.min(axis=2))
    overlap = ~separated.any(axis=1)
    best = np.full(len(a), np.inf)
    for p, q in ((a, b), (b, a)):
        q0, q1 = q, np.roll(q, -1, axis=1)                    # edges of q: (n, 4, 2)
        e = q1 - q0
        d = p[:, :, None, :] - q0[:, None, :, :]              # (n, 4 corners, 4 edges, 2)
        u = np.clip(np.einsum("nced,ned->nce", d, e) / np.einsum("ned,ned->ne", e, e)[:, None, :], 0.0, 1.0)
        closest = q0[:, None, :, :] + u[..., None] * e[:, None, :, :]
        best = np.minimum(best, np.linalg.norm(p[:, :, None, :] - closest, axis=-1).min(axis=(1, 2)))
    return np.where(overlap, 0.0, best)


def footprint_gap(states, geometry) -> float:
    """Smallest distance (m) between the footprints of two cars (0 when they overlap). states: (2, >=3)
    rows [x, y, heading, ...]; geometry: vehicles.params.GeometryParams (footprint size and offset)."""
    states = np.asarray(states, float)
    corners = footprint_corners(states[:, 0], states[:, 1], states[:, 2], geometry.footprint_length_m,
                                geometry.footprint_width_m, geometry.footprint_offset_m)
    return float(rectangle_gap(corners[:1], corners[1:2])[0])
