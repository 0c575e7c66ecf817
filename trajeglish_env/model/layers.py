"""Transformer building blocks with an optional key/value cache for incremental decoding.

Inference is *batch-invariant*: a row's outputs do not depend on which other rows share its batch, so a
scene simulated in a batch of many gives bit-identical tokens to the same scene simulated alone. BLAS
picks different kernels (and summation orders) for very small matrices, so :class:`Linear` pads inputs
of fewer than ``MIN_GEMM_ROWS`` rows; cached decoding attends, per group of rows, over the cached keys up
to the end of the group's model step (masked, a length set by the row alone) rather than over a
batch-dependent prefix.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

MIN_GEMM_ROWS = 32  # below this many rows MKL switches kernels and a row's result depends on the batch
# below this many queries SDPA's CPU kernels round a query's result differently (float32 and bfloat16,
# masked or not; from 4 on, any number of queries and any slot give the same numbers): cached decoding
# computes at least this many
MIN_QUERIES = 4


class _ComputeStack(threading.local):
    """Per thread (engines may decode in threads side by side): the dtypes of :func:`linear_compute`."""

    def __init__(self) -> None:
        # inference linear layers multiply in the last of these dtypes (none: in their own)
        self.dtypes: list[torch.dtype] = []


_COMPUTE_STACK = _ComputeStack()


@contextmanager
def linear_compute(dtype: torch.dtype | None) -> Iterator[None]:
    """Inside, :class:`Linear` layers at inference (no grad) multiply in ``dtype`` (e.g. bfloat16: 4-7x the
    float32 matrix throughput on CPUs with native bfloat16; inputs and weights rounded to it, products
    accumulated in float32, the bias added in float32); None or float32: unchanged. Small inputs are
    padded as in float32 (a single row takes another kernel in bfloat16 too)."""
    if dtype is None or dtype == torch.float32:
        yield
        return
    _COMPUTE_STACK.dtypes.append(dtype)
    try:
        yield
    finally:
        _COMPUTE_STACK.dtypes.pop()


def invariant_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """``F.linear`` whose result per row does not depend on the number of rows (see the module docstring)."""
    rows = x.numel() // max(x.shape[-1], 1)
    if rows >= MIN_GEMM_ROWS or torch.is_grad_enabled():
        return F.linear(x, weight, bias)
    flat = x.reshape(rows, x.shape[-1])
    padded = torch.cat([flat, flat.new_zeros(MIN_GEMM_ROWS - rows, flat.shape[1])])
    return F.linear(padded, weight, bias)[:rows].reshape(*x.shape[:-1], weight.shape[0])


def bucket_rows(rows: int) -> int:
    """``rows`` rounded up to a bucket: at least MIN_GEMM_ROWS, then 8 buckets per doubling (at most 1/8
    padding), so a decoding run meets a few dozen row counts per layer instead of hundreds."""
    if rows <= MIN_GEMM_ROWS:
        return MIN_GEMM_ROWS
    step = 1 << max(rows.bit_length() - 4, 0)
    return -(-rows // step) * step


def bucketed_linear(x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``x @ weight.T`` (no bias) in ``weight``'s dtype, the rows padded with zeros to :func:`bucket_rows`:
    oneDNN compiles (about 1 ms) and caches a kernel per matrix shape and keeps 1,024, so unbounded row
    counts make it compile and evict all along; the padding rides on the dtype conversion's copy. A row's
    numbers do not depend on the padding (the kernels are per row above MIN_GEMM_ROWS rows)."""
    k = x.shape[-1]
    rows = x.numel() // max(k, 1)
    padded = x.new_empty(bucket_rows(rows), k, dtype=weight.dtype)
    padded[:rows].copy_(x.reshape(rows, k))
    padded[rows:].zero_()
    return F.linear(padded, weight)[:rows].reshape(*x.shape[:-1], weight.shape[0])


class Linear(nn.Linear):
    """``nn.Linear`` (same parameters) that is batch-invariant at inference, and multiplies in the dtype
    of :func:`linear_compute` there."""

    _compute_copy: tuple[tuple[torch.dtype, int, int], torch.Tensor] | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x W^T + b`` (batch-invariant; in the compute dtype at inference)."""
        compute = _COMPUTE_STACK.dtypes
        if compute and not torch.is_grad_enabled():
            y = bucketed_linear(x, self._weight_in(compute[-1]))
            # in the parameters' dtype whatever the input's: widening y is exact, and the bias is added in
            # place (the numbers of a mixed-dtype sum, which costs up to 1.4x a widening and an add)
            y = y.to(self.weight.dtype)
            return y if self.bias is None else y.add_(self.bias)
        return invariant_linear(x, self.weight, self.bias)

    def _weight_in(self, dtype: torch.dtype) -> torch.Tensor:
        """The weight in ``dtype``, converted again only when the weight changed (training steps)."""
        key = (dtype, self.weight._version, self.weight.data_ptr())
        if self._compute_copy is None or self._compute_copy[0] != key:
            self._compute_copy = (key, self.weight.detach().to(dtype))
        return self._compute_copy[1]


class Attention(nn.Module):
    """Multi-head attention through PyTorch SDPA (flash/efficient kernels on CUDA)."""

    def __init__(self, d_model: int, num_heads: int, dropout: float = 0.0):
        super().__init__()
        self.num_heads = num_heads
        self.q = Linear(d_model, d_model)
        self.kv = Linear(d_model, 2 * d_model)
        self.out = Linear(d_model, d_model)
        self.dropout = dropout

    def split(self, x: torch.Tensor) -> torch.Tensor:
        """``[B,N,C]`` -> ``[B,H,N,C/H]``: the heads as a batch axis."""
        b, n, c = x.shape
        return x.view(b, n, self.num_heads, c // self.num_heads).transpose(1, 2)  # [B,H,N,Dh]

    def keys_values(self, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Keys and values of ``context``, split into heads (cached by the decoder)."""
        k, v = self.kv(context).chunk(2, dim=-1)
        return self.split(k), self.split(v)

    def attend(
        self,
        x: torch.Tensor,
        k: torch.Tensor,
        v: torch.Tensor,
        mask: torch.Tensor | None,
        causal: bool = False,
    ) -> torch.Tensor:
        """Queries from ``x [B,N,C]`` against split keys/values; ``mask`` broadcastable to [B,H,N,K], or
        (``causal``, training only) the causal mask of a square attention, which SDPA then skips by blocks."""
        q = self.split(self.q(x)).to(k.dtype)  # a reduced-precision cache computes in its own dtype
        p = self.dropout if self.training else 0.0
        if causal and not torch.is_grad_enabled():
            raise ValueError("Attention.attend: causal=True is for training; pass the mask at inference")
        if torch.is_grad_enabled() and q.device.type == "cpu" and torch.is_autocast_enabled("cpu"):
            # bfloat16 autocast on CPU (training): the products run in bfloat16, attention in float32,
            # whose CPU flash kernel's backward is 1.7x faster than in bfloat16 (training/precision.py)
            with torch.autocast("cpu", enabled=False):
                y = F.scaled_dot_product_attention(
                    q.float(), k.float(), v.float(), attn_mask=mask, dropout_p=p, is_causal=causal
                )
        else:
            y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p, is_causal=causal)
        return self._project(y, x.dtype)

    def attend_runs(
        self,
        x: torch.Tensor,
        k: torch.Tensor,
        v: torch.Tensor,
        keys: int,
        mask: torch.Tensor | None,
        runs: tuple[tuple[int, int, int], ...],
    ) -> torch.Tensor:
        """:meth:`attend` (inference) of rows ``x [g,N,C]`` whose keys/values are rows of the full caches
        ``k``/``v [B,H,L,Dh]``: each run ``(first, stop, row)`` of them reads cache rows ``row ..`` and
        keys ``0 .. keys - 1`` as views, so no cache rows are copied (the same numbers: attention is per
        row). ``mask``: per row of ``x`` (``[g,1,N,keys]``), or None."""
        q = self.split(self.q(x)).to(k.dtype)
        y = q.new_empty(q.shape)
        for first, stop, row in runs:
            last = row + stop - first
            part = None if mask is None else mask[first:stop]
            y[first:stop] = F.scaled_dot_product_attention(
                q[first:stop], k[row:last, :, :keys], v[row:last, :, :keys], attn_mask=part
            )
        return self._project(y, x.dtype)

    def _project(self, y: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """The output projection of attention's result ``y [B,H,N,Dh]``."""
        compute = _COMPUTE_STACK.dtypes
        if not (compute and compute[-1] == y.dtype and not torch.is_grad_enabled()):
            y = y.to(dtype)  # else the output projection multiplies in y's dtype: no round trip
        b, h, n, dh = y.shape
        return self.out(y.transpose(1, 2).reshape(b, n, h * dh))

    def forward(
        self, x: torch.Tensor, context: torch.Tensor, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Attend from ``x`` to ``context`` (``mask``: True where attention is allowed)."""
        k, v = self.keys_values(context)
        return self.attend(x, k, v, mask)


class FeedForward(nn.Sequential):
    """The block's MLP: widen by ``mult``, GELU, project back, dropout."""

    def __init__(self, d_model: int, mult: int, dropout: float):
        super().__init__(
            Linear(d_model, mult * d_model),
            nn.GELU(),
            Linear(mult * d_model, d_model),
            nn.Dropout(dropout),
        )


class EncoderBlock(nn.Module):
    """Pre-norm block: self-attention (or, with ``cross``, attention to a context), then feed-forward."""

    def __init__(self, d_model: int, num_heads: int, ff_mult: int, dropout: float, cross: bool = False):
        super().__init__()
        self.norm_x = nn.LayerNorm(d_model)
        self.norm_ctx = nn.LayerNorm(d_model) if cross else None
        self.attn = Attention(d_model, num_heads, dropout)
        self.norm_ff = nn.LayerNorm(d_model)
        self.ff = FeedForward(d_model, ff_mult, dropout)

    def forward(
        self, x: torch.Tensor, context: torch.Tensor | None = None, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The block on ``x`` (with ``context`` for cross-attention)."""
        h = self.norm_x(x)
        if (context is None) != (self.norm_ctx is None):
            raise ValueError("EncoderBlock: pass a context exactly when the block was built with cross=True")
        ctx = h if self.norm_ctx is None else self.norm_ctx(context)
        x = x + self.attn(h, ctx, mask)
        return x + self.ff(self.norm_ff(x))


@dataclass
class DecoderCache:
    """Preallocated self-attention keys/values per layer and precomputed cross-attention keys/values."""

    self_k: list[torch.Tensor]
    self_v: list[torch.Tensor]
    cross_k: list[torch.Tensor]
    cross_v: list[torch.Tensor]
    memory_mask: torch.Tensor  # [B,1,1,M]
    memory_full: bool = False  # the owner knows (host side) that memory_mask is all True

    @property
    def capacity(self) -> int:
        """Positions the cache holds."""
        return int(self.self_k[0].shape[2])

    def rows(self, index: slice) -> DecoderCache:
        """Batch rows ``index`` as views (what is written to them lands in this cache)."""
        return DecoderCache(
            [k[index] for k in self.self_k],
            [v[index] for v in self.self_v],
            [k[index] for k in self.cross_k],
            [v[index] for v in self.cross_v],
            self.memory_mask[index],
        )


@dataclass(frozen=True)
class RowGroup:
    """Rows of a batch (``rows`` None: every row) attending over the cached keys ``0 .. keys - 1`` under
    ``mask [g,1,n,keys]`` (boolean, or additive in the cache dtype); ``positions [w]`` are the cache
    positions of the new keys/values to store, taken from batch row ``writes[0]`` and input slot
    ``writes[1]`` (padding inputs are not stored). ``cache_of`` maps batch rows to cache rows when a call
    computes only some rows of its cache (None: batch row ``b`` is cache row ``b``)."""

    rows: torch.Tensor | None
    keys: int
    mask: torch.Tensor
    positions: torch.Tensor
    writes: tuple[torch.Tensor, torch.Tensor]
    # set when every batch row stores its first ``span[1]`` inputs at positions ``span[0]`` onwards
    span: tuple[int, int] | None = None
    cache_of: torch.Tensor | None = None
    # when the group is not every cache row: runs ``(first, stop, row)`` of its rows (in group order)
    # that are consecutive cache rows from ``row`` on, which attention reads as views instead of a copy
    runs: tuple[tuple[int, int, int], ...] | None = None

    def store(self, cache: torch.Tensor, new: torch.Tensor) -> None:
        """Write the group's new keys (or values) ``new [B,H,n,Dh]`` into ``cache [B,H,L,Dh]``."""
        if self.span is not None:  # the same positions in every row: a strided copy, no gather + scatter
            first, width = self.span
            cache[:, :, first : first + width] = new[:, :, :width].to(cache.dtype)
        else:
            batch_rows, slot = self.writes
            cache_rows = batch_rows if self.cache_of is None else self.cache_of[batch_rows]
            cache[cache_rows, :, self.positions] = new[batch_rows, :, slot].to(cache.dtype)

    @property
    def select(self) -> slice | torch.Tensor:
        """Index of the group's rows (a slice, i.e. views, when it is every row)."""
        return slice(None) if self.rows is None else self.rows

    @property
    def cache_select(self) -> slice | torch.Tensor:
        """Index of the group's rows in the cache."""
        if self.cache_of is None:
            return self.select
        return self.cache_of if self.rows is None else self.cache_of[self.rows]


def row_runs(cache_rows: np.ndarray) -> tuple[tuple[int, int, int], ...]:
    """Runs ``(first, stop, row)`` of ``cache_rows`` (increasing): entries ``first .. stop - 1`` are the
    consecutive cache rows ``row ..``."""
    breaks = np.flatnonzero(np.diff(cache_rows) != 1) + 1
    starts, stops = np.r_[0, breaks], np.r_[breaks, len(cache_rows)]
    return tuple((int(a), int(b), int(cache_rows[a])) for a, b in zip(starts, stops, strict=True))


# one layer's cache in a decoding call: its keys and values [B,H,L,Dh] and the call's row groups
LayerCache = tuple[torch.Tensor, torch.Tensor, list[RowGroup]]


class DecoderBlock(nn.Module):
    """Pre-norm block: masked self-attention (cacheable), cross-attention to the scene, feed-forward."""

    def __init__(self, d_model: int, num_heads: int, ff_mult: int, dropout: float):
        super().__init__()
        self.norm_self = nn.LayerNorm(d_model)
        self.self_attn = Attention(d_model, num_heads, dropout)
        self.norm_cross = nn.LayerNorm(d_model)
        self.cross_attn = Attention(d_model, num_heads, dropout)
        self.norm_ff = nn.LayerNorm(d_model)
        self.ff = FeedForward(d_model, ff_mult, dropout)

    def forward(
        self,
        x: torch.Tensor,
        self_mask: torch.Tensor | None,
        cross_k: torch.Tensor,
        cross_v: torch.Tensor,
        memory_mask: torch.Tensor | None,
        causal: bool = False,
    ) -> torch.Tensor:
        """The whole sequence ``x [B,N,C]`` at once (teacher forcing), self-attention under ``self_mask``
        (``causal``: under the causal mask, ``self_mask`` None; training only)."""
        h = self.norm_self(x)
        k, v = self.self_attn.keys_values(h)
        x = x + self.self_attn.attend(h, k, v, self_mask, causal)
        return self._cross_and_ff(x, cross_k, cross_v, memory_mask)

    def decode(
        self,
        x: torch.Tensor,
        cache: LayerCache,
        cross_k: torch.Tensor,
        cross_v: torch.Tensor,
        memory_mask: torch.Tensor | None,
        queries: slice = slice(None),
        cross_runs: tuple[tuple[int, int, int], ...] | None = None,
    ) -> torch.Tensor:
        """New positions ``x [B,n,C]`` through the cache: each :class:`RowGroup` stores its keys/values
        and attends over its own cached prefix under its own mask (fixed key length per group). Returns
        the outputs of positions ``queries`` only (every position stores its keys and values).
        ``cross_runs``: ``cross_k``/``cross_v`` are the whole cache's, read by runs of rows (see
        :meth:`Attention.attend_runs`)."""
        h = self.norm_self(x)
        k, v = self.self_attn.keys_values(h)
        ck, cv, groups = cache
        x, h = x[:, queries], h[:, queries]
        whole = len(groups) == 1 and groups[0].rows is None  # every row in one group: no scatter needed
        attended = h if whole else torch.zeros_like(h)
        for g in groups:
            rows, mask = g.select, g.mask[:, :, queries]
            g.store(ck, k)
            g.store(cv, v)
            if g.runs is None:
                keys, values = ck[g.cache_select, :, : g.keys], cv[g.cache_select, :, : g.keys]  # views
                out = self.self_attn.attend(h[rows], keys, values, mask)
            else:
                out = self.self_attn.attend_runs(h[rows], ck, cv, g.keys, mask, g.runs)
            if whole:
                attended = out
            else:
                attended[rows] = out
        return self._cross_and_ff(x + attended, cross_k, cross_v, memory_mask, cross_runs)

    def store_keys(self, x: torch.Tensor, cache: LayerCache) -> None:
        """Only the storing part of :meth:`decode`: the keys/values of ``x [B,n,C]`` into the cache."""
        k, v = self.self_attn.keys_values(self.norm_self(x))
        ck, cv, groups = cache
        for g in groups:
            g.store(ck, k)
            g.store(cv, v)

    def _cross_and_ff(
        self,
        x: torch.Tensor,
        cross_k: torch.Tensor,
        cross_v: torch.Tensor,
        memory_mask: torch.Tensor | None,
        runs: tuple[tuple[int, int, int], ...] | None = None,
    ) -> torch.Tensor:
        """Cross-attention (``runs``: rows of ``x`` read runs of the cross caches' rows, see
        :meth:`Attention.attend_runs`), then feed-forward."""
        h = self.norm_cross(x)
        if runs is None:
            x = x + self.cross_attn.attend(h, cross_k, cross_v, memory_mask)
        else:
            x = x + self.cross_attn.attend_runs(h, cross_k, cross_v, cross_k.shape[2], memory_mask, runs)
        return x + self.ff(self.norm_ff(x))
