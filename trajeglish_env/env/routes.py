"""Logged paths as arc-length parametrised polylines (vectorized over agents): the external agents'
routes (progress reward, route observation) and the paths the IDM NPCs drive along."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from trajeglish_env.geometry import wrap_angle


@dataclass(frozen=True)
class Paths:
    """``A`` paths resampled every ``spacing`` m: ``points [A,P,2]``, ``heading [A,P]`` (unwrapped),
    ``count [A]`` real points (padding repeats the last one), ``length [A]`` arc length of the last real
    point (m; the logged length rounded down to a multiple of ``spacing``)."""

    points: np.ndarray
    heading: np.ndarray
    count: np.ndarray
    length: np.ndarray
    spacing: float

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def at(self, rows: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points ``[...,2]`` and headings ``[...]`` at arc lengths ``s`` (clipped to each path) of paths
        ``rows`` (broadcast with ``s``)."""
        rows = np.asarray(rows)
        s = np.clip(s, 0.0, self.length[rows])
        u = s / self.spacing
        k = np.minimum(np.floor(u).astype(np.int64), self.points.shape[1] - 1)
        k1 = np.minimum(k + 1, self.count[rows] - 1)
        f = (u - k)[..., None]
        p = self.points[rows, k] * (1 - f) + self.points[rows, k1] * f
        h = self.heading[rows, k] * (1 - f[..., 0]) + self.heading[rows, k1] * f[..., 0]
        return p, wrap_angle(h)

    def with_rows(self, rows: np.ndarray, other: Paths, source: np.ndarray) -> Paths:
        """These paths with rows ``rows`` replaced by rows ``source`` of ``other`` (same spacing)."""
        both, first = stack_paths([self, other])
        keep = np.arange(len(self))
        take = keep.copy()
        take[np.asarray(rows, dtype=np.int64)] = first[1] + np.asarray(source, dtype=np.int64)
        return Paths(both.points[take], both.heading[take], both.count[take], both.length[take], self.spacing)

    def project(
        self, rows: np.ndarray, xy: np.ndarray, s_prev: np.ndarray, back: float = 5.0, ahead: float = 30.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arc length ``s``, signed lateral offset (left +) and path heading of points ``xy [k,2]`` on paths
        ``rows [k]``, searching ``[s_prev - back, s_prev + ahead]`` (so looping routes never jump)."""
        rows = np.asarray(rows, dtype=np.int64)
        width = int(np.ceil((back + ahead) / self.spacing)) + 1
        first = np.floor((np.asarray(s_prev) - back) / self.spacing).astype(np.int64)
        idx = np.clip(first[:, None] + np.arange(width), 0, (self.count[rows] - 1)[:, None])  # [k,W]
        pts = self.points[rows[:, None], idx]
        d2 = ((pts - xy[:, None, :]) ** 2).sum(-1)
        best = idx[np.arange(len(rows)), np.argmin(d2, axis=1)]
        heading = self.heading[rows, best]
        tangent = np.stack([np.cos(heading), np.sin(heading)], -1)
        rel = xy - self.points[rows, best]
        along = np.clip((rel * tangent).sum(-1), -self.spacing, self.spacing)
        lateral = tangent[:, 0] * rel[:, 1] - tangent[:, 1] * rel[:, 0]
        s = np.clip(best * self.spacing + along, 0.0, self.length[rows])
        return s, lateral, wrap_angle(heading)


def logged_paths(
    xyh: np.ndarray, valid: np.ndarray, spacing: float = 1.0, extension: np.ndarray | float = 0.0
) -> Paths:
    """Paths through the valid states ``xyh [A,T,3]`` / ``valid [A,T]`` of each agent, in time order,
    extended straight ahead by ``extension [A]`` m past the last valid state (along its heading).

    An agent with no valid state gets a one-point path at the origin.
    """
    a, t = valid.shape
    has = valid.any(axis=1)
    first = np.argmax(valid, axis=1)
    last = t - 1 - np.argmax(valid[:, ::-1], axis=1)
    steps = np.arange(t)
    fill = np.where(valid, steps, -1)
    fill = np.maximum(np.maximum.accumulate(fill, axis=1), first[:, None])  # forward-filled step index
    rows = np.arange(a)[:, None]
    pos = np.where(has[:, None, None], xyh[rows, fill, :2], 0.0)
    head = np.unwrap(np.where(has[:, None], xyh[rows, fill, 2], 0.0), axis=1)
    seg = np.linalg.norm(np.diff(pos, axis=1), axis=-1) if t > 1 else np.zeros((a, 0))
    cum = np.concatenate([np.zeros((a, 1)), np.cumsum(seg, axis=1)], axis=1)  # [A,T]
    logged = cum[:, -1]
    ext = np.broadcast_to(np.asarray(extension, dtype=np.float64), (a,))
    length = logged + ext
    count = np.floor(length / spacing + 1e-9).astype(np.int64) + 1
    p = int(count.max()) if a else 1
    grid_length = (count - 1) * float(spacing)
    s = np.minimum(np.arange(p)[None, :] * spacing, grid_length[:, None])  # [A,P]; padding repeats the end
    # index of the logged segment holding each s (cum is non-decreasing)
    k = (cum[:, None, :] <= s[:, :, None]).sum(-1) - 1
    k = np.clip(k, 0, max(t - 2, 0))
    k1 = np.minimum(k + 1, t - 1)
    c0, c1 = np.take_along_axis(cum, k, 1), np.take_along_axis(cum, k1, 1)
    span = c1 - c0
    f = np.where(span > 0, np.clip((s - c0) / np.where(span > 0, span, 1.0), 0.0, 1.0), 0.0)
    p0, p1 = np.take_along_axis(pos, k[..., None], 1), np.take_along_axis(pos, k1[..., None], 1)
    pts = p0 * (1 - f[..., None]) + p1 * f[..., None]
    h0, h1 = np.take_along_axis(head, k, 1), np.take_along_axis(head, k1, 1)
    hd = h0 * (1 - f) + h1 * f
    # straight extension past the last logged state
    end_h = head[np.arange(a), np.maximum(last, 0)] if t else np.zeros(a)
    end_p = pos[np.arange(a), np.maximum(last, 0)]
    beyond = np.maximum(s - logged[:, None], 0.0)
    ahead = beyond > 0
    direction = np.stack([np.cos(end_h), np.sin(end_h)], -1)[:, None, :]
    pts = np.where(ahead[..., None], end_p[:, None, :] + beyond[..., None] * direction, pts)
    hd = np.where(ahead, end_h[:, None], hd)
    return Paths(points=pts, heading=hd, count=count, length=grid_length, spacing=spacing)


def stack_paths(sets: Sequence[Paths]) -> tuple[Paths, np.ndarray]:
    """Several sets of paths as one (rows in order, shorter paths padded with their last point, which no
    query reads) and the first row of each set."""
    spacings = {p.spacing for p in sets}
    if len(spacings) != 1:
        raise ValueError(f"stack_paths: every set must have the same spacing, got {sorted(spacings)}")
    longest = max(p.points.shape[1] for p in sets)

    def grow(a: np.ndarray) -> np.ndarray:
        extra = longest - a.shape[1]
        return np.pad(a, [(0, 0), (0, extra)] + [(0, 0)] * (a.ndim - 2), mode="edge") if extra else a

    first = np.cumsum([0] + [len(p) for p in sets[:-1]])
    return (
        Paths(
            points=np.concatenate([grow(p.points) for p in sets]),
            heading=np.concatenate([grow(p.heading) for p in sets]),
            count=np.concatenate([p.count for p in sets]),
            length=np.concatenate([p.length for p in sets]),
            spacing=spacings.pop(),
        ),
        first,
    )
