"""Fine-tuning (``train --init``): the shipped model adapts to the shared WOMD scene and incompatible
starting checkpoints are refused with one clear line (two DDP processes equal one: test_womd_pipeline)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import grid_vocabulary, straight_road_scene, tiny_config, womd_tfrecord

from trajeglish_env.checkpoint import CheckpointError, load_checkpoint, pretrained_path, save_checkpoint
from trajeglish_env.checkpoint_reading import drawn_base
from trajeglish_env.cli import main
from trajeglish_env.model import TrajeglishModel
from trajeglish_env.scenario_io import load_scenarios, save_scenarios
from trajeglish_env.sources.womd_convert import convert_womd
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary
from trajeglish_env.training.train import TrainConfig, train, validation_nll

QUICK = TrainConfig(
    steps=3, batch_size=2, lr=5e-4, warmup_steps=1, val_fraction=0.0, num_workers=0, checkpoint_every=100
)


@pytest.fixture(scope="module")
def tiny_init(tmp_path_factory) -> Path:
    """A trained-looking tiny checkpoint to start from."""
    torch.manual_seed(3)
    path = tmp_path_factory.mktemp("init") / "tiny.pt"
    return save_checkpoint(path, TrajeglishModel(tiny_config()), grid_vocabulary(), training={"note": "init"})


@pytest.fixture(scope="module")
def scenes_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("scenes")
    save_scenarios(d / "a.scn.npz", [straight_road_scene(num_agents=5, seed=s, steps=40) for s in range(4)])
    return d


def test_finetuning_the_shipped_model_lowers_the_womd_scene_nll(tmp_path: Path) -> None:
    convert_womd([womd_tfrecord()], tmp_path / "womd", progress=False)
    scenes = load_scenarios(tmp_path / "womd" / "motion_data_one_scenario.scn.npz")
    shipped = drawn_base(load_checkpoint(pretrained_path()))  # the trained model the shipped file reads with
    cpu = torch.device("cpu")
    before = validation_nll(shipped.model, scenes, shipped.vocabulary, 4, 0, cpu, batch_size=4)
    config = TrainConfig(**{**QUICK.__dict__, "steps": 2, "batch_size": 4, "lr": 1e-4, "noisy_inputs": False})
    result = train(tmp_path / "womd", tmp_path / "run", shipped.config, config, progress=False, init=shipped)
    tuned = load_checkpoint(result["checkpoint"])
    after = validation_nll(tuned.model, scenes, tuned.vocabulary, 4, 0, cpu, batch_size=4)
    assert after < before - 0.02, (before, after)  # 1.963 -> 1.913 nats/token
    assert tuned.training["init"] == str(pretrained_path()) and tuned.config == shipped.config
    assert np.array_equal(tuned.vocabulary.templates, shipped.vocabulary.templates)


def test_init_starts_from_the_checkpoint_weights(scenes_dir: Path, tiny_init: Path, tmp_path: Path) -> None:
    config = TrainConfig(**{**QUICK.__dict__, "lr": 1e-12, "steps": 1})
    result = train(scenes_dir, tmp_path / "run", tiny_config(), config, progress=False, init=tiny_init)
    start, tuned = load_checkpoint(tiny_init).model.state_dict(), load_checkpoint(result["checkpoint"])
    for name, value in tuned.model.state_dict().items():
        torch.testing.assert_close(value, start[name], rtol=0, atol=1e-6, msg=name)
    assert tuned.vocabulary.method == "xyh-grid"  # the checkpoint's vocabulary, not the shipped one


def test_incompatible_init_is_refused(scenes_dir: Path, tiny_init: Path, tmp_path: Path, capsys) -> None:
    with pytest.raises(CheckpointError, match=r"config differs .*variant .*no-intra \(requested\)"):
        train(
            scenes_dir,
            tmp_path / "a",
            tiny_config().with_variant("no-intra"),
            QUICK,
            progress=False,
            init=tiny_init,
        )
    other = MotionVocabulary(grid_vocabulary().templates * 1.01, method="xyh-grid")
    with pytest.raises(
        CheckpointError,
        match=r"vocabulary differs from the checkpoint's \(xyh-grid vs xyh-grid, "
        r"the same shape \[3, 144, 3\], templates up to 0\.\d+ apart",
    ):
        train(
            scenes_dir, tmp_path / "b", tiny_config(), QUICK, vocabulary=other, progress=False, init=tiny_init
        )
    base = ["train", "--data", str(scenes_dir), "--out", str(tmp_path / "c"), "--steps", "1", "--quiet"]
    assert main([*base, "--init", str(tmp_path / "missing.pt")]) == 2
    assert main([*base, "--init", str(tiny_init), "--preset", "small"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "missing.pt: no such checkpoint file" in err[0]
    assert err[-1].startswith("trajeglish train: error: --init ") and "d_model 32 (checkpoint)" in err[-1]
