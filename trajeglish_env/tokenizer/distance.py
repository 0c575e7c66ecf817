"""The mean corner distance ``d_{l,w}`` between two boxes of the same size, and its cheap bounds.

For two poses of one rigid box (length ``l``, width ``w``) with centre offset ``u`` and heading
difference ``delta``, corner ``k`` moves by ``u + (R(h_b) - R(h_a)) c_k``. Because the four corners
are symmetric about the centre, the *mean squared* corner distance has the closed form
``|u|^2 + r^2 sin^2(delta / 2)`` with ``r^2 = l^2 + w^2``, and the mean (of L2) corner distance ``d``
obeys ``sqrt(meansq / 2) <= d <= sqrt(meansq)``. The tokenizer ranks templates by ``meansq`` (a
matrix product) and uses these bounds to prove which templates can still be the exact argmin of ``d``.
"""

from __future__ import annotations

import numpy as np

# Corner signs in the box frame, ordered (front-left, front-right, rear-right, rear-left).
CORNER_SIGNS = np.array([[0.5, 0.5], [0.5, -0.5], [-0.5, -0.5], [-0.5, 0.5]])

# Box used by k-disks sampling (paper, Alg. 1): 1 m x 1 m.
UNIT_BOX_R2 = 2.0


def corner_distance(
    a: np.ndarray,
    b: np.ndarray,
    size: np.ndarray,
    trig_a: tuple[np.ndarray, np.ndarray] | None = None,
    trig_b: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Mean L2 distance between the ordered corners of boxes ``a``, ``b`` (``[...,3]``) of ``size [...,2]``.

    Works in any frame (both states in the same one) and broadcasts over leading dimensions. ``trig_a`` /
    ``trig_b`` are optional precomputed ``(cos, sin)`` of the headings (the result is bitwise the same).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    size = np.asarray(size, dtype=np.float64)
    ca, sa = (np.cos(a[..., 2]), np.sin(a[..., 2])) if trig_a is None else trig_a
    cb, sb = (np.cos(b[..., 2]), np.sin(b[..., 2])) if trig_b is None else trig_b
    ux = b[..., 0] - a[..., 0]
    uy = b[..., 1] - a[..., 1]
    dc, ds = cb - ca, sb - sa  # R(h_b) - R(h_a) = [[dc, -ds], [ds, dc]]
    total = np.zeros(np.broadcast_shapes(ux.shape, size.shape[:-1]), dtype=np.float64)
    for sx, sy in CORNER_SIGNS:  # four fixed corners, not a per-agent loop
        px = sx * size[..., 0]
        py = sy * size[..., 1]
        ex = ux + dc * px - ds * py
        ey = uy + ds * px + dc * py
        total = total + np.sqrt(ex * ex + ey * ey)
    return total / 4.0


def mean_square_corner_distance(a: np.ndarray, b: np.ndarray, r2: np.ndarray | float) -> np.ndarray:
    """Mean *squared* corner distance ``|u|^2 + r2 sin^2(dh/2)`` (``r2 = l^2 + w^2``), broadcasting."""
    u2 = (b[..., 0] - a[..., 0]) ** 2 + (b[..., 1] - a[..., 1]) ** 2
    return u2 + np.asarray(r2) * np.sin(0.5 * (b[..., 2] - a[..., 2])) ** 2
