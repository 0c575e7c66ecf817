"""A training-loss term against the probability a model puts on colliding motion tokens (issue 15).

Guarded sampling masks, at sampling time, the candidate tokens whose box would overlap another agent: the
agents that acted before in the step at their next states, the others at their current ones. The model
alone has no such mask, and a small per-step probability on colliding tokens adds up over a rollout's 80
steps into the collisions the guard then has to catch. ``train --collision-weight W`` adds, for every
target token of a training window whose agent has some colliding candidate, ``W * -log(1 - m)`` to the
loss, ``m`` being the model's probability of its candidates that would collide in the logged scene
(unlikelihood training). Positions whose logged token collides itself (a log's overlap, or one the
tokenization makes) are left out, so the term never pushes against the data. The candidates, the
obstacles and the overlap rule are the guard's: :func:`blocked_candidates` finds them, vectorized over
the windows' (agent, obstacle, step) triples and the candidates near each obstacle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from trajeglish_env.geometry import to_global
from trajeglish_env.metrics.boxes import box_collisions

MAX_MASS = 0.99  # colliding mass above which a position adds a constant (a situation no token escapes)


@dataclass(frozen=True)
class BlockedCandidates:
    """Target positions ``(batch, agent, step)`` of a batch, each ``[Q]``, and ``mask [Q,D]``: their
    candidate tokens (of the drawn vocabulary, their agent's class) whose box would overlap an obstacle."""

    batch: np.ndarray
    agent: np.ndarray
    step: np.ndarray
    mask: np.ndarray

    @property
    def count(self) -> int:
        return len(self.batch)


def half_diagonal(size: np.ndarray) -> np.ndarray:
    """Radius of the circle around boxes of ``size [...,2]``."""
    return np.hypot(size[..., 0], size[..., 1]) / 2


def blocked_candidates(
    xyh: np.ndarray,
    valid: np.ndarray,
    size: np.ndarray,
    kind: np.ndarray,
    tokens: np.ndarray,
    templates: np.ndarray,
    logged: np.ndarray | None = None,
) -> BlockedCandidates:
    """The colliding candidates of windows ``xyh [B,A,S,3]`` (``valid [B,A,S]``, ``size [B,A,2]``, ``kind
    [B,A]``; slots in acting order) with targets ``tokens [B,A,T]`` (``T = S - 1``; -1: none) over the
    motion templates ``templates [classes,D,3]``. Agent ``a``'s candidates at step ``t`` start from its
    logged state there; an obstacle is any other agent present, at its state of ``t + 1`` when its slot acts
    before ``a``'s, else at ``t``, unless ``a``'s box overlaps it already (no move undoes that). Only
    positions with some colliding candidate are returned, and of the logged targets (the first ``logged
    [B]`` of each window; None: all) those whose own token does not collide: a model's rolled-out token
    that collides is not data, and its position is where the term matters most."""
    b_, a_, s_ = valid.shape
    t_ = tokens.shape[-1]
    if s_ != t_ + 1:
        raise ValueError(f"blocked_candidates: states of {s_} steps need {s_ - 1} target steps, got {t_}")
    xyh = np.asarray(xyh, np.float64)
    size = np.asarray(size, np.float64)
    cur, nxt = xyh[:, :, :t_], xyh[:, :, 1:]
    before = np.arange(a_)[None, :] < np.arange(a_)[:, None]  # [a, o]: slot o acts before slot a
    # every (b, a, o, t) with a target for a, o present where a sees it, near enough for some candidate
    move = np.hypot(templates[..., 0], templates[..., 1]).max(axis=1)  # per class
    reach = move[np.clip(kind, 0, len(move) - 1)] + half_diagonal(size)  # [B,A]
    seen_valid = np.where(before[None, :, :, None], valid[:, None, :, 1:], valid[:, None, :, :t_])
    target = tokens >= 0
    hd = half_diagonal(size)
    b, a, o, t = np.nonzero(
        target[:, :, None, :] & seen_valid & ~np.eye(a_, dtype=bool)[None, :, :, None]
    )  # candidates pairs, filtered by distance below
    obs = np.where(before[a, o][:, None], nxt[b, o, t], cur[b, o, t])
    origin = cur[b, a, t]
    near = np.hypot(*(obs[:, :2] - origin[:, :2]).T) < reach[b, a] + hd[b, o]
    b, a, o, t, obs, origin = b[near], a[near], o[near], t[near], obs[near], origin[near]
    # a box overlapping the obstacle already is left out, as by the guard
    free = ~box_collisions(origin, size[b, a], obs, size[b, o])
    b, a, o, t, obs, origin = b[free], a[free], o[free], t[free], obs[free], origin[free]
    empty = BlockedCandidates(*(np.zeros(0, np.int64),) * 3, np.zeros((0, templates.shape[1]), bool))
    if not len(b):
        return empty
    cls = np.clip(kind[b, a], 0, len(move) - 1)
    cand = to_global(origin[:, None], templates[cls])  # [P,D,3]
    limit = hd[b, a] + hd[b, o]
    dx, dy = cand[..., 0] - obs[:, None, 0], cand[..., 1] - obs[:, None, 1]
    p, v = np.nonzero(dx * dx + dy * dy < (limit * limit)[:, None])
    hit = box_collisions(cand[p, v], size[b[p], a[p]], obs[p], size[b[p], o[p]])
    p, v = p[hit], v[hit]
    # pairs -> positions (b, a, t)
    key = (b * a_ + a) * t_ + t
    positions, inverse = np.unique(key[p], return_inverse=True)
    mask = np.zeros((len(positions), templates.shape[1]), bool)
    mask[inverse, v] = True
    pb, rest = np.divmod(positions, a_ * t_)
    pa, pt = np.divmod(rest, t_)
    token = tokens[pb, pa, pt]
    own = mask[np.arange(len(positions)), np.clip(token, 0, mask.shape[1] - 1)] & (token < mask.shape[1])
    data = np.ones(len(positions), bool) if logged is None else pt < np.asarray(logged)[pb]
    keep = ~(own & data)
    return BlockedCandidates(pb[keep], pa[keep], pt[keep], mask[keep])


def blocked_loss(logits: torch.Tensor, blocked: BlockedCandidates) -> torch.Tensor:
    """Sum over ``blocked``'s positions of ``-log(1 - m)``, ``m`` the probability ``logits [B,T,A,D]`` put on
    their colliding candidates (a 0-d tensor; 0 when there are none)."""
    if not blocked.count:
        return logits.sum() * 0.0
    dev = logits.device
    index = [torch.from_numpy(x).to(dev) for x in (blocked.batch, blocked.step, blocked.agent)]
    lg = logits[index[0], index[1], index[2]].float()  # [Q,D]
    logp = torch.log_softmax(lg, dim=-1)
    mask = torch.from_numpy(blocked.mask).to(dev)
    log_m = torch.logsumexp(logp.masked_fill(~mask, float("-inf")), dim=-1)
    # -log(1 - m) from log m; where nearly every candidate collides (m > MAX_MASS) there is nothing to learn
    # and the term is a constant (no gradient), so such positions cannot swamp the batch
    return -torch.log(-torch.expm1(log_m.clamp(max=math.log(MAX_MASS)))).sum()


def logged_weights(batch: dict[str, torch.Tensor], weights: torch.Tensor | None) -> torch.Tensor | None:
    """The likelihood weights ``[B,A,T]`` of a batch with its rolled-out targets weighed 0 (those past each
    window's ``logged_targets``: a model's own tokens are not data), ``weights`` kept elsewhere (None: 1)."""
    logged = batch.get("logged_targets")
    tokens = batch["tokens"]
    steps = tokens.shape[-1]
    if logged is None or bool((logged >= steps).all()):
        return weights
    keep = (torch.arange(steps, device=tokens.device)[None, None, :] < logged[:, None, None]).float()
    return keep.expand(tokens.shape) if weights is None else weights * keep


def batch_blocked(
    model: torch.nn.Module, batch: dict[str, torch.Tensor], templates: np.ndarray
) -> BlockedCandidates:
    """:func:`blocked_candidates` of a collated training batch, targets as the model draws them."""
    kind = batch["agent_kind"]
    targets = model.drawn_targets(batch["tokens"], kind[:, :, None])
    valid = batch["agent_valid"] & batch["agent_mask"][..., None]
    return blocked_candidates(
        batch["agent_xyh"].cpu().numpy(),
        valid.cpu().numpy(),
        batch["agent_size"].cpu().numpy(),
        kind.cpu().numpy(),
        targets.cpu().numpy(),
        templates,
        None if "logged_targets" not in batch else batch["logged_targets"].cpu().numpy(),
    )
