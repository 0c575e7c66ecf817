"""The benchmark suite's plumbing (the speed figures themselves come from `trajeglish bench`, never tests)."""

from __future__ import annotations

import json
import os
import time
import types
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from helpers import womd_tfrecord

from trajeglish_env.benchmark import measure, suite, womd
from trajeglish_env.benchmark.busy import busy_process, busy_section
from trajeglish_env.benchmark.measure import env_speed
from trajeglish_env.benchmark.suite import (
    SCHEMA_VERSION,
    BenchConfig,
    guard_cost,
    ratios,
    run_suite,
    summary_lines,
)
from trajeglish_env.benchmark.workloads import benchmark_scenes
from trajeglish_env.cli import main
from trajeglish_env.cores import usable_cores
from trajeglish_env.sources.womd import read_womd
from trajeglish_env.training.precision import step_dtype


def test_benchmark_scenes_have_exactly_the_requested_agents() -> None:
    scenes = benchmark_scenes(24)
    assert len(scenes) == 4 and all(s.num_agents == 24 for s in scenes)
    assert all(s.valid[s.sdc, s.current_index] for s in scenes)
    with pytest.raises(ValueError, match="no bundled scene has 500 agents"):
        benchmark_scenes(500)


def test_env_speed_reports_rates_and_memory() -> None:
    run = env_speed(2, npc="replay", steps=2, warmup=1)
    assert run["num_envs"] == 2 and run["agents_per_scene"] == 24 and run["processes"] == 1
    assert run["agent_steps_per_s"] == pytest.approx(run["env_steps_per_s"] * 48, rel=1e-2)
    assert run["peak_rss_mb"] > 50
    # the scenes split over two worker processes: their threads and memory are reported with the caller's
    split = env_speed(2, npc="replay", steps=2, warmup=1, processes=2, torch_threads=1)
    assert split["processes"] == 2 and split["torch_threads"] == 1
    # each worker's own peak holds the torch runtime it forked with (well over 100 MB)
    assert split["peak_rss_mb"] > run["peak_rss_mb"] + 200 and split["agent_steps_per_s"] > 0


def test_env_speed_repeats_rounds_until_the_timed_steps_last_min_seconds() -> None:
    one = env_speed(1, npc="replay", steps=2, warmup=1)
    assert one["rounds"] == 1 and one["timed_steps"] == 2
    # a round of 2 replay steps lasts milliseconds: 0.05 s takes several rounds, each from a reset
    more = env_speed(1, npc="replay", steps=2, warmup=1, min_seconds=0.05)
    assert 2 <= more["rounds"] <= measure.MAX_ROUNDS and more["timed_steps"] == 2
    assert more["rounds"] == measure.MAX_ROUNDS or more["timed_seconds"] >= 0.05
    # the rate is of every timed step of every round (timed_seconds is rounded to the millisecond, which
    # on a run of about 0.05 s moves the rate by up to 1 %: bounded by the rounding, not a fixed share)
    steps = more["rounds"] * more["timed_steps"]
    low, high = steps / (more["timed_seconds"] + 5e-4), steps / max(more["timed_seconds"] - 5e-4, 1e-9)
    assert low - 1e-3 <= more["env_steps_per_s"] <= high + 1e-3
    # an impossible wish stops at MAX_ROUNDS
    capped = env_speed(1, npc="replay", steps=1, warmup=0, min_seconds=1e9)
    assert capped["rounds"] == measure.MAX_ROUNDS
    with pytest.raises(ValueError, match="env min seconds must be >= 0"):
        BenchConfig(env_min_seconds=-1.0)


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
    with pytest.raises(ValueError, match="split processes must be 'auto' or an int >= 2, got 1"):
        BenchConfig(split_processes=1)
    with pytest.raises(SystemExit) as exited:
        main(["bench", "--split-processes", "one", "--quiet"])
    assert exited.value.code == 2
    assert "--split-processes: expected 'auto' or an integer >= 2, got 'one'" in capsys.readouterr().err
    assert main(["bench", "--threads", "lots", "--quiet"]) == 2
    assert "--threads must be 'auto' or a positive integer" in capsys.readouterr().err
    assert main(["bench", "--device", "gpu", "--quiet"]) == 2
    assert "--device must name a torch device" in capsys.readouterr().err
    out = tmp_path / "bench.json"
    args = ["bench", "--sections", "metrics", "training", "--quick", "--json", "--quiet", "--out", str(out)]
    assert main(args) == 0
    printed = json.loads(capsys.readouterr().out)
    written = json.loads(out.read_text())
    assert printed["schema_version"] == written["schema_version"] == SCHEMA_VERSION == 12
    assert printed["complete"] is True and written == printed
    assert written["config"]["batches"] == [1, 8]  # --quick without --batches: a smoke run's batch sizes
    assert written["quick_overrides"]["env_steps"] == 3  # what the quick runs use (config: what was asked)
    assert written["metrics"]["8_evaluated"]["seconds"] > 0 and written["ratios"] == {}
    training = written["training"]  # train's default precision beside float32 (schema 8)
    assert training["precision"] == str(step_dtype("auto", torch.device("cpu"), 128)).removeprefix("torch.")
    assert training["tokens_per_s"] > 0 and training["tokens_per_s_float32"] > 0
    assert f"tokens/s in {training['precision']}" in "\n".join(summary_lines(written))


def test_a_suite_stopped_early_keeps_the_runs_it_finished(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("stopped")  # a lent machine's time limit, a crash: the second run never ends

    monkeypatch.setattr(measure, "metrics_time", broken)
    out = tmp_path / "bench.json"
    with pytest.raises(RuntimeError, match="stopped"):
        main(["bench", "--sections", "tokenizer", "metrics", "--quick", "--quiet", "--out", str(out)])
    written = json.loads(out.read_text())
    assert written["complete"] is False and "metrics" not in written
    assert written["tokenizer"]["agent_steps_per_s"] > 0 and written["ratios"] == {}
    assert summary_lines(written)[-1].startswith("incomplete: the suite stopped before its last run")


def test_env_section_of_the_suite_measures_highway_env_before_and_after() -> None:
    result = run_suite(BenchConfig(sections=("env",), batches=(2,), quick=True), progress=False)
    assert result["schema_version"] == SCHEMA_VERSION
    for key in ("highway_env", "highway_env_highway"):
        runs = result[key]["runs"]
        assert len(runs) == 2 and all(r["agent_steps_per_s"] > 0 for r in runs)
        mean = (runs[0]["agent_steps_per_s"] + runs[1]["agent_steps_per_s"]) / 2
        assert result[key]["agent_steps_per_s"] == pytest.approx(mean, abs=0.01)
    learned = result["env"]["trajeglish"]["2"]
    # quick: 3 timed steps after the warm-up, inside one window cycle of the model (no re-priming step)
    assert learned["timed_steps"] == 3 and learned["window_rebuild_steps"] == 0
    assert result["env"]["replay"]["2"]["window_rebuild_steps"] is None
    # one engine below 96 scenes; the shards a run used are in the JSON and its printed line (schema 10)
    assert learned["engine_shards"] == result["env"]["replay"]["2"]["engine_shards"] == 1
    assert suite._parallelism({**learned, "engine_shards": 2, "torch_threads": 1}) == (
        "2 engine shards in threads x threads 1"
    )
    ratio = learned["agent_steps_per_s"] / result["highway_env"]["agent_steps_per_s"]
    assert result["ratios"]["trajeglish_B2_to_highway_env"] == pytest.approx(ratio, rel=1e-2)
    guarded = result["env"]["trajeglish_guard"]["2"]
    assert guarded["guard"] is True and learned["guard"] is False and guarded["timed_steps"] == 3
    cost = result["guard_cost"]["2"]
    assert cost["slowdown"] == pytest.approx(
        learned["agent_steps_per_s"] / guarded["agent_steps_per_s"], rel=1e-2
    )
    # the AEC env (the lead API) on the four bundled 24-agent scenes, one timestep an env step (schema 9)
    aec = result["aec"]
    assert aec["api"] == "aec" and aec["agents"] == 24
    assert 1 <= aec["torch_threads"] <= min(2, usable_cores())  # "auto": one until a look finds free cores
    assert [r["scenario_id"] for r in aec["scenes"]] == [s.scenario_id for s in benchmark_scenes(24)]
    assert all(
        r["timed_steps"] == 3 and r["agents"] == 24 and r["env_steps_per_s"] > 0 for r in aec["scenes"]
    )
    seconds = sum(3 / r["env_steps_per_s"] for r in aec["scenes"])  # the rate of all timed steps together
    assert aec["env_steps_per_s"] == pytest.approx(12 / seconds, rel=1e-2)
    assert aec["agent_steps_per_s"] == pytest.approx(aec["env_steps_per_s"] * 24, rel=1e-2)
    aec_ratio = aec["env_steps_per_s"] / result["highway_env"]["steps_per_s"]
    assert result["ratios"]["aec_env_to_highway_env"] == pytest.approx(aec_ratio, rel=1e-2)
    assert any(line.startswith("AEC env, 24 agents") for line in summary_lines(result))
    # and in turn with intersection-v0, each AEC run against the runs beside it (schema 12)
    turns = result["aec_interleaved"]
    assert turns["rounds"] == 1 and len(turns["intersection_steps_per_s"]) == 2
    inter, aec_rate = turns["intersection_steps_per_s"], turns["aec_env_steps_per_s"][0]
    assert turns["ratios"] == [pytest.approx(aec_rate / ((inter[0] + inter[1]) / 2), abs=1e-3)]
    assert (
        result["ratios"]["aec_env_to_highway_env_interleaved"] == turns["median_ratio"] == turns["ratios"][0]
    )
    assert any(line.startswith("AEC env and intersection-v0 in turn") for line in summary_lines(result))


# ------------------------------------------------------------------------------------- womd section
def test_womd_section_times_the_shared_scenario_with_all_its_agents() -> None:
    path = womd_tfrecord()
    scene = next(read_womd(path))
    present = int(scene.valid[:, scene.current_index].sum())
    result = run_suite(BenchConfig(sections=("womd",), quick=True, womd=str(path)), progress=False)
    w = result["womd"]
    assert w["file"] == str(path) and w["scenario_id"] == scene.scenario_id and w["agents"] == present
    r = w["rollouts"]
    assert (r["rollouts"], r["horizon"], r["agents"]) == (2, 5, present)
    assert r["seconds"] > 0 and r["agent_steps_per_s"] == pytest.approx(present * 10 / r["seconds"], rel=0.02)
    split = w["rollouts_split"]
    if usable_cores() > 1:  # the same rollouts over one process per core
        assert split["processes"] == usable_cores() and (split["rollouts"], split["horizon"]) == (2, 5)
        assert split["agent_steps_per_s"] == pytest.approx(present * 10 / split["seconds"], rel=0.02)
    else:
        assert split == {"skipped": "one core"}
    e = w["env"]
    assert e["api"] == "aec" and e["agents"] == present and e["timed_steps"] == 3
    assert 1 <= e["torch_threads"] <= min(2, usable_cores())
    assert e["env_steps_per_s"] > 0 and e["agent_steps_per_s"] == pytest.approx(
        e["env_steps_per_s"] * present, rel=0.01
    )
    assert w["highway_env"]["env"] == "intersection-v0" and w["highway_env"]["steps_per_s"] > 0
    ratio = e["env_steps_per_s"] / w["highway_env"]["steps_per_s"]
    assert result["ratios"]["womd_env_to_highway_env"] == pytest.approx(ratio, rel=0.01)
    assert any(
        line.startswith(f"womd {scene.scenario_id} ({present} agents)") for line in summary_lines(result)
    )


def test_womd_file_defaults_to_the_shared_one(monkeypatch: pytest.MonkeyPatch) -> None:
    path = womd_tfrecord()
    monkeypatch.setenv("TRAJEGLISH_SHARED", str(path.parents[2]))
    assert womd.candidate_paths()[0] == path and womd.locate_womd() == path


def test_womd_section_is_skipped_without_a_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    missing = tmp_path / "none.tfrecord"
    result = run_suite(BenchConfig(sections=("womd",), quick=True, womd=str(missing)), progress=False)
    assert result["womd"] == {"skipped": f"no WOMD scenario file at {missing} (--womd)"}
    assert result["ratios"] == {} and "womd: skipped" in "\n".join(summary_lines(result))
    monkeypatch.delenv("TRAJEGLISH_SHARED", raising=False)
    monkeypatch.setattr(womd, "candidate_paths", lambda: [missing])
    reason = run_suite(BenchConfig(sections=("womd",), quick=True), progress=False)["womd"]["skipped"]
    assert str(missing) in reason and "TRAJEGLISH_SHARED is unset" in reason and "--womd FILE" in reason
    (tmp_path / "empty.tfrecord").write_bytes(b"")
    with pytest.raises(ValueError, match="holds no scenario"):  # a bad file fails before anything is timed
        run_suite(BenchConfig(sections=("womd",), womd=str(tmp_path / "empty.tfrecord")), progress=False)


# ------------------------------------------------------------------------------------- busy section
def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def _children() -> set[int]:
    """This process's live child processes (Linux: the children its main thread started)."""
    me = os.getpid()
    return {int(p) for p in Path(f"/proc/{me}/task/{me}/children").read_text().split()}


def test_busy_process_spins_and_is_reaped_even_on_error() -> None:
    with busy_process() as spinner:
        time.sleep(0.5)
        assert spinner.pid in _children() and not _gone(spinner.pid)
        assert spinner.cpu_seconds() > 0.05  # it spins (a share of a core on a loaded machine)
    assert _gone(spinner.pid)
    with pytest.raises(RuntimeError, match="boom"), busy_process() as spinner:
        raise RuntimeError("boom")
    assert _gone(spinner.pid)


def test_busy_section_runs_each_batch_idle_then_beside_the_spinner() -> None:
    seen: list[set[int]] = []

    def run(batch: int) -> dict[str, float]:
        seen.append(_children())
        return {"agent_steps_per_s": 100.0 if len(seen) % 2 else 80.0, "torch_threads": 1}

    before = _children()
    out = busy_section((1, 8), run)
    assert list(out) == ["1", "8"] and len(seen) == 4
    assert seen[0] == seen[2] == before  # idle runs: no spinner
    spinners = [seen[1] - before, seen[3] - before]
    assert all(len(s) == 1 for s in spinners) and all(_gone(pid) for s in spinners for pid in s)
    assert out["8"]["busy_to_idle"] == 0.8 and out["8"]["idle_agent_steps_per_s"] == 100.0
    assert out["8"]["spinner_cpu_share"] is not None
    assert "skipped" in busy_section((), run)


def test_busy_section_of_the_suite_runs_the_env_job_at_auto_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[object, str, int, bool]] = []

    def env_job(
        config: BenchConfig, npc: str, batch: int, processes: int | str = 1
    ) -> Callable[[], dict[str, object]]:
        calls.append((config.torch_threads, npc, batch, config.quick, processes))
        rate = 50.0 if len(calls) % 2 else 45.0
        return lambda: {"agent_steps_per_s": rate, "torch_threads": 1, "processes": 1}

    aec_calls: list[bool] = []

    def aec(quick: bool) -> dict[str, object]:
        aec_calls.append(quick)
        return {"agent_steps_per_s": 1200.0 if len(aec_calls) % 2 else 1080.0, "torch_threads": 2}

    monkeypatch.setattr(suite, "_env_job", env_job)
    monkeypatch.setattr(suite, "_aec", aec)
    config = BenchConfig(sections=("busy",), batches=(1, 8, 32), quick=True, torch_threads=2)
    result = run_suite(config, progress=False)
    assert calls == [("auto", "trajeglish_guard", 1, True, 1)] * 2  # quick: B = 1 only; default NPCs
    assert result["busy"]["1"]["busy_to_idle"] == 0.9
    # the AEC env (the lead API, at its default threads) idle and then beside the busy process
    assert aec_calls == [True, True] and result["busy"]["aec"]["busy_to_idle"] == 0.9
    assert result["ratios"] == {"busy_B1_to_idle": 0.9, "busy_aec_to_idle": 0.9}
    lines = summary_lines(result)
    assert any(line.startswith("busy machine B=   1: 50.0") for line in lines)
    assert any(line.startswith("busy machine AEC env: 1200.0") for line in lines)
    calls.clear()
    full = run_suite(replace(config, quick=False), progress=False)
    # B = 8 is also run with its scenes split over worker processes (B = 1 cannot split)
    assert [(c[2], c[4]) for c in calls] == [(1, 1), (1, 1), (8, 1), (8, 1), (8, "auto"), (8, "auto")]
    assert list(full["busy"]) == ["1", "8", "8_split", "aec"] and "busy_B8_split_to_idle" in full["ratios"]
    calls.clear()
    run_suite(replace(config, quick=False, split=False), progress=False)
    assert [c[4] for c in calls] == [1] * 4
    none = run_suite(replace(config, batches=(32,), quick=False), progress=False)
    assert "skipped" in none["busy"] and "busy: skipped" in "\n".join(summary_lines(none))


def test_env_section_also_runs_the_default_npcs_split_over_processes(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[str, int, int | str]] = []

    def env_job(
        config: BenchConfig, npc: str, batch: int, processes: int | str = 1
    ) -> Callable[[], dict[str, object]]:
        calls.append((npc, batch, processes))
        rate = 300.0 if processes == "auto" else 200.0
        return lambda: {"agent_steps_per_s": rate, "scene_steps_per_s": 1.0, "peak_rss_mb": 1.0}

    monkeypatch.setattr(suite, "_env_job", env_job)
    highway = {"env": "x", "steps_per_s": 1.0, "mean_vehicles": 100.0, "agent_steps_per_s": 100.0}
    monkeypatch.setattr(measure, "highway_env_speed", lambda *a: highway)
    # quick: the section's AEC runs (the real model) are not what this test checks
    config = BenchConfig(sections=("env",), batches=(4, 8), guards=(True,), quick=True)
    result = run_suite(config, progress=False)
    split = [c for c in calls if c[2] == "auto"]
    assert split == [("trajeglish_guard", 8, "auto")]  # B = 4 is too small to split
    assert result["ratios"]["trajeglish_guard_split_B8_to_highway_env"] == 3.0
    assert any("trajeglish_guard_split B=   8" in line for line in summary_lines(result))
    calls.clear()
    run_suite(replace(config, split_processes=16), progress=False)  # e.g. GPU workers, one per core
    assert [c for c in calls if c[2] != 1] == [("trajeglish_guard", 8, 16)]
    calls.clear()
    run_suite(replace(config, split=False), progress=False)
    assert all(c[2] == 1 for c in calls)


def test_the_highway_env_baseline_times_its_steps_not_its_resets(monkeypatch: pytest.MonkeyPatch) -> None:
    """intersection-v0's idling ego ends about 4 episodes in 300 steps; their resets (1 s of its 10) were
    timed with the steps, while the Trajeglish runs time steps only: every ratio read 1.06-1.21x high."""
    import highway_env.envs.intersection_env as intersection

    class SlowResets:
        def __init__(self, config: dict) -> None:
            self.road = types.SimpleNamespace(vehicles=[0] * 10)
            self.n = 0

        def reset(self, seed: int = 0) -> None:
            time.sleep(0.05)

        def step(self, action: int) -> tuple:
            self.n += 1
            return None, 0.0, self.n % 2 == 0, False, {}  # an episode ends every other step

    monkeypatch.setattr(intersection, "IntersectionEnv", SlowResets)
    out = measure.highway_env_speed(vehicles=10, steps=20)
    assert out["steps_per_s"] > 2000 and out["mean_vehicles"] == 10.0  # 10 resets would make it < 40


def test_an_env_run_ends_when_the_bench_is_killed() -> None:
    """A bench killed by SIGKILL left its env run going (re-parented, up to 32 rounds), competing with the
    next measurement; the run now gets SIGTERM when its bench dies."""
    import signal
    import subprocess
    import sys

    child = (
        "import sys, time; import trajeglish_env.benchmark.measure as m; "
        "m.env_speed = lambda **k: time.sleep(60); sys.argv = ['worker', '{}']; "
        "from trajeglish_env.benchmark import worker; print('ready', flush=True); worker.main()"
    )
    bench = (
        "import subprocess, sys, time; "
        f"p = subprocess.Popen([sys.executable, '-c', {child!r}]); print(p.pid, flush=True); time.sleep(60)"
    )
    parent = subprocess.Popen([sys.executable, "-c", bench], stdout=subprocess.PIPE, text=True)
    run = int(parent.stdout.readline())  # type: ignore[union-attr]
    assert parent.stdout.readline().strip() == "ready"  # type: ignore[union-attr]
    time.sleep(0.5)  # the run has armed its signal
    parent.send_signal(signal.SIGKILL)
    parent.wait()

    def alive() -> bool:
        try:
            state = Path(f"/proc/{run}/status").read_text()
        except FileNotFoundError:
            return False
        return "\nState:\tZ" not in state

    deadline = time.monotonic() + 10
    while alive() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not alive()


def test_bench_refuses_a_missing_womd_file_and_too_many_agents_before_timing(capsys) -> None:
    """A --womd path the user typed was skipped with exit 0; --agents beyond the bundled scenes failed in
    the env worker after 35 s of highway-env timing, as a double traceback."""
    assert main(["bench", "--sections", "womd", "--womd", "/nonexistent.tfrecord", "--quick"]) == 2
    assert "--womd /nonexistent.tfrecord: no such WOMD scenario file" in capsys.readouterr().err
    assert main(["bench", "--sections", "env", "--agents", "200", "--quick", "--batches", "1"]) == 2
    assert "--agents 200: no bundled scene has 200 agents" in capsys.readouterr().err
