"""A training-loss term against the probability a model puts on motion tokens that take a vehicle off the
road (issue 15).

Without the guard the model's vehicles leave the road in a third of the held-out highway-env rollouts
(roundabouts, merges, u-turns: it drives straight on where the road bends), and WOSAC weighs off-road a
quarter of the meta-metric. Guarded sampling masks such tokens at sampling time; ``train --offroad-weight
W`` teaches the model alone the same rule: at sampled target positions of vehicles (``positions`` per
window, drawn at random), the candidate tokens whose box would have a corner more than the guard's margin
beyond a road edge (or farther beyond it than the vehicle's box lies already) are found from the scene's
full road edges (:class:`~trajeglish_env.edge_cells.EdgeCells`, the env's rule number for number), and
``W * -log(1 - m)`` is added to the loss, ``m`` the model's probability on them (the colliding-mass term's
form, :func:`~trajeglish_env.training.blocked_mass.blocked_loss`). A logged position whose own token leaves
the road (highway-env's controllers cut the corners where they leave a roundabout) is left out, so the term
never pushes against the data; the model's own rolled-out tokens are no data and stay in. ``horizon`` H
(``train --offroad-horizon``) widens the rule from one step to H, as the colliding-mass term's: a move kept
up (the same template repeated: a constant turn) that takes a corner off the road within H steps counts too,
so a vehicle driving straight on where the road bends meets the term before its box reaches the edge.

The masks are computed where the windows are cut (the loading processes), so the training step only reads
them: ``offroad_slot [K]`` (-1: unused), ``offroad_step [K]`` and ``offroad_mask [K,D]`` per window.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from trajeglish_env.batch_geometry import edge_rows
from trajeglish_env.edge_cells import EdgeCells
from trajeglish_env.geometry import box_corners, to_global
from trajeglish_env.metrics.road_edges import RoadEdges
from trajeglish_env.scenario import ROAD_EDGE_KINDS, AgentKind, Scenario
from trajeglish_env.training.blocked_mass import BlockedCandidates

MARGIN = 0.5  # m: the env's reward margin (sampler.config.OFFROAD_MARGIN; training imports no sampler)


@dataclass(frozen=True)
class OffroadTerm:
    """Where the off-road term looks: ``positions`` vehicle target positions per window, candidates over
    the first ``drawn`` templates kept up ``horizon`` steps, a corner allowed ``margin`` m beyond a road
    edge (the guard's)."""

    positions: int = 32
    drawn: int = 384
    margin: float = MARGIN
    horizon: int = 1

    def __post_init__(self) -> None:
        if self.positions < 1:
            raise ValueError(f"OffroadTerm.positions must be >= 1 per window, got {self.positions}")
        if self.drawn < 1:
            raise ValueError(f"OffroadTerm.drawn must be >= 1 template, got {self.drawn}")
        if not self.margin >= 0:
            raise ValueError(f"OffroadTerm.margin must be >= 0 m, got {self.margin}")
        if self.horizon < 1:
            raise ValueError(f"OffroadTerm.horizon must be >= 1 step, got {self.horizon}")


_EDGES: weakref.WeakKeyDictionary[Scenario, tuple[np.ndarray, np.ndarray]] = weakref.WeakKeyDictionary()
_CELLS: list[EdgeCells] = []  # one per loading process, created on first use


def scene_edges(scene: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """The road-edge rows ``(columns [7,S], links [3,S])`` of a scene (``S = 0``: none), once per scene
    object (the cells are keyed by the identity of ``columns``)."""
    if scene not in _EDGES:
        lines = [p for p in scene.polylines(ROAD_EDGE_KINDS) if len(p) >= 2]
        _EDGES[scene] = edge_rows(RoadEdges.from_polylines(lines) if lines else None)
    return _EDGES[scene]


def _cells() -> EdgeCells:
    if not _CELLS:
        _CELLS.append(EdgeCells())
    return _CELLS[0]


def add_offroad_masks(
    windows: Sequence[dict[str, np.ndarray]],
    scenes: Sequence[Scenario],
    templates: np.ndarray,
    term: OffroadTerm,
    rngs: Sequence[np.random.Generator],
) -> None:
    """Add ``offroad_slot``, ``offroad_step`` and ``offroad_mask`` to each tokenized window (in place; the
    window cut from ``scenes[i]``, positions drawn with ``rngs[i]``) over ``templates [classes,D,3]``."""
    drawn = templates[:, : term.drawn]
    d = drawn.shape[1]
    for w, scene, rng in zip(windows, scenes, rngs, strict=True):
        k = term.positions
        slot, step, mask = np.full(k, -1, np.int64), np.zeros(k, np.int64), np.zeros((k, d), bool)
        w["offroad_slot"], w["offroad_step"], w["offroad_mask"] = slot, step, mask
        columns, links = scene_edges(scene)
        if not columns.shape[1]:
            continue
        vehicle = (w["agent_kind"] == AgentKind.VEHICLE) & w["agent_mask"]
        a, t = np.nonzero((w["tokens"] >= 0) & vehicle[:, None])
        if not len(a):
            continue
        pick = rng.choice(len(a), size=min(k, len(a)), replace=False)
        a, t = a[pick], t[pick]
        n = len(a)
        origin = to_global(w["frame"], w["agent_xyh"][a, t].astype(np.float64))  # [n,3] global
        size = w["agent_size"][a].astype(np.float64)
        moves = drawn[AgentKind.VEHICLE][None]  # [1,D,3]
        cand = [to_global(origin[:, None], moves)]  # [n,D,3] after one step
        for _ in range(1, term.horizon):  # the same move kept up from where the last one ended
            cand.append(to_global(cand[-1], moves))
        kept = np.stack(cand, axis=1)  # [n,H,D,3]
        corners = np.concatenate(
            [box_corners(origin, size)[:, None], box_corners(kept, size[:, None, None]).reshape(n, -1, 4, 2)],
            axis=1,
        )  # [n,1+H*D,4,2]: the box now, then its candidates at each step kept up
        cells = _cells()
        maps = np.full(corners.size // 2, cells.map_ids([(columns, links)])[0])
        padded = (columns[None], links[None], np.array([columns.shape[1]]))
        signed = cells.signed(maps, np.zeros(len(maps), np.int64), corners.reshape(-1, 2), padded)
        excess = signed.reshape(n, -1, 4).max(axis=-1)
        limit = np.maximum(term.margin, excess[:, 0])  # a box off the road may not go farther off
        worst = excess[:, 1:].reshape(n, term.horizon, d).max(axis=1)  # [n,D]: the farthest off over H
        slot[:n], step[:n], mask[:n] = a, t, worst > limit[:, None]


def offroad_candidates(batch: dict[str, torch.Tensor], drawn_targets: torch.Tensor) -> BlockedCandidates:
    """The positions of a collated batch's off-road masks that have some off-road candidate, less the
    logged positions whose own target token (``drawn_targets [B,A,T]``, as the model draws them) is one."""
    slot = batch["offroad_slot"].cpu().numpy()
    step = batch["offroad_step"].cpu().numpy()
    mask = batch["offroad_mask"].cpu().numpy()
    b, k = np.nonzero(slot >= 0)
    a, t, m = slot[b, k], step[b, k], mask[b, k]
    token = drawn_targets.cpu().numpy()[b, a, t]
    own = m[np.arange(len(b)), np.clip(token, 0, m.shape[1] - 1)] & (token < m.shape[1])
    logged = t < batch["logged_targets"].cpu().numpy()[b]
    keep = m.any(axis=1) & ~(own & logged)
    return BlockedCandidates(b[keep], a[keep], t[keep], m[keep])
