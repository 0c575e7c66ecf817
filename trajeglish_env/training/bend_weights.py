"""Training-loss weights for the tokens where the road ahead turns away from an agent's current motion.

Teacher forcing rewards a small model for continuing its own last tokens (the copycat problem, stops 37 and
55): under it the shipped model expects 0.95 of a vehicle's turn once the turn has begun and a quarter of
it where it begins (``scripts/turn_onset_probe.py``; docs/evaluation.md, "Weighing the tokens where the
road bends"), and alone on a racetrack it drives straight on at the bend. ``train --lane-input
--bend-weight W`` weighs the loss of those tokens ``W`` times: a token of agent ``a`` at step ``t`` is a
*bend* token when the lane ahead of ``a`` (the lane points ``a`` reads at ``t``,
:mod:`trajeglish_env.model.lanes`) runs at more than :data:`MISMATCH` radians from the heading ``a`` would
reach by keeping its current turn rate until it gets there. The flag depends only on logged states up to
``t`` and the map (what the model's inputs already hold), never on the token, so the conditional
distribution the loss is minimized by stays the same; the weight moves gradient and capacity to the
positions where the road, not the agent's trend, says what comes next. CAT-K windows are flagged at their
rolled-out states and the road read there.
"""

from __future__ import annotations

import math

import torch

from trajeglish_env.model.lanes import LANE_POINTS, POSITION_SCALE

STEP_SECONDS = 0.1  # every scene source samples at 10 Hz (Scenario.dt)
LOOKAHEAD_SECONDS = 1.5  # the lane is read where the agent will be this far ahead at its current speed
MIN_LOOKAHEAD = 4.0  # metres
MAX_LOOKAHEAD = 30.0  # metres (lane points reach 40 m; ahead ones count at half distance)
MATCH_RADIUS = 4.0  # metres: the lane point read lies this close to the look-ahead point, else no flag
MISMATCH = 0.2  # radians between the lane's direction there and the agent's extrapolated heading
MIN_SPEED = 2.0  # m/s: slower agents are not flagged (their heading says little)
TURN_STEPS = 3  # the turn rate is the heading change over this many steps


def _wrap(angle: torch.Tensor) -> torch.Tensor:
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


def bend_flags(
    xyh: torch.Tensor, valid: torch.Tensor, road: torch.Tensor, road_mask: torch.Tensor
) -> torch.Tensor:
    """Whether each agent's token at each step is a bend token: ``[B,A,T]``.

    ``xyh [B,A,S,3]`` / ``valid [B,A,S]`` logged states (any common frame, ``S > T``); ``road [B,T,A,R,6]`` /
    ``road_mask [B,T,A,R]`` the lane-input features of the window (:func:`~trajeglish_env.model.lanes.
    window_road_view`: lane points first, in each agent's frame at ``t``). Steps before the agent has
    :data:`TURN_STEPS` earlier valid states are never flagged."""
    steps = road.shape[1]
    cur = xyh[:, :, :steps].double()
    ok = valid[:, :, :steps]
    back = torch.zeros_like(ok)
    back[:, :, TURN_STEPS:] = ok[:, :, TURN_STEPS:] & valid[:, :, : steps - TURN_STEPS]
    before = torch.cat([cur[:, :, :TURN_STEPS], cur[:, :, : steps - TURN_STEPS]], dim=2)  # state t - 3
    seconds = TURN_STEPS * STEP_SECONDS
    speed = (cur[..., :2] - before[..., :2]).norm(dim=-1) / seconds  # [B,A,T] m/s
    rate = _wrap(cur[..., 2] - before[..., 2]) / seconds  # rad/s
    reach = (speed * LOOKAHEAD_SECONDS).clamp(MIN_LOOKAHEAD, MAX_LOOKAHEAD)
    lanes = road[..., :LANE_POINTS, :].transpose(1, 2).double()  # [B,A,T,L,6]
    lane_ok = road_mask[..., :LANE_POINTS].transpose(1, 2)
    x, y = lanes[..., 0] * POSITION_SCALE, lanes[..., 1] * POSITION_SCALE
    # where the agent gets by keeping its turn rate: along a circle of that rate (straight when ~0)
    turn = rate * reach / speed.clamp(min=MIN_SPEED)  # heading change on arrival
    chord = torch.where(turn.abs() > 1e-6, 2 * torch.sin(turn / 2) / turn.where(turn.abs() > 1e-6, 1.0), 1.0)
    gx, gy = reach * chord * torch.cos(turn / 2), reach * chord * torch.sin(turn / 2)
    gap = (x - gx[..., None]) ** 2 + (y - gy[..., None]) ** 2
    gap = torch.where(lane_ok, gap, torch.full_like(gap, float("inf")))
    nearest = gap.argmin(-1, keepdim=True)
    near = gap.gather(-1, nearest)[..., 0] < MATCH_RADIUS**2
    direction = torch.atan2(lanes[..., 3].gather(-1, nearest), lanes[..., 2].gather(-1, nearest))[..., 0]
    off = _wrap(direction - turn).abs() > MISMATCH
    return back & (speed > MIN_SPEED) & near & off


def bend_weights(batch: dict[str, torch.Tensor], weight: float) -> torch.Tensor | None:
    """Per-target loss weights ``[B,A,T]`` of a collated lane-input batch (``weight`` at bend tokens, else
    1), or None when ``weight`` is 1."""
    if weight == 1.0:
        return None
    if "road_points" not in batch:
        raise ValueError("bend weights read the windows' lane features: train with --lane-input")
    steps = batch["tokens"].shape[-1]
    valid = batch["agent_valid"] & batch["agent_mask"][..., None]
    road, mask = batch["road_points"][:, :steps], batch["road_mask"][:, :steps]
    flags = bend_flags(batch["agent_xyh"], valid, road, mask)
    return 1.0 + (weight - 1.0) * flags.float()
