"""Closed-loop training windows (CAT-K: closed-loop supervised fine-tuning of tokenized traffic models).

Teacher forcing only ever shows the model logged (or slightly noisy) histories, so in its own rollouts it
meets states it never learned to recover from: a vehicle a little off its lane keeps drifting. CAT-K rolls
each training window out with the model being trained, taking at every (step, agent) the one of its
``top_k`` most likely tokens whose next box lies nearest (mean corner distance) the logged next state; the
window is then trained with those rolled-out tokens as inputs and, as targets, the tokens that lead from
the rolled-out states back toward the log (:func:`recovery_aims`: a 0.1 s token closes a share of the
offset, not all of it as CAT-K's 0.5 s tokens do). The rollout follows the model's own decoding order
(agents one at a time within a step, through the decoder cache), so inputs are exactly what the model would
have produced. Results: docs/evaluation.md, "Closed-loop fine-tuning (CAT-K) on this machine".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from trajeglish_env.geometry import to_global, to_local
from trajeglish_env.model.lanes import road_view
from trajeglish_env.model.masks import START, input_shift
from trajeglish_env.model.neighbours import NeighbourView, neighbour_view
from trajeglish_env.model.network import SceneInputs, TrajeglishModel
from trajeglish_env.tokenizer.distance import corner_distance
from trajeglish_env.tokenizer.nearest import nearest_templates
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary


@dataclass(frozen=True)
class ClosedLoopConfig:
    """CAT-K settings: ``top_k`` tokens the rollout chooses among. Targets close ``recovery`` of the
    rolled-out state's sideways and heading offset from the log per step (1: all at once, as CAT-K with its
    0.5 s tokens; a 0.1 s token cannot close a metre in one step, so the default spreads it over about half
    a second) and ``along_recovery`` of its offset along the log's heading (0: the target moves as the log
    does and keeps the offset; the same share as sideways returns every agent toward its log at one rate, so
    the gaps between rolled-out neighbours return toward the logged ones: fewer collisions, measured);
    offsets beyond ``max_drift`` metres are not trained on. ``teacher_forced``: the batch keeps its
    teacher-forced windows beside the closed-loop ones, so the log's own likelihood stays trained."""

    top_k: int = 5
    recovery: float = 0.2
    along_recovery: float = 0.2
    max_drift: float = 2.0
    teacher_forced: bool = True

    def __post_init__(self) -> None:
        if self.top_k < 1:
            raise ValueError(f"ClosedLoopConfig.top_k must be >= 1, got {self.top_k}")
        if not 0.0 < self.recovery <= 1.0:
            raise ValueError(f"ClosedLoopConfig.recovery must be in (0, 1], got {self.recovery}")
        if not 0.0 <= self.along_recovery <= 1.0:
            raise ValueError(f"ClosedLoopConfig.along_recovery must be in [0, 1], got {self.along_recovery}")
        if not self.max_drift > 0.0:
            raise ValueError(f"ClosedLoopConfig.max_drift must be > 0 metres, got {self.max_drift}")


def _anchors(valid: np.ndarray) -> np.ndarray:
    """``[..., S]`` True at the first step of every valid run (states taken from the log there)."""
    anchored = valid.copy()
    anchored[..., 1:] &= ~valid[..., :-1]
    return anchored


@torch.no_grad()
def closed_loop_rollout(
    model: TrajeglishModel, batch: dict[str, torch.Tensor], vocabulary: MotionVocabulary, top_k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Roll a collated batch of windows out with ``model`` (top-``k`` tokens nearest the log).

    Returns the rolled-out tokens ``[B,A,T]`` (class-local, -1 where the log has no transition) and states
    ``[B,A,S,3]`` (window frame; NaN where the agent is not present). Runs in eval mode, without gradients.
    """
    scene = SceneInputs.from_batch(batch)
    logged = batch["agent_xyh"].detach().cpu().double().numpy()  # [B,A,S,3]
    valid = (batch["agent_valid"] & batch["agent_mask"][..., None]).cpu().numpy()
    size = batch["agent_size"].detach().cpu().double().numpy()
    kind = batch["agent_kind"].cpu().numpy()
    b, a, s = valid.shape
    moving = valid[..., :-1] & valid[..., 1:]  # [B,A,T] the log has a transition t -> t+1
    anchored = _anchors(valid)
    states = np.where(anchored[..., None], logged, np.nan)
    tokens = np.full((b, a, s - 1), -1, dtype=np.int64)
    k = min(top_k, model.cfg.drawn)
    was_training = model.training
    model.eval()
    try:
        dtype = next(model.parameters()).dtype
        cache = model.empty_cache(b, dtype)
        agents = model.encode_into(cache, scene)
        dev = agents.device
        kind_t = scene.agent_kind
        joint = np.where(tokens >= 0, tokens + kind[:, :, None] * model.cfg.vocab_size, -1)
        shift = input_shift(model.cfg.variant, a)
        start, count = np.zeros(b, dtype=np.int64), np.ones(b, dtype=np.int64)
        rows_all = np.arange(b)
        for t in range(s - 1):
            view = _step_view(model, states, size, t, batch)
            for slot in range(a):
                p = t * a + slot
                q = p - shift
                carried = np.full(b, START) if q < 0 else joint[:, q % a, q // a]
                own = np.full(b, -1) if t == 0 else joint[:, slot, t - 1]
                start[:] = p
                hidden = model.decode_at(
                    cache,
                    agents,
                    torch.from_numpy(carried[:, None]).to(dev),
                    torch.from_numpy(own[:, None]).to(dev),
                    start,
                    count,
                    None if view is None else view.index(slice(None), slice(slot, slot + 1)),
                )
                rows = rows_all[moving[:, slot, t]]
                if not len(rows):
                    continue
                logits = model.class_logits(hidden[rows, 0], kind_t[rows, slot])  # [r,V]
                cand = logits.float().topk(k, dim=-1).indices.cpu().numpy()  # [r,k]
                moved = to_global(
                    states[rows, slot, t][:, None], vocabulary.templates[kind[rows, slot][:, None], cand]
                )
                dist = corner_distance(moved, logged[rows, slot, t + 1][:, None], size[rows, slot][:, None])
                pick = np.argmin(dist, axis=1)
                chosen = cand[np.arange(len(rows)), pick]
                tokens[rows, slot, t] = chosen
                joint[rows, slot, t] = chosen + kind[rows, slot] * model.cfg.vocab_size
                keep = ~anchored[rows, slot, t + 1]
                states[rows[keep], slot, t + 1] = moved[np.arange(len(rows)), pick][keep]
    finally:
        model.train(was_training)
    return tokens, states


def _step_road(
    batch: dict[str, torch.Tensor], states: np.ndarray, t: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Road features ``[B,A,R,6]`` and mask of the agents at step ``t`` of the rollout's states (NaN:
    absent), from the windows' road points (``road_source``, :func:`~trajeglish_env.model.lanes.
    window_road_source`)."""
    cur = torch.from_numpy(np.nan_to_num(states[:, :, t]))
    ok = torch.from_numpy(~np.isnan(states[:, :, t, 0]))
    points = batch["road_source"].detach().cpu().double()
    return road_view(points, batch["road_source_mask"].cpu(), cur, ok)


def rolled_out_road(batch: dict[str, torch.Tensor], states: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Road features ``[B,T,A,R,6]`` and mask of a closed-loop rollout's states ``[B,A,S,3]`` at its input
    steps (the windows' ``road_points`` / ``road_mask`` where the rollout put the agents)."""
    steps = batch["input_tokens"].shape[-1]
    feats, mask = zip(*(_step_road(batch, states, t) for t in range(steps)), strict=True)
    return torch.stack(feats, dim=1), torch.stack(mask, dim=1)


def _step_view(
    model: TrajeglishModel, states: np.ndarray, size: np.ndarray, t: int, batch: dict[str, torch.Tensor]
) -> NeighbourView | None:
    """Features ``[B,A]`` at step ``t`` of the rollout's states (NaN: absent), as the sampler computes them;
    None for a model that reads no states."""
    if not model.cfg.reads_states:
        return None
    cur = torch.from_numpy(np.nan_to_num(states[:, :, t]))
    ok = torch.from_numpy(~np.isnan(states[:, :, t, 0]))
    before = max(t - 1, 0)
    prev = torch.from_numpy(np.nan_to_num(states[:, :, before]))
    prev_ok = torch.from_numpy(~np.isnan(states[:, :, before, 0])) & (t > 0)
    view = neighbour_view(cur, ok, prev, prev_ok, torch.from_numpy(size))
    if model.cfg.lane_input:
        view = NeighbourView(view.own, view.pairs, view.mask, *_step_road(batch, states, t))
    return view.to(model.start.device)


def recovery_aims(states: np.ndarray, logged: np.ndarray, config: ClosedLoopConfig) -> np.ndarray:
    """Where targets aim, ``[B,A,T,3]``: the rolled-out state's offset from the log at ``t`` (in the log's
    frame), shrunk by ``recovery`` sideways and in heading and by ``along_recovery`` along the log, carried
    into the log's frame at ``t + 1``."""
    offset = to_local(logged[..., :-1, :], states[..., :-1, :])
    keep = np.array([1.0 - config.along_recovery, 1.0 - config.recovery, 1.0 - config.recovery])
    return to_global(logged[..., 1:, :], keep * offset)


def recovery_targets(
    vocabulary: MotionVocabulary,
    states: np.ndarray,
    logged: np.ndarray,
    moving: np.ndarray,
    size: np.ndarray,
    kind: np.ndarray,
    config: ClosedLoopConfig,
) -> np.ndarray:
    """Targets ``[B,A,T]``: the argmin template (mean corner distance with the agent's box) from the
    rolled-out state at ``t`` to its :func:`recovery_aims`; ``-1`` where ``moving`` is False or the
    rolled-out state lies more than ``max_drift`` metres from the log (nothing sensible to learn there)."""
    targets = np.full(moving.shape, -1, dtype=np.int64)
    near = np.linalg.norm(states[..., :-1, :2] - logged[..., :-1, :2], axis=-1) <= config.max_drift
    bi, ai, ti = np.nonzero(moving & near)
    aim = recovery_aims(states, logged, config)[bi, ai, ti]
    local = to_local(states[bi, ai, ti], aim)
    for k in np.unique(kind[bi, ai]).tolist():
        sel = kind[bi, ai] == k
        index, _ = nearest_templates(vocabulary.search_tables[k], local[sel], size[bi[sel], ai[sel]])
        targets[bi[sel], ai[sel], ti[sel]] = index
    return targets


def closed_loop_batch(
    model: TrajeglishModel,
    batch: dict[str, torch.Tensor],
    vocabulary: MotionVocabulary,
    config: ClosedLoopConfig,
) -> dict[str, torch.Tensor]:
    """``batch`` with ``input_tokens`` replaced by the model's top-``k`` closed-loop rollout and ``tokens``
    (targets) by the tokens that return from it to the log (see the module docstring); with
    ``config.teacher_forced`` these windows follow the batch's own (twice the rows)."""
    tokens, states = closed_loop_rollout(model, batch, vocabulary, config.top_k)
    valid = (batch["agent_valid"] & batch["agent_mask"][..., None]).cpu().numpy()
    targets = recovery_targets(
        vocabulary,
        states,
        batch["agent_xyh"].detach().cpu().double().numpy(),
        valid[..., :-1] & valid[..., 1:],
        batch["agent_size"].detach().cpu().double().numpy(),
        batch["agent_kind"].cpu().numpy(),
        config,
    )
    dev = batch["tokens"].device
    closed = dict(batch)
    closed["input_tokens"] = torch.from_numpy(tokens).to(dev)
    closed["tokens"] = torch.from_numpy(targets).to(dev)
    if model.cfg.reads_states:  # the rolled-out windows' states (neighbours, interaction and bend weights)
        logged = batch["agent_xyh"]
        rolled = torch.from_numpy(states).to(device=dev, dtype=logged.dtype)
        closed["agent_xyh"] = torch.where(torch.isnan(rolled), logged, rolled)
    if model.cfg.lane_input:  # and the road around them there
        road, road_mask = rolled_out_road(batch, states)
        closed["road_points"], closed["road_mask"] = road.to(dev), road_mask.to(dev)
    if not config.teacher_forced:
        return closed
    return {k: torch.cat([v, closed[k]]) for k, v in batch.items()}
