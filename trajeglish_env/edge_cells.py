"""Road-edge cells: the env's off-road rule (the WOSAC reference's nearest road-edge segment and its sign,
:func:`~trajeglish_env.batch_geometry.road_edge_distances`) answered per point from a square grid over
each map instead of a scan of every segment near the point.

Each cell lists the segments that can be the reference's nearest one for some point of the cell, and says
whether every point of it is provably on the road side (``safe``): a point in a safe cell has a reference
distance <= 0 and needs no segment at all; any other point scans only its cell's few segments (the same
float32 formula and first-on-ties choice, so the same segment and number). Cells are computed a block at a
time, when a point first falls in the block; points outside a map's grid are answered by a full scan.

Why a list holds the nearest segment: the reference's selection distance ``f(p, s)`` (planar projection,
z stretched, queries at z = 0: :func:`~trajeglish_env.batch_geometry.selection_d2`) is never below the
planar distance ``d(p, s)``, which is 1-Lipschitz in ``p``, while ``f(., s)`` is Lipschitz with constant
``L_s = sqrt(1 + (Z_STRETCH * slope_s)^2)``. So over a cell of centre ``c`` and half-diagonal ``r`` no
segment with ``d(c, s) - r > min_s' f(c, s') + L_s' r`` can be nearest to one of its points; every other
one is listed (with :data:`SLACK` m to spare for the reference's float32 rounding). A cell is safe when its
centre lies more than ``r`` (plus the slack) on the road side of the line of every listed segment and of
their neighbours (which give the sign beyond a segment's end): the sign is then negative all over it.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from trajeglish_env.batch_geometry import nearest_segments, selection_d2, signed_distances_to
from trajeglish_env.compiled import compiled
from trajeglish_env.geometry import box_corners
from trajeglish_env.metrics.road_edges import Z_STRETCH

CELL = 0.5  # metres: a cell's side
BLOCK = 16  # cells per block side: a block's cells are computed together, when a point first falls in it
SUB = 4  # cells per side of the sub-blocks a block's segments are narrowed down over before its cells
PAD = 40.0  # metres of grid around a map's road edges; points farther out are answered by a full scan
MAX_BLOCKS = 1 << 18  # blocks per map at most (larger cells on a larger map)
SLACK = 0.1  # metres to spare in the bounds: covers the reference's float32 rounding many times over
MAX_MAPS = 512  # maps kept at most; more, and every map's cells are dropped (and computed again on demand)


@dataclass(frozen=True)
class MapGrid:
    """One map's grid: cell side ``cell``, origin ``x0, y0``, ``nbx x nby`` blocks of BLOCK x BLOCK cells;
    its blocks are ``table ..`` of the :class:`EdgeCells` block table."""

    columns: np.ndarray
    links: np.ndarray
    wide: np.ndarray  # the columns in float64, for the bounds
    slope: np.ndarray  # per segment: its Lipschitz constant (:func:`lipschitz`)
    cell: float
    x0: float
    y0: float
    nbx: int
    nby: int
    table: int


def _rows(columns: np.ndarray, rows: tuple[int, ...]) -> list[np.ndarray]:
    """Rows ``rows`` of segment columns ``[7,S]`` (shared by every point) or ``[7,P,S]`` (per point) as
    float64 arrays that broadcast against points ``[P,1]`` (no copy of float64 columns)."""
    return [
        np.asarray(columns[k], np.float64)[None] if columns.ndim == 2 else np.asarray(columns[k], np.float64)
        for k in rows
    ]


def selection_distance(columns: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``[P,S]`` the reference's selection distance (see the module docstring) from points ``x, y [P]``
    to segments ``columns [7,S]`` (or ``[7,P,S]``: per point), in float64 (for bounds; the choice itself
    is made in float32)."""
    ax, ay, az, dx, dy, dz, inverse = _rows(columns, tuple(range(7)))
    ux, uy = x[:, None] - ax, y[:, None] - ay
    t = np.clip((ux * dx + uy * dy) * inverse, 0, 1)
    rx, ry, rz = ux - t * dx, uy - t * dy, float(Z_STRETCH) * (-az - t * dz)
    return np.sqrt(rx * rx + ry * ry + rz * rz)


def planar_distance(columns: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``[P,S]`` 2-D distances (float64) from points ``x, y [P]`` to segments ``columns [7,S]`` (or
    ``[7,P,S]``)."""
    ax, ay, dx, dy = _rows(columns, (0, 1, 3, 4))
    ux, uy = x[:, None] - ax, y[:, None] - ay
    length2 = dx * dx + dy * dy
    t = np.clip(np.where(length2 > 0, (ux * dx + uy * dy) / np.where(length2 > 0, length2, 1), 0), 0, 1)
    return np.hypot(ux - t * dx, uy - t * dy)


def line_side(columns: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``[P,S]`` signed distances (float64) of points ``x, y [P]`` to the lines of segments ``columns
    [7,S]`` (or ``[7,P,S]``): negative on the left (the road side); +inf for a null segment (no side)."""
    ax, ay, dx, dy = _rows(columns, (0, 1, 3, 4))
    length = np.hypot(dx, dy)
    cross = (x[:, None] - ax) * dy - (y[:, None] - ay) * dx
    return np.where(length > 0, cross / np.where(length > 0, length, 1), np.inf)


def _listed(
    columns: np.ndarray, slope: np.ndarray, x: np.ndarray, y: np.ndarray, radius: float
) -> np.ndarray:
    """``[P,S]`` the segments (``columns [7,S]`` or ``[7,P,S]``, Lipschitz constants ``slope`` alike; inf:
    none) that can be the nearest one for some point within ``radius`` of a centre ``x, y [P]``."""
    bound = (selection_distance(columns, x, y) + slope * radius).min(axis=1)
    return planar_distance(columns, x, y) - radius <= bound[:, None] + SLACK


def lipschitz(columns: np.ndarray) -> np.ndarray:
    """``[S]`` how fast (m per m) the selection distance to each segment can change as the point moves."""
    dz, inverse = columns[5].astype(np.float64), columns[6].astype(np.float64)
    return np.sqrt(1 + (float(Z_STRETCH) * dz) ** 2 * inverse)


def _block_lists(grid: MapGrid, bx: int, by: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells of block ``(bx, by)`` of ``grid``: how many segments each lists ``[cells]``, whether it is
    safe ``[cells]``, and the segments ``[sum]`` cell by cell (row by row), each cell's ascending."""
    side = grid.cell * BLOCK
    columns, slope = grid.wide, grid.slope
    cx0, cy0 = np.array([grid.x0 + (bx + 0.5) * side]), np.array([grid.y0 + (by + 0.5) * side])
    near = _listed(columns, slope, cx0, cy0, side * np.sqrt(0.5))[0]
    near = np.flatnonzero(near)
    # sub-blocks of SUB x SUB cells, row by row
    per = BLOCK // SUB
    sy, sx = np.divmod(np.arange(per * per), per)
    sub_side = grid.cell * SUB
    sub = _listed(
        columns[:, near],
        slope[near],
        grid.x0 + bx * side + (sx + 0.5) * sub_side,
        grid.y0 + by * side + (sy + 0.5) * sub_side,
        sub_side * np.sqrt(0.5),
    )
    width = max(int(sub.sum(axis=1).max()), 1)
    order = np.argsort(~sub, axis=1, kind="stable")[:, :width]  # each sub-block's listed, ascending
    real = np.take_along_axis(sub, order, 1)
    jy, jx = np.divmod(np.arange(BLOCK * BLOCK), BLOCK)  # cell order of a slot: row by row
    owner = (jy // SUB) * per + jx // SUB
    index = near[order][owner]  # [cells, width] candidate segments of each cell
    cx = grid.x0 + (bx * BLOCK + jx + 0.5) * grid.cell
    cy = grid.y0 + (by * BLOCK + jy + 0.5) * grid.cell
    r = grid.cell * np.sqrt(0.5)
    cols = columns[:, index]  # [7, cells, width]
    listed = _listed(cols, np.where(real[owner], slope[index], np.inf), cx, cy, r) & real[owner]
    # safe: each cell's centre far enough on the road side of its listed segments and their neighbours
    # (which give the sign beyond a segment's end), checked over the (cell, listed segment) pairs
    at, j = np.nonzero(listed)
    segment = index[at, j]
    clear = -(r + SLACK)
    ok = line_side(columns[:, segment][:, :, None], cx[at], cy[at])[:, 0] <= clear
    for k in (0, 1):
        other = grid.links[k, segment]
        sides = line_side(columns[:, np.maximum(other, 0)][:, :, None], cx[at], cy[at])[:, 0]
        ok &= (other < 0) | (sides <= clear)
    safe = np.bincount(at[~ok], minlength=BLOCK * BLOCK) == 0
    return listed.sum(axis=1), safe, segment


_EPOCHS = itertools.count()


class EdgeCells:
    """The cells of every map queried so far (keyed by the identity of its road-edge ``columns``): a block
    table per map (-1: not computed) pointing into cell arrays shared by all maps, so that points of many
    maps are answered in one vectorized pass."""

    def __init__(self) -> None:
        self.epoch = next(_EPOCHS)  # new at every reset: map indices of another epoch name other maps
        self.maps: list[MapGrid] = []
        self.keys: dict[int, int] = {}
        self.table = np.zeros(0, np.int64)  # per block of every map: its slot in the cell arrays, or -1
        self.slots = 0  # blocks computed
        self.start = np.zeros(0, np.int64)  # per cell (BLOCK * BLOCK per slot): its list in ``flat``
        self.length = np.zeros(0, np.int64)
        self.safe = np.zeros(0, bool)
        self.block_safe = np.zeros(0, bool)  # per slot: every cell of the block safe
        self.flat = np.zeros(4096, np.int64)
        self.used = 0
        self.params = np.zeros((0, 6))  # per map: x0, y0, cell, nbx, nby, table

    # ------------------------------------------------------------------------------------------ maps
    def map_ids(self, edges: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """``[B]`` the map index of each row's road edges ``(columns [7,S], links [3,S])`` (-1: none)."""
        out = np.full(len(edges), -1, np.int64)
        for i, (columns, links) in enumerate(edges):
            if not columns.shape[1]:
                continue
            hit = self.keys.get(id(columns))
            if hit is None or self.maps[hit].columns is not columns:
                if len(self.maps) >= MAX_MAPS:
                    self.__init__()  # type: ignore[misc]
                    return self.map_ids(edges)
                hit = self._add(columns, links)
            out[i] = hit
        return out

    def _add(self, columns: np.ndarray, links: np.ndarray) -> int:
        xs = np.concatenate([columns[0], columns[0] + columns[3]]).astype(np.float64)
        ys = np.concatenate([columns[1], columns[1] + columns[4]]).astype(np.float64)
        lo_x, lo_y, hi_x, hi_y = xs.min() - PAD, ys.min() - PAD, xs.max() + PAD, ys.max() + PAD
        cell = max(CELL, float(np.sqrt((hi_x - lo_x) * (hi_y - lo_y) / MAX_BLOCKS)) / BLOCK)
        nbx = int(np.ceil((hi_x - lo_x) / (cell * BLOCK)))
        nby = int(np.ceil((hi_y - lo_y) / (cell * BLOCK)))
        wide = columns.astype(np.float64)
        grid = MapGrid(columns, links, wide, lipschitz(columns), cell, lo_x, lo_y, nbx, nby, len(self.table))
        self.table = np.concatenate([self.table, np.full(nbx * nby, -1, np.int64)])
        self.params = np.vstack([self.params, [lo_x, lo_y, cell, nbx, nby, grid.table]])
        self.maps.append(grid)
        self.keys[id(columns)] = len(self.maps) - 1
        return len(self.maps) - 1

    # ----------------------------------------------------------------------------------------- cells
    def cells_of(self, maps: np.ndarray, ix: np.ndarray, iy: np.ndarray, compute: bool = True) -> np.ndarray:
        """Cell index (in the cell arrays) of cells ``ix, iy`` of ``maps`` (-1 outside a grid), their
        blocks computed where they were not yet (``compute`` False: -1 for those)."""
        nbx, nby, table = (self.params[maps, k].astype(np.int64) for k in (3, 4, 5))
        bx, by = ix // BLOCK, iy // BLOCK
        inside = (ix >= 0) & (iy >= 0) & (bx < nbx) & (by < nby)
        block = np.where(inside, table + by * nbx + bx, 0)
        slot = np.where(inside, self.table[block], -1)
        missing = inside & (slot < 0)
        if compute and missing.any():
            for b in np.unique(block[missing]).tolist():
                self._compute_block(b)
            slot = np.where(inside, self.table[block], -1)
        return np.where(inside, slot * BLOCK * BLOCK + (iy % BLOCK) * BLOCK + ix % BLOCK, -1)

    def locate(self, maps: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Cell index ``[P]`` of ``points [P,2]`` on ``maps [P]`` (-1: outside its grid)."""
        x0, y0, cell = self.params[maps, 0], self.params[maps, 1], self.params[maps, 2]
        ix = np.floor((points[:, 0] - x0) / cell).astype(np.int64)
        iy = np.floor((points[:, 1] - y0) / cell).astype(np.int64)
        return self.cells_of(maps, ix, iy)

    def _compute_block(self, block: int) -> None:
        """Lists and safe flags of the cells of block ``block`` of the table (see the module docstring):
        the segments that can be nearest in the block, then in each SUB x SUB cells of it, then in each
        cell (each level's bound drawn from the level above); compiled where numba is available
        (:func:`~trajeglish_env.guard_kernels.block_lists`, the same lists)."""
        m = int(np.searchsorted(self.params[:, 5], block, side="right") - 1)
        grid = self.maps[m]
        local = block - grid.table
        bx, by = local % grid.nbx, local // grid.nbx
        kernels = compiled()
        if kernels is None:
            counts, safe, segment = _block_lists(grid, bx, by)
        else:
            place = (grid.cell, grid.x0, grid.y0, bx, by)
            counts, safe, segment = kernels.block_lists(grid.wide, grid.slope, grid.links, *place)
        slot = self.slots
        if (slot + 1) * BLOCK * BLOCK > len(self.start):
            grow = max(64, slot) * BLOCK * BLOCK
            self.start = np.concatenate([self.start, np.zeros(grow, np.int64)])
            self.length = np.concatenate([self.length, np.zeros(grow, np.int64)])
            self.safe = np.concatenate([self.safe, np.zeros(grow, bool)])
            self.block_safe = np.concatenate([self.block_safe, np.zeros(grow // (BLOCK * BLOCK), bool)])
        cells = slice(slot * BLOCK * BLOCK, (slot + 1) * BLOCK * BLOCK)
        self.start[cells] = self.used + np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.length[cells] = counts
        self.safe[cells] = safe
        self.block_safe[slot] = self.safe[cells].all()
        self._append(segment)  # row by row: each cell's segments, ascending
        self.table[block] = slot
        self.slots += 1

    def _append(self, values: np.ndarray) -> None:
        if self.used + len(values) > len(self.flat):
            bigger = np.zeros(max(2 * len(self.flat), self.used + len(values)), np.int64)
            bigger[: self.used] = self.flat[: self.used]
            self.flat = bigger
        self.flat[self.used : self.used + len(values)] = values
        self.used += len(values)

    # --------------------------------------------------------------------------------------- queries
    def all_safe(self, maps: np.ndarray, centre: np.ndarray, reach: np.ndarray) -> np.ndarray:
        """``[n]`` True where every block that the square of half-side ``reach [n]`` around ``centre [n,2]``
        on ``maps [n]`` touches is computed and holds only safe cells: every point within ``reach`` of the
        centre is then on the road. Computes no block (a block not computed yet counts as not safe): the
        blocks a vehicle's candidates reach are computed when its corners are first measured."""
        if not len(maps) or not self.slots:
            return np.zeros(len(maps), bool)
        kernels = compiled()
        if kernels is not None:  # the same verdicts, block by block (guard_kernels.all_safe)
            out = np.empty(len(maps), bool)
            where = (np.ascontiguousarray(centre, np.float64), np.ascontiguousarray(reach, np.float64))
            kernels.all_safe(self.params, self.table, self.block_safe, maps.astype(np.int64), *where, out)
            return out
        x0, y0, side = self.params[maps, 0], self.params[maps, 1], self.params[maps, 2] * BLOCK
        lo_x, lo_y, hi_x, hi_y = (
            np.floor((centre[:, k] + sign * reach - origin) / side).astype(np.int64)
            for sign, k, origin in ((-1, 0, x0), (-1, 1, y0), (1, 0, x0), (1, 1, y0))
        )
        span = int(max((hi_x - lo_x).max(), (hi_y - lo_y).max())) + 1
        k = np.arange(span)
        bx = np.broadcast_to(lo_x[:, None, None] + k[None, None, :], (len(maps), span, span))
        by = np.broadcast_to(lo_y[:, None, None] + k[None, :, None], (len(maps), span, span))
        used = (bx <= hi_x[:, None, None]) & (by <= hi_y[:, None, None])
        many = np.broadcast_to(maps[:, None, None], bx.shape)
        cells = self.cells_of(many[used], bx[used] * BLOCK, by[used] * BLOCK, compute=False)
        ok = np.ones(bx.shape, bool)
        ok[used] = (cells >= 0) & self.block_safe[np.maximum(cells, 0) // (BLOCK * BLOCK)]
        return ok.all(axis=(1, 2))

    def signed(
        self,
        maps: np.ndarray,
        rows: np.ndarray,
        points: np.ndarray,
        padded: tuple[np.ndarray, np.ndarray, np.ndarray],
    ) -> np.ndarray:
        """``[P]`` the reference's signed distance (float32) of ``points [P,2]`` of batch rows ``rows [P]``
        (maps ``maps [P]``; the rows' padded road edges ``padded = (columns [B,7,S], links [B,3,S], count
        [B])``), or -inf where the point's cell is safe (the distance is then <= 0)."""
        return self._compiled("signed_points", (points,), maps, rows, padded, self._signed)

    def box_excess(
        self,
        maps: np.ndarray,
        rows: np.ndarray,
        xyh: np.ndarray,
        size: np.ndarray,
        padded: tuple[np.ndarray, np.ndarray, np.ndarray],
    ) -> np.ndarray:
        """``[P]`` how far the most off-road corner of each box ``xyh [P,3]`` of ``size [P,2]`` lies beyond a
        road edge (:meth:`signed` of its corners, the largest; -inf where all lie in safe cells)."""
        return self._compiled("box_excess", (xyh, size), maps, rows, padded, self._box_excess)

    def _compiled(
        self,
        kernel: str,
        items: tuple[np.ndarray, ...],
        maps: np.ndarray,
        rows: np.ndarray,
        padded: tuple[np.ndarray, np.ndarray, np.ndarray],
        numpy_path: Callable[..., np.ndarray],
    ) -> np.ndarray:
        """``[P]`` the answers of :mod:`~trajeglish_env.guard_kernels`' ``kernel`` for ``items`` (arrays of
        ``P`` rows) on ``maps``/``rows``; ``numpy_path(maps, rows, *items, padded)`` answers those it leaves
        (blocks not computed yet, points outside the grid) and all of them without numba."""
        kernels = compiled()
        if kernels is None or not len(maps):
            return numpy_path(maps, rows, *items, padded)
        out, status = np.empty(len(maps), np.float32), np.zeros(len(maps), np.int8)
        getattr(kernels, kernel)(*items, maps, rows, self._grid(), *padded[:2], out, status)
        left = np.flatnonzero(status)
        if len(left):
            out[left] = numpy_path(maps[left], rows[left], *(a[left] for a in items), padded)
        return out

    def _box_excess(
        self,
        maps: np.ndarray,
        rows: np.ndarray,
        xyh: np.ndarray,
        size: np.ndarray,
        padded: tuple[np.ndarray, np.ndarray, np.ndarray],
    ) -> np.ndarray:
        """:meth:`box_excess` in NumPy."""
        points = box_corners(xyh, size).reshape(-1, 2)
        signed = self._signed(np.repeat(maps, 4), np.repeat(rows, 4), points, padded)
        return signed.reshape(-1, 4).max(axis=-1)

    def _grid(self) -> tuple[np.ndarray, ...]:
        """The cell arrays the compiled queries read."""
        return self.params, self.table, self.start, self.length, self.safe, self.flat

    def _signed(
        self,
        maps: np.ndarray,
        rows: np.ndarray,
        points: np.ndarray,
        padded: tuple[np.ndarray, np.ndarray, np.ndarray],
    ) -> np.ndarray:
        """:meth:`signed` in NumPy (computing the blocks the points fall in)."""
        columns, links, count = padded
        out = np.full(len(points), -np.inf, np.float32)
        cells = self.locate(maps, points)
        todo = np.flatnonzero((cells < 0) | ~self.safe[np.maximum(cells, 0)])
        if not len(todo):
            return out
        c, r, pts = cells[todo], rows[todo], points[todo].astype(np.float32)
        nearest = np.zeros(len(todo), np.int64)
        inside = np.flatnonzero(c >= 0)
        if len(inside):
            nearest[inside] = self._nearest(c[inside], r[inside], pts[inside], columns)
        outside = np.flatnonzero(c < 0)
        if len(outside):
            nearest[outside] = nearest_segments(columns, count, r[outside], pts[outside, None])[:, 0]
        out[todo] = signed_distances_to(columns, links, r, pts[:, None], nearest[:, None])[:, 0]
        return out

    def _nearest(
        self, cells: np.ndarray, rows: np.ndarray, pts: np.ndarray, columns: np.ndarray
    ) -> np.ndarray:
        """The reference's nearest segment ``[q]`` of float32 points ``pts [q,2]`` among their cells'
        lists: one flat pass over every (point, listed segment) pair, the first of the smallest per point."""
        length = self.length[cells]
        first = np.concatenate([[0], np.cumsum(length)[:-1]])
        owner = np.repeat(np.arange(len(cells)), length)
        seg = self.flat[np.repeat(self.start[cells] - first, length) + np.arange(len(owner))]
        cols = columns[rows[owner], :, seg][:, :, None]  # [pairs,7,1]
        d2 = selection_d2(cols, pts[owner, 0, None], pts[owner, 1, None])[:, 0, 0]
        low = np.minimum.reduceat(d2, first)
        hits = np.flatnonzero(d2 == low[owner])
        lead = np.ones(len(hits), bool)  # the first pair (lowest segment) per point: pairs are by point
        lead[1:] = owner[hits[1:]] != owner[hits[:-1]]
        return seg[hits[lead]]
