"""Interaction features (WOSAC §2.2-2.3): distance to the nearest object, collision, time to collision.

Every evaluated object is compared with every simulated agent at every step. The pair loop is
vectorized over (batch x step) chunks, and the exact (costly) geometry runs only on the pairs that can
matter: pairs whose cheap bounds say they may be the nearest object, or that may be followed ahead in
the ego's lane for TTC. Works in float32 like the reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.metrics.boxes import rectangle_signed_distance

__all__ = [
    "CORNER_ROUNDING",
    "FAR_DISTANCE",
    "MAX_TTC",
    "InteractionFeatures",
    "interaction_features",
]

CORNER_ROUNDING = 0.7  # rounded boxes for the nearest-object distance
FAR_DISTANCE = 1e10  # distance reported when an object or its partner is invalid
COLLISION_THRESHOLD = 0.0  # collision iff distance < this
MAX_TTC = 5.0  # seconds
MAX_HEADING_DIFF = np.float32(np.deg2rad(75.0))
MAX_HEADING_DIFF_SMALL_OVERLAP = np.float32(np.deg2rad(10.0))
SMALL_OVERLAP = np.float32(-0.5)  # metres of lateral overlap below which any heading <= 75 deg counts
_BOUND_SLACK = np.float32(1e-2)  # metres of slack on the pruning bounds (covers float32 rounding)
_CHUNK_PAIRS = 1 << 17  # pair entries per chunk (keeps temporaries in cache)


@dataclass(frozen=True, eq=False)
class InteractionFeatures:
    """Per evaluated object and step ``[B, E, T]``: nearest-object distance (m), collision, TTC (s)."""

    distance_to_nearest_object: np.ndarray
    collision: np.ndarray
    time_to_collision: np.ndarray


@dataclass(frozen=True, eq=False)
class _Agents:
    """Per-row (batch x step) agent arrays ``[BT, N]`` and per-agent box constants ``[N]`` (float32)."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    cos: np.ndarray
    sin: np.ndarray
    speed: np.ndarray
    valid: np.ndarray
    half_length: np.ndarray
    half_width: np.ndarray
    radius: np.ndarray  # corner-rounding radius
    core_half: tuple[np.ndarray, np.ndarray]  # half sizes of the rounded box's core rectangle
    core_diagonal: np.ndarray  # half-diagonal of the core
    box_diagonal: np.ndarray  # half-diagonal of the full box


def _rows(values: np.ndarray) -> np.ndarray:
    """``[B, N, T]`` -> ``[B * T, N]`` (one row per batch entry and step)."""
    b, n, t = values.shape
    return np.ascontiguousarray(np.transpose(values, (0, 2, 1))).reshape(b * t, n)


def _prepare(
    xy: np.ndarray, heading: np.ndarray, valid: np.ndarray, size: np.ndarray, speed: np.ndarray
) -> _Agents:
    f32 = np.float32
    heading_rows = _rows(heading.astype(f32))
    half = size.astype(f32) / f32(2)
    radius = f32(CORNER_ROUNDING) * half.min(axis=1)
    core_l, core_w = half[:, 0] - radius, half[:, 1] - radius
    return _Agents(
        x=_rows(xy[..., 0].astype(f32)),
        y=_rows(xy[..., 1].astype(f32)),
        heading=heading_rows,
        cos=np.cos(heading_rows),
        sin=np.sin(heading_rows),
        speed=_rows(speed.astype(f32)),
        valid=_rows(valid),
        half_length=half[:, 0],
        half_width=half[:, 1],
        radius=radius,
        core_half=(core_l, core_w),
        core_diagonal=np.sqrt(core_l * core_l + core_w * core_w),
        box_diagonal=np.sqrt(half[:, 0] ** 2 + half[:, 1] ** 2),
    )


def _group_starts(keys: np.ndarray) -> np.ndarray:
    """Start positions of the runs of equal consecutive ``keys``."""
    return np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))


@dataclass(frozen=True, eq=False)
class _Pairs:
    """Selected (evaluated object, partner) pairs of a chunk: ``pair`` = local row * E + e (sorted),
    agent indices ``e``/``j`` and their linear positions ``at_e``/``at_j`` in the ``[BT, N]`` arrays."""

    pair: np.ndarray
    e: np.ndarray
    j: np.ndarray
    at_e: np.ndarray
    at_j: np.ndarray

    @classmethod
    def of(cls, mask: np.ndarray, rows: slice, ev: np.ndarray) -> _Pairs:
        """The pairs where ``mask [C, E, N]`` is True."""
        n = mask.shape[2]
        pair, j = np.divmod(np.flatnonzero(mask), n)
        row, local_e = np.divmod(pair, len(ev))
        e = ev[local_e]
        base = (row + rows.start) * n
        return cls(pair=pair, e=e, j=j, at_e=base + e, at_j=base + j)

    def subset(self, keep: np.ndarray) -> _Pairs:
        return _Pairs(self.pair[keep], self.e[keep], self.j[keep], self.at_e[keep], self.at_j[keep])


def _take(values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Entries of a ``[BT, N]`` array at linear positions ``at``."""
    return np.take(values.reshape(-1), at)


def _nearest_object(a: _Agents, p: _Pairs, shape: tuple[int, int]) -> np.ndarray:
    """Rounded-box distance ``[C, E]`` from each evaluated object to its nearest valid other agent,
    evaluated exactly on the candidate pairs ``p`` (those that may be the nearest)."""
    out = np.full(shape, np.float32(FAR_DISTANCE), dtype=np.float32)
    if len(p.pair) == 0:
        return out
    e, j = p.e, p.j
    core = rectangle_signed_distance(
        _take(a.x, p.at_j) - _take(a.x, p.at_e),
        _take(a.y, p.at_j) - _take(a.y, p.at_e),
        _take(a.cos, p.at_e),
        _take(a.sin, p.at_e),
        (a.core_half[0][e], a.core_half[1][e]),
        _take(a.cos, p.at_j),
        _take(a.sin, p.at_j),
        (a.core_half[0][j], a.core_half[1][j]),
    )
    distance = core - a.radius[e] - a.radius[j]
    starts = _group_starts(p.pair)
    out.ravel()[p.pair[starts]] = np.minimum.reduceat(distance, starts)
    return out


def _time_to_collision(a: _Agents, p: _Pairs, shape: tuple[int, int]) -> np.ndarray:
    """Time to collision ``[C, E]`` with the nearest followed agent ahead (capped at ``MAX_TTC``),
    looking only at the candidate pairs ``p`` (valid partners close enough to matter)."""
    out = np.full(shape, np.float32(MAX_TTC), dtype=np.float32)
    if len(p.pair) == 0:
        return out
    ddx, ddy = _take(a.x, p.at_j) - _take(a.x, p.at_e), _take(a.y, p.at_j) - _take(a.y, p.at_e)
    cos_e, sin_e = _take(a.cos, p.at_e), _take(a.sin, p.at_e)
    ahead = cos_e * ddx + sin_e * ddy
    across = cos_e * ddy - sin_e * ddx
    # Necessary conditions (gap > 0, lateral < 0) before the costlier heading terms.
    maybe = (ahead > a.half_length[p.e] - _BOUND_SLACK) & (
        np.abs(across) < a.half_width[p.e] + a.box_diagonal[p.j] + _BOUND_SLACK
    )
    p, ahead, across = p.subset(maybe), ahead[maybe], across[maybe]
    yaw_diff = np.abs(_take(a.heading, p.at_j) - _take(a.heading, p.at_e))  # not wrapped (reference)
    c, s = np.abs(np.cos(yaw_diff)), np.abs(np.sin(yaw_diff))
    half_l, half_w = a.half_length[p.j], a.half_width[p.j]
    gap = ahead - a.half_length[p.e] - (half_l * c + half_w * s)
    lateral = np.abs(across) - a.half_width[p.e] - (half_l * s + half_w * c)
    followed = (
        (gap > 0)
        & (yaw_diff <= MAX_HEADING_DIFF)
        & (lateral < 0)
        & ((lateral < SMALL_OVERLAP) | (yaw_diff <= MAX_HEADING_DIFF_SMALL_OVERLAP))
    )
    if not followed.any():
        return out
    p, gap = p.subset(followed), gap[followed]
    starts = _group_starts(p.pair)
    smallest = np.minimum.reduceat(gap, starts)
    counts = np.diff(np.append(starts, len(gap)))
    position = np.where(gap == np.repeat(smallest, counts), np.arange(len(gap)), len(gap))
    lead = np.minimum.reduceat(position, starts)  # first agent with the smallest gap
    closing = _take(a.speed, p.at_e[lead]) - _take(a.speed, p.at_j[lead])
    with np.errstate(divide="ignore", invalid="ignore"):
        ttc = np.where(closing > 0, np.minimum(gap[lead] / closing, np.float32(MAX_TTC)), np.float32(MAX_TTC))
    out.ravel()[p.pair[starts]] = ttc
    return out


def _chunk_features(a: _Agents, rows: slice, ev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-object distance and TTC ``[C, E]`` for one chunk of rows.

    Dense work is limited to squared centre distances; exact geometry runs on pruned pairs:
    - nearest object: a pair can only be the nearest if its centre distance is below that of the
      nearest centre plus the bounding radii (cores lie in their discs; centres lie in the cores);
    - TTC: a lead farther than ``MAX_TTC * speed`` ahead gives the cap anyway (speeds are >= 0), and a
      followed partner overlaps the ego's lane, so only partners within that box's reach are examined.
    """
    x, y, valid = a.x[rows], a.y[rows], a.valid[rows]
    dx = x[:, None, :] - x[:, ev, None]  # [C, E, N]: partner minus evaluated object
    dy = y[:, None, :] - y[:, ev, None]
    d2 = dx * dx + dy * dy
    if not valid.all():  # partners must be valid (for TTC too; the ego's own validity is masked later)
        d2[~np.broadcast_to(valid[:, None, :], d2.shape)] = np.inf
    d2[:, np.arange(len(ev)), ev] = np.inf  # never the object itself
    reach = a.radius + a.core_diagonal
    nearest = np.sqrt(d2.min(axis=2)) + (a.core_diagonal[ev] + reach.max() - a.radius.min() + _BOUND_SLACK)
    candidate = (d2 < (nearest * nearest)[:, :, None]) & valid[:, ev, None]  # no distance for invalid objects
    distance = _nearest_object(a, _Pairs.of(candidate, rows, ev), candidate.shape[:2])
    # A followed partner is ahead by less than the cap distance (plus the boxes) and overlaps laterally.
    reach_o = a.box_diagonal.max() + _BOUND_SLACK
    ahead = np.float32(MAX_TTC) * a.speed[rows][:, ev] + (a.half_length[ev] + reach_o)
    aside = a.half_width[ev] + reach_o
    with np.errstate(invalid="ignore"):
        close = d2 < (ahead * ahead + aside * aside)[:, :, None]
    ttc = _time_to_collision(a, _Pairs.of(close, rows, ev), candidate.shape[:2])
    return distance, ttc


def interaction_features(
    xy: np.ndarray,
    heading: np.ndarray,
    valid: np.ndarray,
    size: np.ndarray,
    speed: np.ndarray,
    evaluated: np.ndarray,
) -> InteractionFeatures:
    """Nearest-object distance, collision and TTC of the ``evaluated`` agents against all agents.

    ``xy [B, N, T, 2]``, ``heading [B, N, T]``, ``valid [B, N, T]``, ``speed [B, N, T]`` (2-D speed
    magnitude, NaN where unknown) and ``size [N, 2]`` (length, width) describe the N simulated agents of
    B batch entries (rollouts or the log); ``evaluated [E]`` are agent indices. Returns ``[B, E, T]``.
    """
    b, n, t = heading.shape
    if (
        xy.shape != (b, n, t, 2)
        or valid.shape != (b, n, t)
        or speed.shape != (b, n, t)
        or size.shape != (n, 2)
    ):
        raise ValueError(
            f"interaction_features: inconsistent shapes xy {xy.shape}, heading {heading.shape}, "
            f"valid {valid.shape}, speed {speed.shape}, size {size.shape}"
        )
    ev = np.asarray(evaluated, dtype=np.int64)
    a = _prepare(xy, heading, valid, size, speed)
    distance = np.empty((b * t, len(ev)), dtype=np.float32)
    ttc = np.empty((b * t, len(ev)), dtype=np.float32)
    step = max(1, _CHUNK_PAIRS // max(1, len(ev) * n))
    for start in range(0, b * t, step):
        rows = slice(start, min(start + step, b * t))
        distance[rows], ttc[rows] = _chunk_features(a, rows, ev)

    def back(rows_first: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(rows_first.reshape(b, t, len(ev)).transpose(0, 2, 1))

    nearest = back(distance)
    return InteractionFeatures(
        distance_to_nearest_object=nearest,
        collision=nearest < COLLISION_THRESHOLD,
        time_to_collision=back(ttc),
    )
