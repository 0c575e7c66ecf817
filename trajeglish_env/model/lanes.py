"""What an agent sees of the road around it where it moves from (``ModelConfig.lane_input``).

The encoder reads the map in a window's frame, and the decoder reads motion tokens: to follow a ring a
small model must learn, from little data, to turn "the lane points ahead of me lie to my left" out of
window-frame coordinates it never sees in its own frame. It did not: alone on a racetrack, the shipped
model's vehicle drives straight on where the lane bends (docs/evaluation.md, "The road in the agent's own
frame"). With ``lane_input`` each decoder position (step ``t``, agent ``a``) also reads, in ``a``'s frame at
``t`` (known before any agent of step ``t`` moves, so the factorization is unchanged), the
:data:`LANE_POINTS` lane-centre points nearest to it that run its way and the :data:`EDGE_POINTS` nearest
road-edge points, each as position, direction relative to ``a`` and type. Points ahead count as
:data:`AHEAD_SCALE` times their distance, so the set reaches further forward than back. The points are the
scene's lane centres and road edges resampled every :data:`SPACING` metres (:func:`scene_road_points`).
Every feature is relative, so a window's frame (training) and the world frame (sampling) give the same
numbers.
"""

from __future__ import annotations

import weakref

import numpy as np
import torch
from torch import nn

from trajeglish_env.model.layers import Linear
from trajeglish_env.scenario import LANE_KINDS, ROAD_EDGE_KINDS, Scenario

SPACING = 2.0  # metres between the road points read (polylines resampled)
LANE_POINTS = 24  # nearest lane-centre points running the agent's way
EDGE_POINTS = 12  # nearest road-edge points
REACH = 40.0  # metres: points farther away are not read
BEHIND = 5.0  # metres: points farther behind the agent than this are not read
AHEAD_SCALE = 0.5  # a point ahead of the agent counts as this fraction of its distance ahead
POINT_FEATURES = 6  # position / 20 m, cos and sin of relative direction, is lane, is edge
POSITION_SCALE = 20.0
ROAD_POINTS = LANE_POINTS + EDGE_POINTS
LANE_PARAMS = "lanes."  # state-dict prefix of LaneEncoder inside the model
SOURCE_POINTS = 4096  # road points a training window keeps for closed-loop rollouts (window_road_source)
SOURCE_MARGIN = 10.0  # metres beyond the logged states' box a closed-loop agent may drift and still read


def _resample(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A polyline ``[n,2]`` resampled every :data:`SPACING` metres along its length (its ends kept), and
    each point's direction of travel (radians)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=-1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if len(points) < 2 or s[-1] <= 0:
        return points[:1], np.zeros(1)
    at = np.append(np.arange(0.0, s[-1], SPACING), s[-1])
    xy = np.stack([np.interp(at, s, points[:, 0]), np.interp(at, s, points[:, 1])], axis=-1)
    i = np.clip(np.searchsorted(s, at, side="right") - 1, 0, len(seg) - 1)
    nonzero = np.flatnonzero(seg > 0)
    i = nonzero[np.clip(np.searchsorted(nonzero, i), 0, len(nonzero) - 1)]  # skip repeated points
    d = points[i + 1] - points[i]
    return xy, np.arctan2(d[:, 1], d[:, 0])


def scene_road_points(scene: Scenario) -> np.ndarray:
    """``[P,4]`` float64 road points of ``scene`` in its frame: x, y, direction (lane centres: of travel;
    road edges: along the polyline) and 1 for a road edge, 0 for a lane centre."""
    out = [np.zeros((0, 4))]
    for k in range(scene.num_polylines):
        kind = int(scene.map_kind[k])
        if kind not in LANE_KINDS and kind not in ROAD_EDGE_KINDS:
            continue
        xy, heading = _resample(scene.polyline(k).astype(np.float64))
        edge = np.full(len(xy), float(kind in ROAD_EDGE_KINDS))
        out.append(np.concatenate([xy, heading[:, None], edge[:, None]], axis=-1))
    return np.concatenate(out)


_POINTS: weakref.WeakKeyDictionary[Scenario, np.ndarray] = weakref.WeakKeyDictionary()


def road_points_of(scene: Scenario) -> np.ndarray:
    """:func:`scene_road_points`, computed once per scene object (Scenarios hash by identity)."""
    points = _POINTS.get(scene)
    if points is None:
        points = _POINTS[scene] = scene_road_points(scene)
    return points


def near_states(points: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The rows of ``points [P,4]`` within :data:`REACH` of the bounding box of positions ``xy [n,2]``: the
    only ones :func:`road_view` can pick for those positions (a cheap exact filter)."""
    if len(xy) == 0:
        return points[:0]
    low, high = xy.min(0) - REACH, xy.max(0) + REACH
    inside = ((points[:, :2] >= low) & (points[:, :2] <= high)).all(-1)
    return points[inside]


def _nearest(key: torch.Tensor, ok: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices ``[...,k]`` of the ``k`` smallest ``key`` (float32, >= 0) where ``ok`` (last dim), nearest
    first, and whether each is real. Equal keys (coincident points of overlapping lanes) go by index, so an
    agent picks the same points whatever else its call holds (more candidates after its own, other agents):
    each key is ranked by its bits (non-negative floats order as their bits) with its index below them."""
    if key.shape[-1] < k:  # fewer points than slots: pad with absent ones
        pad = k - key.shape[-1]
        key = torch.cat([key, key.new_full((*key.shape[:-1], pad), float("inf"))], dim=-1)
        ok = torch.cat([ok, ok.new_zeros(*ok.shape[:-1], pad)], dim=-1)
    masked = torch.where(ok, key.float(), torch.full_like(key, float("inf"), dtype=torch.float32))
    index = torch.arange(key.shape[-1], device=key.device)
    rank = (masked.contiguous().view(torch.int32).to(torch.int64) << 32) | index
    near = rank.topk(k, dim=-1, largest=False).indices
    return near, ok.gather(-1, near)


def road_view(
    points: torch.Tensor, point_mask: torch.Tensor, xyh: torch.Tensor, valid: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Features ``[...,m,R,6]`` (``R`` = :data:`ROAD_POINTS`) and mask ``[...,m,R]`` of the road around
    agents at ``xyh [...,m,3]`` (``valid [...,m]``), from road points ``points [...,P,4]`` (the same frame;
    :func:`scene_road_points`) with ``point_mask [...,P]``. Leading dims broadcast. Positions are taken
    relative to each point set's first point in ``xyh``'s dtype (world coordinates need float64), then
    every pair is compared in float32; the chosen points' features are float32."""
    if points.shape[-2]:
        origin = points[..., :1, :2].to(xyh.dtype)
        p_xy, a_xy = (points[..., :2] - origin).float(), (xyh[..., :2] - origin).float()
    else:
        p_xy, a_xy = points[..., :2].float(), xyh[..., :2].float()
    heading = xyh[..., 2].float()
    c, s = torch.cos(heading)[..., None], torch.sin(heading)[..., None]  # [...,m,1]
    dx = p_xy[..., None, :, 0] - a_xy[..., :, None, 0]  # [...,m,P]
    dy = p_xy[..., None, :, 1] - a_xy[..., :, None, 1]
    x, y = dx * c + dy * s, dy * c - dx * s
    ahead = torch.where(x > 0, x * AHEAD_SCALE, x)
    key = ahead * ahead + y * y
    ok = point_mask[..., None, :] & valid[..., :, None] & (x > -BEHIND) & (dx * dx + dy * dy < REACH * REACH)
    p_heading = points[..., 2].float()
    same_way = torch.cos(p_heading)[..., None, :] * c + torch.sin(p_heading)[..., None, :] * s > 0
    edge = (points[..., 3] > 0.5)[..., None, :]
    lane_near, lane_ok = _nearest(key, ok & ~edge & same_way, LANE_POINTS)
    edge_near, edge_ok = _nearest(key, ok & edge, EDGE_POINTS)
    near, mask = torch.cat([lane_near, edge_near], dim=-1), torch.cat([lane_ok, edge_ok], dim=-1)
    near = near.clamp(max=x.shape[-1] - 1) if x.shape[-1] else near  # padded slots (masked) read point 0

    def pick(v: torch.Tensor) -> torch.Tensor:  # [...,m or 1,P] -> the chosen points' [...,m,R]
        if v.shape[-1] == 0:
            return v.new_zeros(*near.shape)
        return v.expand(*near.shape[:-1], v.shape[-1]).gather(-1, near)

    is_edge = pick(edge.float())
    dh = pick(p_heading[..., None, :]) - heading[..., None]
    feats = torch.stack(
        [
            pick(x) / POSITION_SCALE,
            pick(y) / POSITION_SCALE,
            torch.cos(dh),
            torch.sin(dh),
            1.0 - is_edge,
            is_edge,
        ],
        dim=-1,
    )
    return torch.where(mask[..., None], feats, torch.zeros_like(feats)), mask


def window_road_view(
    points: np.ndarray, xyh: np.ndarray, valid: np.ndarray, steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """Features ``[steps,A,R,6]`` and mask ``[steps,A,R]`` of a training window: its agents' states ``xyh
    [A,S,3]`` (``valid [A,S]``) at steps ``0 .. steps-1`` and the scene's road points ``points [P,4]``,
    all in the window's frame."""
    cur, ok = xyh[:, :steps].transpose(1, 0, 2), valid[:, :steps].T  # [steps,A,3], [steps,A]
    near = near_states(points, cur[ok][:, :2])
    p = torch.from_numpy(near)
    every = torch.ones(len(near), dtype=torch.bool)
    feats, mask = road_view(p, every, torch.from_numpy(cur), torch.from_numpy(ok))
    return feats.numpy(), mask.numpy()


def window_road_source(
    points: np.ndarray, xyh: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The road points ``[SOURCE_POINTS,4]`` (float32) and mask a training window keeps for reading the road
    where a closed-loop rollout (CAT-K) moves its agents: the scene's points (window frame) within
    :data:`REACH` + :data:`SOURCE_MARGIN` of the box of its agents' logged states ``xyh [A,S,3]`` (``valid``),
    the nearest the window's frame first when more are there than the fixed size holds."""
    xy = xyh[valid][:, :2]
    out = np.zeros((SOURCE_POINTS, 4), dtype=np.float32)
    mask = np.zeros(SOURCE_POINTS, dtype=bool)
    if len(xy) == 0:
        return out, mask
    low, high = xy.min(0) - REACH - SOURCE_MARGIN, xy.max(0) + REACH + SOURCE_MARGIN
    near = points[((points[:, :2] >= low) & (points[:, :2] <= high)).all(-1)]
    if len(near) > SOURCE_POINTS:
        near = near[np.argsort(np.linalg.norm(near[:, :2], axis=-1), kind="stable")[:SOURCE_POINTS]]
    out[: len(near)], mask[: len(near)] = near, True
    return out, mask


class LaneEncoder(nn.Module):
    """A position's road points -> a ``[...,C]`` addition to its decoder input: each point through a small
    MLP, max-pooled over the real ones, then a zero-initialized output layer (a trained model extended with
    it starts as it was). Pooled at the MLP's width: the points are many, the positions fewer."""

    def __init__(self, d_model: int, hidden: int = 64):
        super().__init__()
        self.point = nn.Sequential(Linear(POINT_FEATURES, hidden), nn.GELU(), Linear(hidden, hidden))
        self.out = nn.Sequential(nn.GELU(), Linear(hidden, d_model))
        nn.init.zeros_(self.out[1].weight)
        nn.init.zeros_(self.out[1].bias)

    def forward(self, points: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        h = self.point(points)  # [...,R,C]
        pooled = h.masked_fill(~mask[..., None], -1e4).amax(dim=-2)  # finite: no NaN gradients
        pooled = torch.where(mask.any(-1, keepdim=True), pooled, torch.zeros_like(pooled))
        return self.out(pooled)
