"""Which ways the lanes run at each point of a map, for the guard's wrong-way rule
(``SamplingConfig.guard_wrong_way``): a vehicle box centre within :data:`LANE_REACH` m of a lane centre
line whose heading is more than 120 degrees off every lane near it drives against the traffic.

Answered per point from a grid over the map (:data:`CELL` m cells), each cell holding a 32-bit mask of the
directions (:data:`DIRECTION_BINS` bins) of the lane segments that come within ``LANE_REACH`` m of some
point of the cell. A cell lists every lane that comes that near any of its points, so the test errs
towards *allowing*: where lanes cross (junctions) any heading some lane takes is fine, and off the lanes
(parking lots, driveways, SUMO's junctions) no box is against them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.compiled import pair_compiled
from trajeglish_env.scenario import MapKind, Scenario

CELL = 0.5  # metres: a grid cell's side
LANE_REACH = 1.0  # metres from a lane centre line within which a box centre is on that lane
DIRECTION_BINS = 32  # lane directions are kept in bins of 11.25 degrees
AGAINST = np.deg2rad(120.0)  # a heading farther than this from every near lane's direction is against them
MAX_CELLS = 1 << 23  # cells per map at most (larger cells on a larger map: 32 MB of masks)
MAX_SCENES = 64  # scenes whose grids the guard keeps (a WOMD map's: 0.7 MB)
VEHICLE_LANES = frozenset({MapKind.LANE_UNDEFINED, MapKind.LANE_FREEWAY, MapKind.LANE_SURFACE_STREET})


def _agree_masks() -> np.ndarray:
    """``[DIRECTION_BINS]`` per heading bin: the bins of lane directions whose centre lies within
    :data:`AGAINST` of the heading bin's (a heading and a lane direction in bins ``AGAINST`` apart differ by
    ``AGAINST`` give or take a bin's width)."""
    width = 2 * np.pi / DIRECTION_BINS
    gap = np.abs(np.arange(DIRECTION_BINS)[:, None] - np.arange(DIRECTION_BINS)[None])
    gap = np.minimum(gap, DIRECTION_BINS - gap) * width  # angle between the bins' centres
    near = gap <= AGAINST
    return (near * (1 << np.arange(DIRECTION_BINS))).sum(axis=1).astype(np.int64)


AGREE = _agree_masks()


def direction_bin(angle: np.ndarray) -> np.ndarray:
    """The bin ``[...]`` of headings ``angle [...]`` (radians)."""
    width = 2 * np.pi / DIRECTION_BINS
    return (np.floor(np.mod(angle, 2 * np.pi) / width).astype(np.int64)) % DIRECTION_BINS


@dataclass(frozen=True)
class LaneDirections:
    """One map's grid: origin ``x0, y0``, cell side ``cell``, ``masks [ny, nx]`` the lane-direction bits."""

    x0: float
    y0: float
    cell: float
    masks: np.ndarray

    @classmethod
    def of(cls, sc: Scenario) -> LaneDirections | None:
        """The lane directions of ``sc``'s vehicle lanes, or None where it has none."""
        lanes = [
            sc.map_points[sc.map_offsets[k] : sc.map_offsets[k + 1], :2]
            for k in np.flatnonzero(np.isin(sc.map_kind, [int(m) for m in VEHICLE_LANES]))
        ]
        starts = [p[:-1] for p in lanes if len(p) >= 2]
        if not starts:
            return None
        a = np.concatenate(starts).astype(np.float64)
        d = np.concatenate([np.diff(p, axis=0) for p in lanes if len(p) >= 2]).astype(np.float64)
        length = np.hypot(d[:, 0], d[:, 1])
        keep = length > 1e-6
        a, d, length = a[keep], d[keep], length[keep]
        if not len(a):
            return None
        lo = np.minimum(a, a + d).min(axis=0) - LANE_REACH - 1.0
        hi = np.maximum(a, a + d).max(axis=0) + LANE_REACH + 1.0
        cell = max(CELL, float(np.sqrt((hi - lo).prod() / MAX_CELLS)))
        nx, ny = (np.ceil((hi - lo) / cell).astype(int) + 1).tolist()
        # points along every segment at most half a cell apart, each with its segment's direction bin
        n = np.ceil(length / (cell / 2)).astype(np.int64) + 1
        seg = np.repeat(np.arange(len(a)), n)
        frac = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n - 1, n)
        points = a[seg] + frac[:, None] * d[seg]
        bins = direction_bin(np.arctan2(d[:, 1], d[:, 0]))[seg]
        # every cell some point of which lies within LANE_REACH of a point (cell centres within the reach
        # plus half a diagonal; the points' own spacing adds half a cell, covered the same way)
        k = int(np.ceil((LANE_REACH + cell) / cell))
        oy, ox = np.mgrid[-k : k + 1, -k : k + 1]
        near = np.hypot(ox, oy) * cell <= LANE_REACH + cell * (np.sqrt(0.5) + 0.25)
        ox, oy = ox[near], oy[near]
        ix = np.floor((points[:, 0] - lo[0]) / cell).astype(np.int64)
        iy = np.floor((points[:, 1] - lo[1]) / cell).astype(np.int64)
        cx = np.clip(ix[:, None] + ox[None], 0, nx - 1)
        cy = np.clip(iy[:, None] + oy[None], 0, ny - 1)
        flat = (cy * nx + cx).ravel()
        flat_bins = np.repeat(bins, len(ox))
        masks = np.zeros(nx * ny, np.int64)  # 32 bits: int64 keeps the shifts and ORs unsigned
        for b in np.unique(flat_bins).tolist():  # one pass per direction: plain assignment, no ufunc.at
            hit = np.zeros(nx * ny, bool)
            hit[flat[flat_bins == b]] = True
            masks |= hit.astype(np.int64) << b
        return cls(float(lo[0]), float(lo[1]), cell, masks.astype(np.uint32).reshape(ny, nx))

    def lane_bits(self, xy: np.ndarray) -> np.ndarray:
        """``[...]`` the direction bits of the lanes near points ``xy [...,2]`` (0 off the lanes and off the
        grid)."""
        ny, nx = self.masks.shape
        ix = np.floor((xy[..., 0] - self.x0) / self.cell).astype(np.int64)
        iy = np.floor((xy[..., 1] - self.y0) / self.cell).astype(np.int64)
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        bits = self.masks[np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)].astype(np.int64)
        return np.where(inside, bits, 0)

    def against(self, xyh: np.ndarray) -> np.ndarray:
        """``[...]`` boxes at ``xyh [...,3]`` whose centre is on some lane and whose heading runs against
        every lane there (compiled where numba is available: :mod:`~trajeglish_env.pair_kernels`)."""
        kernels = pair_compiled()
        if kernels is not None:
            flat = np.ascontiguousarray(xyh, np.float64).reshape(-1, 3)
            out = np.empty(len(flat), bool)
            kernels.lanes_against(self.masks, self.x0, self.y0, self.cell, flat, AGREE, out)
            return out.reshape(xyh.shape[:-1])
        bits = self.lane_bits(xyh[..., :2])
        return (bits != 0) & ((bits & AGREE[direction_bin(xyh[..., 2])]) == 0)
