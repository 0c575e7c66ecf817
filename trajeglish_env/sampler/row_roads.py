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

from trajeglish_env.model.lanes import POINT_FEATURES, ROAD_POINTS, near_states, road_points_of, road_view

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
        points, point_mask = _row_points(st, rows, xyh, valid)
        feats, mask = road_view(points, point_mask, torch.from_numpy(xyh), torch.from_numpy(valid))
        self.feats[rows], self.mask[rows] = feats, mask
        self.step[rows] = now


def _row_points(
    st: RowStates, rows: np.ndarray, xyh: np.ndarray, valid: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each row's scene road points near its agents ``xyh [k,m,3]`` (``valid [k,m]``), padded:
    ``[k,P,4]`` and mask ``[k,P]``."""
    near = []
    for i, b in enumerate(rows.tolist()):
        sc = st.scenes[b]
        points = road_points_of(sc) if sc is not None else np.zeros((0, 4))
        near.append(near_states(points, xyh[i][valid[i]][:, :2]))
    width = max(len(p) for p in near)
    points = np.zeros((len(rows), width, 4))
    point_mask = np.zeros((len(rows), width), dtype=bool)
    for i, p in enumerate(near):
        points[i, : len(p)], point_mask[i, : len(p)] = p, True
    return torch.from_numpy(points), torch.from_numpy(point_mask)


def _at(
    st: RowStates, rows: np.ndarray, agents: np.ndarray, steps: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """Features ``[k,R,6]`` of single positions: agent ``agents[i]`` of row ``rows[i]`` at ``steps[i]``."""
    xyh, valid = st.mxyh[rows, agents, steps], st.valid[rows, agents, steps]
    feats = torch.zeros(len(rows), ROAD_POINTS, POINT_FEATURES)
    mask = torch.zeros(len(rows), ROAD_POINTS, dtype=torch.bool)
    for b in np.unique(rows).tolist():  # one pass per row: its scene's points
        i = np.flatnonzero(rows == b)
        points, point_mask = _row_points(st, np.array([b]), xyh[i][None], valid[i][None])
        f, m = road_view(points, point_mask, torch.from_numpy(xyh[i])[None], torch.from_numpy(valid[i])[None])
        feats[i], mask[i] = f[0], m[0]
    return feats, mask
