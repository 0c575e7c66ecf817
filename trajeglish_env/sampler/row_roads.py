"""The road around each agent of the sampler's rows (models with ``lane_input``; :mod:`model.lanes`).

A position reads the road around its agent's state at its step. Every decoding call of a step reads the
states of that step, so the features of all agents of a row at its current step are computed once, at the
first call that needs them, and gathered by the later ones (a step's states do not change while it is
decoded); positions of earlier steps (a window being primed) are computed as they come.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from trajeglish_env.model.lanes import POINT_FEATURES, ROAD_POINTS
from trajeglish_env.sampler.road_grid import grid_road_view, road_grid_of

if TYPE_CHECKING:
    from trajeglish_env.sampler.rows import RowStates


class RowRoads:
    """Road features of every agent of each row at the step ``step [B]`` they were computed at (-1:
    none): ``feats [B,N,R,6]`` and ``mask [B,N,R]``."""

    def __init__(self, rows: int):
        self.step = np.full(rows, -1, dtype=np.int64)
        self.feats = torch.zeros(rows, 0, ROAD_POINTS, POINT_FEATURES)
        self.mask = torch.zeros(rows, 0, ROAD_POINTS, dtype=torch.bool)

    def reset(self, rows: np.ndarray) -> None:
        """Forget the features of ``rows`` (restarted, or given another row's states)."""
        self.step[rows] = -1

    def features(
        self, st: RowStates, rows: np.ndarray, agents: np.ndarray, steps: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Features ``[r,n,R,6]`` and mask ``[r,n,R]`` of agents ``agents [r,n]`` (-1: padding, reads
        nothing) of ``rows [r]`` at steps ``steps [r,n]``, from the model's states ``st.mxyh``."""
        r, n = agents.shape
        feats = torch.zeros(r, n, ROAD_POINTS, POINT_FEATURES)
        mask = torch.zeros(r, n, ROAD_POINTS, dtype=torch.bool)
        real = agents >= 0
        current = real & (steps == st.now[rows][:, None])
        if current.any():
            self._fill(st, np.unique(rows[current.any(1)]))
            i, j = np.nonzero(current)
            feats[i, j], mask[i, j] = self.feats[rows[i], agents[i, j]], self.mask[rows[i], agents[i, j]]
        earlier = real & ~current
        if earlier.any():
            i, j = np.nonzero(earlier)
            got = _at(st, rows[i], agents[i, j], steps[i, j])
            feats[i, j], mask[i, j] = got
        return feats, mask

    def _fill(self, st: RowStates, rows: np.ndarray) -> None:
        """Compute the features of every agent of ``rows`` at their current step where not done yet."""
        if self.feats.shape[1] != st.N:  # the rows grew: start afresh
            self.feats = torch.zeros(len(self.step), st.N, ROAD_POINTS, POINT_FEATURES)
            self.mask = torch.zeros(len(self.step), st.N, ROAD_POINTS, dtype=torch.bool)
            self.step[:] = -1
        rows = rows[self.step[rows] != st.now[rows]]
        if not len(rows):
            return
        now = st.now[rows]
        xyh, valid = st.mxyh[rows, :, now], st.valid[rows, :, now]  # [k,N,3], [k,N]
        self.feats[rows], self.mask[rows] = _view(st, rows, xyh, valid)
        self.step[rows] = now


def _view(
    st: RowStates, rows: np.ndarray, xyh: np.ndarray, valid: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """Road features ``[k,m,R,6]`` and mask of agents at ``xyh [k,m,3]`` (``valid [k,m]``) of ``rows [k]``,
    each read from the road points of the grid cells around it (:mod:`sampler.road_grid`)."""
    grids = [road_grid_of(st.scenes[b]) if st.scenes[b] is not None else None for b in rows.tolist()]
    return grid_road_view(grids, xyh, valid)


def _at(
    st: RowStates, rows: np.ndarray, agents: np.ndarray, steps: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """Features ``[k,R,6]`` of single positions: agent ``agents[i]`` of row ``rows[i]`` at ``steps[i]``."""
    xyh, valid = st.mxyh[rows, agents, steps], st.valid[rows, agents, steps]
    feats, mask = _view(st, rows, xyh[:, None], valid[:, None])
    return feats[:, 0], mask[:, 0]
