"""Signed distance between oriented 2-D boxes, optionally with rounded corners (collision geometry).

A box with ``corner_rounding`` f is the Minkowski sum of a core rectangle and a disc of radius
``s = f * min(length, width) / 2`` (f = 0: sharp rectangle, f = 1: capsule), so the distance between
two rounded boxes is the core-to-core signed distance minus both radii (exact, overlapping or not).
The core-to-core signed distance is computed exactly: separating-axis overlap when the cores
intersect (minus the penetration depth), else the nearest vertex-to-rectangle distance.
"""

from __future__ import annotations

import numpy as np

__all__ = ["box_collisions", "box_signed_distance", "rectangle_signed_distance"]


def _outside_distance(px: np.ndarray, py: np.ndarray, half_l: np.ndarray, half_w: np.ndarray) -> np.ndarray:
    """Distance from local points to an axis-aligned rectangle ``[-l, l] x [-w, w]`` (0 inside)."""
    ex = np.maximum(np.abs(px) - half_l, 0)
    ey = np.maximum(np.abs(py) - half_w, 0)
    return np.sqrt(ex * ex + ey * ey)


def _relative(
    dx: np.ndarray, dy: np.ndarray, cos_a: np.ndarray, sin_a: np.ndarray, cos_b: np.ndarray, sin_b: np.ndarray
) -> tuple[np.ndarray, ...]:
    """cos/sin of the heading of B relative to A, and the offset of B in A's frame and of A in B's frame."""
    c = cos_a * cos_b + sin_a * sin_b  # cos(heading_b - heading_a)
    s = cos_a * sin_b - sin_a * cos_b  # sin(heading_b - heading_a)
    ax, ay = cos_a * dx + sin_a * dy, cos_a * dy - sin_a * dx
    bx, by = -(cos_b * dx + sin_b * dy), -(cos_b * dy - sin_b * dx)
    return c, s, ax, ay, bx, by


def _separation(
    c: np.ndarray,
    s: np.ndarray,
    ax: np.ndarray,
    ay: np.ndarray,
    bx: np.ndarray,
    by: np.ndarray,
    half_a: tuple[np.ndarray, np.ndarray],
    half_b: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """Largest gap along the four separating axes (> 0: disjoint; < 0: minus the penetration depth)."""
    la, wa = half_a
    lb, wb = half_b
    ac, as_ = np.abs(c), np.abs(s)
    return np.maximum(
        np.maximum(np.abs(ax) - la - (lb * ac + wb * as_), np.abs(ay) - wa - (lb * as_ + wb * ac)),
        np.maximum(np.abs(bx) - lb - (la * ac + wa * as_), np.abs(by) - wb - (la * as_ + wa * ac)),
    )


def rectangle_signed_distance(
    dx: np.ndarray,
    dy: np.ndarray,
    cos_a: np.ndarray,
    sin_a: np.ndarray,
    half_a: tuple[np.ndarray, np.ndarray],
    cos_b: np.ndarray,
    sin_b: np.ndarray,
    half_b: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """Signed distance between rectangles A and B (negative = minus the penetration depth).

    ``(dx, dy)`` is the centre of B minus the centre of A; headings are given by their cosine and sine;
    ``half_*`` are the (half length, half width). All arguments broadcast together.
    """
    la, wa = half_a
    lb, wb = half_b
    c, s, ax, ay, bx, by = _relative(dx, dy, cos_a, sin_a, cos_b, sin_b)
    separation = _separation(c, s, ax, ay, bx, by, half_a, half_b)
    # Disjoint rectangles: the closest pair of points always involves a vertex of one of them.
    nearest = None
    for sl in (-1, 1):
        for sw in (-1, 1):
            # Corner of B in A's frame (B's axes are (c, s) and (-s, c) there), and vice versa.
            d_b = _outside_distance(ax + sl * lb * c - sw * wb * s, ay + sl * lb * s + sw * wb * c, la, wa)
            d_a = _outside_distance(bx + sl * la * c + sw * wa * s, by - sl * la * s + sw * wa * c, lb, wb)
            both = np.minimum(d_a, d_b)
            nearest = both if nearest is None else np.minimum(nearest, both)
    return np.where(separation > 0, nearest, separation)


def box_signed_distance(
    xyh_a: np.ndarray,
    size_a: np.ndarray,
    xyh_b: np.ndarray,
    size_b: np.ndarray,
    corner_rounding: float = 0.0,
) -> np.ndarray:
    """Signed distance between boxes ``xyh [..., 3]`` (centre, heading) of ``size [..., 2]`` (length, width).

    Broadcasts over the leading axes. ``corner_rounding`` in [0, 1] rounds the corners (WOSAC uses 0.7).
    """
    if not 0.0 <= corner_rounding <= 1.0:
        raise ValueError(f"corner_rounding must be in [0, 1], got {corner_rounding}")
    xyh_a, xyh_b = np.asarray(xyh_a, np.float64), np.asarray(xyh_b, np.float64)
    size_a, size_b = np.asarray(size_a, np.float64), np.asarray(size_b, np.float64)
    for name, arr, last in (
        ("xyh_a", xyh_a, 3),
        ("xyh_b", xyh_b, 3),
        ("size_a", size_a, 2),
        ("size_b", size_b, 2),
    ):
        if arr.ndim == 0 or arr.shape[-1] != last:
            raise ValueError(
                f"box_signed_distance: {name} must have a last dimension of {last}, got {arr.shape}"
            )
    radius_a = corner_rounding * size_a.min(axis=-1) / 2
    radius_b = corner_rounding * size_b.min(axis=-1) / 2
    core = rectangle_signed_distance(
        xyh_b[..., 0] - xyh_a[..., 0],
        xyh_b[..., 1] - xyh_a[..., 1],
        np.cos(xyh_a[..., 2]),
        np.sin(xyh_a[..., 2]),
        (size_a[..., 0] / 2 - radius_a, size_a[..., 1] / 2 - radius_a),
        np.cos(xyh_b[..., 2]),
        np.sin(xyh_b[..., 2]),
        (size_b[..., 0] / 2 - radius_b, size_b[..., 1] / 2 - radius_b),
    )
    return core - radius_a - radius_b


def box_collisions(
    xyh_a: np.ndarray,
    size_a: np.ndarray,
    xyh_b: np.ndarray,
    size_b: np.ndarray,
    corner_rounding: float = 0.0,
) -> np.ndarray:
    """True where the two boxes overlap (signed distance < 0; touching boxes do not collide).

    Sharp boxes (``corner_rounding`` 0, the environment's) only need the separating-axis gap: the signed
    distance is negative exactly where that gap is (it is a non-negative vertex distance elsewhere)."""
    if corner_rounding != 0.0:
        return box_signed_distance(xyh_a, size_a, xyh_b, size_b, corner_rounding) < 0
    xyh_a, xyh_b = np.asarray(xyh_a, np.float64), np.asarray(xyh_b, np.float64)
    size_a, size_b = np.asarray(size_a, np.float64), np.asarray(size_b, np.float64)
    relative = _relative(
        xyh_b[..., 0] - xyh_a[..., 0],
        xyh_b[..., 1] - xyh_a[..., 1],
        np.cos(xyh_a[..., 2]),
        np.sin(xyh_a[..., 2]),
        np.cos(xyh_b[..., 2]),
        np.sin(xyh_b[..., 2]),
    )
    half_a, half_b = (size_a[..., 0] / 2, size_a[..., 1] / 2), (size_b[..., 0] / 2, size_b[..., 1] / 2)
    return _separation(*relative, half_a, half_b) < 0
