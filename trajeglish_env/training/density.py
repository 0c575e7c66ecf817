"""Density estimates on held-out scenes (paper Sec. 4 "Analysis"): NLL per token, per class, against
the number of agents that already acted in the same timestep and against context length, and the
per-class unigram baseline.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.model.layers import linear_compute
from trajeglish_env.model.map_chunks import RED_CLASS
from trajeglish_env.model.masks import teacher_inputs
from trajeglish_env.model.neighbours import batch_view
from trajeglish_env.model.network import SceneInputs
from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.scenario_io import atomic_path
from trajeglish_env.training.dataset import SceneStore
from trajeglish_env.training.train import window_config
from trajeglish_env.training.training_data import TokenizedWindows

KIND_NAMES = [k.name.lower() for k in AgentKind]


@torch.no_grad()
def token_nll(
    ckpt: Checkpoint,
    scenes: Sequence[Scenario],
    windows: int,
    seed: int = 0,
    batch_size: int = 16,
    signals: bool = True,
) -> dict[str, np.ndarray]:
    """Per-token NLL on fixed held-out windows (argmin inputs); ``signals=False``: every map chunk's signal
    class set to none (what a ``signal_input`` model makes of the scene without its signals).

    Returns flat arrays over observed targets: ``nll`` (nats), ``kind``, ``slot`` (agents before it in the
    timestep), ``step`` (timestep in the window), ``token`` (target id), ``red`` (the window's map shows a
    red signal).
    """
    model = ckpt.model.eval()
    ds = TokenizedWindows(scenes, window_config(model.cfg), ckpt.vocabulary, None, seed + 1_000_003)
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("nll", "kind", "slot", "step", "token", "red")}
    for first in range(0, windows, batch_size):
        batch = ds.collated(first, min(windows, first + batch_size))
        scene = SceneInputs.from_batch(batch)
        red = (scene.map_signal == RED_CLASS).any(-1)  # [B]
        if not signals:
            scene = dataclasses.replace(scene, map_signal=torch.zeros_like(scene.map_signal))
        logits = model(scene, batch["input_tokens"], batch_view(model.cfg.reads_states, batch))
        tgt = model.drawn_targets(batch["tokens"], scene.agent_kind[:, :, None]).transpose(1, 2)  # [B,T,A]
        ok = (tgt >= 0) & scene.agent_mask[:, None, :]
        nll = F.cross_entropy(logits[ok], tgt[ok], reduction="none")
        b, t, a = tgt.shape
        # how many real agents act before each one in the timestep (padding slots come first and do not count)
        before = (scene.agent_mask.long().cumsum(-1) - 1)[:, None, :].expand(b, t, a)
        out["nll"].append(nll.numpy())
        out["kind"].append(scene.agent_kind[:, None, :].expand(b, t, a)[ok].numpy())
        out["slot"].append(before[ok].numpy())
        out["step"].append(torch.arange(t)[None, :, None].expand(b, t, a)[ok].numpy())
        out["token"].append(tgt[ok].numpy())
        out["red"].append(red[:, None, None].expand(b, t, a)[ok].numpy())
    return {k: np.concatenate(v) for k, v in out.items()}


@torch.no_grad()
def cached_nll(
    ckpt: Checkpoint,
    scenes: Sequence[Scenario],
    windows: int,
    cache_dtype: torch.dtype,
    seed: int = 0,
    batch_size: int = 16,
    compute_dtype: torch.dtype = torch.float32,
) -> dict[str, float]:
    """Teacher-forced NLL of the held-out windows of :func:`token_nll`, computed through the decoding
    path (:meth:`~trajeglish_env.model.network.TrajeglishModel.decode_at`, key/value cache in
    ``cache_dtype``, linear layers multiplying in ``compute_dtype``, one timestep per call) instead of the
    full forward pass.

    It measures what reduced precision costs in model quality. Returns ``nll`` (the cache path),
    ``reference_nll`` (the float32 full forward pass), ``max_logit_diff`` and ``tokens``.
    """
    with linear_compute(compute_dtype):
        return _cached_nll(ckpt, scenes, windows, cache_dtype, seed, batch_size)


def _cached_nll(
    ckpt: Checkpoint,
    scenes: Sequence[Scenario],
    windows: int,
    cache_dtype: torch.dtype,
    seed: int,
    batch_size: int,
) -> dict[str, float]:
    """:func:`cached_nll` in the caller's compute dtype."""
    model = ckpt.model.eval()
    ds = TokenizedWindows(scenes, window_config(model.cfg), ckpt.vocabulary, None, seed + 1_000_003)
    sums = {"nll": 0.0, "reference_nll": 0.0, "max_logit_diff": 0.0, "tokens": 0.0}
    for first in range(0, windows, batch_size):
        batch = ds.collated(first, min(windows, first + batch_size))
        scene = SceneInputs.from_batch(batch)
        inputs = batch["input_tokens"]
        b, a, t = inputs.shape
        view = batch_view(model.cfg.reads_states, batch)
        full = model(scene, inputs, view)  # [B,T,A,V]
        flat = None if view is None else view.flat_time_major()
        ids = model.global_ids(inputs, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(b, t * a)
        carried, own = teacher_inputs(model.cfg.variant, ids, a)
        cache = model.empty_cache(b, cache_dtype)
        agents = model.encode_into(cache, scene)
        # one timestep per call: for the trajeglish variant the chunk is causal inside (its mask rows)
        steps = []
        for s in range(t):
            chunk = slice(s * a, (s + 1) * a)
            start, count = np.full(b, s * a), np.full(b, a)
            part = None if flat is None else flat.index(slice(None), chunk)
            hidden = model.decode_at(cache, agents, carried[:, chunk], own[:, chunk], start, count, part)
            steps.append(model.class_logits(hidden, scene.agent_kind))
        cached = torch.stack(steps, dim=1)  # [B,T,A,V]
        tgt = model.drawn_targets(batch["tokens"], scene.agent_kind[:, :, None]).transpose(1, 2)
        ok = (tgt >= 0) & scene.agent_mask[:, None, :]
        sums["nll"] += F.cross_entropy(cached[ok].float(), tgt[ok], reduction="sum").item()
        sums["reference_nll"] += F.cross_entropy(full[ok], tgt[ok], reduction="sum").item()
        diff = (cached[ok].float() - full[ok]).abs().max().item() if ok.any() else 0.0
        sums["max_logit_diff"] = max(sums["max_logit_diff"], diff)
        sums["tokens"] += float(ok.sum())
    n = max(sums["tokens"], 1.0)
    return {
        "nll": sums["nll"] / n,
        "reference_nll": sums["reference_nll"] / n,
        "max_logit_diff": sums["max_logit_diff"],
        "tokens": int(sums["tokens"]),
    }


def unigram_nll(
    train_tokens: np.ndarray, train_kind: np.ndarray, tokens: np.ndarray, kind: np.ndarray, vocab: int
) -> np.ndarray:
    """NLL of each token under per-class token frequencies (add-one smoothed) fitted on ``train_*``."""
    counts = np.ones((len(AgentKind), vocab))
    np.add.at(counts, (train_kind, train_tokens), 1.0)
    logp = np.log(counts / counts.sum(-1, keepdims=True))
    return -logp[kind, tokens]


def _by(values: np.ndarray, groups: np.ndarray, n: int) -> list[float | None]:
    sums = np.bincount(groups, weights=values, minlength=n)[:n]
    counts = np.bincount(groups, minlength=n)[:n]
    return [float(s / c) if c else None for s, c in zip(sums, counts, strict=True)]


def _without_signals(
    ckpt: Checkpoint, scenes: Sequence[Scenario], windows: int, seed: int, tok: dict[str, np.ndarray]
) -> dict[str, Any]:
    """What a ``signal_input`` model gains from the signals: its NLL with every signal class set to none,
    overall and per class, and on the tokens of windows whose map shows a red signal, with and without."""
    off = token_nll(ckpt, scenes, windows, seed, signals=False)
    red = tok["red"]
    return {
        "nll": float(off["nll"].mean()),
        "nll_per_class": dict(zip(KIND_NAMES, _by(off["nll"], off["kind"], len(KIND_NAMES)), strict=True)),
        "red_windows": {
            "tokens": int(red.sum()),
            "nll": float(tok["nll"][red].mean()) if red.any() else None,
            "nll_without_signals": float(off["nll"][red].mean()) if red.any() else None,
        },
    }


def summarize(tok: dict[str, np.ndarray], unigram: np.ndarray | None = None) -> dict[str, Any]:
    """Overall/per-class NLL and the two analysis curves, JSON-able."""
    kinds = len(AgentKind)
    res: dict[str, Any] = {
        "tokens": int(len(tok["nll"])),
        "nll": float(tok["nll"].mean()) if len(tok["nll"]) else math.nan,
        "nll_per_class": dict(zip(KIND_NAMES, _by(tok["nll"], tok["kind"], kinds), strict=True)),
        "tokens_per_class": dict(
            zip(KIND_NAMES, np.bincount(tok["kind"], minlength=kinds).tolist(), strict=True)
        ),
    }
    n_slots = int(tok["slot"].max()) + 1 if len(tok["slot"]) else 0
    n_steps = int(tok["step"].max()) + 1 if len(tok["step"]) else 0
    res["nll_vs_agents_before"] = {
        name: _by(tok["nll"][tok["kind"] == k], tok["slot"][tok["kind"] == k], n_slots)
        for k, name in enumerate(KIND_NAMES)
    }
    res["nll_vs_context_steps"] = {
        name: _by(tok["nll"][tok["kind"] == k], tok["step"][tok["kind"] == k], n_steps)
        for k, name in enumerate(KIND_NAMES)
    }
    if unigram is not None:
        res["unigram_nll"] = float(unigram.mean())
        res["unigram_nll_per_class"] = dict(zip(KIND_NAMES, _by(unigram, tok["kind"], kinds), strict=True))
    return res


def evaluate_nll(
    checkpoints: dict[str, Checkpoint],
    data: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    windows: int = 256,
    seed: int = 0,
    unigram_data: str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | None = None,
    plot_dir: str | os.PathLike[str] | None = None,
    cache_dtypes: Sequence[str] = (),
    compute_dtypes: Sequence[str] = (),
) -> dict[str, Any]:
    """NLL table for checkpoints (e.g. trajeglish / no-intra / marginal) plus the unigram baseline.

    The unigram is fitted on ``unigram_data`` (training scenes) when given, else on the held-out tokens
    themselves (an optimistic baseline; reported as such). ``cache_dtypes`` (``"float32"``,
    ``"bfloat16"``): also each model's NLL through the decoding cache in that dtype (:func:`cached_nll`);
    ``compute_dtypes``: also through each of those caches with the linear layers multiplying in these
    dtypes (``through_cache_by_compute[compute][cache]``).
    """
    for name, asked in (("cache_dtypes", cache_dtypes), ("compute_dtypes", compute_dtypes)):
        unknown = sorted(set(asked) - {"float32", "bfloat16"})
        if unknown:
            raise ValueError(f"{name}: {unknown} not supported; expected 'float32' and/or 'bfloat16'")
    if compute_dtypes and not cache_dtypes:
        cache_dtypes = ("float32",)
    scenes = SceneStore(data).scenes
    paths = [str(d) for d in data] if isinstance(data, (list, tuple)) else str(data)
    result: dict[str, Any] = {"data": paths, "windows": windows, "models": {}}
    for name, ckpt in checkpoints.items():
        tok = token_nll(ckpt, scenes, windows, seed)
        if unigram_data is not None:  # fitted on the checkpoint's own tokens (vocabularies may differ)
            fit = token_nll(ckpt, SceneStore(unigram_data).scenes, windows, seed + 1)
            result["unigram_fit"] = str(unigram_data)
        else:
            fit = tok
            result["unigram_fit"] = "held-out tokens (optimistic)"
        uni = unigram_nll(fit["token"], fit["kind"], tok["token"], tok["kind"], ckpt.config.drawn)
        summary = summarize(tok, uni)
        summary["variant"] = ckpt.config.variant.value
        summary["drawn_tokens"] = ckpt.config.drawn  # the NLL is over this many classes per agent kind
        if cache_dtypes:
            summary["through_cache"] = {
                d: cached_nll(ckpt, scenes, windows, getattr(torch, d), seed) for d in cache_dtypes
            }
        if compute_dtypes:
            summary["through_cache_by_compute"] = {
                c: {
                    d: cached_nll(
                        ckpt, scenes, windows, getattr(torch, d), seed, compute_dtype=getattr(torch, c)
                    )
                    for d in cache_dtypes
                }
                for c in compute_dtypes
            }
        if ckpt.config.signal_input:
            summary["without_signals"] = _without_signals(ckpt, scenes, windows, seed, tok)
        result["models"][name] = summary
    any_model = next(iter(result["models"].values()))
    result["unigram_nll"] = any_model["unigram_nll"]
    drawn = {name: m["drawn_tokens"] for name, m in result["models"].items()}
    if len(set(drawn.values())) > 1:  # finer classes raise an NLL at the same quality: say so
        result["note"] = (
            f"the models draw different token counts ({drawn}): an NLL over V classes is not comparable "
            "with one over fewer (finer tokens split the same probability: about log(V1/V2) nats more)"
        )
        warnings.warn(f"nll: {result['note']}", UserWarning, stacklevel=2)
    if plot_dir is not None:
        result["plots"] = plot_density(result, Path(plot_dir))
    return result


def plot_density(result: dict[str, Any], out: Path) -> list[str]:
    """Plots of NLL against agents-before and against context length, one line per model and class."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for key, xlabel, fname in (
        ("nll_vs_agents_before", "agents that already acted in the timestep", "nll_vs_agents_before.png"),
        ("nll_vs_context_steps", "context length (timesteps)", "nll_vs_context.png"),
    ):
        fig, axes = plt.subplots(1, len(KIND_NAMES), figsize=(4 * len(KIND_NAMES), 3.2), sharey=False)
        for ax, cls in zip(axes, KIND_NAMES, strict=True):
            for name, summary in result["models"].items():
                ys = summary[key][cls]
                xs = [i for i, y in enumerate(ys) if y is not None]
                if xs:
                    ax.plot(xs, [ys[i] for i in xs], marker=".", label=name)
            ax.set_title(cls)
            ax.set_xlabel(xlabel)
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("NLL (nats / token)")
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        path = out / fname
        out.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
        plt.close(fig)
        paths.append(str(path))
    return paths
