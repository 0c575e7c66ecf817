"""Per-cell candidate lists of polyline segments for exact nearest-segment queries (2-D uniform grids).

For every grid cell that holds a query point, the list holds every segment whose 2-D distance to the
cell centre is at most ``D + 2h + margin`` (``D``: distance from the centre to the nearest segment,
``h``: the cell's half-diagonal). By the triangle inequality the list then contains every segment
within ``D + h + margin`` of *any* point of the cell (its "covered radius"), in particular the one
nearest to that point. The same bound holds from a cell to the cells nested in it, so lists are built
coarse to fine (32 m cells from all segments, then 4 m, then 1 m cells from their parent's list) and
the cost follows the occupied area, not the size of the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CELL_SIZES", "CellLists", "build_cell_lists"]

CELL_SIZES = (32.0, 4.0, 1.0)  # metres, coarse to fine; each divides the previous one
_EPS = 0.01  # metres of slack covering float32 rounding of the queries
_PAIRS = 1 << 18  # cell x segment pairs per chunk while building lists


@dataclass(frozen=True, eq=False)
class CellLists:
    """Candidates of the F finest occupied cells and the cell of every query point ``[Q]``.

    ``candidates [F, K]`` segment indices (ascending; ``lengths [F]`` real entries, padded by repeating
    the last one); ``centre [F, 2]`` cell centres; ``covered_radius [F]`` the radius each list provably
    covers around any point of its cell.
    """

    candidates: np.ndarray
    lengths: np.ndarray
    centre: np.ndarray
    covered_radius: np.ndarray
    query_cell: np.ndarray


def _squared_distance(
    px: np.ndarray, py: np.ndarray, ax: np.ndarray, ay: np.ndarray, bx: np.ndarray, by: np.ndarray
) -> np.ndarray:
    """Squared 2-D point-to-segment distance, component-wise (broadcasting)."""
    dx, dy = bx - ax, by - ay
    qx, qy = px - ax, py - ay
    length2 = dx * dx + dy * dy
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.where(length2 > 0, (qx * dx + qy * dy) / length2, 0.0), 0.0, 1.0)
    rx, ry = qx - t * dx, qy - t * dy
    return rx * rx + ry * ry


def _cell_ids(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique integer cells ``[U, 2]`` of ``cells [Q, 2]`` and the row of each input in them."""
    lo = cells.min(axis=0)
    extent = cells.max(axis=0) - lo + 1
    key = (cells[:, 0] - lo[0]) * extent[1] + (cells[:, 1] - lo[1])
    if extent[0] * extent[1] <= max(4 * len(cells), 1 << 22):  # dense table: linear time
        used = np.zeros(int(extent[0] * extent[1]), dtype=bool)
        used[key] = True
        unique_key = np.flatnonzero(used)
        row = np.zeros(len(used), dtype=np.int64)
        row[unique_key] = np.arange(len(unique_key))
        inverse = row[key]
    else:
        unique_key, inverse = np.unique(key, return_inverse=True)
    unique = np.stack([unique_key // extent[1] + lo[0], unique_key % extent[1] + lo[1]], axis=1)
    return unique, inverse.reshape(-1)


def _compact(keep: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``index`` reduced to their kept entries (order kept), padded by repeating the last one,
    and the number of kept entries per row."""
    counts = keep.sum(axis=1)
    width = max(int(counts.max()), 1)
    slot = np.cumsum(keep, axis=1) - 1
    out = np.zeros((len(keep), width), dtype=np.int64)
    rows = np.broadcast_to(np.arange(len(keep))[:, None], keep.shape)
    out[rows[keep], slot[keep]] = index[keep]
    last = out[np.arange(len(keep)), np.maximum(counts - 1, 0)]
    pad = np.arange(width)[None, :] >= counts[:, None]
    return np.where(pad, last[:, None], out), counts


def _lists_for(
    centres: np.ndarray,
    half_diagonal: float,
    margin: float,
    ends: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    pool: np.ndarray,
    pool_lengths: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate lists (and their lengths) of the cells at ``centres [C, 2]``, drawn from the first
    ``pool_lengths [C]`` entries of ``pool [C, P]``, and each centre's distance to its nearest segment."""
    lists, lengths, nearest = [], [], []
    step = max(1, _PAIRS // pool.shape[1])
    for s in range(0, len(centres), step):
        idx = pool[s : s + step]
        c = centres[s : s + step]
        d2 = _squared_distance(c[:, 0, None], c[:, 1, None], *(a[idx] for a in ends))
        d2[np.arange(idx.shape[1])[None, :] >= pool_lengths[s : s + step, None]] = np.inf
        best = np.sqrt(d2.min(axis=1))
        reach = best + 2 * half_diagonal + margin + _EPS
        kept, count = _compact(d2 <= (reach * reach)[:, None], idx)
        lists.append(kept)
        lengths.append(count)
        nearest.append(best)
    width = max(x.shape[1] for x in lists)
    padded = [np.concatenate([x, np.repeat(x[:, -1:], width - x.shape[1], axis=1)], axis=1) for x in lists]
    return np.concatenate(padded), np.concatenate(lengths), np.concatenate(nearest)


def build_cell_lists(start: np.ndarray, end: np.ndarray, points: np.ndarray, margin: float) -> CellLists:
    """Candidate lists for the cells of ``points [Q, 2]`` over segments ``start``/``end [S, 2+]``.

    ``margin`` (m) widens the lists so that 3-D queries (whose nearest segment in z-stretched 3-D may
    be a little farther in 2-D) are still usually decided by the list alone.
    """
    start = np.asarray(start, np.float32)
    end = np.asarray(end, np.float32)
    ends = (start[:, 0], start[:, 1], end[:, 0], end[:, 1])
    points = np.asarray(points, np.float32)
    # Cells of every level, finest first: cells[k] [U_k, 2] and the parent row of each cell / query.
    cells, parents = [], []
    child = np.floor(points / CELL_SIZES[-1]).astype(np.int64)
    for k in range(len(CELL_SIZES) - 1, -1, -1):
        unique, inverse = _cell_ids(child)
        cells.append(unique)
        parents.append(inverse)
        if k:
            child = np.floor_divide(unique, round(CELL_SIZES[k - 1] / CELL_SIZES[k]))
    pool = np.broadcast_to(np.arange(len(start))[None, :], (len(cells[-1]), len(start)))
    pool_lengths = np.full(len(cells[-1]), len(start))
    for level, size in enumerate(CELL_SIZES):
        finest_first = len(CELL_SIZES) - 1 - level
        centres = ((cells[finest_first] + 0.5) * size).astype(np.float32)
        half = size * np.sqrt(0.5)
        lists, lengths, nearest = _lists_for(centres, half, margin, ends, pool, pool_lengths)
        if finest_first:  # the next finer level draws from its parent cell's list
            pool, pool_lengths = lists[parents[finest_first]], lengths[parents[finest_first]]
    covered = (nearest + size * np.sqrt(0.5) + margin + _EPS / 2).astype(np.float32)
    return CellLists(
        candidates=lists, lengths=lengths, centre=centres, covered_radius=covered, query_cell=parents[0]
    )
