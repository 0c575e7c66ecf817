"""Tokenize trajectories into motion tokens (paper, Sec. 3.1) and render tokens back into states.

Tokenization is iterative: the token of step ``t -> t+1`` is the template nearest (mean corner distance,
with the agent's own length and width) to the logged state at ``t+1``, applied from the *tokenized* state
at ``t``, so the discretization error never accumulates. Arrays have any leading batch shape
``[..., N, T]`` (scenes x agents); all agents of one class are processed together at each step.

Gaps (documented contract):
- ``tokens[..., t]`` is the token of the transition ``t -> t+1``; it is ``-1`` unless the agent is valid
  at both ``t`` and ``t+1``.
- The tokenized state at the first valid step of an agent, and at the first step after any gap, is the
  logged state itself ("anchored", flagged in ``anchored``); error there is 0 and it is excluded from error
  statistics. Tokenized states are NaN where the agent is invalid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from trajeglish_env.geometry import to_global, to_local
from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.tokenizer.nearest import SearchTable, nearest_templates, templates_within
from trajeglish_env.tokenizer.noise import NoiseConfig, sample_nucleus
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary


class TokenizeError(ValueError):
    """Bad input to tokenize/render; the message names the argument, agent and step."""


@dataclass(frozen=True)
class TokenizedTrajectories:
    """Result of :func:`tokenize` (shapes for input ``xyh [..., N, T, 3]``)."""

    tokens: np.ndarray  # [..., N, T-1] int64 argmin token of step t -> t+1 (the training target); -1 if none
    input_tokens: np.ndarray  # [..., N, T-1] int64 noisy token (equals ``tokens`` without noise)
    xyh: np.ndarray  # [..., N, T, 3] tokenized states (NaN where invalid)
    valid: np.ndarray  # [..., N, T] bool, as given
    anchored: np.ndarray  # [..., N, T] bool: state copied from the log (first step of each valid run)
    error: np.ndarray  # [..., N, T] mean corner distance logged vs tokenized (m); NaN where invalid

    @cached_property
    def steps_since_anchor(self) -> np.ndarray:
        """``[..., N, T]`` int64 steps since the last anchor (0 at anchors); -1 where invalid."""
        t = np.arange(self.valid.shape[-1])
        last_anchor = np.maximum.accumulate(np.where(self.anchored, t, -1), axis=-1)
        return np.where(self.valid, t - last_anchor, -1)


def _fail(msg: str) -> None:
    raise TokenizeError(msg)


def _where(shape: tuple[int, ...], flat_index: int) -> str:
    index = np.unravel_index(flat_index, shape)
    names = [f"batch {i}" for i in index[:-2]] + [f"agent {index[-2]}", f"step {index[-1]}"]
    return ", ".join(names)


def check_inputs(xyh: np.ndarray, valid: np.ndarray, size: np.ndarray, kind: np.ndarray) -> None:
    """Validate shapes, dtypes and values of trajectory arrays; raise TokenizeError naming the problem."""
    if not isinstance(xyh, np.ndarray) or xyh.ndim < 3 or xyh.shape[-1] != 3:
        _fail(
            f"xyh: expected an array [..., N, T, 3] (x, y, heading), got shape {getattr(xyh, 'shape', None)}"
        )
    if not isinstance(valid, np.ndarray) or valid.shape != xyh.shape[:-1]:
        _fail(f"valid: expected shape {xyh.shape[:-1]} to match xyh, got {getattr(valid, 'shape', None)}")
    if valid.dtype != np.bool_:
        _fail(f"valid: expected dtype bool, got {valid.dtype}")
    if not isinstance(size, np.ndarray) or size.shape != xyh.shape[:-2] + (2,):
        _fail(
            f"size: expected shape {xyh.shape[:-2] + (2,)} (length, width per agent), "
            f"got {getattr(size, 'shape', None)}"
        )
    if not isinstance(kind, np.ndarray) or kind.shape != xyh.shape[:-2]:
        _fail(
            f"kind: expected shape {xyh.shape[:-2]} (one AgentKind per agent), "
            f"got {getattr(kind, 'shape', None)}"
        )
    if not np.issubdtype(kind.dtype, np.integer) or (
        kind.size and ((kind < 0) | (kind >= len(AgentKind))).any()
    ):
        _fail(
            f"kind: expected integer AgentKind values 0..{len(AgentKind) - 1}, got {np.unique(kind).tolist()}"
        )
    bad = valid & ~np.isfinite(xyh).all(-1)
    if bad.any():
        flat = int(np.flatnonzero(bad)[0])
        _fail(
            f"xyh: non-finite state at {_where(valid.shape, flat)} marked valid: {xyh.reshape(-1, 3)[flat]}"
        )
    used = valid.any(-1)
    bad_size = used & ~(np.isfinite(size).all(-1) & (size > 0).all(-1))
    if bad_size.any():
        flat = int(np.flatnonzero(bad_size)[0])
        agent = ", ".join(_where(valid.shape, flat * valid.shape[-1]).split(", ")[:-1])
        _fail(f"size: {agent} needs a finite length and width > 0, got {size.reshape(-1, 2)[flat].tolist()}")


def nearest_moves(
    table: SearchTable, base: np.ndarray, target: np.ndarray, size: np.ndarray, threads: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step of tokenizing ``m`` agents of one class: from states ``base [m,3]`` towards ``target [m,3]``
    (boxes ``size [m,2]``), the nearest template ``[m]``, its corner distance to the target ``[m]`` (m) and
    the state it leads to ``[m,3]``."""
    index, dist = nearest_templates(table, to_local(base, target), size, threads=threads)
    return index, dist, to_global(base, table.templates[index])


def tokenize_moves(
    vocab: MotionVocabulary, base: np.ndarray, target: np.ndarray, size: np.ndarray, kind: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`tokenize` of single moves, lean for a few agents stepped at a time (an env's supplied egos):
    ``n`` agents at finite states ``base [n,3]`` moving to finite ``target [n,3]`` (``size [n,2]``, ``kind
    [n]``). Returns the tokens ``[n]``, the tokenized states ``[n,3]`` and their corner distances to the
    targets ``[n]``, the numbers :func:`tokenize` gives for the same two-step tracks."""
    n = len(base)
    tokens, states, error = np.empty(n, np.int64), np.empty((n, 3)), np.empty(n)
    base, target, size = (np.asarray(a, dtype=np.float64) for a in (base, target, size))
    for k in np.unique(kind).tolist():
        at = np.flatnonzero(kind == k)
        tokens[at], error[at], states[at] = nearest_moves(
            vocab.search_tables[k], base[at], target[at], size[at]
        )
    return tokens, states, error


def tokenize(
    vocab: MotionVocabulary,
    xyh: np.ndarray,
    valid: np.ndarray,
    size: np.ndarray,
    kind: np.ndarray,
    *,
    noise: NoiseConfig | None = None,
    rng: np.random.Generator | Sequence[np.random.Generator] | None = None,
    threads: int = 1,
) -> TokenizedTrajectories:
    """Tokenize ``xyh [..., N, T, 3]`` (``valid [..., N, T]``, ``size [..., N, 2]``, ``kind [..., N]``).

    With ``noise`` (and a NumPy ``rng``), ``input_tokens`` are sampled as in the paper's regularization;
    ``tokens`` (targets) and ``xyh`` (states) are always those of the argmin tokenization. ``rng`` may also
    be one Generator per scene of ``xyh [S, N, T, 3]``: each scene's noisy tokens are then those of
    tokenizing it alone with its own Generator (training tokenizes a batch of windows in one pass).
    ``threads`` splits the nearest-template search over a thread pool (the result does not depend on it).
    """
    xyh = np.asarray(xyh)
    kind = np.asarray(kind)
    check_inputs(xyh, valid, size, kind)
    batch_shape, steps = xyh.shape[:-2], xyh.shape[-2]
    draws = _Draws.make(rng, valid, noise is not None)
    rows = int(np.prod(batch_shape))
    # Rows sorted by class (each class one contiguous block) and stored time-major (each step contiguous).
    order = np.argsort(kind.reshape(rows), kind="stable")
    identity = bool((order == np.arange(rows)).all())
    bounds = np.searchsorted(kind.reshape(rows)[order], np.arange(vocab.num_kinds + 1))
    by_row = xyh.reshape(rows, steps, 3) if identity else xyh.reshape(rows, steps, 3)[order]
    logged = np.ascontiguousarray(by_row.transpose(1, 0, 2), dtype=np.float64)
    ok = np.ascontiguousarray(
        (valid.reshape(rows, steps) if identity else valid.reshape(rows, steps)[order]).T
    )
    box = size.reshape(rows, 2)[order].astype(np.float64)
    if draws is not None:
        draws.sort_rows(order, ok)

    anchored = ok.copy()
    anchored[1:] &= ~ok[:-1]
    states = np.where(anchored[..., None], logged, np.nan)
    tokens = np.full((max(steps - 1, 0), rows), -1, dtype=np.int64)
    input_tokens = tokens.copy() if noise is not None else tokens
    # The template's distance to the local target *is* the corner distance between the tokenized and the
    # logged state (the metric is frame-invariant), so errors come out of the search for free.
    error = np.where(ok, 0.0, np.nan)
    margin = noise.margin(vocab.size) if noise is not None else 0.0

    for t in range(steps - 1):
        moving = ok[t] & ok[t + 1]
        for k in range(vocab.num_kinds):
            lo, hi = int(bounds[k]), int(bounds[k + 1])
            if hi == lo:
                continue
            part = moving[lo:hi]
            active: slice | np.ndarray = slice(lo, hi) if part.all() else lo + np.flatnonzero(part)
            if isinstance(active, np.ndarray) and not len(active):
                continue
            base = states[t, active]
            table = vocab.search_tables[k]
            if noise is None:
                index, dist, states[t + 1, active] = nearest_moves(
                    table, base, logged[t + 1, active], box[active], threads
                )
            else:
                local = to_local(base, logged[t + 1, active])
                pair_row, pair_template, pair_dist = templates_within(table, local, box[active], margin)
                heads = np.flatnonzero(np.r_[True, pair_row[1:] != pair_row[:-1]])
                index, dist = pair_template[heads], pair_dist[heads]
                uniform = draws.take(active)  # type: ignore[union-attr]
                input_tokens[t, active] = pair_template[sample_nucleus(pair_row, pair_dist, noise, uniform)]
                states[t + 1, active] = to_global(base, table.templates[index])
            tokens[t, active] = index
            error[t + 1, active] = dist

    inverse = np.argsort(order)

    def back(a: np.ndarray) -> np.ndarray:
        """Time-major, class-sorted ``[T, R, ...]`` back to the caller's ``[..., N, T, ...]``."""
        a = np.ascontiguousarray(np.swapaxes(a, 0, 1))
        if not identity:
            a = a[inverse]
        return a.reshape(*batch_shape, *a.shape[1:])

    valid_out = valid.copy()
    anchored_out = valid.copy()
    anchored_out[..., 1:] &= ~valid[..., :-1]
    tokens_out = back(tokens)
    return TokenizedTrajectories(
        tokens=tokens_out,
        input_tokens=tokens_out.copy() if noise is None else back(input_tokens),
        xyh=back(states),
        valid=valid_out,
        anchored=anchored_out,
        error=back(error),
    )


class _Draws:
    """The uniform numbers of noisy tokenization, in the order tokenizing each scene alone draws them: one
    ``rng.random(n)`` per (step, class) with moving agents, agents in index order."""

    def __init__(self, rng: np.random.Generator | None, scene_rngs: Sequence[np.random.Generator] | None):
        self.rng, self.scene_rngs = rng, scene_rngs
        self.scene = self.pool = self.first = self.used = np.zeros(0, dtype=np.int64)

    @classmethod
    def make(
        cls, rng: np.random.Generator | Sequence[np.random.Generator] | None, valid: np.ndarray, noisy: bool
    ) -> _Draws | None:
        """The draws for ``rng`` (None without noise); fails naming what noisy tokenization expects."""
        if not noisy:
            return None
        if isinstance(rng, np.random.Generator):
            return cls(rng, None)
        gens = list(rng) if isinstance(rng, Sequence) else None
        if not gens or not all(isinstance(g, np.random.Generator) for g in gens):
            _fail(
                "rng: noisy tokenization needs a numpy.random.Generator, or one per scene (for reproducible "
                f"sampling), got {type(rng).__name__}"
            )
        if valid.ndim != 3 or len(gens) != valid.shape[0]:  # type: ignore[arg-type]
            _fail(
                f"rng: one Generator per scene needs xyh [S, N, T, 3] with S = {len(gens)} scenes, got "  # type: ignore[arg-type]
                f"valid of shape {valid.shape}"
            )
        return cls(None, gens)

    def sort_rows(self, order: np.ndarray, ok: np.ndarray) -> None:
        """Draw each scene's numbers up front (its moving agent-steps) for rows sorted by ``order``
        (``ok [T, R]``: validity, time-major, rows in that order)."""
        if self.scene_rngs is None:
            return
        self.scene = order // max(len(order) // len(self.scene_rngs), 1)  # rows are scene-major
        moves = np.bincount(self.scene, weights=(ok[:-1] & ok[1:]).sum(0), minlength=len(self.scene_rngs))
        counts = moves.astype(np.int64)
        self.pool = np.concatenate([g.random(int(n)) for g, n in zip(self.scene_rngs, counts, strict=True)])
        self.first = np.cumsum(counts) - counts
        self.used = np.zeros(len(counts), dtype=np.int64)

    def take(self, active: slice | np.ndarray) -> np.ndarray:
        """The numbers of the sorted rows ``active`` (one class, ascending) at the current step."""
        if self.rng is not None:
            n = active.stop - active.start if isinstance(active, slice) else len(active)
            return self.rng.random(n)
        scene = self.scene[active]
        count = np.bincount(scene, minlength=len(self.used))
        rank = np.arange(len(scene)) - (np.cumsum(count) - count)[scene]
        out = self.pool[self.first[scene] + self.used[scene] + rank]
        self.used += count
        return out


def render(
    vocab: MotionVocabulary,
    tokens: np.ndarray,
    kind: np.ndarray,
    start_xyh: np.ndarray | None = None,
    *,
    anchor_xyh: np.ndarray | None = None,
    anchored: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """States ``[..., N, T, 3]`` and validity ``[..., N, T]`` produced by ``tokens [..., N, T-1]``.

    Either from ``start_xyh [..., N, 3]`` (a NaN row means "not present"), or, as :func:`tokenize` does,
    from anchors: where ``anchored [..., N, T]`` is set the state is taken from ``anchor_xyh [..., N, T, 3]``.
    A ``-1`` token makes the agent invalid from the next step until it is anchored again.
    """
    tokens = np.asarray(tokens)
    kind = np.asarray(kind)
    if tokens.ndim < 2 or not np.issubdtype(tokens.dtype, np.integer):
        _fail(f"tokens: expected an integer array [..., N, T-1], got {tokens.dtype} shape {tokens.shape}")
    batch_shape, steps = tokens.shape[:-1], tokens.shape[-1] + 1
    if kind.shape != batch_shape:
        _fail(f"kind: expected shape {batch_shape} to match tokens, got {kind.shape}")
    if not np.issubdtype(kind.dtype, np.integer) or (
        kind.size and ((kind < 0) | (kind >= vocab.num_kinds)).any()
    ):
        _fail(f"kind: expected integer AgentKind values 0..{vocab.num_kinds - 1}")
    if ((tokens < -1) | (tokens >= vocab.size)).any():
        _fail(
            f"tokens: values must be -1 (none) or 0..{vocab.size - 1}, "
            f"got range [{tokens.min()}, {tokens.max()}]"
        )
    if (anchor_xyh is None) != (anchored is None) or (start_xyh is None) == (anchored is None):
        _fail("render: give either start_xyh, or anchor_xyh together with anchored")
    rows = int(np.prod(batch_shape))
    tok = tokens.reshape(rows, steps - 1)
    agent_kind = kind.reshape(rows).astype(np.int64)
    anchor_flag = np.zeros((rows, steps), dtype=bool)
    anchor_state = np.zeros((rows, steps, 3))
    if anchored is not None and anchor_xyh is not None:
        anchored, anchor_xyh = np.asarray(anchored), np.asarray(anchor_xyh)
        if anchored.shape != batch_shape + (steps,) or anchor_xyh.shape != batch_shape + (steps, 3):
            _fail(
                f"anchored/anchor_xyh: expected shapes {batch_shape + (steps,)} and "
                f"{batch_shape + (steps, 3)}"
            )
        anchor_flag = anchored.reshape(rows, steps).astype(bool)
        anchor_state = anchor_xyh.reshape(rows, steps, 3).astype(np.float64)
        start = np.where(anchor_flag[:, :1], anchor_state[:, 0], np.nan)
    else:
        start = np.asarray(start_xyh, dtype=np.float64)
        if start.shape != batch_shape + (3,):
            _fail(f"start_xyh: expected shape {batch_shape + (3,)}, got {start.shape}")
        start = start.reshape(rows, 3)
    states = np.full((rows, steps, 3), np.nan)
    states[:, 0] = start
    for t in range(steps - 1):  # sequential in time only; all agents at once
        template = vocab.templates[agent_kind, np.maximum(tok[:, t], 0)]
        moved = to_global(states[:, t], template)
        nxt = np.where((tok[:, t] >= 0)[:, None], moved, np.nan)
        states[:, t + 1] = np.where(anchor_flag[:, t + 1, None], anchor_state[:, t + 1], nxt)
    ok = np.isfinite(states).all(-1)
    return states.reshape(*batch_shape, steps, 3), ok.reshape(*batch_shape, steps)


def tokenize_scenario(
    vocab: MotionVocabulary,
    scenario: Scenario,
    *,
    noise: NoiseConfig | None = None,
    rng: np.random.Generator | None = None,
) -> TokenizedTrajectories:
    """Tokenize every agent of a Scenario (``[N, T]`` outputs)."""
    return tokenize(vocab, scenario.xyh, scenario.valid, scenario.size, scenario.kind, noise=noise, rng=rng)
