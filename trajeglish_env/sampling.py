"""Token sampling (temperature, nucleus) and cached decoding of whole token sequences with forcing.

``decode_tokens`` runs the model through its key/value cache: tokens of agents the model controls are
sampled, all others are *forced* (fed as given, never sampled). For the trajeglish variant positions are
decoded one at a time (each agent conditions on the agents before it in the same step); the other
variants decode a whole timestep at once, which their masks make equivalent.
"""

from __future__ import annotations

import numpy as np
import torch

from trajeglish_env.model.config import Variant
from trajeglish_env.model.masks import carried_position
from trajeglish_env.model.network import SceneInputs, TrajeglishModel

START = -2  # carried id meaning "the start token"


def nucleus_mask(probs: torch.Tensor, top_p: float) -> torch.Tensor:
    """Boolean mask of the smallest set of most likely tokens whose total probability is >= ``top_p``."""
    if not 0 < top_p <= 1:
        raise ValueError(f"top_p must be in (0, 1], got {top_p}")
    sorted_p, order = probs.sort(dim=-1, descending=True)
    before = sorted_p.cumsum(-1) - sorted_p  # mass of the strictly more likely tokens
    keep_sorted = before < top_p
    keep_sorted[..., 0] = True
    return torch.zeros_like(keep_sorted).scatter(-1, order, keep_sorted)


def sample_logits(
    logits: torch.Tensor,
    temperature: float = 1.0,
    top_p: float = 1.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Sample token ids ``[...]`` from logits ``[..., V]``; ``temperature == 0`` gives the argmax."""
    if temperature < 0:
        raise ValueError(f"temperature must be >= 0, got {temperature}")
    if temperature == 0:
        return logits.argmax(-1)
    probs = torch.softmax(logits.float() / temperature, dim=-1)
    if top_p < 1.0:
        probs = probs * nucleus_mask(probs, top_p)
    flat = probs.reshape(-1, probs.shape[-1])
    return torch.multinomial(flat, 1, generator=generator).view(probs.shape[:-1])


_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


def _splitmix(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser (a bijective 64-bit mixer), vectorized; uint64 arithmetic wraps."""
    x = x ^ (x >> np.uint64(30))
    x = x * _MIX1
    x = x ^ (x >> np.uint64(27))
    x = x * _MIX2
    return x ^ (x >> np.uint64(31))


def stream_seed(seed: int | np.ndarray, index: int | np.ndarray) -> np.ndarray:
    """An independent 64-bit seed for sub-stream ``index`` of ``seed`` (e.g. one per rollout)."""
    s = np.asarray(seed, dtype=np.uint64)
    return _splitmix(s * _GOLDEN + _splitmix(np.asarray(index, dtype=np.uint64) + _GOLDEN))


def counter_uniform(seed: np.ndarray, step: np.ndarray, agent: np.ndarray) -> np.ndarray:
    """Uniform numbers in [0, 1) that depend only on ``(seed, step, agent)`` (counter-based, vectorized):
    a scene's draws are the same whichever other scenes share its batch and in whatever order."""
    x = _splitmix(np.asarray(seed, dtype=np.uint64) ^ _splitmix(np.asarray(step, dtype=np.uint64) * _MIX1))
    x = _splitmix(x + _splitmix(np.asarray(agent, dtype=np.uint64) + _GOLDEN))
    return (x >> np.uint64(11)).astype(np.float64) * 2.0**-53


def sample_with_uniform(
    logits: torch.Tensor, temperature: float, top_p: float, uniform: np.ndarray
) -> np.ndarray:
    """Token ids ``[n]`` from logits ``[n, V]`` by inverting each row's CDF at ``uniform [n]`` (float64;
    ``temperature == 0`` gives the argmax)."""
    if temperature < 0:
        raise ValueError(f"temperature must be >= 0, got {temperature}")
    if temperature == 0:
        return logits.argmax(-1).numpy()
    probs = torch.softmax(logits.double() / temperature, dim=-1)
    if top_p < 1.0:
        probs = probs * nucleus_mask(probs, top_p)
    cdf = probs.cumsum(-1)
    u = torch.from_numpy(np.asarray(uniform, dtype=np.float64))[:, None] * cdf[:, -1:]
    return torch.searchsorted(cdf, u, right=True).clamp_(max=logits.shape[-1] - 1)[:, 0].numpy()


@torch.no_grad()
def decode_tokens(
    model: TrajeglishModel,
    scene: SceneInputs,
    given: torch.Tensor,
    sample: torch.Tensor,
    temperature: float = 1.0,
    top_p: float = 1.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Complete token sequences ``[B,A,T]`` (class-local ids, -1 = unobserved).

    ``given [B,A,T]``: tokens fed as they are where ``sample`` is False (forced agents, or -1 for agents
    that are absent/padding); ``sample [B,A,T]`` bool: positions the model samples.
    """
    b, a, t = given.shape
    if sample.shape != given.shape:
        raise ValueError(
            f"sample mask shape {tuple(sample.shape)} must equal given tokens {tuple(given.shape)}"
        )
    if t > model.cfg.steps:
        raise ValueError(f"the model decodes at most {model.cfg.steps} steps per window, got {t}")
    sample = sample & scene.agent_mask[:, :, None]
    out = torch.where(sample, torch.full_like(given, -1), given).clone()
    cache, agents = model.start_decoding(scene, max_length=a * t)
    joint = model.global_ids(out, scene.agent_kind[:, :, None])  # updated as tokens are sampled
    chunk = 1 if model.cfg.variant is Variant.TRAJEGLISH else a
    for p in range(0, a * t, chunk):
        positions = range(p, p + chunk)
        carried = torch.stack(
            [_carried_ids(joint, carried_position(model.cfg.variant, q, a), a, b) for q in positions], dim=1
        )
        slots = [q % a for q in positions]
        step = p // a
        own = joint[:, slots, step - 1] if step > 0 else torch.full((b, len(slots)), -1, dtype=torch.long)
        logits = model.decode(cache, agents, scene.agent_kind[:, slots], carried, own)  # [B,chunk,V]
        todo = sample[:, slots, step]
        if todo.any():
            drawn = sample_logits(logits, temperature, top_p, generator)
            new = torch.where(todo, drawn, out[:, slots, step])
            out[:, slots, step] = new
            joint[:, slots, step] = model.global_ids(new, scene.agent_kind[:, slots])
    return out


def _carried_ids(joint: torch.Tensor, position: int, agents: int, batch: int) -> torch.Tensor:
    """Joint ids ``[B]`` of the token at flattened ``position`` (START before the sequence)."""
    if position < 0:
        return torch.full((batch,), START, dtype=torch.long, device=joint.device)
    step, slot = divmod(position, agents)
    return joint[:, slot, step]
