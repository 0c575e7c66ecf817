"""The Trajeglish encoder-decoder (paper Sec. 3.2).

Encoder: :mod:`trajeglish_env.model.encoder` (agents and map -> the scene memory).
Decoder: the multi-agent token sequence flattened time-major in agent order, a start token prepended and
the last token popped; token embeddings (zeros where the agent is not observed) plus time and target-agent
embeddings; a masked transformer with cross-attention to the memory; a head tied to the token embedding.
Tokens of class ``k`` live at ids ``k * V .. k * V + V - 1``; logits are restricted to the agent's class.

Shapes: B batch, A agent slots, T future steps, M polylines, P points, C width, V vocabulary.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from trajeglish_env.model.config import ModelConfig, Variant
from trajeglish_env.model.encoder import SceneEncoder, SceneInputs
from trajeglish_env.model.lanes import LaneEncoder
from trajeglish_env.model.layers import (
    MIN_QUERIES,
    DecoderBlock,
    DecoderCache,
    Linear,
    RowGroup,
    invariant_linear,
    row_runs,
)
from trajeglish_env.model.masks import START, decoder_mask, teacher_inputs
from trajeglish_env.model.neighbours import NeighbourEncoder, NeighbourView


def additive_mask(allowed: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """A boolean attention mask as the additive one SDPA derives from it (0 / -inf in ``dtype``): built
    once per call and shared by every layer instead of converted by each attention (same results)."""
    return torch.zeros(allowed.shape, dtype=dtype, device=allowed.device).masked_fill_(
        ~allowed, float("-inf")
    )


JOINT_HEAD_ROWS = 64  # rows of several classes whose logits come from one product (exact: checked 1 .. 64)


class TrajeglishModel(nn.Module):
    """Encoder-decoder over multi-agent motion tokens; see the module docstring for the layout."""

    _drawn_copy: tuple[tuple[object, ...], torch.Tensor] | None = None

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        c = cfg.d_model
        self.encoder = SceneEncoder(cfg)
        self.token = nn.Embedding(cfg.num_kinds * cfg.vocab_size, c)
        self.token_bias = (
            nn.Parameter(torch.zeros(cfg.num_kinds * cfg.vocab_size)) if cfg.token_bias else None
        )
        if cfg.drawn < cfg.vocab_size:  # per class, the drawn token each token counts as (see ModelConfig)
            self.register_buffer(
                "token_source", torch.arange(cfg.vocab_size).repeat(cfg.num_kinds, 1), persistent=True
            )
        self.start = nn.Parameter(torch.randn(c) * 0.02)
        self.time = nn.Embedding(cfg.steps, c)
        self.target_agent = Linear(c, c)
        # trajeglish inputs carry the previous agent's token; the predicted agent's own previous token
        # (earlier in the sequence, so allowed) is added through its own projection: it tells the model the
        # agent's current motion directly instead of through an attention look-up that is slow to learn.
        self.own_previous = Linear(c, c) if cfg.variant is Variant.TRAJEGLISH else None
        self.neighbours = NeighbourEncoder(c) if cfg.neighbour_input else None
        self.lanes = LaneEncoder(c) if cfg.lane_input else None
        self.blocks = nn.ModuleList(
            DecoderBlock(c, cfg.num_heads, cfg.ff_mult, cfg.dropout) for _ in range(cfg.decoder_layers)
        )
        self.norm = nn.LayerNorm(c)
        nn.init.normal_(self.token.weight, std=0.02)
        self.register_buffer("mask", decoder_mask(cfg.variant, cfg.steps, cfg.max_agents), persistent=False)
        self._additive: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}  # see _additive_mask

    # ---------------------------------------------------------------------------------- helpers
    def global_ids(self, tokens: torch.Tensor, kind: torch.Tensor) -> torch.Tensor:
        """Class-local token ids (``-1`` = unobserved) -> ids in the joint embedding table (``-1`` kept)."""
        return torch.where(tokens >= 0, tokens + kind * self.cfg.vocab_size, torch.full_like(tokens, -1))

    def embed_tokens(self, ids: torch.Tensor) -> torch.Tensor:
        """Embeddings of joint ids, zeros where ``ids < 0`` (unobserved agent or padding)."""
        return self.token(ids.clamp(min=0)) * (ids >= 0)[..., None]

    def _head(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The tied head's weights ``[K*D, C]`` and bias ``[K*D]`` of the ``D`` drawn tokens of each class."""
        k, v, d = self.cfg.num_kinds, self.cfg.vocab_size, self.cfg.drawn
        weight, bias = self.token.weight, self.token_bias
        if d < v:
            weight = weight.view(k, v, -1)[:, :d].reshape(k * d, -1)
            bias = None if bias is None else bias.view(k, v)[:, :d].reshape(-1)
        return weight, bias

    def drawn_targets(self, tokens: torch.Tensor, kind: torch.Tensor) -> torch.Tensor:
        """Targets (class-local ids, ``-1`` kept; ``kind`` broadcasts to ``tokens``) as the drawn tokens
        they count as: themselves, unless the model reads more tokens than it draws (``drawn_size``)."""
        if self.cfg.drawn == self.cfg.vocab_size:
            return tokens
        kind = kind.clamp(0, self.cfg.num_kinds - 1).expand_as(tokens)
        mapped = self.token_source[kind, tokens.clamp(min=0)]
        return torch.where(tokens >= 0, mapped, tokens)

    def class_logits(self, hidden: torch.Tensor, kind: torch.Tensor) -> torch.Tensor:
        """Tied head restricted to the class: ``hidden [...,C]``, ``kind [...]`` -> ``[...,D]`` (the drawn
        tokens, ``ModelConfig.drawn``)."""
        weight, bias = self._head()
        d = self.cfg.drawn
        logits = invariant_linear(self.norm(hidden), weight)  # [..., K*D]
        if bias is not None:
            logits = logits + bias
        logits = logits.view(*logits.shape[:-1], self.cfg.num_kinds, d)
        index = kind.clamp(0, self.cfg.num_kinds - 1)[..., None, None].expand(*kind.shape, 1, d)
        return logits.gather(-2, index).squeeze(-2)

    def class_logits_by_kind(self, hidden: torch.Tensor, kind: np.ndarray) -> torch.Tensor:
        """:meth:`class_logits` of ``hidden [n,C]`` with the classes ``kind [n]`` known on the host: only
        each class's slice of the head is multiplied (the same numbers, a third of the work); up to
        :data:`JOINT_HEAD_ROWS` rows of several classes in one product with every class's slice (a call
        per class costs more than the work it saves there: 485 -> 401 us a single env's head pass)."""
        x = self.norm(hidden)
        v, d = self.cfg.vocab_size, self.cfg.drawn
        kind = np.clip(kind, 0, self.cfg.num_kinds - 1)
        present = np.unique(kind)
        bias = self.token_bias
        if len(present) == 1:
            k = int(present[0])
            out = invariant_linear(x, self.token.weight[k * v : k * v + d])
            return out if bias is None else out + bias[k * v : k * v + d]
        if len(kind) <= JOINT_HEAD_ROWS and not torch.is_grad_enabled():
            classes = self.cfg.num_kinds
            rows, at = torch.arange(len(kind), device=x.device), torch.from_numpy(kind).to(x.device)
            out = invariant_linear(x, self._drawn_head()).view(len(kind), classes, d)[rows, at]
            return out if bias is None else out + bias.view(classes, v)[:, :d][at]
        out = x.new_empty(len(kind), d)
        for k in present.tolist():
            rows = torch.from_numpy(np.flatnonzero(kind == k)).to(x.device)
            out[rows] = invariant_linear(x[rows], self.token.weight[k * v : k * v + d])
            if bias is not None:
                out[rows] += bias[k * v : k * v + d]
        return out

    def _drawn_head(self) -> torch.Tensor:
        """The head's rows of every class's drawn tokens ``[num_kinds * drawn, C]`` (a copy where ``drawn <
        vocab_size``, made again only when the weights change)."""
        w, k, v, d = self.token.weight, self.cfg.num_kinds, self.cfg.vocab_size, self.cfg.drawn
        key = (w._version, w.data_ptr(), w.device, w.dtype)
        if self._drawn_copy is None or self._drawn_copy[0] != key:
            self._drawn_copy = (key, w.detach().view(k, v, -1)[:, :d].reshape(k * d, -1).contiguous())
        return self._drawn_copy[1]

    def _positions(self, agents: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """Time + target-agent embeddings of flattened positions ``index`` (``[n]``, or ``[B,n]`` per row)."""
        a = agents.shape[1]
        if index.dim() == 1:
            return self.time(index // a)[None] + self.target_agent(agents[:, index % a])
        slot = agents.gather(1, (index % a)[..., None].expand(-1, -1, agents.shape[-1]))
        return self.time(index // a) + self.target_agent(slot)

    def _decoder_inputs(
        self, carried_ids: torch.Tensor, own_ids: torch.Tensor, view: NeighbourView | None = None
    ) -> torch.Tensor:
        """Embeddings of the tokens positions carry (the start token where :data:`START`), plus, for the
        trajeglish variant, the projected previous token of each position's own agent, plus (with
        ``neighbour_input``) what each position's agent sees of its neighbours (``view [B,n]``), plus (with
        ``lane_input``) what it sees of the road around it (the view's ``road``)."""
        is_start = (carried_ids == START)[..., None]
        x = torch.where(is_start, self.start, self.embed_tokens(carried_ids))
        if self.own_previous is not None:
            x = x + self.own_previous(self.embed_tokens(own_ids))
        if self.cfg.reads_states and view is None:
            raise ValueError(
                "this model reads the states of its agents' step (ModelConfig.neighbour_input / lane_input): "
                "pass their view (trajeglish_env.model.neighbours)"
            )
        if self.neighbours is not None and view is not None:
            x = x + self.neighbours(view).to(x.dtype)
        if self.lanes is not None and view is not None:
            if view.road_code is not None:  # encoded beforehand (the sampler)
                return x + view.road_code.to(x.dtype)
            if view.road is None or view.road_mask is None:
                raise ValueError(
                    "this model reads the road around its agents (ModelConfig.lane_input): the view has no "
                    "road features (trajeglish_env.model.lanes)"
                )
            x = x + self.lanes(view.road, view.road_mask).to(x.dtype)
        return x

    # ---------------------------------------------------------------------------------- training
    def forward(
        self, scene: SceneInputs, input_tokens: torch.Tensor, view: NeighbourView | None = None
    ) -> torch.Tensor:
        """Teacher-forced logits ``[B,T,A,V]`` for targets at every (step, agent slot).

        ``input_tokens [B,A,T]`` class-local ids of the tokens fed as input (the noisy ones in training;
        ``-1`` where unobserved); position (t, a) never sees its own or later tokens. ``view [B,T,A]``:
        the neighbour features (:func:`~trajeglish_env.model.neighbours.window_view`), read by models with
        ``neighbour_input``.
        """
        b, a, t = input_tokens.shape
        kind = scene.agent_kind[:, None, :].expand(b, t, a)
        return self.class_logits(self.hidden(scene, input_tokens, view), kind)

    def hidden(
        self, scene: SceneInputs, input_tokens: torch.Tensor, view: NeighbourView | None = None
    ) -> torch.Tensor:
        """The decoder's last states ``[B,T,A,C]`` of :meth:`forward` (before the head)."""
        b, a, t = input_tokens.shape
        if a > self.cfg.max_agents or t > self.cfg.steps:
            raise ValueError(
                f"model takes at most {self.cfg.max_agents} agents x {self.cfg.steps} steps, got {a} x {t}"
            )
        memory, memory_mask, agents = self.encoder(scene)
        ids = self.global_ids(input_tokens, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(b, t * a)
        flat = None if view is None else view.index(slice(None), slice(0, t)).flat_time_major()
        x = self._decoder_inputs(*teacher_inputs(self.cfg.variant, ids, a), flat)
        x = x + self._positions(agents, torch.arange(t * a, device=x.device))
        # training: the trajeglish variant's mask is the causal one, which SDPA skips block by block (the
        # same numbers; inference keeps the explicit mask, bit for bit the cached decoding's)
        causal = self.cfg.variant is Variant.TRAJEGLISH and torch.is_grad_enabled()
        mask = (
            None
            if causal
            else decoder_mask(self.cfg.variant, t, a, x.device)
            if a != self.cfg.max_agents
            else self.mask[: t * a, : t * a]
        )
        mem_mask = memory_mask[:, None, None, :]
        for block in self.blocks:
            k, v = block.cross_attn.keys_values(memory)
            x = block(x, mask, k, v, mem_mask, causal)
        return x.view(b, t, a, -1)

    def loss(
        self,
        scene: SceneInputs,
        input_tokens: torch.Tensor,
        targets: torch.Tensor,
        view: NeighbourView | None = None,
        weights: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, float]:
        """Mean cross-entropy (nats) over observed targets ``[B,A,T]`` (``-1`` ignored) and their count; with
        ``weights [B,A,T]`` (training's :mod:`~trajeglish_env.training.interaction_weights`) the weighted mean
        and the observed targets' weight sum. With gradients on (training) the head multiplies only the
        positions that have a target, each by its class's slice (:meth:`_target_loss`)."""
        if torch.is_grad_enabled():
            return self._target_loss(self.hidden(scene, input_tokens, view), scene, targets, weights)
        return self.loss_of_logits(self.forward(scene, input_tokens, view), scene, targets, weights)

    def _target_loss(
        self,
        hidden: torch.Tensor,
        scene: SceneInputs,
        targets: torch.Tensor,
        weights: torch.Tensor | None,
    ) -> tuple[torch.Tensor, float]:
        """:meth:`loss_of_logits` of :meth:`class_logits` at the observed targets alone: the same sums, the
        head's work cut to the positions with a target (in training windows of small scenes most of the
        24 slots are empty) and to their class's tokens (a third of the tied head's rows)."""
        k, d = self.cfg.num_kinds, self.cfg.drawn
        tgt = self.drawn_targets(targets, scene.agent_kind[:, :, None]).transpose(1, 2)  # [B,T,A]
        tgt = torch.where(scene.agent_mask[:, None, :], tgt, torch.full_like(tgt, -1))
        keep = tgt >= 0
        x, tgt = self.norm(hidden[keep]), tgt[keep]  # [n,C], [n]
        kind = scene.agent_kind.clamp(0, k - 1)[:, None, :].expand_as(keep)[keep]
        weight, bias = self._head()
        weight = weight.view(k, d, -1)
        each = x.new_zeros(len(tgt), dtype=torch.float32)
        for c in torch.unique(kind).tolist():
            rows = kind == c
            logits = F.linear(x[rows], weight[c], None if bias is None else bias[c * d : (c + 1) * d])
            each = each.index_put(
                (rows.nonzero()[:, 0],), F.cross_entropy(logits.float(), tgt[rows], reduction="none")
            )
        if weights is None:
            n = len(tgt)
            return each.sum() / max(n, 1), n
        w = weights.transpose(1, 2)[keep].to(each.dtype)
        total = float(w.sum())
        return (each * w).sum() / max(total, 1e-9), total

    def loss_of_logits(
        self,
        logits: torch.Tensor,
        scene: SceneInputs,
        targets: torch.Tensor,
        weights: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, float]:
        """:meth:`loss` of teacher-forced ``logits [B,T,A,D]`` already computed (:meth:`forward`)."""
        tgt = self.drawn_targets(targets, scene.agent_kind[:, :, None]).transpose(1, 2)  # [B,T,A]
        tgt = torch.where(scene.agent_mask[:, None, :], tgt, torch.full_like(tgt, -1))
        if weights is None:
            n = int((tgt >= 0).sum())
            loss = F.cross_entropy(
                logits.reshape(-1, logits.shape[-1]), tgt.reshape(-1), ignore_index=-1, reduction="sum"
            )
            return loss / max(n, 1), n
        each = F.cross_entropy(
            logits.reshape(-1, logits.shape[-1]), tgt.reshape(-1), ignore_index=-1, reduction="none"
        )  # 0 where ignored
        w = (weights.transpose(1, 2).reshape(-1) * (tgt.reshape(-1) >= 0)).to(each.dtype)
        total = float(w.sum())
        return (each * w).sum() / max(total, 1e-9), total

    # ---------------------------------------------------------------------------------- decoding
    def empty_cache(self, batch: int, dtype: torch.dtype) -> DecoderCache:
        """A zeroed cache of ``batch`` rows for one whole context (``max_agents * steps`` positions, keys
        and values in ``dtype``); its memory is all visible, so that unused rows stay finite."""
        h, dh = self.cfg.num_heads, self.cfg.d_model // self.cfg.num_heads
        length, memory = self.cfg.max_agents * self.cfg.steps, self.cfg.max_agents + self.cfg.latent_queries
        dev = self.start.device
        layers = range(len(self.blocks))
        return DecoderCache(
            self_k=[torch.zeros(batch, h, length, dh, dtype=dtype, device=dev) for _ in layers],
            self_v=[torch.zeros(batch, h, length, dh, dtype=dtype, device=dev) for _ in layers],
            cross_k=[torch.zeros(batch, h, memory, dh, dtype=dtype, device=dev) for _ in layers],
            cross_v=[torch.zeros(batch, h, memory, dh, dtype=dtype, device=dev) for _ in layers],
            memory_mask=torch.ones(batch, 1, 1, memory, dtype=torch.bool, device=dev),
        )

    @torch.no_grad()
    def encode_into(self, cache: DecoderCache, scene: SceneInputs) -> torch.Tensor:
        """Encode the scene into a cache (e.g. :meth:`DecoderCache.rows` views of a bigger one): its
        cross-attention keys/values and memory mask are overwritten. Returns the agent embeddings
        ``[B,A,C]``, which every decoding call of these rows takes."""
        memory, memory_mask, agents = self.encoder(scene)
        if tuple(memory.shape[:2]) != (cache.cross_k[0].shape[0], cache.cross_k[0].shape[2]):
            raise ValueError(
                f"encode_into: a scene memory of {tuple(memory.shape[:2])} (rows, entries) does not fit a "
                f"cache of {cache.cross_k[0].shape[0]} rows and {cache.cross_k[0].shape[2]} memory entries"
            )
        for i, blk in enumerate(self.blocks):
            k, v = blk.cross_attn.keys_values(memory)
            cache.cross_k[i].copy_(k)
            cache.cross_v[i].copy_(v)
        cache.memory_mask.copy_(memory_mask[:, None, None, :])
        return agents

    @torch.no_grad()
    def prime(
        self,
        cache: DecoderCache,
        agents: torch.Tensor,
        carried_ids: torch.Tensor,
        own_ids: torch.Tensor,
        view: NeighbourView | None = None,
    ) -> None:
        """Store positions ``0 .. n-1`` of every row (teacher forcing a window's known steps) without
        computing their outputs: the last layer stops once its keys and values are stored."""
        b, n = carried_ids.shape
        start, count = np.zeros(b, dtype=np.int64), np.full(b, n, dtype=np.int64)
        self._decode(cache, agents, carried_ids, own_ids, start, count, outputs=False, view=view)

    @torch.no_grad()
    def decode_at(
        self,
        cache: DecoderCache,
        agents: torch.Tensor,
        carried_ids: torch.Tensor,
        own_ids: torch.Tensor,
        start: np.ndarray,
        count: np.ndarray,
        view: NeighbourView | None = None,
        read: tuple[int, int] | None = None,
    ) -> torch.Tensor:
        """Hidden states ``[B,n,C]`` (logits: :meth:`class_logits`) of a chunk of positions per row: row
        ``b`` decodes positions ``start[b] .. start[b]+count[b]-1`` of its own window (``count`` 0: the row
        is idle; inputs past ``count[b]`` are padding), storing them in its cache.

        ``carried_ids [B,n]``: joint ids of the tokens those positions carry as input (:data:`START`: the
        start token, ``-1``: unobserved; see :mod:`~trajeglish_env.model.masks`); ``own_ids [B,n]``: joint
        ids of the same agents' tokens one step earlier (-1: none; only the trajeglish variant uses them).
        ``start``/``count`` are host arrays (no device sync). A position's numbers depend neither on the
        other rows nor on its chunk: a row attends over the keys up to the end of the step after its chunk's
        first position (masked; or of its last position's step, for chunks of more than two steps), rows
        bounded alike attend together, and attention gets at least :data:`~trajeglish_env.model.layers.
        MIN_QUERIES` queries (inputs are padded), the fewest from which SDPA's CPU kernels round alike. ``view
        [B,n]``: the positions' neighbour features (models with ``neighbour_input``). ``read = (first,
        stop)``: only the outputs of input slots ``first .. stop - 1`` are read (the others are zeros; the
        last layer stores their keys and values only, as priming does)."""
        out = self._decode(cache, agents, carried_ids, own_ids, start, count, True, view, read)
        assert out is not None
        return out

    def _group_mask(
        self, first: np.ndarray, queries: torch.Tensor, keys: int, cache: DecoderCache
    ) -> torch.Tensor:
        """The additive self-attention mask ``[g,1,n,keys]`` of a row group whose rows decode the (clamped)
        cache positions ``queries [g,n]`` from ``first [g]`` on: rows of :meth:`_additive_mask`, one shared by
        every row (expanded, no copy) when they all start alike, as the rows of a lockstep batch do."""
        full = self._additive_mask(cache.self_k[0].dtype)
        if (first == first[0]).all():
            return full[queries[0], :keys][None, None].expand(len(first), 1, -1, -1)
        return full[queries][:, None, :, :keys].contiguous()

    def _additive_mask(self, dtype: torch.dtype) -> torch.Tensor:
        """The decoder mask as the additive one SDPA derives from it (0 / -inf, :func:`additive_mask`) in
        ``dtype``, made once per dtype and device instead of at every call (the same numbers)."""
        key = (dtype, self.mask.device)
        cached = self._additive.get(key)
        if cached is None:
            cached = self._additive[key] = additive_mask(self.mask, dtype)
        return cached

    def _decode(
        self,
        cache: DecoderCache,
        agents: torch.Tensor,
        carried_ids: torch.Tensor,
        own_ids: torch.Tensor,
        start: np.ndarray,
        count: np.ndarray,
        outputs: bool,
        view: NeighbourView | None = None,
        read: tuple[int, int] | None = None,
    ) -> torch.Tensor | None:
        """:meth:`decode_at`; with ``outputs`` False the last layer only stores its keys and values."""
        n, a = carried_ids.shape[1], agents.shape[1]
        start, count = np.asarray(start, dtype=np.int64), np.asarray(count, dtype=np.int64)
        busy = count > 0
        if (count > n).any() or (busy & ((start < 0) | (start + count > cache.capacity))).any():
            raise ValueError(
                f"decode_at: chunks {list(zip(start.tolist(), count.tolist(), strict=True))} need inputs "
                f"({n}) >= count and must fit the cache ({cache.capacity})"
            )
        dev = carried_ids.device
        if n < MIN_QUERIES:  # pad with idle inputs: attention computes a few queries otherwise rounded
            pad = carried_ids.new_full((carried_ids.shape[0], MIN_QUERIES - n), -1)
            carried_ids, own_ids = torch.cat([carried_ids, pad], 1), torch.cat([own_ids, pad], 1)
            if view is not None:
                view = view.padded(MIN_QUERIES)
            out = self._decode(cache, agents, carried_ids, own_ids, start, count, outputs, view, read)
            return None if out is None else out[:, :n]
        if read is not None:  # at least MIN_QUERIES read slots (within the inputs)
            first = min(read[0], n - MIN_QUERIES)
            read = (first, max(read[1], first + MIN_QUERIES))
        batch, cache_of, rows_np, cross_runs = len(count), None, np.arange(len(count)), None
        memory_mask = cache.memory_mask
        if busy.any() and not busy.all():  # compute the busy rows only (a row's numbers are the same)
            rows_np = np.flatnonzero(busy)
            cache_of = torch.from_numpy(rows_np).to(dev)
            carried_ids, own_ids, agents = carried_ids[cache_of], own_ids[cache_of], agents[cache_of]
            view = None if view is None else view.index(cache_of)
            start, count, busy = start[rows_np], count[rows_np], busy[rows_np]
            memory_mask = memory_mask[cache_of]
            cross_runs = row_runs(rows_np)  # attention reads the caches' rows as views, run by run
        # the model step whose end bounds a row's keys: its last position's; when decoding, at least the step
        # after its first position's (capped by the cache), so that a chunk that looks one step ahead attends
        # as one that does not (attention rounds with the number of keys, masked ones too)
        step = (start + count - 1) // a
        if outputs:
            step = np.maximum(step, np.minimum(start // a + 1, cache.capacity // a - 1))
        if busy.any():  # idle rows ride along with the largest group (nothing written), so it needs no copy
            values, counts = np.unique(step[busy], return_counts=True)
            step = np.where(busy, step, values[np.argmax(counts)])
        # every row stores the same positions: one strided copy per layer
        span = (
            (int(start[0]), int(count[0]))
            if cache_of is None and busy.all() and (start == start[0]).all() and (count == count[0]).all()
            else None
        )
        groups = []
        for s in np.unique(step[busy]).tolist():
            rows = np.flatnonzero(step == s)
            index = None if len(rows) == len(step) else torch.from_numpy(rows).to(dev)
            queries = torch.from_numpy(start[rows]).to(dev)[:, None] + torch.arange(n, device=dev)
            keys = (s + 1) * a
            mask = self._group_mask(start[rows], queries.clamp(max=cache.capacity - 1), keys, cache)
            local, slot = np.nonzero(count[rows][:, None] > np.arange(n))  # host side: no device sync
            writes = (torch.from_numpy(rows[local]).to(dev), torch.from_numpy(slot).to(dev))
            positions = queries[torch.from_numpy(local).to(dev), writes[1]]
            runs = None if index is None and cache_of is None else row_runs(rows_np[rows])
            groups.append(RowGroup(index, keys, mask, positions, writes, span, cache_of, runs))
        index = torch.from_numpy(start).to(dev)[:, None] + torch.arange(n, device=dev)  # [B,n]
        index = index.clamp(max=cache.capacity - 1)
        x = self._decoder_inputs(carried_ids, own_ids, view) + self._positions(agents, index)
        # a memory with nothing masked needs no mask (the same numbers: SDPA adds zeros otherwise)
        cross_mask = None if cache.memory_full else additive_mask(memory_mask, cache.cross_k[0].dtype)
        last = len(self.blocks) - 1
        for i, block in enumerate(self.blocks):
            kv = (cache.self_k[i], cache.self_v[i], groups)
            cross = (cache.cross_k[i], cache.cross_v[i], cross_mask)
            if i == last and not outputs:
                block.store_keys(x, kv)
                return None
            if i == last and read is not None and read != (0, n):
                part = block.decode(x, kv, *cross, slice(*read), cross_runs)
                x = part.new_zeros(part.shape[0], n, part.shape[-1])
                x[:, read[0] : read[1]] = part
                break
            x = block.decode(x, kv, *cross, cross_runs=cross_runs)
        if cache_of is None:
            return x
        out = x.new_zeros(batch, n, x.shape[-1])  # idle rows: zeros (never read)
        out[cache_of] = x
        return out
