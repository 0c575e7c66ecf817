"""How each model variant lays out its decoder inputs and which of them a prediction may use.

Position ``p = t * A + a`` of the flattened (time-major) sequence predicts the token of agent slot ``a``
at step ``t``. Its input carries one earlier token (:func:`carried_position`):
- trajeglish: the previous token of the flattened sequence (``p - 1``; a start token at ``p = 0``), so a
  plain causal mask lets agent ``a`` condition on the tokens that agents ``0..a-1`` chose this step;
- no-intra and marginal / no-map: the same agent's token at the previous step (``p - A``; start tokens in
  the first step), so every input of step ``t`` is known when step ``t`` begins. no-intra attends to all
  positions of steps ``<= t`` (everything up to the previous step, nothing of this step); marginal only to
  its own agent's positions of steps ``<= t``.
"""

from __future__ import annotations

import torch

from trajeglish_env.model.config import Variant


def input_shift(variant: Variant, agents: int) -> int:
    """Distance from a position back to the position whose token its input carries."""
    return 1 if variant is Variant.TRAJEGLISH else agents


def carried_position(variant: Variant, position: int, agents: int) -> int:
    """Position whose token is the input of ``position`` (-1: the start token)."""
    q = position - input_shift(variant, agents)
    return q if q >= 0 else -1


def decoder_mask(
    variant: Variant, steps: int, agents: int, device: torch.device | None = None
) -> torch.Tensor:
    """Boolean ``[L, L]`` mask (True = may attend), ``L = steps * agents``."""
    length = steps * agents
    p = torch.arange(length, device=device)[:, None]
    q = torch.arange(length, device=device)[None, :]
    if variant is Variant.TRAJEGLISH:
        return q <= p
    same_or_earlier_step = q // agents <= p // agents
    if variant is Variant.NO_INTRA:
        return same_or_earlier_step
    return same_or_earlier_step & (q % agents == p % agents)
