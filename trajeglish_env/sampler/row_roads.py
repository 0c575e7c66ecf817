"""The road around each agent of the sampler's rows, encoded (models with ``lane_input``; :mod:`model.lanes`).

A position reads the road around its agent's state at its step, through the model's lane encoder, whose
output depends on that position alone. Every decoding call of a step reads the states of that step, so the
codes of all agents of a row at its current step are computed once, at the first call that needs them,
and gathered by the later ones (a step's states do not change while it is decoded, nor after), and kept for
the steps a new window primes. Look-ahead positions (:mod:`~trajeglish_env.sampler.parallel`) read the
next step's states as the drafts give them. Each agent's code last computed is kept with the state it was
computed at, and reused wherever the agent is at exactly that state again (the road features are a
function of the agent's state alone): by the next look-ahead of the step, at the next step where the
drafts held, and at every step an agent stands still. Positions of steps never played (a row's logged
history, primed by its first window) are computed as they come.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import torch

from trajeglish_env.model.lanes import POINT_FEATURES, ROAD_POINTS
from trajeglish_env.sampler.road_grid import grid_road_view, road_grid_of

if TYPE_CHECKING:
    from trajeglish_env.sampler.rows import RowStates

Encoder = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # road features [n,R,6], mask -> codes [n,C]


class RowRoads:
    """Road codes of every agent of each row at its last ``depth`` steps, in ring slots (a step's slot:
    step % depth): ``code [B,N,D,C]`` and ``held [B,D]``, the step a slot holds (-1: none); and each
    agent's code last computed, ``kept [B,N,C]``, at the state ``kept_at [B,N,3]`` (NaN: none).
    ``encode``: the model's lane encoder (``width`` channels, on ``device``, where the codes are kept);
    ``depth``: the steps a new window primes, plus one (its step), so priming reads them instead of
    computing them again."""

    def __init__(self, rows: int, encode: Encoder, width: int, device: torch.device, depth: int = 1):
        self.encode, self.width, self.device, self.depth = encode, width, device, max(1, depth)
        self.held = np.full((rows, self.depth), -1, dtype=np.int64)
        self._empty: torch.Tensor | None = None
        self._size(0)

    def _size(self, agents: int) -> None:
        """Empty buffers for ``agents`` agents a row."""
        rows = len(self.held)
        self.code = torch.zeros(rows, agents, self.depth, self.width, device=self.device)
        self.kept = torch.zeros(rows, agents, self.width, device=self.device)
        self.kept_at = np.full((rows, agents, 3), np.nan)
        self.held[:] = -1

    def reset(self, rows: np.ndarray) -> None:
        """Forget the codes of ``rows`` (restarted, or given another row's states)."""
        self.held[rows] = -1
        self.kept_at[rows] = np.nan

    def codes(self, st: RowStates, rows: np.ndarray, agents: np.ndarray, steps: np.ndarray) -> torch.Tensor:
        """Codes ``[r,n,C]`` of agents ``agents [r,n]`` (-1: padding, reads no road) of ``rows [r]`` at
        steps ``steps [r,n]``, from the model's states ``st.mxyh``."""
        if self.code.shape[1] != st.N:  # the rows grew: start afresh
            self._size(st.N)
        r, n = agents.shape
        out = self.empty().expand(r, n, -1).clone()
        real = agents >= 0
        now = st.now[rows][:, None]
        current = real & (steps == now)
        if current.any():
            self._fill(st, np.unique(rows[current.any(1)]))
        ahead = real & (steps == now + 1)
        if ahead.any():
            i, j = np.nonzero(ahead)
            out[i, j] = self._kept(st, rows[i], agents[i, j], steps[i, j])
        slot = steps % self.depth
        held = real & ~ahead & (self.held[rows[:, None], slot] == steps)  # the current step's among them
        if held.any():
            i, j = np.nonzero(held)
            out[i, j] = self.code[rows[i], agents[i, j], slot[i, j]]
        earlier = real & ~ahead & ~held
        earlier[earlier] = st.valid[rows[:, None], np.maximum(agents, 0), steps][earlier]  # else no road
        if earlier.any():
            i, j = np.nonzero(earlier)
            out[i, j] = self._encode_at(st, rows[i], st.mxyh[rows[i], agents[i, j], steps[i, j]])
        return out

    def empty(self) -> torch.Tensor:
        """The code ``[C]`` of a position that reads no road (no point near, or no agent)."""
        if self._empty is None:
            none = torch.zeros(1, ROAD_POINTS, POINT_FEATURES, device=self.device)
            mask = torch.zeros(1, ROAD_POINTS, dtype=torch.bool, device=self.device)
            self._empty = self.encode(none, mask)[0].float()
        return self._empty

    def _fill(self, st: RowStates, rows: np.ndarray) -> None:
        """Encode every agent of ``rows`` at their current step where not done yet (the kept codes where an
        agent stands at their state: drafts that held, agents standing still)."""
        slot = st.now[rows] % self.depth
        todo = self.held[rows, slot] != st.now[rows]
        rows, slot = rows[todo], slot[todo]
        if not len(rows):
            return
        now = st.now[rows]
        xyh, valid = st.mxyh[rows, :, now], st.valid[rows, :, now]  # [k,N,3], [k,N]
        hit = valid & (xyh == self.kept_at[rows]).all(-1)
        k, a = np.nonzero(hit)
        self.code[rows[k], a, slot[k]] = self.kept[rows[k], a]
        k, a = np.nonzero(~valid)
        self.code[rows[k], a, slot[k]] = self.empty()
        k, a = np.nonzero(valid & ~hit)
        if len(k):
            got = self._encode_at(st, rows[k], xyh[k, a])
            self.code[rows[k], a, slot[k]] = got
            self.kept[rows[k], a], self.kept_at[rows[k], a] = got, xyh[k, a]
        self.held[rows, slot] = now

    def _kept(self, st: RowStates, rows: np.ndarray, agents: np.ndarray, steps: np.ndarray) -> torch.Tensor:
        """Codes ``[k,C]`` of single positions (agent ``agents[i]`` of row ``rows[i]`` at ``steps[i]``), the
        kept ones where the agent is at their state, else computed and kept."""
        xyh, valid = st.mxyh[rows, agents, steps], st.valid[rows, agents, steps]
        hit = valid & (xyh == self.kept_at[rows, agents]).all(-1)
        miss = np.flatnonzero(valid & ~hit)
        if len(miss):
            got = self._encode_at(st, rows[miss], xyh[miss])
            self.kept[rows[miss], agents[miss]], self.kept_at[rows[miss], agents[miss]] = got, xyh[miss]
        ok = torch.from_numpy(valid).to(self.device)[:, None]
        return torch.where(ok, self.kept[rows, agents], self.empty())

    def _encode_at(self, st: RowStates, rows: np.ndarray, xyh: np.ndarray) -> torch.Tensor:
        """Codes ``[k,C]`` of single agents at states ``xyh [k,3]`` of ``rows [k]``."""
        feats, mask = road_features(st, rows, xyh[:, None], np.ones((len(rows), 1), bool))
        return self.encode(feats[:, 0].to(self.device), mask[:, 0].to(self.device)).float()


def road_features(
    st: RowStates, rows: np.ndarray, xyh: np.ndarray, valid: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """Road features ``[k,m,R,6]`` and mask of agents at ``xyh [k,m,3]`` (``valid [k,m]``) of ``rows [k]``,
    each read from the road points of the grid cells around it (:mod:`sampler.road_grid`)."""
    grids = [road_grid_of(st.scenes[b]) if st.scenes[b] is not None else None for b in rows.tolist()]
    return grid_road_view(grids, xyh, valid)
