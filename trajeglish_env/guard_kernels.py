"""Compiled kernels of guarded sampling (numba, when installed): the road-edge queries and the box overlaps
the guard asks most, number for number the NumPy code they stand in for.

The guard asks the road-edge cells (:mod:`~trajeglish_env.edge_cells`) for the signed distance of a few
dozen box corners at a time, a few times per pair of a step; in NumPy each ask is some fifty array calls
whatever its size, so a small env spends its time in their overhead. A compiled loop answers a corner in
well under a microsecond. It runs the very same float32 operations in the same order (IEEE arithmetic,
no fused multiply-adds: numba's default), so every answer equals the NumPy path's
(``tests/test_guard_kernels.py`` compares them corner by corner on real maps). Without numba, or for
corners the kernel leaves (a block of cells not computed yet, a point outside the map's grid), the NumPy
path answers. The boxes' overlap (:func:`box_overlaps`) is the separating-axis gap of
:func:`~trajeglish_env.metrics.boxes.box_collisions`, in the same operations (sines and cosines from the
same C library: NumPy's equal it here, checked by the tests).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np

from trajeglish_env.edge_cells import BLOCK, SUB
from trajeglish_env.edge_cells import SLACK as CELL_SLACK
from trajeglish_env.metrics.road_edges import Z_STRETCH

LEFT = 1  # status of a corner the kernel did not answer (block not computed, or outside the grid)
STRETCH = np.float32(Z_STRETCH)
STRETCH64 = float(Z_STRETCH)  # the cells' bounds are drawn in float64
HALF_ROOT = float(np.sqrt(0.5))  # a square's half-diagonal per side


def _load_numba() -> Any:
    """numba, or None where it is missing or switched off (``TRAJEGLISH_NO_NUMBA=1``: the NumPy path)."""
    if os.environ.get("TRAJEGLISH_NO_NUMBA", "") not in ("", "0"):
        return None
    try:
        import numba
    except ImportError:
        return None
    return numba


_NUMBA = _load_numba()
AVAILABLE = _NUMBA is not None


def _jit(f: Callable[..., Any]) -> Callable[..., Any]:
    """``f`` compiled (cached on disk) where numba is available; else ``f`` itself, never called."""
    return _NUMBA.njit(cache=True, nogil=True)(f) if AVAILABLE else f


@_jit
def _signed_point(
    px: float,
    py: float,
    m: int,
    r: int,
    params: np.ndarray,
    table: np.ndarray,
    start: np.ndarray,
    length: np.ndarray,
    safe: np.ndarray,
    flat: np.ndarray,
    columns: np.ndarray,
    links: np.ndarray,
) -> tuple[np.float32, bool]:  # pragma: no cover - compiled (its NumPy twin is EdgeCells._signed)
    """The reference's signed distance (float32) of point ``(px, py)`` of batch row ``r`` on map ``m`` from
    its cell's listed segments (-inf in a safe cell), and whether it was answered (False where its block is
    not computed yet or it lies outside the grid)."""
    f32 = np.float32
    zero, one = f32(0.0), f32(1.0)
    x0, y0, cell = params[m, 0], params[m, 1], params[m, 2]
    nbx, nby, base = np.int64(params[m, 3]), np.int64(params[m, 4]), np.int64(params[m, 5])
    ix = np.int64(np.floor((px - x0) / cell))
    iy = np.int64(np.floor((py - y0) / cell))
    bx, by = ix // BLOCK, iy // BLOCK
    if ix < 0 or iy < 0 or bx >= nbx or by >= nby:
        return f32(0.0), False
    slot = table[base + by * nbx + bx]
    if slot < 0:
        return f32(0.0), False
    c = slot * BLOCK * BLOCK + (iy % BLOCK) * BLOCK + ix % BLOCK
    if safe[c]:
        return f32(-np.inf), True
    x, y = f32(px), f32(py)
    # the nearest listed segment: the reference's selection distance, float32, first on ties (a flat
    # segment's z term is +0, which changes no number: the NumPy path drops it on flat maps)
    best, seg = f32(np.inf), -1
    for q in range(start[c], start[c] + length[c]):
        s = flat[q]
        ux, uy = x - columns[r, 0, s], y - columns[r, 1, s]
        dx, dy = columns[r, 3, s], columns[r, 4, s]
        t = ux * dx
        t += uy * dy
        t *= columns[r, 6, s]
        t = min(max(t, zero), one)
        ux -= t * dx
        uy -= t * dy
        rz = STRETCH * (zero - columns[r, 2, s] - t * columns[r, 5, s])
        d2 = ux * ux + uy * uy + rz * rz
        if d2 < best:
            best, seg = d2, s
    if seg < 0:
        return f32(0.0), False
    # its signed distance, the sign beyond an end taken from the vertex shared with the neighbour
    sx, sy, sdx, sdy = columns[r, 0, seg], columns[r, 1, seg], columns[r, 3, seg], columns[r, 4, seg]
    ux, uy = x - sx, y - sy
    length2 = sdx * sdx + sdy * sdy
    tt = (ux * sdx + uy * sdy) / length2 if length2 > zero else zero
    tc = min(max(tt, zero), one)
    rx, ry = ux - tc * sdx, uy - tc * sdy
    magnitude = np.sqrt(rx * rx + ry * ry)
    sign = np.sign(ux * sdy - uy * sdx)
    previous, following = links[r, 0, seg], links[r, 1, seg]
    before = tt < zero and previous >= 0
    if before or (tt > one and following >= 0):
        other = previous if before else following
        convex = (links[r, 2, seg] if before else links[r, 2, other]) > 0
        ox, oy = x - columns[r, 0, other], y - columns[r, 1, other]
        other_side = np.sign(ox * columns[r, 4, other] - oy * columns[r, 3, other])
        sign = max(sign, other_side) if convex else min(sign, other_side)
    return sign * magnitude, True


@_jit
def signed_points(
    points: np.ndarray,
    maps: np.ndarray,
    rows: np.ndarray,
    grid: tuple[np.ndarray, ...],
    columns: np.ndarray,
    links: np.ndarray,
    out: np.ndarray,
    status: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out [P]``: :func:`_signed_point` of ``points [P,2]`` of rows ``rows`` on maps ``maps`` (``grid``: the
    cells' ``params, table, start, length, safe, flat``); ``status [P]`` LEFT where not answered."""
    params, table, start, length, safe, flat = grid
    for i in range(points.shape[0]):
        v, ok = _signed_point(
            points[i, 0],
            points[i, 1],
            maps[i],
            rows[i],
            params,
            table,
            start,
            length,
            safe,
            flat,
            columns,
            links,
        )
        out[i] = v
        if not ok:
            status[i] = LEFT


@_jit
def box_excess(
    xyh: np.ndarray,
    size: np.ndarray,
    maps: np.ndarray,
    rows: np.ndarray,
    grid: tuple[np.ndarray, ...],
    columns: np.ndarray,
    links: np.ndarray,
    out: np.ndarray,
    status: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out [P]``: the largest :func:`_signed_point` of the corners of boxes ``xyh [P,3]`` of ``size [P,2]``
    (:func:`~trajeglish_env.geometry.box_corners`, the same operations); ``status [P]`` LEFT where a corner
    was not answered."""
    params, table, start, length, safe, flat = grid
    for i in range(xyh.shape[0]):
        c, s = np.cos(xyh[i, 2]), np.sin(xyh[i, 2])
        worst = np.float32(-np.inf)
        for k in range(4):
            lx = (0.5 if k < 2 else -0.5) * size[i, 0]
            ly = (0.5 if k == 0 or k == 3 else -0.5) * size[i, 1]
            x = xyh[i, 0] + c * lx - s * ly
            y = xyh[i, 1] + s * lx + c * ly
            v, ok = _signed_point(
                x, y, maps[i], rows[i], params, table, start, length, safe, flat, columns, links
            )
            if not ok:
                status[i] = LEFT
            worst = max(worst, v)
        out[i] = worst


@_jit
def _listed(
    wide: np.ndarray,
    slope: np.ndarray,
    segments: np.ndarray,
    real: np.ndarray,
    x: float,
    y: float,
    radius: float,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled (its NumPy twin is edge_cells._listed)
    """``out [k]``: which of ``segments [k]`` (columns ``wide [7,S]`` float64, Lipschitz constants ``slope``;
    ``real [k]`` False: padding, never listed) can be the nearest one for some point within ``radius`` of
    ``(x, y)``: the bound is the smallest selection distance plus slope times radius, a segment is listed
    where its planar distance less the radius is within it (plus the slack)."""
    bound = np.inf
    for q in range(segments.shape[0]):
        if not real[q]:
            continue
        s = segments[q]
        ax, ay, az, dx, dy, dz, inverse = (
            wide[0, s],
            wide[1, s],
            wide[2, s],
            wide[3, s],
            wide[4, s],
            wide[5, s],
            wide[6, s],
        )
        ux, uy = x - ax, y - ay
        t = min(max((ux * dx + uy * dy) * inverse, 0.0), 1.0)
        rx, ry, rz = ux - t * dx, uy - t * dy, STRETCH64 * (-az - t * dz)
        bound = min(bound, np.sqrt(rx * rx + ry * ry + rz * rz) + slope[s] * radius)
    for q in range(segments.shape[0]):
        if not real[q]:
            out[q] = False
            continue
        s = segments[q]
        ax, ay, dx, dy = wide[0, s], wide[1, s], wide[3, s], wide[4, s]
        ux, uy = x - ax, y - ay
        length2 = dx * dx + dy * dy
        t = min(max((ux * dx + uy * dy) / length2 if length2 > 0 else 0.0, 0.0), 1.0)
        out[q] = np.hypot(ux - t * dx, uy - t * dy) - radius <= bound + CELL_SLACK


@_jit
def _line_side(wide: np.ndarray, s: int, x: float, y: float) -> float:  # pragma: no cover - compiled
    """The signed distance of ``(x, y)`` to the line of segment ``s`` (edge_cells.line_side)."""
    ax, ay, dx, dy = wide[0, s], wide[1, s], wide[3, s], wide[4, s]
    length = np.hypot(dx, dy)
    cross = (x - ax) * dy - (y - ay) * dx
    return cross / length if length > 0 else np.inf


@_jit
def block_lists(
    wide: np.ndarray,
    slope: np.ndarray,
    links: np.ndarray,
    cell: float,
    x0: float,
    y0: float,
    bx: int,
    by: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """The lists of the BLOCK x BLOCK cells of block ``(bx, by)`` of a map (``EdgeCells._compute_block``,
    the same three levels and numbers): ``counts [cells]``, ``safe [cells]`` and the segments ``[sum]``,
    cell by cell (row by row), each cell's ascending."""
    side = cell * BLOCK
    segments = np.arange(wide.shape[1])
    every = np.ones(wide.shape[1], np.bool_)
    flags = np.empty(wide.shape[1], np.bool_)
    _listed(
        wide, slope, segments, every, x0 + (bx + 0.5) * side, y0 + (by + 0.5) * side, side * HALF_ROOT, flags
    )
    near = np.flatnonzero(flags)
    per = BLOCK // SUB
    sub_side = cell * SUB
    sub = np.empty((per * per, near.shape[0]), np.bool_)
    real = np.ones(near.shape[0], np.bool_)
    for k in range(per * per):
        sy, sx = k // per, k % per
        cx, cy = x0 + bx * side + (sx + 0.5) * sub_side, y0 + by * side + (sy + 0.5) * sub_side
        _listed(wide, slope, near, real, cx, cy, sub_side * HALF_ROOT, sub[k])
    r = cell * HALF_ROOT
    clear = -(r + CELL_SLACK)
    counts = np.zeros(BLOCK * BLOCK, np.int64)
    safe = np.ones(BLOCK * BLOCK, np.bool_)
    found = np.empty(BLOCK * BLOCK * max(near.shape[0], 1), np.int64)
    used = 0
    flags = np.empty(near.shape[0], np.bool_)
    for j in range(BLOCK * BLOCK):
        jy, jx = j // BLOCK, j % BLOCK
        owner = (jy // SUB) * per + jx // SUB
        cx, cy = x0 + (bx * BLOCK + jx + 0.5) * cell, y0 + (by * BLOCK + jy + 0.5) * cell
        _listed(wide, slope, near, sub[owner], cx, cy, r, flags)
        for q in range(near.shape[0]):
            if not flags[q]:
                continue
            s = near[q]
            found[used] = s
            used += 1
            counts[j] += 1
            ok = _line_side(wide, s, cx, cy) <= clear
            for k in range(2):
                other = links[k, s]
                if other >= 0 and not _line_side(wide, other, cx, cy) <= clear:
                    ok = False
            if not ok:
                safe[j] = False
    return counts, safe, found[:used].copy()


@_jit
def box_gap(
    ax: float,
    ay: float,
    ah: float,
    al: float,
    aw: float,
    bx: float,
    by: float,
    bh: float,
    bl: float,
    bw: float,
) -> float:  # pragma: no cover - compiled
    """The separating-axis gap of box ``(ax, ay, ah)`` (length ``al``, width ``aw``) and box ``(bx, by, bh)``
    (:func:`~trajeglish_env.metrics.boxes.box_collisions`' operations): negative where they overlap."""
    dx, dy = bx - ax, by - ay
    cos_a, sin_a, cos_b, sin_b = np.cos(ah), np.sin(ah), np.cos(bh), np.sin(bh)
    c = cos_a * cos_b + sin_a * sin_b
    s = cos_a * sin_b - sin_a * cos_b
    pax, pay = cos_a * dx + sin_a * dy, cos_a * dy - sin_a * dx
    pbx, pby = -(cos_b * dx + sin_b * dy), -(cos_b * dy - sin_b * dx)
    la, wa, lb, wb = al / 2, aw / 2, bl / 2, bw / 2
    ac, as_ = np.abs(c), np.abs(s)
    return np.maximum(
        np.maximum(np.abs(pax) - la - (lb * ac + wb * as_), np.abs(pay) - wa - (lb * as_ + wb * ac)),
        np.maximum(np.abs(pbx) - lb - (la * ac + wa * as_), np.abs(pby) - wb - (la * as_ + wa * ac)),
    )


@_jit
def box_overlaps(
    a: np.ndarray, size_a: np.ndarray, b: np.ndarray, size_b: np.ndarray, out: np.ndarray
) -> None:
    """``out [n]``: where boxes ``a [n,3]`` (``size_a [n,2]``) and ``b [n,3]`` overlap
    (:func:`~trajeglish_env.metrics.boxes.box_collisions` with sharp corners: the separating-axis gap, the
    same operations)."""  # pragma: no cover - compiled
    for i in range(a.shape[0]):
        ax, ay, ah, al, aw = a[i, 0], a[i, 1], a[i, 2], size_a[i, 0], size_a[i, 1]
        out[i] = box_gap(ax, ay, ah, al, aw, b[i, 0], b[i, 1], b[i, 2], size_b[i, 0], size_b[i, 1]) < 0


@_jit
def all_safe(
    params: np.ndarray,
    table: np.ndarray,
    block_safe: np.ndarray,
    maps: np.ndarray,
    centre: np.ndarray,
    reach: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled (its NumPy twin is EdgeCells.all_safe)
    """``out [n]``: :meth:`~trajeglish_env.edge_cells.EdgeCells.all_safe` (every block the square of
    half-side ``reach`` around ``centre`` touches computed and safe), block by block."""
    for i in range(maps.shape[0]):
        m = maps[i]
        x0, y0, side = params[m, 0], params[m, 1], params[m, 2] * BLOCK
        nbx, nby, base = np.int64(params[m, 3]), np.int64(params[m, 4]), np.int64(params[m, 5])
        lo_x = np.int64(np.floor((centre[i, 0] + -1 * reach[i] - x0) / side))
        lo_y = np.int64(np.floor((centre[i, 1] + -1 * reach[i] - y0) / side))
        hi_x = np.int64(np.floor((centre[i, 0] + 1 * reach[i] - x0) / side))
        hi_y = np.int64(np.floor((centre[i, 1] + 1 * reach[i] - y0) / side))
        ok = True
        for by in range(lo_y, hi_y + 1):
            for bx in range(lo_x, hi_x + 1):
                if bx < 0 or by < 0 or bx >= nbx or by >= nby:
                    ok = False
                    break
                slot = table[base + by * nbx + bx]
                if slot < 0 or not block_safe[slot]:
                    ok = False
                    break
            if not ok:
                break
        out[i] = ok
