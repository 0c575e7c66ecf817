"""How each model variant lays out its decoder inputs and which of them a prediction may use.

Position ``p = t * A + a`` of the flattened (time-major) sequence predicts the token of agent slot ``a``
at step ``t``. Its input carries one earlier token (:func:`input_shift` positions back; :data:`START`
before the sequence):
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

START = -2  # carried joint id meaning "the start token" (-1 means an unobserved token)


def input_shift(variant: Variant, agents: int) -> int:
    """Distance from a position back to the position whose token its input carries."""
    return 1 if variant is Variant.TRAJEGLISH else agents


def teacher_inputs(variant: Variant, ids: torch.Tensor, agents: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Carried and own-previous joint ids ``[B,L]`` of every position of a known flattened sequence of
    joint ids ``ids [B,L]`` (teacher forcing): the inputs the decoder takes for those positions."""
    b, shift = ids.shape[0], input_shift(variant, agents)
    carried = torch.cat([ids.new_full((b, shift), START), ids[:, :-shift]], dim=1)
    own = torch.cat([ids.new_full((b, agents), -1), ids[:, :-agents]], dim=1)
    return carried, own


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
