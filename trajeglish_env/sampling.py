"""Token sampling (temperature, nucleus) and cached decoding of whole token sequences with forcing.

``decode_tokens`` runs the model through its key/value cache: tokens of agents the model controls are
sampled, all others are *forced* (fed as given, never sampled). For the trajeglish variant positions are
decoded one at a time (each agent conditions on the agents before it in the same step); the other
variants decode a whole timestep at once, which their masks make equivalent.
"""

from __future__ import annotations

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
