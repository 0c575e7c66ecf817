"""scripts/guarded_rollout_scenes.py: scenes whose simulated agents follow a guarded rollout of the model
(history and the other agents kept), written as shards that training reads."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO, bundle_scene

from trajeglish_env.scenario import MapKind
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
    module = _script_module()
    from trajeglish_env.checkpoint import load_pretrained

    ckpt = load_pretrained()
    scene = bundle_scene("highway-merge-999000")
    cold = [module.guarded_scenes(ckpt, scene, 1, seed, temperature=0.0)[0].xyh for seed in (1, 2)]
    hot = [module.guarded_scenes(ckpt, scene, 1, seed, temperature=1.0)[0].xyh for seed in (1, 2)]
    np.testing.assert_array_equal(cold[0], cold[1])
    assert not np.array_equal(hot[0], hot[1])


def _script_module():  # type: ignore[no-untyped-def]
    import importlib.util

    spec = importlib.util.spec_from_file_location("grs", REPO / "scripts" / "guarded_rollout_scenes.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_failure_cut_drops_what_led_to_a_collision_and_nothing_of_a_clean_log() -> None:
    """--clean-horizon: a generated log never fails; a vehicle moved onto another at step s loses its
    states (and its partner's) from s - H on, a vehicle pushed off the road loses its own, the rest stay."""
    from dataclasses import replace

    module = _script_module()
    scene = bundle_scene("highway-merge-999000")
    cur, sim = scene.current_index, np.flatnonzero(scene.valid[:, scene.current_index])
    first = module.first_failures(scene)
    assert (first[sim] == scene.num_steps).all() and (first[~scene.valid[:, cur]] == -1).all()
    kept, cut = module.cut_failures(scene, 10)
    assert cut == 0 and np.array_equal(kept.valid, scene.valid)

    a, b, c = sim[:3]
    s, wide = cur + 30, cur + 50
    xyh = scene.xyh.copy()
    xyh[a, s:] = xyh[b, s:]  # a sits on b from step s on
    xyh[c, wide:, 1] += 60.0  # c leaves the road sideways at step `wide`
    valid = scene.valid.copy()
    valid[[a, b, c], s:] = True
    broken = replace(scene, xyh=xyh, valid=valid)
    first = module.first_failures(broken)
    assert first[a] == first[b] == s and first[c] == wide
    others = np.setdiff1d(sim, [a, b, c])
    assert (first[others] > s).all()  # none of the others fails by then
    kept, cut = module.cut_failures(broken, 10)
    assert not kept.valid[[a, b], s - 10 :].any() and kept.valid[[a, b], s - 11].all()
    assert (
        not kept.valid[c, wide - 10 :].any() and kept.valid[c, : wide - 10][scene.valid[c, : wide - 10]].all()
    )
    np.testing.assert_array_equal(kept.valid[:, : cur + 1], scene.valid[:, : cur + 1])  # history untouched
    assert (kept.xyh[~kept.valid] == 0).all()

    parked = scene.xyh.copy()
    parked[c, :, 1] += 60.0  # c off the road in the log itself, from its first step on
    first = module.first_failures(replace(scene, xyh=parked))
    assert first[c] == scene.num_steps  # a vehicle already off the road is not cut for it
    roadless = replace(broken, map_kind=np.full_like(scene.map_kind, int(MapKind.LANE_SURFACE_STREET)))
    first = module.first_failures(roadless)  # a map without road edges: collisions alone
    assert first[a] == first[b] == s and first[c] == scene.num_steps


def test_a_killed_run_resumes_after_its_written_shards(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Each shard holds the rollouts of its own input scenes, written atomically: a rerun skips the shards
    on disk and writes the missing ones exactly as the first run did (seeds follow the scene index)."""
    from dataclasses import replace

    module = _script_module()
    monkeypatch.setattr(module, "SCENES_PER_SHARD", 2)  # 2 rollouts a scene: one input scene a shard
    scene = bundle_scene("highway-merge-999000")
    scenes = [scene, replace(scene, scenario_id="second")]
    save_scenarios(tmp_path / "in" / "s.scn.npz", scenes)
    argv = ["grs", "--data", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--rollouts", "2"]
    monkeypatch.setattr(sys, "argv", [*argv, "--guard", "off", "--clean-horizon", "10"])
    module.main()
    first, second = sorted((tmp_path / "out").glob("*.scn.npz"))
    assert [s.scenario_id for s in load_scenarios(second)] == ["second-alone0", "second-alone1"]
    kept_bytes, lost = first.read_bytes(), load_scenarios(second)
    second.unlink()  # the run was killed while it was on the second shard
    mtime = first.stat().st_mtime_ns
    module.main()
    assert first.stat().st_mtime_ns == mtime and first.read_bytes() == kept_bytes  # not written again
    for again, before in zip(
        load_scenarios(second), lost, strict=True
    ):  # the same rollouts, cut the same way
        np.testing.assert_array_equal(again.xyh, before.xyh)
        np.testing.assert_array_equal(again.valid, before.valid)
    monkeypatch.setattr(sys, "argv", [*argv, "--guard", "off", "--clean-horizon", "5"])
    with pytest.raises(SystemExit, match=r"other settings \(clean_horizon: 10 there, 5 now\)"):
        module.main()  # never mixes rollouts of other settings into the shards there
    monkeypatch.setattr(
        sys, "argv", [*argv[:4], str(tmp_path / "other"), "--rollouts", "2", "--clean-horizon", "-1"]
    )
    with pytest.raises(SystemExit):  # argparse's error (exit status 2), before anything is written
        module.main()
    assert not (tmp_path / "other").exists()
    (tmp_path / "out" / "settings.json").unlink()  # shards of an unknown run
    monkeypatch.setattr(sys, "argv", [*argv, "--guard", "off", "--clean-horizon", "10"])
    with pytest.raises(SystemExit, match="2 shards but no settings.json"):
        module.main()
