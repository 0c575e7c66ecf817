"""Long rollouts (`trajeglish long-rollouts`): onsets are counted once per event, rates per agent-second
before and after the split, rollouts run far past the log, and the guard keeps them collision-free."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import bundle_scene, tiny

from trajeglish_env.batch_geometry import road_edges
from trajeglish_env.cli import main
from trajeglish_env.long_rollouts import LongRolloutConfig, event_onsets, long_rollout_rates
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.scenario import AgentKind, MapKind, Scenario


def test_onsets_count_each_event_once() -> None:
    t = 8
    xyh = np.zeros((1, 3, t, 3))
    xyh[0, 0, :, 0] = np.arange(t) * 1.0  # drives into agent 1 (parked at x = 9) from step 4 on
    xyh[0, 1, :, 0] = 9.0
    xyh[0, 2, :, 1] = -30.0 - np.arange(t) * 1.0  # walks off the road south: a pedestrian is never off-road
    xyh[0, 2, :, 0] = 50.0
    xyh[0, 2, 6:, 1] = -30.0  # (and back)
    xs = np.arange(-20.0, 80.0, 1.0)
    scene = Scenario.from_arrays(
        xyh[0], np.ones((3, t), bool), np.tile([4.5, 2.0], (3, 1)),
        np.array([AgentKind.VEHICLE, AgentKind.VEHICLE, AgentKind.PEDESTRIAN]), current_index=0,
        polylines=[np.stack([xs, np.full_like(xs, -3.0)], -1), np.stack([xs[::-1], xs * 0 + 3.0], -1)],
        polyline_kinds=[MapKind.ROAD_EDGE_BOUNDARY] * 2,
    )  # fmt: skip
    moved = xyh.copy()
    moved[0, 0, 5:, 1] = np.array([1.0, 2.5, 2.5])  # and swerves: its corners pass the edge at y = 3
    onsets = event_onsets(scene.size, scene.kind, road_edges(scene), moved, np.ones((1, 3, t), bool))
    hits = np.argwhere(onsets["collision"][0])
    assert hits.tolist() == [[0, 4], [1, 4]]  # both at step 5 (index 4 of steps 1..), once
    off = np.argwhere(onsets["offroad"][0])
    assert off.tolist() == [[0, 5]]  # vehicle 0 at step 6; the pedestrian never


def test_rates_past_the_log_and_the_guard() -> None:
    scenes = [bundle_scene("highway-roundabout-999000"), bundle_scene("highway-merge-999000")]
    config = LongRolloutConfig(seconds=11.0, rollouts=2, sampling=SamplingConfig(temperature=1.0))
    result = long_rollout_rates(tiny(), scenes, config, progress=False)
    plain, guarded = result["methods"]["trajeglish"], result["methods"]["trajeglish+guard"]
    for m in (plain, guarded):
        assert len(m["agent_seconds"]) == 11 and min(m["agent_seconds"]) > 5  # 8 s of log, then 3 s past it
        assert len(m["collision"]["per_second"]) == 11
    assert plain["collision"]["before"] > 0.01  # the untrained model crashes (0.019 per agent-second)
    assert guarded["collision"]["before"] == guarded["collision"]["after"] == 0.0
    assert guarded["collision"]["within_1_5x"] and guarded["collision"]["ratio"] is None


def test_the_command_writes_json_table_and_plot(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    from trajeglish_env.checkpoint import save_checkpoint
    from trajeglish_env.scenario_io import save_scenarios

    save_scenarios(tmp_path / "data" / "s.scn.npz", [bundle_scene("highway-two-way-999000")])
    ckpt = tiny()
    save_checkpoint(tmp_path / "tiny.pt", ckpt.model, ckpt.vocabulary)
    code = main(
        ["long-rollouts", "--data", str(tmp_path / "data"), "--ckpt", str(tmp_path / "tiny.pt"),
         "--seconds", "9", "--rollouts", "1", "--guard", "on", "--out", str(tmp_path / "out"),
         "--json", "--quiet"]
    )  # fmt: skip
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert list(result["methods"]) == ["trajeglish+guard"] and result["scenes"] == 1
    assert (tmp_path / "out" / "long_rollout_rates.png").stat().st_size > 1000
    assert "| trajeglish+guard |" in (tmp_path / "out" / "long_rollouts.md").read_text()


def test_the_split_is_a_whole_second() -> None:
    """The onset rates are per second: a split of 8.5 s was rounded to 8 without a word."""
    with pytest.raises(ValueError, match="whole number of seconds .*got 8.5"):
        LongRolloutConfig(seconds=30.0, split_s=8.5)
    assert LongRolloutConfig(seconds=30.0, split_s=8).split_s == 8
