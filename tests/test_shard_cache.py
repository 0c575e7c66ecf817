"""Training over many shards with a bounded shard cache: the sample order covers every scene once per
epoch, K shards at a time, and a training run never holds more than K shards."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import grid_vocabulary, straight_road_scene, tiny_config

from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training import shard_cache
from trajeglish_env.training.shard_cache import ShardBlockOrder, ShardedScenes, split_shards
from trajeglish_env.training.train import TrainConfig, train


@pytest.fixture(scope="module")
def shards(tmp_path_factory) -> Path:
    """Eight shards of two or three small scenes each (19 scenes)."""
    d = tmp_path_factory.mktemp("shards")
    seed = 0
    for k in range(8):
        count = 2 + k % 2
        scenes = [straight_road_scene(num_agents=4, seed=seed + i, steps=30) for i in range(count)]
        save_scenarios(d / f"s-{k:02d}.scn.npz", scenes)
        seed += count
    return d


def test_block_order_covers_every_scene_once_per_epoch_k_shards_at_a_time() -> None:
    counts = (2, 3, 2, 3, 2, 3, 2, 3)
    order = ShardBlockOrder(counts, block=3, seed=5)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    for epoch in range(2):
        scenes = [order(epoch * 20 + g)[1] for g in range(20)]
        assert sorted(scenes) == list(range(20)) and order(epoch * 20)[0] == epoch
        shard_of = (np.searchsorted(offsets, scenes, side="right") - 1).tolist()
        # the epoch is a run of blocks, each holding every scene of at most 3 shards and nothing else
        i, blocks = 0, 0
        while i < 20:
            block, j = {shard_of[i]}, i
            while j < 20 and len(block | {shard_of[j]}) <= 3:
                block.add(shard_of[j])
                j += 1
            assert j - i == sum(counts[k] for k in block), (epoch, i, block)
            i, blocks = j, blocks + 1
        assert blocks == 3  # 8 shards in blocks of 3, 3, 2
    assert [order(g) for g in range(20)] == [ShardBlockOrder(counts, 3, 5)(g) for g in range(20)]
    assert [order(g) for g in range(20)] != [ShardBlockOrder(counts, 3, 6)(g) for g in range(20)]


def test_sharded_scenes_read_headers_and_keep_k_shards(shards: Path) -> None:
    scenes = ShardedScenes.from_paths([shards], cache_shards=2)
    assert len(scenes) == 20 and scenes.all_sources() == ["test"] and scenes._cache == {}
    assert scenes[0].scenario_id == "straight-0" and scenes[19].scenario_id == "straight-19"
    for i in range(20):
        assert scenes[i].scenario_id == f"straight-{i}" and len(scenes._cache) <= 2
    train_files, val_files = split_shards(scenes.files, 0.25)
    assert [f.name for f in val_files] == ["s-00.scn.npz", "s-04.scn.npz"] and len(train_files) == 6


def test_training_with_a_shard_cache_holds_at_most_k_shards(
    shards: Path, tmp_path: Path, monkeypatch
) -> None:
    held: list[int] = []
    real = shard_cache.ShardedScenes.shard

    def spy(self, k):
        out = real(self, k)
        held.append(len(self._cache))
        return out

    monkeypatch.setattr(shard_cache.ShardedScenes, "shard", spy)
    config = TrainConfig(
        steps=4,
        batch_size=4,
        warmup_steps=1,
        num_workers=0,
        val_fraction=0.25,
        val_windows=3,
        val_every=4,
        checkpoint_every=4,
        shard_cache=2,
    )
    result = train(shards, tmp_path, tiny_config(), config, grid_vocabulary(), progress=False)
    assert result["steps"] == 4 and np.isfinite(result["val_nll"])
    assert len(held) == 16 and max(held) <= 2
