"""Vectorized 2-D geometry shared by sources, tokenizer, dataset and metrics (NumPy, any batch shape)."""

from __future__ import annotations

import numpy as np

# Unit-box corner signs in the box frame, ordered (front-left, front-right, rear-right, rear-left).
_CORNER_SIGNS = np.array([[0.5, 0.5], [0.5, -0.5], [-0.5, -0.5], [-0.5, 0.5]])


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap radians to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def rotation(heading: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 2, 2]`` for headings ``[...]``."""
    c, s = np.cos(heading), np.sin(heading)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def box_corners(xyh: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Ordered corners ``[...,4,2]`` of boxes ``xyh [...,3]`` (centre, heading) of size ``[...,2]`` (l, w)."""
    local = _CORNER_SIGNS * np.asarray(size)[..., None, :]  # [...,4,2]
    c, s = np.cos(xyh[..., 2])[..., None], np.sin(xyh[..., 2])[..., None]
    x = xyh[..., None, 0] + c * local[..., 0] - s * local[..., 1]
    y = xyh[..., None, 1] + s * local[..., 0] + c * local[..., 1]
    return np.stack([x, y], -1)


def to_local(origin: np.ndarray, xyh: np.ndarray) -> np.ndarray:
    """Express states ``xyh [...,3]`` in the frame of states ``origin [...,3]`` (broadcasting)."""
    d = xyh[..., :2] - origin[..., :2]
    c, s = np.cos(origin[..., 2]), np.sin(origin[..., 2])
    x = c * d[..., 0] + s * d[..., 1]
    y = -s * d[..., 0] + c * d[..., 1]
    return np.stack([x, y, wrap_angle(xyh[..., 2] - origin[..., 2])], -1)


def to_global(origin: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_local`: states given in the frame of ``origin`` back to the global frame."""
    c, s = np.cos(origin[..., 2]), np.sin(origin[..., 2])
    x = origin[..., 0] + c * local[..., 0] - s * local[..., 1]
    y = origin[..., 1] + s * local[..., 0] + c * local[..., 1]
    return np.stack([x, y, wrap_angle(origin[..., 2] + local[..., 2])], -1)


def transform_points(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Points ``[...,2]`` into the frame of a single state ``origin [3]``."""
    d = points - origin[:2]
    c, s = np.cos(origin[2]), np.sin(origin[2])
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def resample_polyline(points: np.ndarray, spacing: float) -> np.ndarray:
    """Resample a polyline ``[n,2]`` at (about) uniform arc-length ``spacing``, keeping both end points."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 2:
        return points.copy()
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    total = arc[-1]
    if total <= 0:
        return points[:1].copy()
    n = max(int(np.ceil(total / spacing)), 1) + 1
    s = np.linspace(0.0, total, n)
    return np.stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])], -1)
