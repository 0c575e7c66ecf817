"""Exact nearest template under the mean corner distance, fast enough for millions of agent-steps.

Templates are ranked by the mean *squared* corner distance, which is a quadratic form and so one
float32 matrix product per block of rows (:class:`SearchTable`). The exact mean corner distance ``d``
is then computed in float64 only for the templates that the bounds ``max(|u|, rho) <= d`` and
``sqrt(meansq / 2) <= d <= sqrt(meansq)`` cannot rule out (see :mod:`.distance`); for most rows that
is the ranking's first template alone. Rows are sorted by dx and each block of rows is compared with
the templates whose dx lies within a margin of the block's (any other template is farther than the
margin in dx alone); rows whose best distance exceeds the margin are searched over all templates.
The result is the exact argmin of ``d`` (ties go to the lowest template index), not an approximation.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from trajeglish_env.tokenizer.distance import corner_distance

CHUNK_ROWS = 4096
BLOCK_ROWS = 1024  # rows searched together against one window of templates
WINDOW_M = 0.08  # dx margin of a block's template window (m); rows whose best is farther are searched fully
# Rows per matrix product: small enough that OpenBLAS stays single-threaded (its threads spin badly on a busy
# machine, and a 6-deep product is memory-bound anyway), large enough to amortise the call.
_MATMUL_ROWS = 256
# Allowance for float32 rounding of the ranking key, times sum_k |Q_k| |W_k|: about 4x the worst case of a
# 6-term float32 dot product with float32-rounded inputs, so no candidate is ever missed (extras cost time).
_KEY_TOLERANCE = 2e-6


@dataclass(frozen=True)
class SearchTable:
    """Precomputed float32 ranking matrix for one template set ``[V,3]`` (local dx, dy, dh).

    Columns are sorted by dx so that a block of rows with similar dx can be compared with a contiguous
    window of templates only (any template outside the window is provably farther than the window margin).
    """

    templates: np.ndarray  # [V,3] float64, caller's order
    order: np.ndarray  # [V] template index of each sorted column (sorted by dx, stable)
    sorted_dx: np.ndarray  # [V] dx of each sorted column
    center: np.ndarray  # [2] xy offset subtracted from both sides (improves float32 conditioning)
    weights: np.ndarray  # [6,V] float32, sorted columns
    weight_bound: np.ndarray  # [6] float64, max_i |weights[k, i]|
    cos: np.ndarray  # [V] cos of template headings (caller's order)
    sin: np.ndarray  # [V] sin of template headings (caller's order)
    index_weights: np.ndarray  # [6,V] float32, ``weights`` in the caller's order (see templates_within)

    @classmethod
    def build(cls, templates: np.ndarray) -> SearchTable:
        """Precompute the ranking matrix of ``templates [V,3]``."""
        templates = np.asarray(templates, dtype=np.float64)
        order = np.argsort(templates[:, 0], kind="stable")
        center = templates[:, :2].mean(0)
        sorted_t = templates[order]
        txy = sorted_t[:, :2] - center
        one_minus_cos = 1.0 - np.cos(sorted_t[:, 2])
        sin = np.sin(sorted_t[:, 2])
        w = np.stack([-2 * txy[:, 0], -2 * txy[:, 1], -one_minus_cos, -sin, one_minus_cos, (txy**2).sum(1)])
        by_index = np.empty_like(w)
        by_index[:, order] = w
        return cls(
            templates,
            order,
            sorted_t[:, 0].copy(),
            center,
            np.ascontiguousarray(w, dtype=np.float32),
            np.abs(w).max(1),
            np.cos(templates[:, 2]),
            np.sin(templates[:, 2]),
            np.ascontiguousarray(by_index, dtype=np.float32),
        )

    @property
    def size(self) -> int:
        """Number of templates."""
        return int(self.templates.shape[0])

    def query(self, local: np.ndarray, r2: np.ndarray) -> Query:
        """Ranking inputs for rows ``local [m,3]`` with box constants ``r2 [m]`` (see :class:`Query`)."""
        txy = local[:, :2] - self.center
        half_r2 = 0.5 * r2
        cos, sin = np.cos(local[:, 2]), np.sin(local[:, 2])
        one_minus_cos = 1.0 - cos
        q = np.empty((len(local), 6), dtype=np.float32)
        q[:, :2] = txy
        q[:, 2] = half_r2 * one_minus_cos
        q[:, 3] = half_r2 * sin
        q[:, 4] = half_r2
        q[:, 5] = 1.0
        const = (txy**2).sum(1) + half_r2 * one_minus_cos
        tol = _KEY_TOLERANCE * (np.abs(q) @ self.weight_bound) + 1e-12
        return Query(q, const, tol, cos, sin)


@dataclass(frozen=True)
class Query:
    """Rows to rank: ``matrix [m,6]`` float32 (``meansq = matrix @ weights + const``), the float32 rounding
    ``tolerance [m]`` of that key, and ``cos``/``sin [m]`` of the rows' local headings."""

    matrix: np.ndarray
    const: np.ndarray
    tolerance: np.ndarray
    cos: np.ndarray
    sin: np.ndarray


def thin_matmul(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``a [m,k] @ b [k,n]`` into ``out``'s memory, in row slices that keep BLAS single-threaded."""
    key = out.reshape(-1)[: len(a) * b.shape[1]].reshape(len(a), b.shape[1])
    for start in range(0, len(a), _MATMUL_ROWS):
        stop = min(start + _MATMUL_ROWS, len(a))
        np.matmul(a[start:stop], b, out=key[start:stop])
    return key


def nearest_templates(
    table: SearchTable,
    local: np.ndarray,
    size: np.ndarray,
    *,
    block: int = BLOCK_ROWS,
    window: float = WINDOW_M,
    threads: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact argmin over templates of the mean corner distance to ``local [M,3]`` for boxes ``size [M,2]``.

    Returns (index ``[M]`` int64, distance ``[M]`` float64 in metres). Rows are sorted by dx and searched in
    blocks against the templates whose dx lies within ``window`` metres of the block's range; a row whose
    best distance there exceeds ``window`` is searched again over all templates. ``threads > 1`` spreads the
    blocks over a thread pool (NumPy releases the GIL in the heavy array operations).
    """
    m = local.shape[0]
    index = np.empty(m, dtype=np.int64)
    dist = np.empty(m, dtype=np.float64)
    if m == 0:
        return index, dist
    order = np.argsort(local[:, 0], kind="stable")
    xs = local[order, 0]
    starts = np.arange(0, m, block)
    stops = np.minimum(starts + block, m)
    lo = np.searchsorted(table.sorted_dx, xs[starts] - window, "left")
    hi = np.searchsorted(table.sorted_dx, xs[stops - 1] + window, "right")
    full = (hi - lo) * 5 >= table.size * 3  # a window of most templates: search them all directly
    lo[full], hi[full] = 0, table.size
    retry: list[np.ndarray] = []

    def run(blocks: np.ndarray) -> None:
        buffer = np.empty(min(block, m) * table.size, dtype=np.float32)
        for b in blocks:
            rows = order[starts[b] : stops[b]]
            if hi[b] == lo[b]:
                retry.append(rows)
                continue
            found, best = _search(table, int(lo[b]), int(hi[b]), local[rows], size[rows], buffer)
            index[rows], dist[rows] = found, best
            if not full[b]:
                # Templates outside the window are > `window` away in dx alone: they cannot beat `best`.
                missed = best > window
                if missed.any():
                    retry.append(rows[missed])

    all_blocks = np.arange(len(starts))
    if threads <= 1 or len(all_blocks) < 2:
        run(all_blocks)
    else:
        pool = _thread_pool(threads)
        for future in [pool.submit(run, all_blocks[i::threads]) for i in range(threads)]:
            future.result()
    if retry:
        rows = np.concatenate(retry)
        buffer = np.empty(min(block, m) * table.size, dtype=np.float32)
        for start in range(0, len(rows), block):
            part = rows[start : start + block]
            index[part], dist[part] = _search(table, 0, table.size, local[part], size[part], buffer)
    return index, dist


_POOLS: dict[int, ThreadPoolExecutor] = {}


def _thread_pool(threads: int) -> ThreadPoolExecutor:
    """A process-wide pool per thread count (created on first use)."""
    if threads not in _POOLS:
        _POOLS[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="tokenizer")
    return _POOLS[threads]


def _lower_bound_ok(
    table: SearchTable, local: np.ndarray, r2: np.ndarray, cols: np.ndarray, bound: np.ndarray
) -> np.ndarray:
    """Keep pairs whose lower bound ``max(|u|, r |sin(dh/2)|)`` on the exact distance is within ``bound``."""
    t = table.templates[cols]
    u2 = (local[:, 0] - t[:, 0]) ** 2 + (local[:, 1] - t[:, 1]) ** 2
    rho2 = r2 * np.sin(0.5 * (local[:, 2] - t[:, 2])) ** 2
    return np.maximum(u2, rho2) <= bound**2 * (1 + 1e-9) + 1e-18


def _search(
    table: SearchTable, lo: int, hi: int, local: np.ndarray, size: np.ndarray, buffer: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Exact nearest among sorted template columns ``lo:hi`` (template indices in the caller's order)."""
    r2 = size[:, 0] ** 2 + size[:, 1] ** 2
    query = table.query(local, r2)
    key = thin_matmul(query.matrix, table.weights[:, lo:hi], buffer)
    column = key.argmin(1)
    first = table.order[lo + column]
    trig = (table.cos[first], table.sin[first])
    best = corner_distance(table.templates[first], local, size, trig, (query.cos, query.sin))
    threshold = 2.0 * best**2 - query.const + query.tolerance  # an exact argmin j has meansq_j <= 2 d_first^2
    key[np.arange(len(local)), column] = np.inf
    ambiguous = np.flatnonzero(key.min(1) <= threshold)
    if len(ambiguous):
        r, c = np.nonzero(key[ambiguous] <= threshold[ambiguous, None])
        r = ambiguous[r]
        c = table.order[lo + c]
        keep = _lower_bound_ok(table, local[r], r2[r], c, best[r])
        r, c = r[keep], c[keep]
        d = corner_distance(table.templates[c], local[r], size[r])
        # Include the first-ranked template of each row, then keep the (distance, index)-smallest per row.
        r = np.concatenate([r, ambiguous])
        c = np.concatenate([c, first[ambiguous]])
        d = np.concatenate([d, best[ambiguous]])
        order = np.lexsort((c, d, r))
        r, c, d = r[order], c[order], d[order]
        head = np.ones(len(r), dtype=bool)
        head[1:] = r[1:] != r[:-1]
        first[r[head]] = c[head]
        best[r[head]] = d[head]
    return first, best


def templates_within(
    table: SearchTable, local: np.ndarray, size: np.ndarray, margin: float, chunk: int = CHUNK_ROWS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every template whose exact distance is within ``margin`` metres of the row's nearest one.

    Returns pairs (row ``[P]``, template ``[P]``, distance ``[P]``), sorted by row then distance then index.
    The ranking runs over the templates in index order, so its candidates come out sorted by (row, index)
    and two stable sorts (distance, then a radix sort of the chunk's rows) order them (a lexsort of the
    three keys took twice as long; tokenizing batches of windows makes these arrays large).
    """
    chunk = min(chunk, np.iinfo(np.int16).max)  # a chunk's rows are sorted as int16 (numpy's radix sort)
    out_r, out_c, out_d = [], [], []
    buffer = np.empty(min(chunk, local.shape[0]) * table.size, dtype=np.float32)
    for start in range(0, local.shape[0], chunk):
        stop = min(start + chunk, local.shape[0])
        loc, sz = local[start:stop], size[start:stop]
        r2 = sz[:, 0] ** 2 + sz[:, 1] ** 2
        query = table.query(loc, r2)
        key = thin_matmul(query.matrix, table.index_weights, buffer)
        first = key.argmin(1)
        best = corner_distance(table.templates[first], loc, sz, (table.cos[first], table.sin[first]))
        # Exact d_j <= d_first + margin implies meansq_j <= 2 (d_first + margin)^2, and max(|u|, rho) <= d_j.
        bound = best + margin
        r, c = np.nonzero(key <= (2.0 * bound**2 - query.const + query.tolerance)[:, None])
        keep = _lower_bound_ok(table, loc[r], r2[r], c, bound[r])
        r, c = r[keep], c[keep]
        d = corner_distance(
            table.templates[c], loc[r], sz[r], (table.cos[c], table.sin[c]), (query.cos[r], query.sin[r])
        )
        dmin = np.full(len(loc), np.inf)
        np.minimum.at(dmin, r, d)
        keep = d <= dmin[r] + margin
        r, c, d = r[keep], c[keep], d[keep]
        by_d = np.argsort(d, kind="stable")  # ties keep (row, index) order
        order = by_d[np.argsort(r[by_d].astype(np.int16), kind="stable")]
        out_r.append(r[order] + start)
        out_c.append(c[order])
        out_d.append(d[order])
    if not out_r:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64), np.empty(0, dtype=np.float64)
    return np.concatenate(out_r), np.concatenate(out_c), np.concatenate(out_d)


def brute_force_nearest(
    templates: np.ndarray, local: np.ndarray, size: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Reference argmin over all templates (float64, ``O(M V)`` memory); for tests and small inputs."""
    d = corner_distance(templates[None, :, :], local[:, None, :], size[:, None, :])
    index = d.argmin(1)
    return index, d[np.arange(len(local)), index]
