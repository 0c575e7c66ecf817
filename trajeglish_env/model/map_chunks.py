"""Map polylines cut into fixed-length chunks (VectorNet-style vectors) for the model's map encoder.

Chunking is done once per scene (the result is cached by the dataset and the sampler); selecting the
chunks nearest to an agent and moving them into its frame is a handful of array operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.geometry import transform_points
from trajeglish_env.scenario import Scenario


@dataclass(frozen=True)
class MapChunks:
    """All polylines of a scene cut into chunks of at most ``P`` points.

    ``points [C,P,2]`` global coordinates (padding repeats the last point), ``mask [C,P]`` real points,
    ``kind [C]`` MapKind of the source polyline, ``polyline [C]`` index of the source polyline.
    """

    points: np.ndarray
    mask: np.ndarray
    kind: np.ndarray
    polyline: np.ndarray

    @property
    def num_chunks(self) -> int:
        return int(self.kind.shape[0])


def chunk_map(scenario: Scenario, points_per_chunk: int) -> MapChunks:
    """Cut every polyline into consecutive chunks of ``points_per_chunk`` points (sharing end points)."""
    if points_per_chunk < 2:
        raise ValueError(f"points_per_chunk must be >= 2, got {points_per_chunk}")
    lengths = np.diff(scenario.map_offsets)
    step = points_per_chunk - 1  # consecutive chunks share one point so no segment is lost
    n_chunks = np.where(lengths <= 1, lengths, np.maximum(1, -(-(lengths - 1) // step)))
    total = int(n_chunks.sum())
    poly = np.repeat(np.arange(len(lengths)), n_chunks)
    first = np.repeat(np.cumsum(n_chunks) - n_chunks, n_chunks)
    within = np.arange(total) - first
    start = scenario.map_offsets[:-1][poly] + within * step
    end = scenario.map_offsets[1:][poly]
    idx = start[:, None] + np.arange(points_per_chunk)[None, :]
    mask = idx < end[:, None]
    idx = np.minimum(idx, (end - 1)[:, None])
    pts = scenario.map_points[idx] if total else np.zeros((0, points_per_chunk, 2))
    return MapChunks(points=pts, mask=mask, kind=scenario.map_kind[poly], polyline=poly)


def nearest_chunks(
    chunks: MapChunks, origin: np.ndarray, max_chunks: int, radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ``max_chunks`` chunks with a point nearest to ``origin [3]`` within ``radius``, in its frame.

    Returns ``points [M,P,2]`` float32, ``point_mask [M,P]``, ``kind [M]`` int64, ``mask [M]`` (padded
    to ``max_chunks``, nearest first).
    """
    p = chunks.points.shape[1] if chunks.num_chunks else 1
    out_pts = np.zeros((max_chunks, p, 2), dtype=np.float32)
    out_pmask = np.zeros((max_chunks, p), dtype=bool)
    out_kind = np.zeros(max_chunks, dtype=np.int64)
    out_mask = np.zeros(max_chunks, dtype=bool)
    if chunks.num_chunks == 0:
        return out_pts, out_pmask, out_kind, out_mask
    d2 = ((chunks.points - origin[:2]) ** 2).sum(-1)
    d2 = np.where(chunks.mask, d2, np.inf).min(-1)
    inside = np.flatnonzero(d2 <= radius * radius)
    if len(inside) > max_chunks:
        inside = inside[np.argpartition(d2[inside], max_chunks - 1)[:max_chunks]]
    inside = inside[np.argsort(d2[inside], kind="stable")]
    m = len(inside)
    out_pts[:m] = transform_points(chunks.points[inside], origin)
    out_pmask[:m] = chunks.mask[inside]
    out_kind[:m] = chunks.kind[inside]
    out_mask[:m] = True
    return out_pts, out_pmask, out_kind, out_mask
