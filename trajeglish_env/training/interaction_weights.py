"""Training-loss weights for the tokens of agents closing in on the agent ahead of them.

The NPCs' failure is rare in the data: a follower's tokens while it closes in on a slower or stopped
vehicle are a few percent of all tokens, and the likelihood a small model earns by reacting to that vehicle is
small against the rest (docs/evaluation.md, "Followers behind a hard stop"). ``train --interaction-weight W``
weighs those tokens' loss ``W`` times. Whether a token is weighed depends only on the logged states of the
step the agent moves from and the one before it (what the model's inputs already tell it), never on the token
itself, so the conditional distribution the loss is minimized by stays the same: the weight moves capacity
and gradient towards those situations, not the model's answer in them.

A token of agent ``a`` at step ``t`` is *closing in* when another agent ``b`` at step ``t`` lies ahead of
``a`` in its path (in ``a``'s frame: in front, boxes overlapping sideways within :data:`LATERAL_MARGIN`), at
most :data:`REACH` metres bumper to bumper, and either ``a`` closes the gap fast enough to reach ``b`` within
:data:`TIME_TO_CONTACT` seconds or follows it closer than :data:`HEADWAY` seconds.
"""

from __future__ import annotations

import torch

from trajeglish_env.model.neighbours import in_frame

STEP_SECONDS = 0.1  # every scene source samples at 10 Hz (Scenario.dt)
REACH = 40.0  # metres bumper to bumper
LATERAL_MARGIN = 0.5  # metres beyond the two half widths
TIME_TO_CONTACT = 4.0  # seconds at the current closing speed
MIN_CLOSING = 0.3  # m/s: slower closing is not closing in
HEADWAY = 0.6  # seconds: following closer than this at any speed above MIN_SPEED
MIN_SPEED = 1.0  # m/s


def closing_in(xyh: torch.Tensor, valid: torch.Tensor, size: torch.Tensor, steps: int) -> torch.Tensor:
    """Whether each agent closes in on an agent ahead at each of the first ``steps`` steps: ``[B,A,steps]``.

    ``xyh [B,A,S,3]`` states in any common frame, ``valid [B,A,S]``, ``size [B,A,2]`` (length, width).
    Step 0 has no earlier state in the window, so no velocity: never closing in."""
    cur = xyh[:, :, :steps].transpose(1, 2).double()  # [B,T,A,3]
    ok = valid[:, :, :steps].transpose(1, 2)
    prev = torch.cat([cur[:, :1], cur[:, :-1]], dim=1)
    moving = ok & torch.cat([torch.zeros_like(ok[:, :1]), ok[:, :-1]], dim=1)  # [B,T,A]
    vel = (cur[..., :2] - prev[..., :2]) / STEP_SECONDS  # m/s
    heading = cur[..., 2]
    rel = in_frame(cur[:, :, None, :, :2] - cur[:, :, :, None, :2], heading[..., None])  # [B,T,A(me),A,2]
    rel_vel = in_frame(vel[:, :, None, :] - vel[:, :, :, None], heading[..., None])
    length, width = size[..., 0].double(), size[..., 1].double()  # [B,A]
    half_len = (length[:, :, None] + length[:, None, :]) / 2  # [B,A,A]
    half_wid = (width[:, :, None] + width[:, None, :]) / 2 + LATERAL_MARGIN
    gap = rel[..., 0] - half_len[:, None]
    in_path = (rel[..., 0] > 0) & (rel[..., 1].abs() < half_wid[:, None]) & (gap < REACH)
    closing = -rel_vel[..., 0]
    speed = vel.norm(dim=-1)[..., None]  # [B,T,A,1]
    fast = (closing > MIN_CLOSING) & (gap < TIME_TO_CONTACT * closing)
    close = (speed > MIN_SPEED) & (gap < HEADWAY * speed)
    a = xyh.shape[1]
    others = ~torch.eye(a, dtype=torch.bool, device=xyh.device)
    pair = moving[..., :, None] & moving[..., None, :] & others & in_path & (fast | close)
    return pair.any(-1).transpose(1, 2)  # [B,A,T]


def interaction_weights(batch: dict[str, torch.Tensor], weight: float) -> torch.Tensor | None:
    """Per-target loss weights ``[B,A,T]`` of a collated batch (``weight`` where an agent closes in, else 1),
    or None when ``weight`` is 1 (plain likelihood)."""
    if weight == 1.0:
        return None
    steps = batch["tokens"].shape[-1]
    valid = batch["agent_valid"] & batch["agent_mask"][..., None]
    flags = closing_in(batch["agent_xyh"], valid, batch["agent_size"], steps)
    return 1.0 + (weight - 1.0) * flags.float()
