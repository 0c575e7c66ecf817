"""The road around each agent of the sampler's rows (models with ``lane_input``; :mod:`model.lanes`).

A position reads the road around its agent's state at its step. Every decoding call of a step reads the
states of that step, so the features of all agents of a row at its current step are computed once, at the
first call that needs them, and gathered by the later ones (a step's states do not change while it is
decoded). Look-ahead positions (:mod:`~trajeglish_env.sampler.parallel`) read the next step's states as
the drafts give them. Each agent's features last computed are kept with the state they were computed at,
and reused wherever the agent is at exactly that state again (features are a function of the agent's
state alone): by the next look-ahead of the step, at the next step where the drafts held, and at every
step an agent stands still. Positions of earlier steps (a window
being primed) are computed as they come.
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
    none): ``feats [B,N,R,6]`` and ``mask [B,N,R]``; and each agent's features last computed
    (``kept_feats``/``kept_mask``), at the state ``kept_at [B,N,3]`` (NaN: none)."""

    def __init__(self, rows: int):
        self.step = np.full(rows, -1, dtype=np.int64)
        self._size(0)

    def _size(self, agents: int) -> None:
        """Empty buffers for ``agents`` agents a row."""
        rows = len(self.step)
        self.feats = torch.zeros(rows, agents, ROAD_POINTS, POINT_FEATURES)
        self.mask = torch.zeros(rows, agents, ROAD_POINTS, dtype=torch.bool)
        self.kept_feats, self.kept_mask = self.feats.clone(), self.mask.clone()
        self.kept_at = np.full((rows, agents, 3), np.nan)
        self.step[:] = -1

    def reset(self, rows: np.ndarray) -> None:
        """Forget the features of ``rows`` (restarted, or given another row's states)."""
        self.step[rows] = -1
        self.kept_at[rows] = np.nan

    def features(
        self, st: RowStates, rows: np.ndarray, agents: np.ndarray, steps: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Features ``[r,n,R,6]`` and mask ``[r,n,R]`` of agents ``agents [r,n]`` (-1: padding, reads
        nothing) of ``rows [r]`` at steps ``steps [r,n]``, from the model's states ``st.mxyh``."""
        if self.feats.shape[1] != st.N:  # the rows grew: start afresh
            self._size(st.N)
        r, n = agents.shape
        feats = torch.zeros(r, n, ROAD_POINTS, POINT_FEATURES)
        mask = torch.zeros(r, n, ROAD_POINTS, dtype=torch.bool)
        real = agents >= 0
        now = st.now[rows][:, None]
        current = real & (steps == now)
        if current.any():
            self._fill(st, np.unique(rows[current.any(1)]))
            i, j = np.nonzero(current)
            feats[i, j], mask[i, j] = self.feats[rows[i], agents[i, j]], self.mask[rows[i], agents[i, j]]
        ahead = real & (steps == now + 1)
        if ahead.any():
            i, j = np.nonzero(ahead)
            feats[i, j], mask[i, j] = self._kept(st, rows[i], agents[i, j], steps[i, j])
        earlier = real & ~current & ~ahead
        if earlier.any():
            i, j = np.nonzero(earlier)
            feats[i, j], mask[i, j] = _at(st, rows[i], agents[i, j], steps[i, j])
        return feats, mask

    def _fill(self, st: RowStates, rows: np.ndarray) -> None:
        """Compute the features of every agent of ``rows`` at their current step where not done yet (the
        kept ones where an agent stands at their state: drafts that held, agents standing still)."""
        rows = rows[self.step[rows] != st.now[rows]]
        if not len(rows):
            return
        now = st.now[rows]
        xyh, valid = st.mxyh[rows, :, now], st.valid[rows, :, now]  # [k,N,3], [k,N]
        hit = valid & (xyh == self.kept_at[rows]).all(-1)
        k, a = np.nonzero(hit)
        rk = rows[k]
        self.feats[rk, a], self.mask[rk, a] = self.kept_feats[rk, a], self.kept_mask[rk, a]
        k, a = np.nonzero(~valid)
        self.feats[rows[k], a], self.mask[rows[k], a] = 0.0, False
        k, a = np.nonzero(valid & ~hit)
        if len(k):
            got, got_mask = _view(st, rows[k], xyh[k, a, None], np.ones((len(k), 1), bool))
            self.feats[rows[k], a], self.mask[rows[k], a] = got[:, 0], got_mask[:, 0]
            self.kept_feats[rows[k], a], self.kept_mask[rows[k], a] = got[:, 0], got_mask[:, 0]
            self.kept_at[rows[k], a] = xyh[k, a]
        self.step[rows] = now

    def _kept(
        self, st: RowStates, rows: np.ndarray, agents: np.ndarray, steps: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Features ``[k,R,6]`` of single positions (agent ``agents[i]`` of row ``rows[i]`` at ``steps[i]``),
        taken from the kept ones where the agent is at their state, else computed and kept."""
        xyh, valid = st.mxyh[rows, agents, steps], st.valid[rows, agents, steps]
        hit = valid & (xyh == self.kept_at[rows, agents]).all(-1)
        miss = np.flatnonzero(valid & ~hit)
        if len(miss):
            got, got_mask = _view(st, rows[miss], xyh[miss, None], valid[miss, None])
            self.kept_feats[rows[miss], agents[miss]] = got[:, 0]
            self.kept_mask[rows[miss], agents[miss]] = got_mask[:, 0]
            self.kept_at[rows[miss], agents[miss]] = xyh[miss]
        ok = torch.from_numpy(valid)
        feats = torch.where(ok[:, None, None], self.kept_feats[rows, agents], 0.0)
        return feats, self.kept_mask[rows, agents] & ok[:, None]


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
