"""What an agent sees of its neighbours where it moves from (``ModelConfig.neighbour_input``).

Trajeglish's decoder reads only tokens: where an agent is, and how far the vehicle ahead of it is, the model
must integrate from the window's initial states and every token since, through attention. A small model
trained on little data learns that slowly, and its vehicles then drive into the ones ahead (issue 15). With
``neighbour_input`` each decoder position (step ``t``, agent ``a``) also reads the states of step ``t``,
which are known before any agent of step ``t`` moves (so the factorization is unchanged): ``a``'s own
velocity, and its :data:`NEIGHBOURS` nearest agents within :data:`REACH` metres, each as position, heading,
velocity relative to ``a`` in ``a``'s frame, and size. Every feature is relative, so a window's frame
(training) and the world frame (sampling) give the same numbers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from trajeglish_env.model.layers import Linear

NEIGHBOURS = 8  # nearest agents each position reads
REACH = 60.0  # metres: agents farther away are not read
OWN_FEATURES = 3  # velocity in the agent's frame (metres per step), whether it is known
PAIR_FEATURES = 9  # position / 20 m, cos and sin of relative heading, relative velocity, known, size / 5 m
POSITION_SCALE, SIZE_SCALE = 20.0, 5.0
NEIGHBOUR_PARAMS = "neighbours."  # state-dict prefix of NeighbourEncoder inside the model


@dataclass(frozen=True)
class NeighbourView:
    """Features of positions ``[...]``: ``own [...,3]``, ``pairs [...,K,9]`` and ``mask [...,K]`` (a real
    neighbour); for models with ``lane_input`` also ``road [...,R,6]`` and ``road_mask [...,R]``
    (:mod:`~trajeglish_env.model.lanes`), or instead ``road_code [...,C]``, what the model's lane encoder
    makes of them, computed beforehand (the sampler encodes each agent-step once). Float32 on the model's
    device."""

    own: torch.Tensor
    pairs: torch.Tensor
    mask: torch.Tensor
    road: torch.Tensor | None = None
    road_mask: torch.Tensor | None = None
    road_code: torch.Tensor | None = None

    def _map(self, f: Callable[[torch.Tensor], torch.Tensor]) -> NeighbourView:
        road = None if self.road is None or self.road_mask is None else (f(self.road), f(self.road_mask))
        code = None if self.road_code is None else f(self.road_code)
        return NeighbourView(f(self.own), f(self.pairs), f(self.mask), *(road or (None, None)), code)

    def index(self, *index: torch.Tensor | slice) -> NeighbourView:
        """The same features at ``index`` of the leading dimensions (e.g. a batch's busy rows)."""
        return self._map(lambda x: x[index])

    def padded(self, n: int) -> NeighbourView:
        """``[B,m,...]`` -> ``[B,n,...]`` (``n >= m``): zeros after the first ``m`` positions."""

        def pad(x: torch.Tensor) -> torch.Tensor:
            return torch.cat([x, x.new_zeros(x.shape[0], n - x.shape[1], *x.shape[2:])], dim=1)

        return self._map(pad)

    def flat_time_major(self) -> NeighbourView:
        """``[B,T,A,...]`` -> ``[B,T*A,...]``: the decoder's flattened sequence."""
        b, t, a = self.own.shape[:3]
        return self._map(lambda x: x.reshape(b, t * a, *x.shape[3:]))

    def to(self, device: torch.device) -> NeighbourView:
        return self._map(lambda x: x.to(device))


def in_frame(v: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """Vectors ``v [...,2]`` in the frame of headings ``heading [...]``."""
    c, s = torch.cos(heading), torch.sin(heading)
    return torch.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1]], dim=-1)


def neighbour_view(
    xyh: torch.Tensor,
    valid: torch.Tensor,
    prev_xyh: torch.Tensor,
    prev_valid: torch.Tensor,
    size: torch.Tensor,
    focal: torch.Tensor | None = None,
) -> NeighbourView:
    """Features ``[...,m]`` of agents ``focal [...,m]`` (slot indices; None: every agent, ``m = A``) at one
    step: states ``xyh [...,A,3]`` (any common frame) and ``valid [...,A]``, the same agents' states one
    step earlier (``prev_*``; velocities are 0 and unknown where either is missing), sizes ``size
    [...,A,2]`` (length, width). Computed in ``xyh``'s dtype (the sampler passes float64 world
    coordinates), returned in float32. The sampler asks for the agents it decodes only."""
    a = xyh.shape[-2]
    if focal is None:
        focal = torch.arange(a, device=xyh.device).expand(*xyh.shape[:-2], a)
    m = focal.shape[-1]

    def pick(x: torch.Tensor) -> torch.Tensor:  # per-agent [...,A,F] -> the focal agents' [...,m,F]
        return x.gather(-2, focal[..., None].expand(*focal.shape, x.shape[-1]))

    xy, h = xyh[..., :2], xyh[..., 2:]
    moving = (valid & prev_valid)[..., None]  # [...,A,1]
    vel = torch.where(moving, xy - prev_xyh[..., :2], torch.zeros_like(xy))
    known = moving.to(xy.dtype)
    f_xy, f_h, f_vel, f_known = pick(xy), pick(h)[..., 0], pick(vel), pick(known)
    own = torch.cat([in_frame(f_vel, f_h), f_known], dim=-1)
    rel = in_frame(xy[..., None, :, :] - f_xy[..., :, None, :], f_h[..., None])  # [...,m,A,2]
    dist = rel.norm(dim=-1)
    me = focal[..., None] == torch.arange(a, device=xyh.device)
    f_valid = pick(valid[..., None])[..., 0]
    seen = f_valid[..., None] & valid[..., None, :] & ~me & (dist < REACH)
    k = min(NEIGHBOURS, max(a - 1, 1))
    key = torch.where(seen, dist, torch.full_like(dist, float("inf")))
    near = key.topk(k, dim=-1, largest=False).indices  # [...,m,k] nearest first
    mask = seen.gather(-1, near)

    def them(x: torch.Tensor) -> torch.Tensor:  # per-agent [...,A,F] -> the neighbours' [...,m,k,F]
        expanded = x[..., None, :, :].expand(*x.shape[:-2], m, a, x.shape[-1])
        return expanded.gather(-2, near[..., None].expand(*near.shape, x.shape[-1]))

    dh = them(h)[..., 0] - f_h[..., None]
    pairs = torch.cat(
        [
            rel.gather(-2, near[..., None].expand(*near.shape, 2)) / POSITION_SCALE,
            torch.cos(dh)[..., None],
            torch.sin(dh)[..., None],
            in_frame(them(vel) - f_vel[..., None, :], f_h[..., None]),
            them(known) * f_known[..., None, :],
            them(size) / SIZE_SCALE,
        ],
        dim=-1,
    )
    pairs = torch.where(mask[..., None], pairs, torch.zeros_like(pairs))
    if k < NEIGHBOURS:  # fewer agents than neighbour slots: pad with absent ones
        pad = NEIGHBOURS - k
        pairs = torch.cat([pairs, pairs.new_zeros(*pairs.shape[:-2], pad, PAIR_FEATURES)], dim=-2)
        mask = torch.cat([mask, mask.new_zeros(*mask.shape[:-1], pad)], dim=-1)
    return NeighbourView(own.float(), pairs.float(), mask)


def window_view(xyh: torch.Tensor, valid: torch.Tensor, size: torch.Tensor, steps: int) -> NeighbourView:
    """Features ``[B,steps,A]`` of a batch of windows: states ``xyh [B,A,S,3]`` and ``valid [B,A,S]`` of
    steps ``0 .. S-1``, sizes ``[B,A,2]``. Step 0 has no earlier state (as in sampling, where a window's
    first step reads no velocity either)."""
    cur = xyh[:, :, :steps].transpose(1, 2)  # [B,T,A,3]
    ok = valid[:, :, :steps].transpose(1, 2)
    prev = torch.cat([cur[:, :1], cur[:, :-1]], dim=1)
    prev_ok = torch.cat([torch.zeros_like(ok[:, :1]), ok[:, :-1]], dim=1)
    sizes = size[:, None].expand(-1, cur.shape[1], -1, -1)
    return neighbour_view(cur, ok, prev, prev_ok, sizes)


class NeighbourEncoder(nn.Module):
    """A position's features -> a ``[...,C]`` addition to its decoder input: each neighbour through a small
    MLP, max-pooled over the real ones, plus the own velocity's projection, then a zero-initialized output
    layer (a trained model extended with it starts as it was)."""

    def __init__(self, d_model: int, hidden: int = 64):
        super().__init__()
        self.pair = nn.Sequential(Linear(PAIR_FEATURES, hidden), nn.GELU(), Linear(hidden, d_model))
        self.own = Linear(OWN_FEATURES, d_model)
        self.out = nn.Sequential(nn.GELU(), Linear(d_model, d_model))
        nn.init.zeros_(self.out[1].weight)
        nn.init.zeros_(self.out[1].bias)

    def forward(self, view: NeighbourView) -> torch.Tensor:
        pairs = self.pair(view.pairs)  # [...,K,C]
        pooled = pairs.masked_fill(~view.mask[..., None], -1e4).amax(dim=-2)  # finite: no NaN gradients
        pooled = torch.where(view.mask.any(-1, keepdim=True), pooled, torch.zeros_like(pooled))
        return self.out(pooled + self.own(view.own))


def batch_view(reads_states: bool, batch: dict[str, torch.Tensor]) -> NeighbourView | None:
    """The features of a collated batch of training windows (``agent_xyh``, ``agent_valid``,
    ``agent_mask``, ``agent_size``; the logged states; with ``road_points`` / ``road_mask``, the windows'
    road features), or None for a model that reads no states (``ModelConfig.reads_states``)."""
    if not reads_states:
        return None
    valid = batch["agent_valid"] & batch["agent_mask"][..., None]
    steps = batch["input_tokens"].shape[-1]
    view = window_view(batch["agent_xyh"].float(), valid, batch["agent_size"].float(), steps)
    if "road_points" not in batch:
        return view
    road, road_mask = batch["road_points"][:, :steps], batch["road_mask"][:, :steps]
    return NeighbourView(view.own, view.pairs, view.mask, road, road_mask)
