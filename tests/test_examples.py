"""Every example runs with small settings (and ``trajeglish demo`` with a tiny model), as the README shows."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest
from helpers import REPO, shared_file, tiny_checkpoint

from trajeglish_env.benchmark.womd import SHARED_FILE as WOMD_SAMPLE
from trajeglish_env.checkpoint import save_checkpoint
from trajeglish_env.cli import main as cli_main


def example(name: str) -> ModuleType:
    path = REPO / "examples" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"example_{name}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    ckpt = tiny_checkpoint()
    return save_checkpoint(tmp_path_factory.mktemp("model") / "tiny.pt", ckpt.model, ckpt.vocabulary)


def test_quickstart(tmp_path: Path, tiny_model: Path) -> None:
    out = example("quickstart").main(
        ["--smoke", "--checkpoint", str(tiny_model), "--out", str(tmp_path / "q.gif")]
    )
    assert out["steps"] >= 1 and Path(out["video"]).stat().st_size > 1000
    out = example("quickstart").main(["--npc", "idm", "--out", str(tmp_path / "q.gif")])
    # the observation-only policy drives the whole exit scene without incident
    assert out["collision_steps"] == 0 and out["offroad_steps"] == 0 and out["progress_m"] > 50


def test_train_ppo_ego_smoke(tmp_path: Path) -> None:
    # the smoke's 2 training scenes split over 2 worker processes (SB3VecEnv -> SplitEgoEnv)
    argv = ["--smoke", "--npc", "idm", "--processes", "2", "--out", str(tmp_path)]
    result = example("train_ppo_ego").main(argv)
    saved = json.loads((tmp_path / "comparison.json").read_text())
    assert set(saved["comparison"]) == {"ppo", "random", "constant_velocity"} == set(result["comparison"])
    assert (tmp_path / "ppo_ego.zip").is_file() and (tmp_path / "learning_curve.png").is_file()
    assert (tmp_path / "learning_curve.csv").read_text().startswith("timesteps,")


def test_partial_control_eval_smoke(tiny_model: Path) -> None:
    results = example("partial_control_eval").main(["--smoke", "--checkpoint", str(tiny_model)])
    assert set(results) == {"trajeglish/first", "trajeglish/last", "replay/first", "replay/last"}
    assert all(r["episodes"] == 2 for r in results.values())
    assert results["replay/first"]["collision_rate"] == 0.0  # the log never collides with the ego's log path


def test_womd_scene_smoke(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the default sample is found as bench finds it: $TRAJEGLISH_SHARED first (a clone anywhere works)
    monkeypatch.setenv("TRAJEGLISH_SHARED", str(shared_file(WOMD_SAMPLE).parents[2]))
    out = example("womd_scene").main(["--smoke", "--npc", "idm", "--out", str(tmp_path / "w.gif")])
    assert out["agents"] == 83 and out["steps"] == 6 and Path(out["video"]).is_file()


def test_cli_demo_with_a_checkpoint(
    tmp_path: Path, tiny_model: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = cli_main(
        ["demo", "--ckpt", str(tiny_model), "--steps", "5", "--out", str(tmp_path), "--json", "--quiet"]
    )
    result = json.loads(capsys.readouterr().out)
    assert code == 0 and result["steps"] == 5 and result["npcs"] >= 1
    assert Path(result["video"]).is_file()
    # the tiny model's 7 guarded NPCs of the default scene over 5 steps (seed 0): none collides or leaves
    # the road (unguarded, one of them left it)
    assert result["npc_collision_rate"] == 0.0 and result["npc_offroad_rate"] == 0.0
    # the steady rate after the first timestep (which pays the first use's compiling), and that step apart
    assert result["env_steps_per_s"] > 0 and result["first_step_s"] > 0
