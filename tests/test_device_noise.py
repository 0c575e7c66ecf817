"""Noisy input tokens drawn on the training device (``TrainConfig.noise_on_device``, run here on the CPU):
the loading processes ship the argmin windows with what the draw needs, and the training process's draw
gives the loader's noisy tokens, up to rounding."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import grid_vocabulary, load_bundle, straight_road_scene, tiny_config

from trajeglish_env.checkpoint import load_checkpoint, load_pretrained
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.tokenizer import NoiseConfig
from trajeglish_env.training.dataset import collate_windows
from trajeglish_env.training.device_noise import NOISE_FIELDS, DeviceTemplates, device_input_tokens
from trajeglish_env.training.train import TrainConfig, train, window_config
from trajeglish_env.training.training_data import TokenizedWindows


@pytest.mark.parametrize("dropout", [0.0, 0.3])
def test_the_device_draws_the_loaders_noisy_tokens(dropout: float) -> None:
    ckpt = load_pretrained()
    bundle = load_bundle()
    scenes = [bundle.get(i) for i in range(len(bundle))]  # highway-env and SUMO: three agent classes
    args = (scenes, window_config(ckpt.config), ckpt.vocabulary, NoiseConfig(), 21, None, dropout)
    loader = collate_windows(TokenizedWindows(*args).__getitems__(range(48)))
    shipped = collate_windows(TokenizedWindows(*args, noise_on_device=True).__getitems__(range(48)))
    assert set(NOISE_FIELDS) <= set(shipped) and not set(NOISE_FIELDS) & set(loader)
    assert torch.equal(shipped["tokens"], loader["tokens"])
    assert torch.equal(shipped["input_tokens"] >= 0, loader["input_tokens"] >= 0)  # hidden stay hidden
    drawn = device_input_tokens(shipped, DeviceTemplates.of(ckpt.vocabulary, "cpu"), NoiseConfig())
    observed = loader["input_tokens"] >= 0
    same = (drawn == loader["input_tokens"])[observed].double().mean()
    noisy = (drawn != loader["tokens"])[observed].double().mean()
    assert same > 0.999 and 0.15 < noisy < 0.5, (float(same), float(noisy))
    assert torch.equal(drawn[~observed], loader["input_tokens"][~observed])
    # no noise: the argmin tokens as they are
    assert torch.equal(
        device_input_tokens(shipped, DeviceTemplates.of(ckpt.vocabulary, "cpu"), NoiseConfig(0.0)),
        shipped["input_tokens"],
    )


def test_training_with_the_noise_on_the_device_resumes_either_way(tmp_path) -> None:
    """A run trains with the noise drawn in its own process, and may go on with the loaders drawing it (the
    same draws up to rounding): the switch is not a change of schedule."""
    save_scenarios(
        tmp_path / "s.scn.npz", [straight_road_scene(num_agents=5, seed=s, steps=40) for s in range(4)]
    )
    base = dict(steps=6, batch_size=4, warmup_steps=2, val_every=100, checkpoint_every=3, num_workers=0)
    run, model, vocab = tmp_path / "run", tiny_config(), grid_vocabulary()
    on = TrainConfig(**base, val_fraction=0.0, noise_on_device=True)
    first = train(tmp_path, run, model, on, vocabulary=vocab, progress=False, time_limit=0.0)
    assert first["steps"] == 1 and first["stopped_by_time_limit"]
    assert load_checkpoint(run / "last.pt").trainer["train_config"]["noise_on_device"] is True
    off = TrainConfig(**base, val_fraction=0.0, noise_on_device=False)
    second = train(tmp_path, run, model, off, vocabulary=vocab, progress=False, resume=True)
    assert second["resumed_from"] == 1 and second["steps"] == 6 and np.isfinite(second["train_loss"])
