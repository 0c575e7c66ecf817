"""Map polylines cut into fixed-length chunks (VectorNet-style vectors) for the model's map encoder.

Chunking is done once per scene (the result is cached by the dataset and the sampler); selecting the
chunks nearest to an agent and moving them into its frame is a handful of array operations.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from trajeglish_env.geometry import transform_points
from trajeglish_env.scenario import Scenario, SignalState

# The model's signal classes (ModelConfig.signal_input): 0 no signal (or unknown), 1 stop, 2 caution, 3 go,
# indexed by SignalState (flashing stop acts as a stop sign, flashing caution as caution).
SIGNAL_CLASSES = 4
RED_CLASS = 1
_SIGNAL_CLASS = np.zeros(max(SignalState) + 1, dtype=np.int64)
for _state, _class in (
    (SignalState.ARROW_STOP, 1),
    (SignalState.STOP, 1),
    (SignalState.FLASHING_STOP, 1),
    (SignalState.ARROW_CAUTION, 2),
    (SignalState.CAUTION, 2),
    (SignalState.FLASHING_CAUTION, 2),
    (SignalState.ARROW_GO, 3),
    (SignalState.GO, 3),
):
    _SIGNAL_CLASS[_state] = _class


@dataclass(frozen=True)
class MapChunks:
    """All polylines of a scene cut into chunks of at most ``P`` points.

    ``points [C,P,2]`` global coordinates (padding repeats the last point), ``mask [C,P]`` real points,
    ``kind [C]`` MapKind of the source polyline, ``polyline [C]`` index of the source polyline, ``signal
    [C]`` the column of the scene's ``signal_state`` that controls the source lane (-1: none).
    """

    points: np.ndarray
    mask: np.ndarray
    kind: np.ndarray
    polyline: np.ndarray
    signal: np.ndarray

    @property
    def num_chunks(self) -> int:
        return int(self.kind.shape[0])

    @cached_property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Each chunk's bounding circle: centre ``[C,2]`` (its real points' box centre; inf for a chunk
        without real points) and radius ``[C]``; computed once per scene's chunks."""
        real = self.mask[..., None]
        low = np.where(real, self.points, np.inf).min(axis=1)
        high = np.where(real, self.points, -np.inf).max(axis=1)
        empty = ~self.mask.any(axis=1)
        centre = np.where(empty[:, None], np.inf, (low + high) / 2)
        d2 = ((self.points - np.where(empty[:, None], 0.0, centre)[:, None]) ** 2).sum(-1)
        return centre, np.sqrt(np.where(self.mask, d2, 0.0).max(axis=1, initial=0.0))


def strided_points(offsets: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Every ``stride``-th point of each polyline (``offsets [K+1]`` into its points) and its last one: the
    kept points' indices and the polylines' new offsets."""
    lengths = np.diff(offsets)
    kept = np.where(lengths > 0, (lengths - 1) // stride + 1 + ((lengths - 1) % stride > 0), 0)
    new_offsets = np.concatenate([[0], np.cumsum(kept)]).astype(offsets.dtype)
    poly = np.repeat(np.arange(len(lengths)), kept)
    within = np.arange(int(kept.sum())) - new_offsets[:-1][poly]
    index = np.minimum(offsets[:-1][poly] + within * stride, offsets[1:][poly] - 1)
    return index, new_offsets


def chunk_map(scenario: Scenario, points_per_chunk: int, stride: int = 1) -> MapChunks:
    """Cut every polyline into consecutive chunks of ``points_per_chunk`` points (sharing end points),
    taking every ``stride``-th point of it (and its last: ``ModelConfig.map_stride``)."""
    if points_per_chunk < 2:
        raise ValueError(f"points_per_chunk must be >= 2, got {points_per_chunk}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    offsets, map_points = scenario.map_offsets, scenario.map_points
    if stride > 1:
        index, offsets = strided_points(offsets, stride)
        map_points = map_points[index]
    lengths = np.diff(offsets)
    step = points_per_chunk - 1  # consecutive chunks share one point so no segment is lost
    n_chunks = np.where(lengths <= 1, lengths, np.maximum(1, -(-(lengths - 1) // step)))
    total = int(n_chunks.sum())
    poly = np.repeat(np.arange(len(lengths)), n_chunks)
    first = np.repeat(np.cumsum(n_chunks) - n_chunks, n_chunks)
    within = np.arange(total) - first
    start = offsets[:-1][poly] + within * step
    end = offsets[1:][poly]
    idx = start[:, None] + np.arange(points_per_chunk)[None, :]
    mask = idx < end[:, None]
    idx = np.minimum(idx, (end - 1)[:, None])
    pts = map_points[idx] if total else np.zeros((0, points_per_chunk, 2))
    return MapChunks(
        points=pts, mask=mask, kind=scenario.map_kind[poly], polyline=poly, signal=_signals(scenario)[poly]
    )


# metres of slack in the bounds below (far more than the rounding of the circles and of the distances)
_BOUND_SLACK = 1e-3


def _nearest_d2(
    chunks: MapChunks, anchors: np.ndarray, radius: float = np.inf, keep: int | None = None
) -> np.ndarray:
    """``[C]`` squared distance from each chunk's nearest point to the nearest of ``anchors [A,2]``, measured
    only where it can matter (inf elsewhere): for chunks whose bounding circle reaches within ``radius`` of
    an anchor and, with ``keep``, within the ``keep``-th smallest upper bound of the chunks' distances (at
    least ``keep`` chunks lie that near, so no chunk beyond it is among the nearest ``keep``); and for each
    such chunk, only from the anchors that can be its nearest (those whose lower bound is within the
    chunk's upper bound). On the shared WOMD scene's map a window's 64 nearest of 1,193 chunks need 220-320
    measured, from 3 of the window's 24 agents each on average (4.5 -> 0.6 ms a window)."""
    best = np.full(len(chunks.points), np.inf)
    centre, reach = chunks.bounds
    dx, dy = centre[:, 0, None] - anchors[None, :, 0], centre[:, 1, None] - anchors[None, :, 1]
    gaps2 = dx * dx + dy * dy  # [C,A] squared centre-to-anchor distances
    gap = np.sqrt(gaps2.min(axis=1))
    limit = radius
    if keep is not None and 0 < keep < len(gap):
        limit = min(limit, float(np.partition(gap + reach, keep - 1)[keep - 1]))
    near = np.flatnonzero(gap - reach <= limit + _BOUND_SLACK)
    if not len(near):
        return best
    # an anchor farther from a chunk's circle than the nearest anchor's far side cannot be its nearest
    low = np.sqrt(gaps2[near]) - reach[near, None]
    pair, anchor = np.nonzero(low <= (gap[near] + reach[near] + _BOUND_SLACK)[:, None])
    chunk = near[pair]
    d2 = ((chunks.points[chunk] - anchors[anchor][:, None, :]) ** 2).sum(-1)  # [pairs,P]
    d2 = np.where(chunks.mask[chunk], d2, np.inf).min(axis=1)
    nearest = np.full(len(near), np.inf)
    np.minimum.at(nearest, pair, d2)
    best[near] = nearest
    return best


def _signals(scenario: Scenario) -> np.ndarray:
    """``[K]`` per polyline, the signal (column of ``signal_state``) controlling it, -1 for none (the first
    signal listed for a lane, when several are)."""
    out = np.full(scenario.num_polylines, -1, dtype=np.int64)
    if scenario.signal_state is None or not len(scenario.signal_lane_id):
        return out
    order = np.argsort(scenario.signal_lane_id, kind="stable")  # equal ids: the first listed first
    ids = scenario.signal_lane_id[order]
    at = np.minimum(np.searchsorted(ids, scenario.map_id), len(ids) - 1)
    found = ids[at] == scenario.map_id
    out[found] = order[at[found]]
    return out


def signal_classes(scenario: Scenario, chunks: MapChunks, step: int) -> np.ndarray:
    """``[C]`` the model's signal class (see :data:`SIGNAL_CLASSES`) of every chunk at ``step`` (past the
    log's end: its last step)."""
    out = np.zeros(chunks.num_chunks, dtype=np.int64)
    controlled = np.flatnonzero(chunks.signal >= 0)
    if len(controlled) and scenario.signal_state is not None:
        t = min(max(int(step), 0), scenario.signal_state.shape[0] - 1)
        out[controlled] = _SIGNAL_CLASS[scenario.signal_state[t, chunks.signal[controlled]].astype(np.int64)]
    return out


AHEAD_STEPS = (8, 16, 24)  # map_select="ahead": anchors this many 0.1 s steps on


def ahead_anchors(now: np.ndarray, prev: np.ndarray, prev_ok: np.ndarray) -> np.ndarray:
    """``[n * (1 + len(AHEAD_STEPS)), 2]`` world xy for ``map_select="ahead"``: the agents' positions
    ``now [n,3]`` and where each would be :data:`AHEAD_STEPS` steps on at the speed and turn rate of its move
    from ``prev [n,3]`` (one step before; where ``prev_ok [n]`` is False, where it stands)."""
    now, prev = np.asarray(now, np.float64), np.asarray(prev, np.float64)
    step = np.where(prev_ok[:, None], now[:, :2] - prev[:, :2], 0.0)
    speed = np.hypot(step[:, 0], step[:, 1])  # m a step
    turn = np.where(prev_ok, np.angle(np.exp(1j * (now[:, 2] - prev[:, 2]))), 0.0)  # rad a step
    k = np.arange(max(AHEAD_STEPS))
    heading = now[:, 2, None] + turn[:, None] * k[None]  # [n,K] the heading of each step's move
    moves = speed[:, None, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    path = now[:, None, :2] + np.cumsum(moves, axis=1)  # [n,K,2] after 1..K steps
    picked = path[:, np.asarray(AHEAD_STEPS) - 1]  # [n,H,2]
    return np.concatenate([now[:, :2], picked.transpose(1, 0, 2).reshape(-1, 2)]).astype(np.float64)


def map_anchors(map_select: str, now: np.ndarray, prev: np.ndarray, prev_ok: np.ndarray) -> np.ndarray | None:
    """The ``anchors`` of :func:`nearest_chunks` for ``ModelConfig.map_select``: None (``"frame"``), the
    agents' positions ``now [n,3]`` (``"agents"``), or those and the road ahead (``"ahead"``,
    :func:`ahead_anchors` from their states ``prev [n,3]`` one step before, known where ``prev_ok``)."""
    if map_select == "frame":
        return None
    if map_select == "agents":
        return now[:, :2]
    return ahead_anchors(now, prev, prev_ok)


def scene_anchors(map_select: str, scene: Scenario, agents: np.ndarray, step: int) -> np.ndarray | None:
    """:func:`map_anchors` of a scene's logged ``agents`` at ``step`` (their moves from the step before)."""
    before = max(step - 1, 0)
    ok = scene.valid[agents, before] & (step > 0)
    return map_anchors(map_select, scene.xyh[agents, step], scene.xyh[agents, before], ok)


def nearest_chunks(
    chunks: MapChunks,
    origin: np.ndarray,
    max_chunks: int,
    radius: float,
    signal: np.ndarray | None = None,
    anchors: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ``max_chunks`` chunks with a point nearest to ``origin [3]`` within ``radius``, in its frame;
    with ``anchors [A,2]`` (world xy, e.g. the window's agents), nearest to any of them instead; equally
    near chunks by index.

    Returns ``points [M,P,2]`` float32, ``point_mask [M,P]``, ``kind [M]`` int64, ``mask [M]`` and their
    signal classes ``[M]`` int64 (from ``signal [C]``, :func:`signal_classes`; zeros without it), padded
    to ``max_chunks``, nearest first.
    """
    p = chunks.points.shape[1] if chunks.num_chunks else 1
    out_pts = np.zeros((max_chunks, p, 2), dtype=np.float32)
    out_pmask = np.zeros((max_chunks, p), dtype=bool)
    out_kind = np.zeros(max_chunks, dtype=np.int64)
    out_mask = np.zeros(max_chunks, dtype=bool)
    out_signal = np.zeros(max_chunks, dtype=np.int64)
    if chunks.num_chunks == 0:
        return out_pts, out_pmask, out_kind, out_mask, out_signal
    seen = origin[None, :2] if anchors is None or not len(anchors) else anchors
    d2 = _nearest_d2(chunks, seen, radius, max_chunks)
    inside = np.flatnonzero(d2 <= radius * radius)
    inside = inside[np.lexsort((inside, d2[inside]))[:max_chunks]]  # nearest first, ties by index
    m = len(inside)
    out_pts[:m] = transform_points(chunks.points[inside], origin)
    out_pmask[:m] = chunks.mask[inside]
    out_kind[:m] = chunks.kind[inside]
    out_mask[:m] = True
    if signal is not None:
        out_signal[:m] = signal[inside]
    return out_pts, out_pmask, out_kind, out_mask, out_signal
