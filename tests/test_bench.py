"""The benchmark suite's plumbing (the speed figures themselves come from `trajeglish bench`, never tests)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from trajeglish_env.benchmark.measure import env_speed
from trajeglish_env.benchmark.suite import BenchConfig, guard_cost, ratios, run_suite, summary_lines
from trajeglish_env.benchmark.workloads import benchmark_scenes
from trajeglish_env.cli import main


def test_benchmark_scenes_have_exactly_the_requested_agents() -> None:
    scenes = benchmark_scenes(24)
    assert len(scenes) == 4 and all(s.num_agents == 24 for s in scenes)
    assert all(s.valid[s.sdc, s.current_index] for s in scenes)
    with pytest.raises(ValueError, match="no bundled scene has 500 agents"):
        benchmark_scenes(500)


def test_env_speed_reports_rates_and_memory() -> None:
    run = env_speed(2, npc="replay", steps=2, warmup=1)
    assert run["num_envs"] == 2 and run["agents_per_scene"] == 24
    assert run["agent_steps_per_s"] == pytest.approx(run["env_steps_per_s"] * 48, rel=1e-2)
    assert run["peak_rss_mb"] > 50


def test_ratios_and_summary_of_a_result() -> None:
    result = {
        "machine": {"cpu_count": 2},
        "highway_env": {"steps_per_s": 50.0, "mean_vehicles": 20.0, "agent_steps_per_s": 1000.0},
        "env": {
            "trajeglish": {"8": {"agent_steps_per_s": 2500.0, "scene_steps_per_s": 104.2, "peak_rss_mb": 9}},
            "trajeglish_guard": {
                "8": {"agent_steps_per_s": 2000.0, "scene_steps_per_s": 83.3, "peak_rss_mb": 9}
            },
        },
        "seconds": 1.0,
    }
    result["ratios"] = ratios(result)
    assert result["ratios"] == {
        "trajeglish_B8_to_highway_env": 2.5,
        "trajeglish_guard_B8_to_highway_env": 2.0,
    }
    result["guard_cost"] = guard_cost(result["env"])
    assert result["guard_cost"] == {"8": {"off": 2500.0, "on": 2000.0, "slowdown": 1.25}}
    lines = summary_lines(result)
    assert any("2.5x intersection" in line for line in lines) and any(
        "1.25x slower" in line for line in lines
    )


def test_bench_config_and_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match="unknown section"):
        BenchConfig(sections=("gpu",))
    with pytest.raises(ValueError, match="batch sizes"):
        BenchConfig(batches=(0,))
    with pytest.raises(ValueError, match="guards"):
        BenchConfig(guards=())
    assert main(["bench", "--threads", "lots", "--quiet"]) == 2
    assert "--threads must be 'auto' or a positive integer" in capsys.readouterr().err
    out = tmp_path / "bench.json"
    assert main(["bench", "--sections", "metrics", "--quick", "--json", "--quiet", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    written = json.loads(out.read_text())
    assert printed["schema_version"] == written["schema_version"] == 3
    assert written["metrics"]["8_evaluated"]["seconds"] > 0 and written["ratios"] == {}


def test_env_section_of_the_suite_measures_highway_env_before_and_after() -> None:
    result = run_suite(BenchConfig(sections=("env",), batches=(2,), quick=True), progress=False)
    assert result["schema_version"] == 3
    for key in ("highway_env", "highway_env_highway"):
        runs = result[key]["runs"]
        assert len(runs) == 2 and all(r["agent_steps_per_s"] > 0 for r in runs)
        mean = (runs[0]["agent_steps_per_s"] + runs[1]["agent_steps_per_s"]) / 2
        assert result[key]["agent_steps_per_s"] == pytest.approx(mean, abs=0.01)
    learned = result["env"]["trajeglish"]["2"]
    # quick: 3 timed steps after the warm-up, inside one window cycle of the model (no re-priming step)
    assert learned["timed_steps"] == 3 and learned["window_rebuild_steps"] == 0
    assert result["env"]["replay"]["2"]["window_rebuild_steps"] is None
    ratio = learned["agent_steps_per_s"] / result["highway_env"]["agent_steps_per_s"]
    assert result["ratios"]["trajeglish_B2_to_highway_env"] == pytest.approx(ratio, rel=1e-2)
    guarded = result["env"]["trajeglish_guard"]["2"]
    assert guarded["guard"] is True and learned["guard"] is False and guarded["timed_steps"] == 3
    cost = result["guard_cost"]["2"]
    assert cost["slowdown"] == pytest.approx(
        learned["agent_steps_per_s"] / guarded["agent_steps_per_s"], rel=1e-2
    )
