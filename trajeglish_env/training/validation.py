"""Held-out NLL during training: fixed windows of validation scenes, argmin input tokens."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from trajeglish_env.model.neighbours import batch_view
from trajeglish_env.model.network import SceneInputs, TrajeglishModel
from trajeglish_env.scenario import Scenario
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary
from trajeglish_env.training.dataset import window_config
from trajeglish_env.training.training_data import TokenizedWindows


def batch_to(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """The batch's tensors on ``device``."""
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


@torch.no_grad()
def validation_nll(
    model: TrajeglishModel,
    scenes: Sequence[Scenario],
    vocabulary: MotionVocabulary,
    windows: int,
    seed: int,
    device: torch.device,
    batch_size: int = 16,
) -> float:
    """Mean NLL (nats/token) on fixed windows of held-out scenes, with argmin input tokens."""
    ds = TokenizedWindows(scenes, window_config(model.cfg), vocabulary, None, seed + 1_000_003)
    was_training = model.training
    model.eval()
    total, count = 0.0, 0
    for first in range(0, windows, batch_size):
        batch = batch_to(ds.collated(first, min(windows, first + batch_size)), device)
        view = batch_view(model.cfg.reads_states, batch)
        mean, n = model.loss(SceneInputs.from_batch(batch), batch["input_tokens"], batch["tokens"], view)
        total += float(mean) * n
        count += n
    model.train(was_training)
    return total / max(count, 1)
