"""scripts/guarded_rollout_scenes.py: scenes whose simulated agents follow a guarded rollout of the model
(history and the other agents kept), written as shards that training reads."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
from helpers import REPO, bundle_scene

from trajeglish_env.scenario_io import load_scenarios, save_scenarios


def test_guarded_rollout_scenes(tmp_path: Path) -> None:
    scene = bundle_scene("highway-merge-999000")
    save_scenarios(tmp_path / "in" / "s.scn.npz", [scene])
    script = REPO / "scripts" / "guarded_rollout_scenes.py"
    cmd = [sys.executable, str(script), "--data", str(tmp_path / "in"), "--out", str(tmp_path / "out")]
    done = subprocess.run([*cmd, "--rollouts", "2"], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    (shard,) = sorted((tmp_path / "out").glob("*.scn.npz"))
    made = load_scenarios(shard)
    cur, sim = scene.current_index, scene.valid[:, scene.current_index]
    assert [s.scenario_id for s in made] == [f"{scene.scenario_id}-guarded{r}" for r in range(2)]
    for s in made:
        np.testing.assert_array_equal(
            s.xyh[:, : cur + 1], scene.xyh[:, : cur + 1]
        )  # the history is the log's
        assert s.valid[sim, cur + 1 :].all()  # the simulated agents exist through the rollout
        assert np.abs(s.xyh[sim, -1, :2] - scene.xyh[sim, -1, :2]).max() > 0.1  # and drove on their own
    assert not np.array_equal(made[0].xyh, made[1].xyh)  # two different rollouts


def test_guarded_rollout_scenes_take_the_temperature() -> None:
    """At temperature 0 every rollout is the guarded argmax one, whatever its seed; at 1 seeds differ."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("grs", REPO / "scripts" / "guarded_rollout_scenes.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    from trajeglish_env.checkpoint import load_pretrained

    ckpt = load_pretrained()
    scene = bundle_scene("highway-merge-999000")
    cold = [module.guarded_scenes(ckpt, scene, 1, seed, temperature=0.0)[0].xyh for seed in (1, 2)]
    hot = [module.guarded_scenes(ckpt, scene, 1, seed, temperature=1.0)[0].xyh for seed in (1, 2)]
    np.testing.assert_array_equal(cold[0], cold[1])
    assert not np.array_equal(hot[0], hot[1])
