"""Footprints as convex polygons: boxes at poses, overlap by separating axes, and the distance between two.

Every function broadcasts over leading dimensions, so a whole episode (time x objects) is one call. Polygons are
``[..., K, 2]`` world corners in order (either winding); boxes are ``(x_min, x_max, y_min, y_max)`` in the
object's own frame (x forward, y left), placed at a pose ``(x, y, yaw)``, as ``parksim.vehicle.footprint`` places
the ego's body (whose box is ``VehicleParams.extent``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["Box", "box_polygon", "overlaps", "polygon_distance", "overlap_matrix", "nearest_distance"]

_SLACK = 1e-9
"""Metres added to the bounding circles' reach when pruning pairs: far above the rounding of their centres and
radii (1e-15 m at garage scale), so no pair that the exact tests would count is pruned."""

Box = tuple[float, float, float, float]
"""A footprint in the object's own frame: ``(x_min, x_max, y_min, y_max)``, metres."""


def box_polygon(pose: Sequence[float] | np.ndarray, box: Box) -> np.ndarray:
    """World corners of ``box`` at ``pose``, front-left first and counter-clockwise (as ``vehicle.footprint``).

    Args:
        pose: ``[..., 3]`` poses ``(x, y, yaw)`` (metres, radians).
        box: ``(x_min, x_max, y_min, y_max)`` in the object's frame.

    Returns:
        ``[..., 4, 2]`` float64 corners.
    """
    p = np.asarray(pose, np.float64)
    x0, x1, y0, y1 = box
    local = np.array([[x1, y1], [x0, y1], [x0, y0], [x1, y0]])
    c, s = np.cos(p[..., 2])[..., None], np.sin(p[..., 2])[..., None]
    x = local[:, 0] * c - local[:, 1] * s + p[..., 0:1]
    y = local[:, 0] * s + local[:, 1] * c + p[..., 1:2]
    return np.stack([x, y], -1)


def _unit_normals(polygon: np.ndarray) -> np.ndarray:
    """``[..., K, 2]`` unit normals of the edges (an axis-aligned edge gives an exact ``(0, 1)``-like axis)."""
    edges = np.roll(polygon, -1, axis=-2) - polygon
    normals = np.stack([-edges[..., 1], edges[..., 0]], -1)
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True)


def overlaps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether convex polygons overlap, by the separating-axis test; touching counts as overlapping.

    Both polygons are projected on every edge normal of either; they are apart when some projection leaves a gap.
    The projections round like any dot product (a few float64 spacings at the coordinates' magnitude), so polygons
    closer than that may be reported either way, and farther ones never are.

    Args:
        a: ``[..., K, 2]`` corners.
        b: ``[..., L, 2]`` corners, leading dimensions broadcasting with ``a``'s.

    Returns:
        ``[...]`` bool.
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    lead = np.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    a = np.broadcast_to(a, (*lead, *a.shape[-2:]))
    b = np.broadcast_to(b, (*lead, *b.shape[-2:]))
    axes = np.concatenate([_unit_normals(a), _unit_normals(b)], axis=-2)          # [..., K + L, 2]
    pa = np.einsum("...nd,...kd->...nk", axes, a)                                  # [..., axes, K]
    pb = np.einsum("...nd,...kd->...nk", axes, b)
    apart = (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
    return ~apart.any(-1)


def _point_to_edges(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """``[..., P]``: each point's distance to the nearest point on the polygon's boundary."""
    a = polygon[..., None, :, :]                                   # [..., 1, K, 2]
    e = np.roll(polygon, -1, axis=-2)[..., None, :, :] - a
    d = points[..., :, None, :] - a                                 # [..., P, K, 2]
    t = np.clip(np.sum(d * e, -1) / np.sum(e * e, -1), 0.0, 1.0)
    return np.linalg.norm(d - t[..., None] * e, axis=-1).min(-1)


def polygon_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance between convex polygons: 0 where they overlap (``overlaps``), else the shortest gap.

    Two disjoint convex polygons are nearest at a corner of one, so the gap is the smallest distance of a corner
    of either to an edge of the other.

    Args:
        a: ``[..., K, 2]`` corners.
        b: ``[..., L, 2]`` corners, leading dimensions broadcasting with ``a``'s.

    Returns:
        ``[...]`` float64 metres.
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    gap = np.minimum(_point_to_edges(a, b).min(-1), _point_to_edges(b, a).min(-1))
    return np.where(overlaps(a, b), 0.0, gap)


def _circles(polygons: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``([..., 2] centres, [...] radii)`` of circles around polygons (about their corners' mean)."""
    centres = polygons.mean(-2)
    return centres, np.linalg.norm(polygons - centres[..., None, :], axis=-1).max(-1)


def _bounds(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``([P, Q] lower, [P, Q] upper)`` bounds of the distances between polygons: their bounding circles' gap, and
    the distance between their centres (two points inside them)."""
    (ca, ra), (cb, rb) = _circles(a), _circles(b)
    d = np.linalg.norm(ca[:, None] - cb[None], axis=-1)
    return d - ra[:, None] - rb[None] - _SLACK, d + _SLACK


def overlap_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Which of ``a`` overlaps which of ``b`` (``overlaps`` on every pair whose bounding circles meet).

    Args:
        a: ``[P, K, 2]`` convex polygons.
        b: ``[Q, L, 2]`` convex polygons.

    Returns:
        ``[P, Q]`` bool.
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    out = np.zeros((len(a), len(b)), bool)
    if out.size:
        i, j = np.nonzero(_bounds(a, b)[0] <= 0)
        out[i, j] = overlaps(a[i], b[j])
    return out


def nearest_distance(a: np.ndarray, b: np.ndarray) -> float:
    """The smallest ``polygon_distance`` between any of ``a`` and any of ``b``.

    Measured exactly only on the pairs whose bounding circles allow it to be the smallest.

    Args:
        a: ``[P, K, 2]`` convex polygons (P > 0).
        b: ``[Q, L, 2]`` convex polygons (Q > 0).

    Returns:
        Metres (0 when any pair overlaps).
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    low, high = _bounds(a, b)
    i, j = np.nonzero(low <= high.min())
    return float(polygon_distance(a[i], b[j]).min())
