"""Rows with identical histories (the rollouts of one scene at their first step) are encoded and primed
once and copied (sampler/windows.py ``_identical_rows``): the rollouts are those of rows built one by one."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import bundle_scene, record_encoded, tiny_checkpoint

from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import RolloutEngine

# float32: under "auto" one rollout multiplies in float32 and four in bfloat16 on CPUs with native bfloat16
CONFIG = SamplingConfig(seed=7, guard=True, compute_dtype="float32")


def test_identical_rows_are_built_once_and_roll_out_as_built_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    ckpt = tiny_checkpoint()
    sc = bundle_scene("highway-roundabout-999000")
    active = sc.valid[:, sc.current_index].copy()
    encoded = record_encoded(monkeypatch, ckpt.model)
    built = RolloutEngine(ckpt, sc, 4, 12, active, config=CONFIG)
    built._build_windows(np.arange(4))  # what the first step does before it decodes
    engine = built
    subsets = int(engine.num_subsets[0])
    assert subsets >= 2 and (engine.num_subsets == subsets).all()
    assert sum(int(s.agent_mask.shape[0]) for s in encoded) == subsets  # one row encoded per subset rank
    for w in engine.windows:  # every row holds the first row's windows
        assert (w.slots == w.slots[:1]).all()
        for tensor in (*w.cache.self_k, *w.cache.cross_v):
            assert torch_equal_rows(tensor)
    encoded.clear()
    engine = RolloutEngine(ckpt, sc, 4, 12, active, config=CONFIG)
    engine.run()
    built = len(encoded)
    monkeypatch.undo()
    alone = [RolloutEngine(ckpt, sc, 1, 12, active, config=CONFIG, first_rollout=r) for r in range(4)]
    for r, single in enumerate(alone):
        single.run()
        assert np.array_equal(single.xyh[0], engine.xyh[r]), f"rollout {r}"
    assert built > subsets  # the later rebuilds, where the rollouts differ, are made row by row
    assert not np.array_equal(engine.xyh[0], engine.xyh[1])


def torch_equal_rows(tensor) -> bool:  # type: ignore[no-untyped-def]
    return bool((tensor == tensor[:1]).all())
