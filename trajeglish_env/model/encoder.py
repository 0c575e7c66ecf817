"""The Trajeglish scene encoder (paper Sec. 3.2): what the encoder sees, the VectorNet-style polyline
encoder and the scene encoder that turns agents and map into the memory the decoder attends to.

Each agent's initial state (length, width, position, heading, class) goes through an MLP, plus a learned
embedding of its slot in the order (also its identity across the token sequence); polylines are encoded
permutation-invariantly; a latent-query attention layer (Wayformer-style) and self-attention layers give
the scene memory. Shapes: B batch, A agent slots, M polylines, P points, C width.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn

from trajeglish_env.model.config import ModelConfig
from trajeglish_env.model.layers import EncoderBlock, Linear
from trajeglish_env.model.map_chunks import SIGNAL_CLASSES

POSITION_SCALE = 50.0  # metres -> network units
SIGNAL_PARAMS = "encoder.polylines.signal."  # state-dict prefix of the signal embedding (signal_input)
SIZE_SCALE = 5.0


@dataclass
class SceneInputs:
    """What the encoder sees: agents' initial states and the map, in the window's frame.

    ``agent_xyh [B,A,3]`` initial states, ``agent_size [B,A,2]``, ``agent_kind [B,A]`` long,
    ``agent_mask [B,A]`` bool; ``map_points [B,M,P,2]``, ``map_point_mask [B,M,P]``, ``map_kind [B,M]``,
    ``map_mask [B,M]``; ``map_signal [B,M]`` long, each chunk's signal class at the window's first step
    (:func:`~trajeglish_env.model.map_chunks.signal_classes`; read when ``ModelConfig.signal_input``).
    """

    agent_xyh: torch.Tensor
    agent_size: torch.Tensor
    agent_kind: torch.Tensor
    agent_mask: torch.Tensor
    map_points: torch.Tensor
    map_point_mask: torch.Tensor
    map_kind: torch.Tensor
    map_mask: torch.Tensor
    map_signal: torch.Tensor

    def rows(self, index: slice | torch.Tensor) -> SceneInputs:
        """The inputs of batch rows ``index``."""
        return SceneInputs(*(getattr(self, f.name)[index] for f in fields(self)))

    @classmethod
    def from_batch(cls, batch: dict[str, torch.Tensor]) -> SceneInputs:
        """From a collated training batch (``agent_xyh [B,A,S,3]``: the first state is the initial one)."""
        return cls(
            agent_xyh=batch["agent_xyh"][:, :, 0].float(),
            agent_size=batch["agent_size"].float(),
            agent_kind=batch["agent_kind"].long(),
            agent_mask=batch["agent_mask"] & batch["agent_valid"][:, :, 0],
            map_points=batch["map_points"].float(),
            map_point_mask=batch["map_point_mask"],
            map_kind=batch["map_kind"].long(),
            map_mask=batch["map_mask"],
            map_signal=batch["map_signal"].long(),
        )


class PolylineEncoder(nn.Module):
    """VectorNet-style: per-point MLP, max-pool, second MLP on [point, pooled], max-pool again.

    At inference the polylines are encoded in blocks of ``INFERENCE_BLOCK`` (only those with points): the
    per-point activations of a whole batch are hundreds of MB, a block's stay in the CPU cache, which
    makes re-encoding the windows of a batched env several times faster (same per-polyline results)."""

    INFERENCE_BLOCK = 128

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c = cfg.d_model
        self.point = nn.Sequential(Linear(5, c), nn.LayerNorm(c), nn.GELU(), Linear(c, c))
        self.second = nn.Sequential(Linear(2 * c, c), nn.LayerNorm(c), nn.GELU(), Linear(c, c))
        self.kind = nn.Embedding(cfg.num_map_kinds, c)
        self.signal = None
        if cfg.signal_input:  # zeros: a model extended with it starts as it was (class 0 stays zero)
            self.signal = nn.Embedding(SIGNAL_CLASSES, c, padding_idx=0)
            nn.init.zeros_(self.signal.weight)

    def forward(
        self,
        points: torch.Tensor,
        point_mask: torch.Tensor,
        kind: torch.Tensor,
        signal: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``points [B,M,P,2]``, ``point_mask [B,M,P]``, ``kind [B,M]`` (and the signal classes ``signal
        [B,M]``, read with ``signal_input``) -> ``[B,M,C]`` (padding polylines: their embeddings only)."""
        embedding = self.kind(kind.clamp(0, self.kind.num_embeddings - 1))
        if self.signal is not None and signal is not None:
            embedding = embedding + self.signal(signal.clamp(0, SIGNAL_CLASSES - 1))
        if torch.is_grad_enabled():
            return self._encode(points, point_mask) + embedding
        b, m, p, _ = points.shape
        present = torch.nonzero(point_mask.reshape(b * m, p).any(-1)).squeeze(1)
        flat_points, flat_mask = points.reshape(b * m, p, 2), point_mask.reshape(b * m, p)
        out = embedding.new_zeros(b * m, embedding.shape[-1])
        for chunk in present.split(self.INFERENCE_BLOCK):
            out[chunk] = self._encode_present(flat_points[chunk], flat_mask[chunk])
        return out.view(b, m, -1) + embedding

    def _encode_present(self, points: torch.Tensor, point_mask: torch.Tensor) -> torch.Tensor:
        """:meth:`_encode` of polylines ``[m, P, 2]`` that all have points, with the MLPs evaluated on their
        points only (the others are pooled out anyway)."""
        nxt = torch.cat([points[:, 1:], points[:, -1:]], dim=1)
        feats = torch.cat([points / POSITION_SCALE, nxt - points, point_mask[..., None].float()], dim=-1)
        first = self.point(feats[point_mask])  # [points, C]
        neg = torch.finfo(first.dtype).min
        h = first.new_full((*point_mask.shape, first.shape[-1]), neg)
        h[point_mask] = first
        pooled = h.amax(dim=1, keepdim=True).expand_as(h)[point_mask]
        out = torch.full_like(h, neg)
        out[point_mask] = self.second(torch.cat([first, pooled], dim=-1))
        return out.amax(dim=1)

    def _encode(self, points: torch.Tensor, point_mask: torch.Tensor) -> torch.Tensor:
        """Features ``[..., C]`` of polylines ``points [..., P, 2]`` (zeros for those without points)."""
        nxt = torch.cat([points[..., 1:, :], points[..., -1:, :]], dim=-2)
        feats = torch.cat([points / POSITION_SCALE, nxt - points, point_mask[..., None].float()], dim=-1)
        h = self.point(feats)
        neg = torch.finfo(h.dtype).min
        present = point_mask.any(-1, keepdim=True)  # [...,1]: padding polylines have no points
        pooled = h.masked_fill(~point_mask[..., None], neg).amax(dim=-2, keepdim=True)
        # A padding polyline's pool is the fill value; fed on, it overflows the next layer to inf once the
        # weights grow, and the discarded output still sends NaN gradients back. Zero it first.
        pooled = torch.where(present[..., None], pooled, torch.zeros_like(pooled))
        h = self.second(torch.cat([h, pooled.expand_as(h)], dim=-1))
        out = h.masked_fill(~point_mask[..., None], neg).amax(dim=-2)
        return torch.where(present, out, torch.zeros_like(out))


class SceneEncoder(nn.Module):
    """Agents + map -> scene memory ``[B, A + Q, C]`` and its padding mask."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c = cfg.d_model
        self.cfg = cfg
        self.agent = nn.Sequential(Linear(4 + 2 + cfg.num_kinds, c), nn.GELU(), Linear(c, c))
        self.slot = nn.Embedding(cfg.max_agents, c)
        self.polylines = PolylineEncoder(cfg) if cfg.variant.uses_map else None
        self.map_layers = nn.ModuleList(
            EncoderBlock(c, cfg.num_heads, cfg.ff_mult, cfg.dropout) for _ in range(cfg.map_layers)
        )
        self.latents = nn.Parameter(torch.randn(cfg.latent_queries, c) * 0.02)
        self.latent_attn = EncoderBlock(c, cfg.num_heads, cfg.ff_mult, cfg.dropout, cross=True)
        self.layers = nn.ModuleList(
            EncoderBlock(c, cfg.num_heads, cfg.ff_mult, cfg.dropout) for _ in range(cfg.encoder_layers)
        )
        self.norm = nn.LayerNorm(c)

    def agent_embedding(self, scene: SceneInputs) -> torch.Tensor:
        """Per-agent embedding of the initial state plus slot embedding, ``[B,A,C]``."""
        xyh = scene.agent_xyh
        feats = torch.cat(
            [
                xyh[..., :2] / POSITION_SCALE,
                torch.cos(xyh[..., 2:3]),
                torch.sin(xyh[..., 2:3]),
                scene.agent_size / SIZE_SCALE,
                F.one_hot(scene.agent_kind.clamp(0, self.cfg.num_kinds - 1), self.cfg.num_kinds).to(
                    xyh.dtype
                ),
            ],
            dim=-1,
        )
        a = xyh.shape[1]
        emb = self.agent(feats) + self.slot.weight[:a]
        return emb * scene.agent_mask[..., None]

    def forward(self, scene: SceneInputs) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Returns ``(memory [B,A+Q,C], memory_mask [B,A+Q], agent_embedding [B,A,C])``."""
        agents = self.agent_embedding(scene)
        b = agents.shape[0]
        context, context_mask = agents, scene.agent_mask
        if self.polylines is not None:
            pl = self.polylines(scene.map_points, scene.map_point_mask, scene.map_kind, scene.map_signal)
            pl_mask = scene.map_mask
            for layer in self.map_layers:
                pl = layer(pl, mask=pl_mask[:, None, None, :] | _eye_like(pl_mask))
            context = torch.cat([agents, pl], dim=1)
            context_mask = torch.cat([scene.agent_mask, pl_mask], dim=1)
        latents = self.latents.expand(b, -1, -1)
        latents = self.latent_attn(
            latents, context, mask=context_mask[:, None, None, :] | _any_false(context_mask)
        )
        memory = torch.cat([agents, latents], dim=1)
        memory_mask = torch.cat([scene.agent_mask, torch.ones_like(latents[..., 0], dtype=torch.bool)], dim=1)
        for layer in self.layers:
            memory = layer(memory, mask=memory_mask[:, None, None, :])
        return self.norm(memory), memory_mask, agents


def _eye_like(mask: torch.Tensor) -> torch.Tensor:
    """Let every (even padded) query attend to itself so that no attention row is empty."""
    n = mask.shape[-1]
    return torch.eye(n, dtype=torch.bool, device=mask.device)[None, None]


def _any_false(mask: torch.Tensor) -> torch.Tensor:
    """Where a context is entirely padding, open it (its values are zeros) to keep SDPA finite."""
    return (~mask.any(-1))[:, None, None, None]
