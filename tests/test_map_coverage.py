"""What a model's windows show of the road ahead (`trajeglish map-coverage`): on the bundled highway-env
scenes 64 chunks of 20 points 0.5 m apart nearest the frame agent (the model shipped until stop 29) show a
fifth of the vehicles' next 8 s of path, chunks of every 4th point three times as much."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from helpers import bundle_scene, straight_road_scene

from trajeglish_env.checkpoint import load_pretrained
from trajeglish_env.cli import main
from trajeglish_env.env.scenes import load_bundle
from trajeglish_env.map_coverage import CoverageConfig, coverage_by_kind, coverage_table, vehicle_coverage


def test_strided_and_agent_chosen_chunks_show_more_of_the_road_ahead() -> None:
    bundle = load_bundle()
    scenes = [bundle.get(i) for i in range(16)]  # the 16 bundled highway-env scenes
    shipped = dataclasses.replace(load_pretrained().config, map_select="frame")
    frame = coverage_by_kind(scenes, shipped, (1, 4))["all"]
    agents = coverage_by_kind(scenes, dataclasses.replace(shipped, map_select="agents"), (1, 4))["all"]
    assert frame["stride 1"]["vehicles"] == 133  # the bundle of stop 80 (two-way remade)
    assert frame["stride 1"]["path_shown"] == pytest.approx(0.197, abs=0.002)
    assert frame["stride 1"]["seconds_ahead_median"] == 0.1  # most vehicles' next state is off the chunks
    assert frame["stride 4"]["path_shown"] == pytest.approx(0.622, abs=0.002)
    assert agents["stride 1"]["path_shown"] == pytest.approx(0.353, abs=0.002)
    assert agents["stride 4"]["path_shown"] == pytest.approx(0.760, abs=0.002)
    assert agents["stride 4"]["seconds_ahead_median"] == pytest.approx(5.8)
    table = coverage_table(coverage_by_kind(scenes[:2], shipped, (1, 4)))
    assert table.splitlines()[0].startswith("| kind | vehicles | stride 1: path shown / s ahead |")
    assert "| highway/merge | " in table and "| all | " in table


def test_a_road_that_is_all_shown_and_standing_vehicles_are_left_out() -> None:
    scene = straight_road_scene(num_agents=6, steps=40)  # cars along a straight 1 m-spaced road
    cfg = dataclasses.replace(load_pretrained().config, map_select="agents", map_stride=8)
    got = vehicle_coverage(scene, cfg, CoverageConfig(horizon=20))
    assert got.shape[1] == 2 and len(got) >= 1
    assert np.all(got[:, 0] == 1.0)  # every next state lies on a shown lane
    assert len(vehicle_coverage(scene, cfg, CoverageConfig(horizon=20, min_travel=1e6))) == 0
    with pytest.raises(ValueError, match="CoverageConfig"):
        CoverageConfig(tolerance=0)


def test_seconds_ahead_is_the_first_state_off_the_lanes_capped_at_the_horizon() -> None:
    """All shown: exactly horizon / 10 s (it was one step more, 2.1 s for a 20-step horizon), or the log's
    last step when the log ends first; a vehicle leaving the lanes at step k: k / 10 s."""
    scene = straight_road_scene(num_agents=6, steps=40)  # current step 10: 29 steps of future
    cfg = dataclasses.replace(load_pretrained().config, map_select="agents", map_stride=8)
    assert vehicle_coverage(scene, cfg, CoverageConfig(horizon=20)).tolist() == [[1.0, 2.0]] * 4
    assert vehicle_coverage(scene, cfg, CoverageConfig(horizon=80)).tolist() == [[1.0, 2.9]] * 4
    xyh = scene.xyh.copy()
    xyh[2, scene.current_index + 7 :, 1] = 30.0  # vehicle 2 is 26.5 m off every lane from step 7 on
    got = vehicle_coverage(dataclasses.replace(scene, xyh=xyh), cfg, CoverageConfig(horizon=20))
    assert got.tolist() == [[1.0, 2.0], [0.3, 0.7], [1.0, 2.0], [1.0, 2.0]]  # 6 of its 20 states shown


def test_the_command_prints_a_table_and_json(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    from trajeglish_env.scenario_io import save_scenarios

    save_scenarios(tmp_path / "s.scn.npz", [bundle_scene("highway-merge-999000")])
    assert main(["map-coverage", "--data", str(tmp_path), "--stride", "1", "4", "--json", "--quiet"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scenes"] == 1 and out["strides"] == [1, 4] and out["map_select"] == "agents"  # the shipped
    row = out["by_kind"]["highway/merge"]
    assert row["stride 4"]["path_shown"] > row["stride 1"]["path_shown"]
    assert main(["map-coverage", "--data", str(tmp_path), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "| highway/merge | " in printed and "by_kind" not in printed
