"""The GPU-machine job (scripts/device_train.sh, trajeglish_env/device_job.py) on the CPU with tiny settings:
it generates, trains, brings back a checkpoint that loads and a summary, and a second call resumes the
first; bad set-ups fail with one clear line; ``train``'s wall-clock budget stops and resumes exactly."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers import REPO, grid_vocabulary, straight_road_scene, tiny_checkpoint, tiny_config

from trajeglish_env import device_job
from trajeglish_env.checkpoint import load_checkpoint, pretrained_path, save_checkpoint
from trajeglish_env.cores import can_fork
from trajeglish_env.scenario_io import save_scenarios, scenario_ids
from trajeglish_env.training.train import TrainConfig, train

BASH = shutil.which("bash")
SCRIPT = REPO / "scripts" / "device_train.sh"


def _job(tmp: Path, name: str, **env: str) -> subprocess.CompletedProcess[str]:
    """One call of the script: DEVICE=cpu, tiny model, a few seconds of training."""
    settings = dict(
        DEVICE="cpu",
        PRESET="tiny",
        MINUTES="5",
        TRAIN_MINUTES="0.05",
        SCENES="0",
        SUMO_SCENES="0",
        VAL_SCENES="0",
        BATCH="4",
        STEPS="100000",
        GEN_WORKERS="1",
        TRAIN_WORKERS="0",
        DATA_IN=str(tmp / "carried"),
        WHEELS=str(tmp / "no-wheels"),
        WORK=str(tmp / f"work-{name}"),
        OUT=str(tmp / f"out-{name}"),
        PYTHON=sys.executable,
        OMP_NUM_THREADS="1",
    )
    settings.update(env)
    full = {k: v for k, v in os.environ.items() if k not in settings and k != "RUN_IN"}
    return subprocess.run(  # the script logs everything on stdout (and into its log)
        [BASH, str(SCRIPT)],
        cwd=REPO,
        env={**full, **settings},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=300,
    )


def _carry_scenes(tmp: Path, n: int) -> None:
    """``n`` small straight-road scenes in the carried training folder (DATA_IN/train) of ``_job``."""
    carried = tmp / "carried" / "train"
    carried.mkdir(parents=True)
    save_scenarios(
        carried / "s.scn.npz", [straight_road_scene(num_agents=5, seed=s, steps=40) for s in range(n)]
    )


@pytest.mark.skipif(BASH is None, reason="needs bash")
def test_a_call_trains_and_a_second_call_resumes(tmp_path: Path) -> None:
    _carry_scenes(tmp_path, 6)

    # two highway-env scenes and two with a stop event generated, six carried; the schedule of STEPS goes
    # on over several calls
    first = _job(tmp_path, "1", SCENES="2", STOP_SCENES="2", FIT_STEPS="0")
    assert first.returncode == 0, first.stdout[-3000:]
    out1 = tmp_path / "out-1"
    summary1 = json.loads((out1 / "summary.json").read_text())
    assert summary1["step"] >= 1 and summary1["params"]["PRESET"] == "tiny"
    assert summary1["train_scenes"] == 10 - 1  # every 20th scene (the first) held out
    (stops,) = (tmp_path / "work-1").rglob("stop-s*-n2")
    assert all("+stop" in sid for f in stops.glob("*.scn.npz") for sid in scenario_ids(f))
    assert "highway" in summary1["sources"]
    ckpt = load_checkpoint(out1 / "model.pt")
    assert ckpt.config.d_model == tiny_config().d_model and ckpt.training["step"] == summary1["step"]
    assert (out1 / "resume" / "last.pt.000").is_file() and (out1 / "log.txt").is_file()
    assert len([p for p in out1.rglob("*") if p.is_file()]) <= device_job.MAX_FILES

    second = _job(tmp_path, "2", RUN_IN=str(out1 / "resume"))
    assert second.returncode == 0, second.stdout[-3000:]
    summary2 = json.loads((tmp_path / "out-2" / "summary.json").read_text())
    assert summary2["step"] > summary1["step"]  # it went on from the first call's step
    assert [c["call"] for c in summary2["calls"]] == [0, 1]
    assert summary2["calls"][1]["train"]["resumed_from"] == summary1["step"]
    assert load_checkpoint(tmp_path / "out-2" / "model.pt").training["step"] == summary2["step"]

    # a resumed run keeps its schedule: another STEPS is refused with one clear line
    third = _job(tmp_path, "3", RUN_IN=str(out1 / "resume"), STEPS="50")
    assert third.returncode == 2
    assert "STEPS=50 but the run in RUN_IN was started with STEPS=100000" in third.stdout


@pytest.mark.skipif(BASH is None, reason="needs bash")
def test_a_new_run_can_start_from_the_shipped_model(tmp_path: Path) -> None:
    _carry_scenes(tmp_path, 4)
    job = _job(
        tmp_path,
        "init",
        PRESET="small",
        INIT="shipped",
        STEPS="3",
        BATCH="2",
        SIGNAL_INPUT="1",
        NEIGHBOUR_INPUT="1",
        LANE_INPUT="1",
        BEND_WEIGHT="3",
    )
    assert job.returncode == 0, job.stdout[-3000:]
    tuned = load_checkpoint(tmp_path / "out-init" / "model.pt")
    assert tuned.training["init"] == str(pretrained_path()) and tuned.training["step"] >= 1
    assert tuned.config.signal_input  # the shipped model, extended with the signal input
    assert tuned.config.neighbour_input  # and with the neighbour input
    assert tuned.config.lane_input  # and with the road input
    assert tuned.training["train_config"]["bend_weight"] == 3.0
    summary = json.loads((tmp_path / "out-init" / "summary.json").read_text())
    assert summary["params"]["SIGNAL_INPUT"] == "1"  # kept for a resumed call
    assert summary["params"]["NEIGHBOUR_INPUT"] == "1"
    missing = _job(tmp_path, "noinit", INIT=str(tmp_path / "absent.pt"))
    assert missing.returncode == 2 and "INIT=" in missing.stdout and "no such checkpoint" in missing.stdout


@pytest.mark.skipif(BASH is None, reason="needs bash")
def test_a_run_from_a_checkpoint_keeps_its_model_and_vocabulary_over_calls(tmp_path: Path) -> None:
    """INIT=a checkpoint whose model and vocabulary are not a preset's (as a GPU run's checkpoint carried
    to the next call): the new run and its resumed calls train that model on that vocabulary."""
    _carry_scenes(tmp_path, 4)
    start = tiny_checkpoint(vocab_size=128)
    init = save_checkpoint(tmp_path / "grid128.pt", start.model, start.vocabulary)
    first = _job(tmp_path, "own1", PRESET="", INIT=str(init), FIT_STEPS="0", NOISE_ON_DEVICE="1")
    assert first.returncode == 0, first.stdout[-3000:]
    assert "noisy input tokens drawn on cpu in training" in first.stdout  # checked first, then on
    second = _job(tmp_path, "own2", PRESET="", RUN_IN=str(tmp_path / "out-own1" / "resume"))
    assert second.returncode == 0, second.stdout[-3000:]
    summary = json.loads((tmp_path / "out-own2" / "summary.json").read_text())
    assert [c["train"]["resumed_from"] for c in summary["calls"]] == [
        0,
        summary["calls"][0]["train"]["steps"],
    ]
    assert all(0 <= c["train"]["data_wait_share"] <= 1 for c in summary["calls"])
    assert [c["noise_on_device"] for c in summary["calls"]] == [1, 0]  # auto: on with CUDA only
    tuned = load_checkpoint(tmp_path / "out-own2" / "model.pt")
    assert tuned.config == start.config and tuned.training["step"] == summary["step"] > 0
    assert (tuned.vocabulary.templates == start.vocabulary.templates).all()
    # a PRESET set beside INIT is the model asked for: this one is not the checkpoint's, so train refuses,
    # and the call still brings back its log and summary (no checkpoint)
    bad = _job(tmp_path, "own4", NOISE_ON_DEVICE="yes")
    assert bad.returncode == 2 and "NOISE_ON_DEVICE=yes: expected 0, 1 or auto" in bad.stdout
    clash = _job(tmp_path, "own3", PRESET="small", INIT=str(init))
    assert clash.returncode == 2 and "the model config differs from the checkpoint's" in clash.stdout
    assert "Traceback" not in clash.stdout
    assert (tmp_path / "out-own3" / "log.txt").is_file() and not (tmp_path / "out-own3" / "model.pt").exists()
    assert "step" not in json.loads((tmp_path / "out-own3" / "summary.json").read_text())


@pytest.mark.skipif(BASH is None, reason="needs bash")
def test_a_new_run_can_extend_its_checkpoints_vocabulary(tmp_path: Path) -> None:
    _carry_scenes(tmp_path, 4)
    start = tiny_checkpoint()
    init = save_checkpoint(tmp_path / "tiny.pt", start.model, start.vocabulary)
    job = _job(tmp_path, "ext", INIT=str(init), EXTEND="2048", STEPS="3")
    assert job.returncode == 0, job.stdout[-3000:]
    tuned = load_checkpoint(tmp_path / "out-ext" / "model.pt")
    assert tuned.config.vocab_size == 2048 and tuned.config.token_bias
    n = start.vocabulary.size
    assert (tuned.vocabulary.templates[:, :n] == start.vocabulary.templates).all()
    summary = json.loads((tmp_path / "out-ext" / "summary.json").read_text())
    assert summary["params"]["EXTEND"] == "2048"
    # the same extension carried (make device-vocab) is trained on as it is; extension() says why another
    # is not (the job then extends the vocabulary itself)
    tuned.vocabulary.save(tmp_path / "carried" / "vocab_extended_2048.npz")
    carried = _job(tmp_path, "extc", INIT=str(init), EXTEND="2048", STEPS="3")
    assert carried.returncode == 0, carried.stdout[-3000:]
    assert "no extending here" in carried.stdout and "extended " not in carried.stdout
    again = load_checkpoint(tmp_path / "out-extc" / "model.pt").vocabulary
    assert (again.templates == tuned.vocabulary.templates).all()
    from trajeglish_env.device_job import extension

    path = tmp_path / "carried" / "vocab_extended_2048.npz"
    assert extension(path, str(init), 2048) == ""
    assert extension(path, str(init), 1024) == f"{path} holds 2048 tokens per class, not 1024"
    assert extension(path, "shipped", 2048) == f"{path} does not begin with shipped's 384 templates"
    path.write_bytes(b"not a vocabulary")
    assert extension(path, str(init), 2048).startswith(f"{path}: not a readable vocabulary")
    alone = _job(tmp_path, "ext0", EXTEND="2048")
    assert alone.returncode == 2 and "EXTEND=2048 needs INIT" in alone.stdout
    bad = _job(tmp_path, "extb", EXTEND="many", INIT=str(init))
    assert bad.returncode == 2 and "EXTEND=many: expected a number of tokens" in bad.stdout


@pytest.mark.skipif(BASH is None, reason="needs bash")
def test_a_new_run_can_train_on_a_vocabulary_fitted_on_its_scenes(tmp_path: Path) -> None:
    # highway-env scenes (varied motion); the windows' map chunks nearest any of their agents
    job = _job(
        tmp_path,
        "v",
        VOCAB="128",
        SCENES="10",
        DATA_IN="",
        MAP_SELECT="agents",
        MAP_STRIDE="4",
        REPEAT="highway=2",
        CLOSED_LOOP="3",
        NEIGHBOUR_INPUT="1",
        INTERACTION_WEIGHT="2.5",
        COLLISION_WEIGHT="1.5",
        COLLISION_HORIZON="4",
        COLLISION_ROLLED_OUT_ONLY="1",
        COLLISION_SOURCES="highway",
        COLLISION_FORM="versus-target",
        HISTORY_DROPOUT="0.3",
    )
    assert job.returncode == 0, job.stdout[-3000:]
    ckpt = load_checkpoint(tmp_path / "out-v" / "model.pt")
    assert ckpt.config.vocab_size == 128 and ckpt.vocabulary.size == 128
    assert ckpt.config.map_select == "agents" and ckpt.config.map_stride == 4
    assert "vehicle" in ckpt.vocabulary.metadata["coverage"]  # fitted with the motion-envelope cover
    summary = json.loads((tmp_path / "out-v" / "summary.json").read_text())
    assert summary["params"]["VOCAB"] == "128"  # kept for a resumed call, which does not refit
    assert summary["params"]["MAP_SELECT"] == "agents" and summary["params"]["MAP_STRIDE"] == "4"
    assert summary["params"]["FIT_STEPS"] == "1"  # the default: the schedule fitted to the call's budget
    assert summary["params"]["REPEAT"] == "highway=2"  # kept for a resumed call (`train --repeat`)
    assert tuple(map(tuple, ckpt.training["train_config"]["repeat"])) == (("highway", 2),)
    assert summary["params"]["CLOSED_LOOP"] == "3"  # CAT-K windows, kept for a resumed call
    assert ckpt.training["train_config"]["closed_loop_top_k"] == 3
    assert ckpt.config.neighbour_input  # CAT-K windows of a model that reads its neighbours
    assert summary["params"]["INTERACTION_WEIGHT"] == "2.5"  # kept for a resumed call
    assert ckpt.training["train_config"]["interaction_weight"] == 2.5
    assert summary["params"]["COLLISION_WEIGHT"] == "1.5"  # kept for a resumed call
    assert ckpt.training["train_config"]["collision_weight"] == 1.5
    assert summary["params"]["COLLISION_HORIZON"] == "4"  # kept for a resumed call
    assert ckpt.training["train_config"]["collision_horizon"] == 4
    assert summary["params"]["COLLISION_ROLLED_OUT_ONLY"] == "1"  # kept for a resumed call
    assert ckpt.training["train_config"]["collision_rolled_out_only"] is True
    assert summary["params"]["COLLISION_SOURCES"] == "highway"  # kept for a resumed call
    assert tuple(ckpt.training["train_config"]["collision_sources"]) == ("highway",)
    assert summary["params"]["COLLISION_FORM"] == "versus-target"  # kept for a resumed call
    assert ckpt.training["train_config"]["collision_form"] == "versus_target"
    assert summary["params"]["HISTORY_DROPOUT"] == "0.3"  # kept for a resumed call
    assert ckpt.training["train_config"]["history_dropout"] == 0.3
    clash = _job(tmp_path, "vi", VOCAB="640", INIT="shipped")
    assert clash.returncode == 2 and "keeps its checkpoint's vocabulary" in clash.stdout
    bad = _job(tmp_path, "vb", VOCAB="big")
    assert bad.returncode == 2 and "VOCAB=big: expected a number of tokens" in bad.stdout
    bad_map = _job(tmp_path, "vm", MAP_SELECT="lanes")
    assert bad_map.returncode == 2 and "MAP_SELECT=lanes: expected frame, agents or ahead" in bad_map.stdout
    bad_stride = _job(tmp_path, "vs", MAP_STRIDE="0")
    assert bad_stride.returncode == 2 and "MAP_STRIDE=0: expected a whole number >= 1" in bad_stride.stdout
    bad_closed = _job(tmp_path, "vc", CLOSED_LOOP="-1")
    assert bad_closed.returncode == 2 and "CLOSED_LOOP=-1: expected a number of tokens" in bad_closed.stdout
    refused = (  # (run name, setting, what the refusal says)
        ("vw", {"INTERACTION_WEIGHT": "0.5"}, "INTERACTION_WEIGHT=0.5: expected a loss weight >= 1"),
        ("vx", {"COLLISION_WEIGHT": "-1"}, "COLLISION_WEIGHT=-1: expected a loss weight >= 0"),
        ("vh", {"COLLISION_HORIZON": "0"}, "COLLISION_HORIZON=0: expected a whole number of steps"),
        ("vo", {"COLLISION_ROLLED_OUT_ONLY": "yes"}, "COLLISION_ROLLED_OUT_ONLY=yes: expected 0 or 1"),
        ("vz", {"COLLISION_SOURCES": "sumo;rm"}, "COLLISION_SOURCES=sumo;rm: expected scene sources"),
        ("vf", {"COLLISION_FORM": "hinge"}, "COLLISION_FORM=hinge: expected mass or versus-target"),
        ("vg", {"OFFROAD_FORM": "hinge"}, "OFFROAD_FORM=hinge: expected mass or versus-target"),
        ("vk", {"OFFROAD_HORIZON": "0"}, "OFFROAD_HORIZON=0: expected steps >= 1"),
        ("vj", {"OFFROAD_HORIZON": "5"}, "OFFROAD_HORIZON=5 needs OFFROAD_WEIGHT > 0"),
    )
    for name, setting, says in refused:
        bad = _job(tmp_path, name, **setting)
        assert bad.returncode == 2 and says in bad.stdout, (setting, bad.stdout[-2000:])
    # OFFROAD_WEIGHT reaches `train`, which refuses it beside CAT-K windows (masks cut at logged states)
    clash_offroad = _job(
        tmp_path,
        "vq",
        SCENES="10",
        DATA_IN="",
        OFFROAD_WEIGHT="0.5",
        OFFROAD_FORM="versus-target",
        CLOSED_LOOP="3",
        NEIGHBOUR_INPUT="1",
    )
    assert clash_offroad.returncode != 0 and "offroad_weight masks are cut at logged states" in (
        clash_offroad.stdout
    )
    bad_offroad = _job(tmp_path, "vr", OFFROAD_WEIGHT="lots")
    assert bad_offroad.returncode == 2 and "OFFROAD_WEIGHT=lots: expected a loss weight >= 0" in (
        bad_offroad.stdout
    )
    bad_dropout = _job(tmp_path, "vd", HISTORY_DROPOUT="1")
    assert (
        bad_dropout.returncode == 2 and "HISTORY_DROPOUT=1: expected a share in [0, 1)" in bad_dropout.stdout
    )
    alone = _job(tmp_path, "vn", HISTORY_DROPOUT="0.3")
    assert alone.returncode == 2 and "HISTORY_DROPOUT=0.3 needs NEIGHBOUR_INPUT=1" in alone.stdout
    bad_fit = _job(tmp_path, "vf", FIT_STEPS="yes")
    assert bad_fit.returncode == 2 and "FIT_STEPS=yes: expected 0 or 1" in bad_fit.stdout


@pytest.mark.skipif(BASH is None, reason="needs bash")
def test_bad_setups_fail_with_one_clear_line(tmp_path: Path) -> None:
    no_out = _job(tmp_path, "x", OUT="")
    assert no_out.returncode == 2 and "OUT is not set" in no_out.stdout
    bad_signal = _job(tmp_path, "s", SIGNAL_INPUT="yes")
    assert bad_signal.returncode == 2 and "SIGNAL_INPUT=yes: expected 0 or 1" in bad_signal.stdout
    bad_stops = _job(tmp_path, "t", STOP_SCENES="some")
    assert bad_stops.returncode == 2 and "STOP_SCENES=some: expected a whole number" in bad_stops.stdout
    bad_neighbours = _job(tmp_path, "n", NEIGHBOUR_INPUT="2")
    assert bad_neighbours.returncode == 2 and "NEIGHBOUR_INPUT=2: expected 0 or 1" in bad_neighbours.stdout
    bad_lanes = _job(tmp_path, "l", LANE_INPUT="2")
    assert bad_lanes.returncode == 2 and "LANE_INPUT=2: expected 0 or 1" in bad_lanes.stdout
    bad_bend = _job(tmp_path, "b", BEND_WEIGHT="0.5")
    assert bad_bend.returncode == 2 and "BEND_WEIGHT=0.5: expected a loss weight >= 1" in bad_bend.stdout
    blind_bend = _job(tmp_path, "bb", BEND_WEIGHT="4")
    assert blind_bend.returncode == 2 and "BEND_WEIGHT=4 needs LANE_INPUT=1" in blind_bend.stdout
    if not torch.cuda.is_available():
        no_cuda = _job(tmp_path, "y", DEVICE="cuda")
        assert no_cuda.returncode == 2 and "DEVICE=cuda but torch" in no_cuda.stdout


def test_pack_splits_the_checkpoint_and_resume_rebuilds_it(tmp_path: Path, monkeypatch) -> None:
    run = tmp_path / "run"
    ckpt = tiny_checkpoint()
    save_checkpoint(run / "last.pt", ckpt.model, ckpt.vocabulary, trainer={"step": 7, "history": []})
    save_checkpoint(run / "model.pt", ckpt.model, ckpt.vocabulary, training={"step": 7})
    monkeypatch.setattr(device_job, "PART_BYTES", 200_000)
    facts = {"call": 0, "params": {"PRESET": "tiny", "STEPS": "9"}}
    summary = device_job.pack(run, tmp_path / "out", facts, None)
    parts = sorted((tmp_path / "out" / "resume").glob("last.pt.*"))
    assert len(parts) > 1 and summary["files"]["model.pt"] > 0
    rebuilt = device_job.resume(tmp_path / "out" / "resume", tmp_path / "again")
    assert (tmp_path / "again" / "last.pt").read_bytes() == (run / "last.pt").read_bytes()
    assert rebuilt["RESUME_STEP"] == "7" and rebuilt["SAVED_STEPS"] == "9" and rebuilt["CALL"] == "1"
    parts[-1].unlink()  # an incomplete series does not load: a clear error, not a crash
    with pytest.raises(device_job.JobError, match="does not load"):
        device_job.resume(tmp_path / "out" / "resume", tmp_path / "again2")
    # a run whose schedule is done (FIT_STEPS=1 fits it to the first call) is refused, not resumed for nothing
    done = {"step": 9, "history": [], "train_config": {"steps": 9}}
    save_checkpoint(run / "last.pt", ckpt.model, ckpt.vocabulary, trainer=done)
    device_job.pack(run, tmp_path / "out2", facts, None)
    with pytest.raises(device_job.JobError, match=r"finished its schedule \(step 9 of 9.*FIT_STEPS=0"):
        device_job.resume(tmp_path / "out2" / "resume", tmp_path / "again3")


def test_time_limit_stops_and_the_resume_is_exact(tmp_path: Path) -> None:
    scenes = tmp_path / "scenes"
    save_scenarios(
        scenes / "a.scn.npz", [straight_road_scene(num_agents=5, seed=s, steps=40) for s in range(4)]
    )
    cfg = dict(steps=5, batch_size=4, warmup_steps=2, val_every=100, log_every=1, checkpoint_every=100)
    quick = TrainConfig(**cfg, num_workers=0, val_fraction=0.0)
    kw = dict(vocabulary=grid_vocabulary(), progress=False)
    straight = train(scenes, tmp_path / "a", tiny_config(), quick, **kw)
    cut = train(scenes, tmp_path / "b", tiny_config(), quick, time_limit=0.0, **kw)
    assert cut["steps"] == 1 and cut["stopped_by_time_limit"]
    assert load_checkpoint(tmp_path / "b" / "last.pt").trainer["step"] == 1  # checkpointed where it stopped
    # another number of loader processes (another machine) may resume: batches do not depend on it
    more = TrainConfig(**cfg, num_workers=1, val_fraction=0.0)
    resumed = train(scenes, tmp_path / "b", tiny_config(), more, resume=True, **kw)
    assert resumed["resumed_from"] == 1 and resumed["steps"] == straight["steps"] == 5
    a = load_checkpoint(tmp_path / "a" / "model.pt").model.state_dict()
    b = load_checkpoint(tmp_path / "b" / "model.pt").model.state_dict()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=f"{k} differs after a timed stop")


def test_fit_steps_ends_the_schedule_with_the_budget_and_resume_keeps_it(tmp_path: Path) -> None:
    scenes = tmp_path / "scenes"
    save_scenarios(
        scenes / "a.scn.npz", [straight_road_scene(num_agents=5, seed=s, steps=40) for s in range(4)]
    )
    cfg = dict(batch_size=2, warmup_steps=15, val_every=10_000, log_every=1, checkpoint_every=10_000)
    kw = dict(vocabulary=grid_vocabulary(), progress=False)
    config = TrainConfig(steps=1_000_000, **cfg, num_workers=0, val_fraction=0.0)
    with pytest.raises(ValueError, match="needs a time_limit"):
        train(scenes, tmp_path / "x", tiny_config(), config, fit_steps=True, **kw)
    fitted = train(scenes, tmp_path / "a", tiny_config(), config, time_limit=8.0, fit_steps=True, **kw)
    n = fitted["steps_fitted_to_time"]
    # the rate of steps 5..15 sets the length: far fewer than the most allowed, more than the probe
    assert 15 < n < 1_000_000 and fitted["steps"] <= n
    ckpt = load_checkpoint(tmp_path / "a" / "last.pt")
    assert ckpt.trainer["train_config"]["steps"] == n
    lrs = [row["lr"] for row in ckpt.trainer["history"]]
    if fitted["steps"] == n:  # finished inside the budget: the learning rate decayed to 0 on the last step
        schedule = dataclasses.replace(
            config, steps=n, decay_from=tuple(ckpt.trainer["train_config"]["decay_from"])
        )
        assert lrs[-1] == pytest.approx(schedule.lr_at(n - 1)) and lrs[-1] < 0.1 * config.lr
    # a resume with the same (unfitted) request keeps the fitted length and finishes it
    again = train(
        scenes, tmp_path / "a", tiny_config(), config, resume=True, time_limit=60.0, fit_steps=True, **kw
    )
    assert again["steps"] == again["steps_fitted_to_time"] == n


# ------------------------------------------------------------------------- the GPU bench job
BENCH_SCRIPT = REPO / "scripts" / "device_bench.sh"


def _bench_job(tmp: Path, **env: str) -> subprocess.CompletedProcess[str]:
    settings = {"OUT": str(tmp / "out"), "PYTHON": sys.executable, "WHEELS": str(tmp / "no-wheels"), **env}
    return subprocess.run(
        [BASH, str(BENCH_SCRIPT)],
        cwd=REPO,
        env={**os.environ, **settings},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=300,
    )


@pytest.mark.skipif(BASH is None, reason="needs bash")
def test_the_gpu_bench_job_dry_runs_on_the_cpu_and_refuses_a_machine_without_cuda(tmp_path: Path) -> None:
    done = _bench_job(tmp_path, DEVICE="cpu", QUICK="1", BATCHES="2")
    assert done.returncode == 0, done.stdout[-3000:]
    result = json.loads((tmp_path / "out" / "bench_gpu.json").read_text())
    assert result["config"]["quick"] is True and result["config"]["device"] == "cpu" and result["complete"]
    run = result["env"]["trajeglish_guard"]["2"]
    assert run["device"] == "cpu" and run["processes"] == 1 and run["agent_steps_per_s"] > 0
    assert "env trajeglish_guard B=   2" in (tmp_path / "out" / "bench_gpu.txt").read_text()
    assert "trajeglish_guard_split" not in result["env"]  # --no-split: the GPU runs stay in one process
    if torch.cuda.is_available():
        return
    refused = _bench_job(tmp_path / "second")
    assert refused.returncode == 2
    assert "device_bench: ERROR: torch sees no CUDA device on this machine" in refused.stdout
    assert "DEVICE=gpu: expected cuda or cpu" in _bench_job(tmp_path / "third", DEVICE="gpu").stdout
    refused = _bench_job(tmp_path / "fourth", SPLIT="1")
    assert "SPLIT=1: expected a number of worker processes >= 2" in refused.stdout


@pytest.mark.skipif(BASH is None or not can_fork(), reason="needs bash and forked workers")
def test_the_gpu_bench_job_also_times_the_scenes_split_over_workers(tmp_path: Path) -> None:
    done = _bench_job(tmp_path, DEVICE="cpu", QUICK="1", BATCHES="8", SPLIT="2")
    assert done.returncode == 0, done.stdout[-3000:]
    result = json.loads((tmp_path / "out" / "bench_gpu.json").read_text())
    assert result["env"]["trajeglish_guard"]["8"]["processes"] == 1
    split = result["env"]["trajeglish_guard_split"]["8"]
    assert split["processes"] == 2 and split["agent_steps_per_s"] > 0


def test_scenes_an_earlier_job_left_in_work_that_generate_refuses_stop_the_job(tmp_path: Path) -> None:
    """A WORK folder holding another generator version's scenes (the default /tmp/trajeglish_device of an
    earlier job): generate refused it, the refusal could come after the time limit, and the job trained on
    whatever was left, reporting success. It stops now, and the log says WORK held an earlier job's scenes."""
    stale = tmp_path / "work-stale" / "data" / "val-highway-s7-n2"
    stale.mkdir(parents=True)
    (stale / "other.scn.npz").write_bytes(b"from an earlier job")
    done = _job(tmp_path, "stale", VAL_SCENES="2", VAL_SEED="7", DATA_IN="")
    assert done.returncode != 0 and "refused its folder" in done.stdout
    assert "holds scenes of an earlier job" in done.stdout
