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
the windows' (agent, obstacle, step) triples and the candidates near each obstacle. ``horizon`` H (``train
--collision-horizon``) widens the rule from one step to H: a move kept up that runs into an agent's
window states of the next H steps counts too, since most collisions of the model alone are set up steps
before the last move that makes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from trajeglish_env.geometry import to_global
from trajeglish_env.metrics.boxes import box_collisions

# what batch_blocked reads of a batch
TERM_KEYS = ("agent_kind", "tokens", "agent_valid", "agent_mask", "agent_xyh", "agent_size", "logged_targets")
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
    horizon: int = 1,
    rolled_out_only: bool = False,
) -> BlockedCandidates:
    """The colliding candidates of windows ``xyh [B,A,S,3]`` (``valid [B,A,S]``, ``size [B,A,2]``, ``kind
    [B,A]``; slots in acting order) with targets ``tokens [B,A,T]`` (``T = S - 1``; -1: none) over the
    motion templates ``templates [classes,D,3]``. Agent ``a``'s candidates at step ``t`` start from its
    logged state there; an obstacle is any other agent present, at its state of ``t + 1`` when its slot acts
    before ``a``'s, else at ``t``, unless ``a``'s box overlaps it already (no move undoes that). Only
    positions with some colliding candidate are returned, and of the logged targets (the first ``logged
    [B]`` of each window; None: all) those whose own token does not collide: a model's rolled-out token
    that collides is not data, and its position is where the term matters most.

    ``horizon`` H > 1 also counts a candidate as colliding when, kept up (the same move repeated: constant
    speed and turn rate), it overlaps an obstacle at the obstacle's window state of ``t + h``, h = 2 .. H
    (within the window): a collision course one token ahead of which no single move escapes.

    ``rolled_out_only``: only the targets past ``logged`` (a model's own rolled-out states) count, so the
    logged targets are left to the likelihood alone and keep the log's kinematics."""
    b_, a_, s_ = valid.shape
    t_ = tokens.shape[-1]
    if s_ != t_ + 1:
        raise ValueError(f"blocked_candidates: states of {s_} steps need {s_ - 1} target steps, got {t_}")
    if horizon < 1:
        raise ValueError(f"blocked_candidates: horizon must be >= 1 step, got {horizon}")
    xyh = np.asarray(xyh, np.float64)
    size = np.asarray(size, np.float64)
    cur, nxt = xyh[:, :, :t_], xyh[:, :, 1:]
    before = np.arange(a_)[None, :] < np.arange(a_)[:, None]  # [a, o]: slot o acts before slot a
    move = np.hypot(templates[..., 0], templates[..., 1]).max(axis=1)  # per class
    hd = half_diagonal(size)
    reach1 = move[np.clip(kind, 0, len(move) - 1)]  # [B,A]: farthest one-step move
    target = tokens >= 0
    if rolled_out_only:
        if logged is None:
            raise ValueError("blocked_candidates: rolled_out_only needs the windows' logged target counts")
        target &= np.arange(t_)[None, None, :] >= np.asarray(logged)[:, None, None]
    # every (b, a, o, t) with a target for a and o present where a sees it after some h <= H steps
    seen_valid = np.where(before[None, :, :, None], valid[:, None, :, 1:], valid[:, None, :, :t_])
    later = np.zeros_like(seen_valid)
    for h in range(2, horizon + 1):
        later[..., : t_ - h + 1] |= valid[:, None, :, h:]
    b, a, o, t = np.nonzero(
        target[:, :, None, :] & (seen_valid | later) & ~np.eye(a_, dtype=bool)[None, :, :, None]
    )
    origin = cur[b, a, t]
    # the obstacle as the candidates meet it after h steps (h = 1: the guard's rule), and whether it is there
    obstacles, present = [], []
    for h in range(1, horizon + 1):
        th = np.minimum(t + h, s_ - 1)
        obs = np.where(before[a, o][:, None], nxt[b, o, t], cur[b, o, t]) if h == 1 else xyh[b, o, th]
        ok = (
            np.where(before[a, o], valid[b, o, t + 1], valid[b, o, t])
            if h == 1
            else (t + h < s_) & valid[b, o, th]
        )
        obstacles.append(obs)
        present.append(ok)
    lim = hd[b, a] + hd[b, o]  # centre distance below which two boxes may overlap
    # at step h, a pair is active when the obstacle is there and near enough for a kept-up candidate
    active = [
        present[h] & (np.hypot(*(obstacles[h][:, :2] - origin[:, :2]).T) < (h + 1) * reach1[b, a] + lim)
        for h in range(horizon)
    ]
    # a box overlapping the obstacle already is left out, as by the guard
    free = ~(present[0] & box_collisions(origin, size[b, a], obstacles[0], size[b, o]))
    active = [x & free for x in active]
    used = np.logical_or.reduce(active)
    if not used.any():
        return BlockedCandidates(*(np.zeros(0, np.int64),) * 3, np.zeros((0, templates.shape[1]), bool))
    # candidates per position (b, a, t), shared by its pairs: the move kept up for h + 1 steps
    key = (b * a_ + a) * t_ + t
    positions, pos_of = np.unique(key[used], return_inverse=True)
    pair_pos = np.full(len(b), -1)
    pair_pos[used] = pos_of
    pb, rest = np.divmod(positions, a_ * t_)
    pa, pt = np.divmod(rest, t_)
    cls = np.clip(kind[pb, pa], 0, len(move) - 1)
    mask = np.zeros((len(positions), templates.shape[1]), bool)
    cand = cur[pb, pa, pt][:, None].repeat(templates.shape[1], 1)
    for h in range(horizon):
        cand = to_global(cand, templates[cls])  # [Q,D,3]
        pairs = np.flatnonzero(active[h])
        if not len(pairs):
            continue
        q, obs = pair_pos[pairs], obstacles[h][pairs]
        dx, dy = cand[q, :, 0] - obs[:, None, 0], cand[q, :, 1] - obs[:, None, 1]
        r, v = np.nonzero(~mask[q] & (dx * dx + dy * dy < (lim[pairs] * lim[pairs])[:, None]))
        pr = pairs[r]
        over = box_collisions(cand[q[r], v], size[b[pr], a[pr]], obs[r], size[b[pr], o[pr]])
        mask[q[r][over], v[over]] = True
    some = mask.any(1)
    positions, mask, pb, pa, pt = positions[some], mask[some], pb[some], pa[some], pt[some]
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


def versus_target_loss(
    logits: torch.Tensor, blocked: BlockedCandidates, targets: torch.Tensor
) -> torch.Tensor:
    """Sum over ``blocked``'s positions of ``log(1 + m / p)``: ``m`` the probability ``logits [B,T,A,D]``
    put on their colliding candidates, ``p`` the one on their target token (``targets [B,A,T]``, as
    drawn). Only the target and the colliding candidates get gradients, so no other token (standing among
    them) lowers it: the colliding mass is taught away towards the target's motion, not away from motion.
    Positions whose target collides itself, or is not drawn, are left out (0-d; 0 when none is left)."""
    dev = logits.device
    index = [torch.from_numpy(x).to(dev) for x in (blocked.batch, blocked.step, blocked.agent)]
    token = targets[index[0], index[2], index[1]].long()
    mask = torch.from_numpy(blocked.mask).to(dev)
    drawn = (token >= 0) & (token < mask.shape[1])
    rows = torch.arange(len(token), device=dev)
    keep = drawn & ~mask[rows, token.clamp(0, mask.shape[1] - 1)]
    if not bool(keep.any()):
        return logits.sum() * 0.0
    lg = logits[index[0][keep], index[1][keep], index[2][keep]]  # [Q,D]
    lg = lg.to(torch.promote_types(lg.dtype, torch.float32))
    # log m - log p without the softmax's normaliser (it cancels), so no other token gets a gradient
    log_m = torch.logsumexp(lg.masked_fill(~mask[keep], float("-inf")), dim=-1)
    log_p = lg.gather(1, token[keep][:, None])[:, 0]
    return torch.nn.functional.softplus(log_m - log_p).sum()


TERM_FORMS = ("mass", "versus_target")  # the forms of the colliding- and off-road-mass terms (TrainConfig)


def term_loss(
    form: str, logits: torch.Tensor, blocked: BlockedCandidates, targets: torch.Tensor
) -> torch.Tensor:
    """A mass term in ``form``: ``blocked_loss`` (mass) or ``versus_target_loss`` (versus_target)."""
    return (
        versus_target_loss(logits, blocked, targets)
        if form == "versus_target"
        else blocked_loss(logits, blocked)
    )


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
    model: torch.nn.Module,
    batch: dict[str, torch.Tensor],
    templates: np.ndarray,
    horizon: int = 1,
    rolled_out_only: bool = False,
    rows: np.ndarray | None = None,
) -> BlockedCandidates:
    """:func:`blocked_candidates` of a collated training batch, targets as the model draws them; ``rows``:
    of those windows alone (their positions still index the whole batch; None: every window)."""
    if rows is not None and not len(rows):
        empty = np.zeros(0, dtype=np.int64)
        return BlockedCandidates(empty, empty, empty, np.zeros((0, len(templates[0])), dtype=bool))
    if rows is not None:
        index = torch.from_numpy(rows).to(batch["tokens"].device)
        sub = {k: batch[k][index] for k in TERM_KEYS if k in batch}
        blocked = batch_blocked(model, sub, templates, horizon, rolled_out_only)
        return replace(blocked, batch=rows[blocked.batch])
    if rolled_out_only and "logged_targets" not in batch:
        raise ValueError("collision_rolled_out_only: the batch has no logged_targets (an older dataset's)")
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
        horizon,
        rolled_out_only,
    )
