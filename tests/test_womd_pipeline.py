"""The WOMD workflow end to end with tiny settings: TFRecords -> shards -> fine-tune -> submission .tar.gz ->
local scores, through the CLI; an interrupted export resumes; two ranks (the processes torchrun starts)
give the one-process files bit for bit."""

from __future__ import annotations

import dataclasses
import json
import os
import socket
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp
from helpers import (
    grid_vocabulary,
    queue_scene,
    small_womd_records,
    tiny_config,
    womd_submission,
    write_tfrecord,
)

import trajeglish_env.submission_export as export_module
from trajeglish_env.checkpoint import load_checkpoint, save_checkpoint
from trajeglish_env.cli import main
from trajeglish_env.metrics import score_rollouts
from trajeglish_env.metrics.log_details_io import details_path, load_log_details
from trajeglish_env.metrics.submission import read_submission, read_submission_metadata
from trajeglish_env.model import TrajeglishModel
from trajeglish_env.scenario_io import load_scenarios, save_scenarios
from trajeglish_env.submission_export import ExportConfig, sample_scenario

ROLLOUTS = "2"  # tiny settings (the README's run has WOSAC's 32)
METADATA = [
    *("--account-name", "someone@example.com", "--method-name", "trajeglish-tiny"),
    *("--authors", "A. Author", "B. Author", "--affiliation", "Nowhere"),
    *("--description", "tiny test model", "--method-link", "https://example.com/paper"),
]


def _commands(root: Path, out: str) -> list[list[str]]:
    """The workflow's commands, writing under ``root/out`` (inputs under ``root``)."""
    o = root / out
    shards, run, sub = str(o / "shards"), str(o / "run"), str(o / "sub")
    inputs = sorted(str(p) for p in root.glob("validation.tfrecord-*"))
    train = ["train", "--data", shards, "--out", run, "--init", str(root / "tiny.pt"), "--steps", "2"]
    train += ["--batch-size", "2", "--warmup", "1", "--val-every", "100", "--workers", "0"]
    train += ["--precision", "float32"]  # bfloat16 rounds each rank's weight gradients before the sum
    # both runs export the one-process fine-tuned model (two-rank training matches it to 1e-6, not bitwise)
    export = ["export-submission", "--data", shards, "--out", sub, "--ckpt", str(root / "one/run/model.pt")]
    generate = [
        "generate",
        "--scenes",
        "2",
        "--scenes-per-shard",
        "1",
        "--kinds",
        "merge",
        "--out",
        str(o / "gen"),
    ]
    return [
        generate,
        ["convert-womd", *inputs, "--out", shards],
        train,
        [*export, "--rollouts", ROLLOUTS, *METADATA],
        ["score-submission", f"{sub}/submission.tar.gz", "--data", shards, "--out", str(o / "scores.json")],
        ["evaluate", "--data", shards, "--submission", f"{sub}/submission.tar.gz", "--out", str(o / "eval")],
    ]


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """Two small WOMD TFRecords cut from the shared scenario and a tiny checkpoint to fine-tune."""
    root = tmp_path_factory.mktemp("womd")
    first, second = small_womd_records(keep=4)
    write_tfrecord(root / "validation.tfrecord-00000-of-00002", [first])
    write_tfrecord(root / "validation.tfrecord-00001-of-00002", [second])
    torch.manual_seed(0)
    save_checkpoint(root / "tiny.pt", TrajeglishModel(tiny_config()), grid_vocabulary())
    return root


def run_one_process(root: Path) -> dict[str, dict]:
    """The workflow in one process; the export is interrupted after its first scenario and resumed."""
    results = {}
    generate, convert, train, export, score, evaluate = _commands(root, "one")
    for command in (generate, convert, train):
        results[command[0]] = _run(command)
    real = export_module.sample_scenario
    calls = []

    def crash_on_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt  # the job is killed while sampling the second scenario
        return real(*args, **kwargs)

    export_module.sample_scenario = crash_on_second
    try:
        assert main([*export, "--processes", "2", "--quiet"]) == 130  # interrupted: one line, exit 130
    finally:
        export_module.sample_scenario = real
    # resumed with another process count: it never changes the rollouts, so the settings still match
    for command in ([*export, "--processes", "1"], score, evaluate):
        results[command[0]] = _run(command)
    return results


def _run(command: list[str]) -> dict:
    import contextlib
    import io

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        assert main([*command, "--json", "--quiet"]) == 0, command
    return json.loads(buffer.getvalue())


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank(rank: int, world: int, port: int, root: str) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        WORLD_SIZE=str(world),
        RANK=str(rank),
        LOCAL_RANK=str(rank),
    )
    torch.set_num_threads(1)
    for command in _commands(Path(root), "two"):
        assert main([*command, "--quiet"]) == 0, command
    torch.distributed.barrier()  # both ranks done before either tears its connections down
    torch.distributed.destroy_process_group()


def test_tfrecords_to_a_scored_submission_and_two_ranks_write_the_same_files(root: Path) -> None:
    one = run_one_process(root)
    assert one["convert-womd"]["scenes"] == 2 and one["train"]["steps"] == 2
    export = one["export-submission"]
    assert export["scenarios"] == 2 and export["resumed"] == 1 and export["sampled"] == 1  # resumed
    assert [Path(p).name for p in export["shards"]] == [
        "submission.binproto-00000-of-00002",
        "submission.binproto-00001-of-00002",
    ]
    archive = Path(export["archive"])
    rollouts = read_submission(archive)
    assert [r.scenario_id for r in rollouts] == ["637f20cafde22ff8", "637f20cafde22ff8-b"]
    assert all(r.xyz.shape == (2, 4, 80, 3) for r in rollouts)
    for meta in read_submission_metadata(archive):
        assert meta is not None and meta.validate() is meta
        assert meta.authors == ("A. Author", "B. Author") and meta.method_link == "https://example.com/paper"
        assert meta.acknowledge_complies_with_closed_loop_requirement and not meta.uses_lidar_data
        assert meta.num_model_parameters == "95K"  # counted from the tiny checkpoint

    # the files hold exactly the rollouts the sampler draws; scored from them, the same numbers
    ckpt = load_checkpoint(root / "one" / "run" / "model.pt")
    shard = root / "one" / "shards" / "validation-00001-of-00002.scn.npz"
    (scene,), (details,) = load_scenarios(shard), load_log_details(details_path(shard))
    direct = sample_scenario(ckpt, scene, details, ExportConfig(rollouts=2))
    split = sample_scenario(ckpt, scene, details, ExportConfig(rollouts=2, processes=2))
    np.testing.assert_array_equal(split.xyz, direct.xyz)  # a rollout per process: the same files
    with pytest.raises(ValueError, match="processes must be a positive int or 'auto'"):
        ExportConfig(processes=0)
    np.testing.assert_array_equal(direct.xyz, rollouts[1].xyz)
    np.testing.assert_array_equal(direct.heading, rollouts[1].heading)
    assert np.all(direct.z == np.float32(details.xyz[scene.valid[:, 10], 10, 2])[None, :, None])
    per_scenario = json.loads((root / "one" / "scores.json").read_text())["per_scenario"]
    in_memory = score_rollouts(scene, direct.xyh, direct.object_id, rollouts_z=direct.z, details=details)
    assert per_scenario[1] == in_memory.to_dict()
    scores = one["score-submission"]["scores"]
    table = one["evaluate"]["methods"]
    assert table["submission"]["scores"] == scores  # `trajeglish evaluate` on the same rollouts
    assert one["evaluate"]["log_details"] and table["log"]["scores"]["metametric"] > scores["metametric"]

    # two ranks (the processes torchrun starts) write the one-process files
    mp.start_processes(_rank, args=(2, _free_port(), str(root)), nprocs=2, start_method="spawn")
    a, b = root / "one", root / "two"
    for name in ("highway-00000.scn.npz", "highway-00001.scn.npz"):
        (x,), (y,) = load_scenarios(a / "gen" / name), load_scenarios(b / "gen" / name)
        assert x.equals(y)
    for name in ("validation-00000-of-00002", "validation-00001-of-00002"):
        (x,), (y,) = (
            load_scenarios(a / "shards" / f"{name}.scn.npz"),
            load_scenarios(b / "shards" / f"{name}.scn.npz"),
        )
        assert x.equals(y)
        (dx,), (dy,) = (
            load_log_details(a / "shards" / f"{name}.details.npz"),
            load_log_details(b / "shards" / f"{name}.details.npz"),
        )
        assert all(np.array_equal(getattr(dx, f), getattr(dy, f)) for f in ("xyz", "heading", "box", "map_z"))
    tuned_one, tuned_two = (load_checkpoint(d / "run" / "model.pt") for d in (a, b))
    assert tuned_two.training["processes"] == 2 and tuned_two.training["init"] == str(root / "tiny.pt")
    for key, value in tuned_one.model.state_dict().items():
        atol = 2e-5 if key.endswith("kv.bias") else 1e-6  # as in test_train: zero-gradient key biases
        torch.testing.assert_close(value, tuned_two.model.state_dict()[key], rtol=0, atol=atol, msg=key)
    for name in ("sub/submission.tar.gz", "sub/submission.binproto-00001-of-00002", "scores.json"):
        one_bytes, two_bytes = (a / name).read_bytes(), (b / name).read_bytes()
        assert one_bytes == two_bytes or name == "scores.json", name
    one_scores, two_scores = (json.loads((d / "scores.json").read_text()) for d in (a, b))
    assert two_scores["processes"] == 2 and two_scores["per_scenario"] == one_scores["per_scenario"]
    one_eval, two_eval = (json.loads((d / "eval" / "evaluation.json").read_text()) for d in (a, b))
    assert two_eval["processes"] == 2 and two_eval["methods"] == one_eval["methods"]


def test_bad_inputs_fail_with_one_line(root: Path, tmp_path: Path, capsys) -> None:
    shards, sub = str(tmp_path / "shards"), str(tmp_path / "sub")
    inputs = sorted(str(p) for p in root.glob("validation.tfrecord-*"))
    assert main(["convert-womd", *inputs, "--out", shards, "--quiet"]) == 0
    export = ["export-submission", "--data", shards, "--ckpt", str(root / "tiny.pt"), "--quiet"]
    assert main([*export, "--out", sub, *METADATA, "--rollouts", "1", "--steps", "1"]) == 0  # quick
    said = capsys.readouterr().err  # allowed for a quick try, but said, not silent
    assert "--steps 1: WOSAC and score-submission need 80 steps" in said
    assert "--rollouts 1: WOSAC takes exactly 32 joint rollouts per scenario" in said
    cases = {
        "missing or invalid: account_name (--account-name)": [*export, "--out", str(tmp_path / "a")],
        "num_model_parameters '1.5M' must be": [
            *export,
            "--out",
            str(tmp_path / "b"),
            *METADATA,
            "--num-model-parameters",
            "1.5M",
        ],
        "holds an export with other settings (config.rollouts: 1 -> 32; config.seed: 0 -> 3; "
        "config.steps: 1 -> 80)": [
            *export,
            "--out",
            sub,
            *METADATA,
            "--seed",
            "3",
        ],
        "no such scenario file or directory": [
            *export,
            "--out",
            str(tmp_path / "c"),
            *METADATA,
            "--data",
            str(tmp_path / "nothing"),
        ],
        "no such WOMD TFRecord file": [
            "convert-womd",
            str(tmp_path / "missing.tfrecord"),
            "--out",
            str(tmp_path),
        ],
        "cannot read submission: no such file": [
            "score-submission",
            str(tmp_path / "x.tar.gz"),
            "--data",
            shards,
        ],
    }
    other = tmp_path / "other"
    save_scenarios(other / "queue.scn.npz", [queue_scene()])  # scenes the submission was not sampled on
    cases["of the submission is not in the data (1 scenes in 1 files"] = [
        "score-submission",
        str(womd_submission()),
        "--data",
        str(other),
        "--quiet",
    ]
    for message, command in cases.items():
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (message, err)
    # WOMD shards without their raw log details cannot give the submission's z
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "w.scn.npz").write_bytes((tmp_path / "shards/validation-00000-of-00002.scn.npz").read_bytes())
    assert main([*export, "--out", str(tmp_path / "d"), *METADATA, "--data", str(bare)]) == 2
    assert "w.details.npz: missing (WOMD z values)" in capsys.readouterr().err


def test_conversion_in_worker_processes_writes_the_same_shards(root: Path, tmp_path: Path) -> None:
    from trajeglish_env.sources.womd_convert import convert_womd

    inputs = sorted(root.glob("validation.tfrecord-*"))
    one = convert_womd(inputs, tmp_path / "one", progress=False)
    two = convert_womd(inputs, tmp_path / "two", progress=False, workers=2)
    assert two["workers"] == 2 and {
        k: v for k, v in two.items() if k not in ("outputs", "seconds", "workers")
    } == {k: v for k, v in one.items() if k not in ("outputs", "seconds", "workers")}
    for shard in (tmp_path / "one").iterdir():
        if shard.name.endswith(".scn.npz"):
            (a,), (b,) = load_scenarios(shard), load_scenarios(tmp_path / "two" / shard.name)
            assert a.equals(b)
        else:
            (a,), (b,) = load_log_details(shard), load_log_details(tmp_path / "two" / shard.name)
            assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.map_z, b.map_z)


def test_score_submission_refuses_what_would_give_wrong_scores(tmp_path: Path, capsys) -> None:
    """A WOMD shard without its raw log details (minADE off by metres, silently, before), a scenario in the
    data twice, and an --out that is a directory are refused in one line before any scoring."""
    from helpers import womd_tfrecord

    shards = tmp_path / "shards"
    assert main(["convert-womd", str(womd_tfrecord()), "--out", str(shards), "--quiet"]) == 0
    (shard,) = shards.glob("*.scn.npz")
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / shard.name).write_bytes(shard.read_bytes())
    score = ["score-submission", str(womd_submission()), "--quiet"]
    cases = {
        f"{bare / shard.name}: scene '637f20cafde22ff8' comes from WOMD but": ["--data", str(bare)],
        "is in both": ["--data", str(shards), str(bare)],
        "is a directory; give the JSON file to write": ["--data", str(shards), "--out", str(tmp_path)],
    }
    for message, args in cases.items():
        assert main([*score, *args]) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (message, err)


def test_a_validation_scene_is_simulated_exactly_as_its_test_form_twin() -> None:
    """The export samples from the history alone; agents that only the future holds are left out, so the
    rollouts are those of the scene's test-form twin, bit for bit (before, their empty rows shifted the
    agents' random draws: 5 m apart after 20 steps)."""
    from helpers import tiny, womd_tfrecord

    from trajeglish_env.metrics import read_womd_details
    from trajeglish_env.sources.womd import read_womd

    scene, details = next(read_womd(womd_tfrecord())), next(read_womd_details(womd_tfrecord()))
    seen = np.flatnonzero(scene.valid[:, : scene.current_index + 1].any(axis=1))
    assert len(seen) < scene.num_agents  # the shared scene holds future-only agents
    per_track = ("track_id", "xyz", "heading", "box", "object_type")
    twin_details = dataclasses.replace(details, **{f: getattr(details, f)[seen] for f in per_track})
    config = ExportConfig(rollouts=1, steps=6, processes=1)
    validation = sample_scenario(tiny(), scene, details, config)
    test_form = sample_scenario(tiny(), scene.with_agents(seen), twin_details, config)
    np.testing.assert_array_equal(test_form.xyz, validation.xyz)
    np.testing.assert_array_equal(test_form.object_id, validation.object_id)
