"""The road points near each agent, looked up in a grid of cells (the sampler's road features, lane input).

:func:`model.lanes.road_view` compares every agent it is given with every road point it is given. On a
city map (the shared WOMD scene: 4,124 points within reach of its 83 agents' box) that pairwise work was
most of what the road features cost a step. A grid of :data:`CELL`-metre cells over the scene's points
hands each agent only the points of the cells around its own that can hold a point ``road_view`` picks:
within :data:`~trajeglish_env.model.lanes.REACH` of it and less than
:data:`~trajeglish_env.model.lanes.BEHIND` behind it (about 1.4 times the points it can read on the WOMD
scene).
"""

from __future__ import annotations

import math
import weakref

import numpy as np
import torch

from trajeglish_env.model.lanes import BEHIND, POINT_FEATURES, REACH, ROAD_POINTS, road_points_of, road_view
from trajeglish_env.scenario import Scenario

CELL = REACH / 4  # metres: the side of a cell (smaller cells give tighter sets, more cells to visit)
MARGIN = 0.01  # metres: a cell is skipped only when it lies this much beyond what road_view can read
SPAN = math.ceil(REACH / CELL)  # cells each side of an agent's own that can hold a point within REACH


class RoadGrid:
    """A scene's road points ``[P,4]`` (:func:`model.lanes.scene_road_points`) sorted by grid cell."""

    def __init__(self, points: np.ndarray):
        self.points = np.asarray(points, dtype=np.float64)
        if not len(self.points):
            self.origin, self.shape = np.zeros(2), np.ones(2, dtype=np.int64)
            self.start = self.count = np.zeros(1, dtype=np.int64)
            self.local = _local(self.points, self.origin)
            return
        self.origin = self.points[:, :2].min(0)
        ij = np.floor((self.points[:, :2] - self.origin) / CELL).astype(np.int64)
        self.shape = ij.max(0) + 1
        cell = ij[:, 0] * self.shape[1] + ij[:, 1]
        order = np.argsort(cell, kind="stable")
        self.points = self.points[order]
        self.count = np.bincount(cell, minlength=int(self.shape.prod()))
        self.start = np.cumsum(self.count) - self.count
        self.local = _local(self.points, self.origin)

    def near(self, xyh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices ``[n,K]`` into :attr:`points` of the points in the cells around each state ``xyh [n,3]``
        that can hold a point ``road_view`` picks, and their mask (``K``: the most any state has). A cell is
        skipped when it lies :data:`REACH` or farther away, or wholly :data:`BEHIND` metres or more behind
        the agent (by a centimetre's margin: no point it holds can be read)."""
        xyh = np.asarray(xyh, dtype=np.float64).reshape(-1, 3)
        n = len(xyh)
        ij = np.floor((xyh[:, :2] - self.origin) / CELL).astype(np.int64)
        d = np.arange(-SPAN, SPAN + 1)
        i = (ij[:, 0, None, None] + d[None, :, None]).repeat(len(d), 2).reshape(n, -1)
        j = (ij[:, 1, None, None] + d[None, None, :]).repeat(len(d), 1).reshape(n, -1)
        inside = (i >= 0) & (i < self.shape[0]) & (j >= 0) & (j < self.shape[1])
        low_x = self.origin[0] + i * CELL - xyh[:, :1]  # the cells' corners relative to the agent [n,C]
        low_y = self.origin[1] + j * CELL - xyh[:, 1:2]
        gap_x = np.maximum(np.maximum(low_x, -(low_x + CELL)), 0.0)
        gap_y = np.maximum(np.maximum(low_y, -(low_y + CELL)), 0.0)
        within = gap_x * gap_x + gap_y * gap_y < (REACH + MARGIN) ** 2
        c, s = np.cos(xyh[:, 2:3]), np.sin(xyh[:, 2:3])  # the farthest ahead of a cell is at a corner
        ahead = np.maximum(low_x * c, (low_x + CELL) * c) + np.maximum(low_y * s, (low_y + CELL) * s)
        inside &= within & (ahead > -BEHIND - MARGIN)
        cell = np.where(inside, i * self.shape[1] + j, 0)
        lens = np.where(inside, self.count[cell], 0).ravel()
        starts = self.start[cell].ravel()
        per_agent = lens.reshape(n, -1).sum(1)
        width = int(per_agent.max()) if n else 0
        index = np.zeros((n, width), dtype=np.int64)
        mask = np.zeros((n, width), dtype=bool)
        total = int(lens.sum())
        if total:
            k = np.arange(total)
            point = np.repeat(starts - (np.cumsum(lens) - lens), lens) + k
            agent = np.repeat(np.arange(n), per_agent)
            slot = k - np.repeat(np.cumsum(per_agent) - per_agent, per_agent)
            index[agent, slot], mask[agent, slot] = point, True
        return index, mask


def _local(points: np.ndarray, origin: np.ndarray) -> torch.Tensor:
    """``points [P,4]`` as float32, positions relative to ``origin``."""
    local = points.astype(np.float32)
    local[:, :2] = points[:, :2] - origin
    return torch.from_numpy(local)


_GRIDS: weakref.WeakKeyDictionary[Scenario, RoadGrid] = weakref.WeakKeyDictionary()


def road_grid_of(scene: Scenario) -> RoadGrid:
    """The :class:`RoadGrid` of ``scene``'s road points, built once per scene object."""
    grid = _GRIDS.get(scene)
    if grid is None:
        grid = _GRIDS[scene] = RoadGrid(road_points_of(scene))
    return grid


def grid_road_view(
    grids: list[RoadGrid | None], xyh: np.ndarray, valid: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`model.lanes.road_view` of agents at ``xyh [k,m,3]`` (``valid [k,m]``) of rows whose scenes'
    grids are ``grids`` (None: no road), each agent compared only with the points of the cells around it:
    features ``[k,m,R,6]`` and mask ``[k,m,R]`` (an invalid agent, or a row without a road, reads nothing).
    Positions are taken relative to each grid's corner, where float32 holds centimetres."""
    k, m = valid.shape
    feats = torch.zeros(k, m, ROAD_POINTS, POINT_FEATURES)
    mask = torch.zeros(k, m, ROAD_POINTS, dtype=torch.bool)
    by_grid: dict[int, list[int]] = {}
    for r, grid in enumerate(grids):
        if grid is not None and valid[r].any():
            by_grid.setdefault(id(grid), []).append(r)
    for rows in by_grid.values():  # rows of one scene (its rollouts) share one lookup
        grid = grids[rows[0]]
        assert grid is not None
        r, a = np.nonzero(valid[rows])
        r = np.asarray(rows)[r]
        states = xyh[r, a].copy()
        states[:, :2] -= grid.origin
        index, near = grid.near(xyh[r, a])
        points = grid.local[torch.from_numpy(index)]  # [n,K,4]
        f, got = road_view(
            points,
            torch.from_numpy(near),
            torch.from_numpy(states)[:, None],
            torch.ones(len(r), 1, dtype=torch.bool),
        )
        feats[r, a], mask[r, a] = f[:, 0], got[:, 0]
    return feats, mask
