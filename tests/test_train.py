"""Training: a tiny model overfits, resume is exact, two DDP processes equal one, checkpoints are safe."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp
from helpers import grid_vocabulary, straight_road_scene, tiny_config

from trajeglish_env.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from trajeglish_env.model import TrajeglishModel
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.tokenizer.baselines import xyh_grid_templates
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary
from trajeglish_env.training import run_records
from trajeglish_env.training.train import TrainConfig, train


@pytest.fixture(scope="module")
def scenes_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("scenes")
    save_scenarios(d / "a.scn.npz", [straight_road_scene(num_agents=5, seed=s, steps=40) for s in range(4)])
    return d


def _quick(**kw) -> TrainConfig:
    base = dict(
        steps=6,
        batch_size=4,
        warmup_steps=2,
        val_every=100,
        log_every=1,
        checkpoint_every=3,
        num_workers=0,
        val_fraction=0.0,
    )
    return TrainConfig(**{**base, **kw})


def _weights(path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path).model.state_dict()


def test_tiny_model_overfits_a_tiny_dataset(scenes_dir, tmp_path) -> None:
    cfg = _quick(steps=60, lr=3e-3, warmup_steps=5, noisy_inputs=False, log_every=5)
    result = train(scenes_dir, tmp_path, tiny_config(), cfg, vocabulary=grid_vocabulary(), progress=False)
    history = load_checkpoint(tmp_path / "last.pt").trainer["history"]
    first, last = history[0]["loss"], result["train_loss"]
    assert first > 4.0  # ~log(144) at the start
    assert last < 0.5 * first, (first, last)
    assert (
        (tmp_path / "metrics.csv")
        .read_text()
        .startswith("step,loss,val_nll,lr,grad_norm,tokens_per_s,data_wait")
    )
    assert (tmp_path / "training_curve.png").stat().st_size > 1000
    assert 0 < result["data_wait_share"] < 1


def test_the_share_of_time_spent_waiting_for_batches_is_measured(scenes_dir, tmp_path, monkeypatch) -> None:
    """A loader slower than the model shows as ``data_wait`` near 1 (per logged row and for the run)."""
    import time

    from trajeglish_env.training.training_data import TokenizedWindows

    fetch = TokenizedWindows.__getitems__

    def slow(self, gs):  # type: ignore[no-untyped-def]
        time.sleep(0.3)
        return fetch(self, gs)

    monkeypatch.setattr(TokenizedWindows, "__getitems__", slow)
    cfg = _quick(checkpoint_every=100)  # no checkpoint inside the logged intervals but the last
    result = train(scenes_dir, tmp_path, tiny_config(), cfg, vocabulary=grid_vocabulary(), progress=False)
    assert result["data_wait_share"] > 0.5, result
    rows = load_checkpoint(tmp_path / "last.pt").trainer["history"]
    assert len(rows) == 6 and min(r["data_wait"] for r in rows) > 0.5, rows


def test_resume_continues_exactly(scenes_dir, tmp_path, monkeypatch) -> None:
    straight = train(
        scenes_dir, tmp_path / "a", tiny_config(), _quick(), vocabulary=grid_vocabulary(), progress=False
    )
    assert straight["steps"] == 6 and straight["resumed_from"] == 0

    import trajeglish_env.training.train as train_module

    real_write = train_module.write_metrics

    def crash_at_step_4(path, history):
        if history[-1]["step"] == 4:
            raise KeyboardInterrupt  # the job is killed after the step-3 checkpoint
        real_write(path, history)

    monkeypatch.setattr(train_module, "write_metrics", crash_at_step_4)
    with pytest.raises(KeyboardInterrupt):
        train(
            scenes_dir, tmp_path / "b", tiny_config(), _quick(), vocabulary=grid_vocabulary(), progress=False
        )
    assert load_checkpoint(tmp_path / "b" / "last.pt").trainer["step"] == 3
    monkeypatch.setattr(train_module, "write_metrics", real_write)
    resumed = train(
        scenes_dir,
        tmp_path / "b",
        tiny_config(),
        _quick(),
        vocabulary=grid_vocabulary(),
        resume=True,
        progress=False,
    )
    assert resumed["resumed_from"] == 3 and resumed["steps"] == 6
    a, b = _weights(tmp_path / "a" / "model.pt"), _weights(tmp_path / "b" / "model.pt")
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=f"parameter {k} differs after resume")
    with pytest.raises(CheckpointError, match=r"other settings than requested now \(lr: 0\.\d+ -> 0\.001\)"):
        train(
            scenes_dir,
            tmp_path / "b",
            tiny_config(),
            _quick(lr=1e-3),
            vocabulary=grid_vocabulary(),
            resume=True,
            progress=False,
        )

    other = MotionVocabulary(grid_vocabulary().templates * 1.1, method="xyh-grid")  # same size, other tokens
    with pytest.raises(CheckpointError, match=r"b/last.pt: the run was trained with another vocabulary"):
        train(
            scenes_dir, tmp_path / "b", tiny_config(), _quick(), vocabulary=other, resume=True, progress=False
        )

    # a new run into a folder that holds one is refused (its checkpoint untouched) unless asked to overwrite
    def new_run(out: str, **kw) -> dict:
        return train(
            scenes_dir, tmp_path / out, tiny_config(), vocabulary=grid_vocabulary(), progress=False, **kw
        )

    kept = (tmp_path / "b" / "last.pt").read_bytes()
    with pytest.raises(FileExistsError, match=r"holds a run .*--resume to continue it, --overwrite"):
        new_run("b", config=_quick())
    assert (tmp_path / "b" / "last.pt").read_bytes() == kept
    again = new_run("b", config=_quick(steps=2), overwrite=True)
    assert again["resumed_from"] == 0 and again["steps"] == 2
    (tmp_path / "c").mkdir()  # a folder with a finished model alone (a copied model.pt) is a run too
    (tmp_path / "c" / "model.pt").write_bytes((tmp_path / "b" / "model.pt").read_bytes())
    with pytest.raises(FileExistsError, match=r"holds a run \(model\.pt\)"):
        new_run("c", config=_quick())
    # ... and resuming it would train a new model over the kept one: refused, the model untouched
    model_bytes = (tmp_path / "c" / "model.pt").read_bytes()
    with pytest.raises(
        FileExistsError, match=r"holds a model \(model.pt\) but no last.pt .*--init .*c/model.pt"
    ):
        new_run("c", config=_quick(), resume=True)
    assert (tmp_path / "c" / "model.pt").read_bytes() == model_bytes
    with pytest.raises(ValueError, match="one of --resume .* and --overwrite"):
        new_run("c", config=_quick(), resume=True, overwrite=True)
    # --overwrite removes the old run's files once the new inputs have loaded (a typo in the new command
    # keeps them), so a run stopped early never leaves the old model beside its own last.pt
    (tmp_path / "c" / "training_curve.png").write_bytes(b"old")
    with pytest.raises(FileNotFoundError):
        train(tmp_path / "nowhere", tmp_path / "c", tiny_config(), _quick(), overwrite=True, progress=False)
    assert (tmp_path / "c" / "model.pt").read_bytes() == model_bytes
    run_records.clear_old_run(tmp_path / "c")
    assert not any((tmp_path / "c" / f).exists() for f in run_records.RUN_FILES)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank: int, world: int, port: int, scenes: str, out: str) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        WORLD_SIZE=str(world),
        RANK=str(rank),
        LOCAL_RANK=str(rank),
    )
    torch.set_num_threads(1)
    train(scenes, out, tiny_config(), _ddp_quick(), vocabulary=grid_vocabulary(), progress=False)
    torch.distributed.barrier()  # both ranks done before either tears its connections down
    torch.distributed.destroy_process_group()


def _ddp_quick() -> TrainConfig:
    """float32: bfloat16 autocast rounds each process's weight gradients before they are summed (the
    property checked here is the loss normalisation, exact only up to float32 rounding)."""
    return _quick(steps=3, precision="float32")


def test_two_processes_equal_one_process_on_the_combined_batch(scenes_dir, tmp_path) -> None:
    train(
        scenes_dir,
        tmp_path / "one",
        tiny_config(),
        _ddp_quick(),
        vocabulary=grid_vocabulary(),
        progress=False,
    )
    mp.start_processes(
        _ddp_worker,
        args=(2, _free_port(), str(scenes_dir), str(tmp_path / "two")),
        nprocs=2,
        start_method="spawn",
    )
    a, b = _weights(tmp_path / "one" / "model.pt"), _weights(tmp_path / "two" / "model.pt")
    for k in a:
        # Key biases get a gradient of exactly zero in theory (softmax ignores them), i.e. float noise that
        # Adam normalises to lr-sized steps; every other parameter must match to float precision.
        atol = 2e-5 if k.endswith("kv.bias") else 1e-6
        torch.testing.assert_close(
            a[k], b[k], rtol=0, atol=atol, msg=lambda m, k=k: f"{k} differs under DDP: {m}"
        )
    assert load_checkpoint(tmp_path / "two" / "model.pt").training["processes"] == 2


def test_checkpoint_round_trip_and_clear_errors(tmp_path) -> None:
    torch.manual_seed(0)
    model = TrajeglishModel(tiny_config())
    path = save_checkpoint(tmp_path / "m.pt", model, grid_vocabulary(), training={"note": "test"})
    ckpt = load_checkpoint(path)
    assert (
        ckpt.config == tiny_config()
        and ckpt.vocabulary.equals(grid_vocabulary())
        and ckpt.training == {"note": "test"}
    )
    for k, v in model.state_dict().items():
        assert torch.equal(v, ckpt.model.state_dict()[k])
    truncated = tmp_path / "cut.pt"
    truncated.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(CheckpointError, match="cut.pt: not a readable checkpoint"):
        load_checkpoint(truncated)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(CheckpointError, match="not a trajeglish_env checkpoint"):
        load_checkpoint(foreign)
    payload = torch.load(path, weights_only=True)
    payload["version"] = 7
    torch.save(payload, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match="version 7 is not supported"):
        load_checkpoint(tmp_path / "future.pt")
    small = MotionVocabulary(np.stack([xyh_grid_templates(256)] * 3), method="xyh-grid")
    with pytest.raises(
        CheckpointError, match="vocabulary has 3 classes x 294 templates but the model expects 3 x 144"
    ):
        save_checkpoint(tmp_path / "bad.pt", model, small)
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")
    with pytest.raises(FileNotFoundError, match="no such checkpoint"):  # either except catches a missing file
        load_checkpoint(tmp_path / "missing.pt")
    with pytest.raises(FileNotFoundError, match="a directory, not a checkpoint file"):
        load_checkpoint(tmp_path)
    from trajeglish_env.scenario_io import load_scenarios

    with pytest.raises(FileNotFoundError, match=r"a directory, not a scenario file \(\*\.scn\.npz\)"):
        load_scenarios(tmp_path)


def test_curves_command_overlays_runs_and_rejects_bad_files(tmp_path, capsys) -> None:
    import json

    from trajeglish_env.cli import main

    for name, vals in (("a", (3.5, 3.0, 2.6)), ("b", (3.4, 3.2, 3.1))):
        run = tmp_path / name
        run.mkdir()
        rows = ["step,loss,val_nll,lr,grad_norm,tokens_per_s"]
        rows += [f"{100 * (i + 1)},{v + 0.1},{v},0.0005,1.0,3000" for i, v in enumerate(vals)]
        rows.insert(2, "150,3.3,,0.0005,1.0,3000")  # a logging row without validation
        (run / "metrics.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "curves.png"
    assert (
        main(["curves", f"trajeglish={tmp_path / 'a'}", str(tmp_path / "b"), "--out", str(out), "--json"])
        == 0
    )
    result = json.loads(capsys.readouterr().out)
    assert result["last_val_nll"] == {"trajeglish": 2.6, "b": 3.1}
    assert out.stat().st_size > 5000
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "metrics.csv").write_text("epoch,acc\n1,0.5\n")
    assert main(["curves", str(tmp_path / "c"), "--out", str(out)]) == 2
    assert "not a training metrics file" in capsys.readouterr().err
    assert main(["curves", str(tmp_path / "missing"), "--out", str(out)]) == 2
    assert "no metrics.csv" in capsys.readouterr().err


def test_non_finite_gradients_skip_the_update_and_never_reach_a_checkpoint(
    scenes_dir, tmp_path, monkeypatch, capsys
) -> None:
    from trajeglish_env.training.loss import TrainingLoss

    original = TrainingLoss.forward

    def poison(steps) -> None:
        """The loss of the given 1-based steps (a predicate) becomes NaN."""
        calls = {"n": 0}

        def forward(self, batch):
            calls["n"] += 1
            loss_sum, n = original(self, batch)
            return (loss_sum * float("nan"), n) if steps(calls["n"]) else (loss_sum, n)

        monkeypatch.setattr(TrainingLoss, "forward", forward)

    poison(lambda step: step == 2)
    result = train(
        scenes_dir, tmp_path / "a", tiny_config(), _quick(), vocabulary=grid_vocabulary(), progress=False
    )
    assert result["steps"] == 6 and np.isfinite(result["train_loss"])
    assert "non-finite gradients at step 2; update skipped" in capsys.readouterr().err
    assert all(torch.isfinite(w).all() for w in _weights(tmp_path / "a" / "model.pt").values())

    # gradients that stay non-finite stop the run; the checkpoint keeps the last finite weights
    poison(lambda step: step >= 4)
    with pytest.raises(
        run_records.TrainingDiverged,
        match=r"in a row up to step 14 had non-finite gradients.*b/last.pt keeps the weights of step 12\); "
        r"train again with a lower --lr: from it with --init .*b/last.pt and another --out, or from the ",
    ):
        train(
            scenes_dir,
            tmp_path / "b",
            tiny_config(),
            _quick(steps=20),
            vocabulary=grid_vocabulary(),
            progress=False,
        )
    assert load_checkpoint(tmp_path / "b" / "last.pt").trainer["step"] == 12

    model = TrajeglishModel(tiny_config())
    with torch.no_grad():
        next(model.parameters())[0] = float("nan")
    optimizer = torch.optim.AdamW(model.parameters())
    with pytest.raises(RuntimeError, match="not finite at step 7"):
        facts = run_records.RunFacts(train_scenes=0, val_scenes=0, sources=(), processes=1, init=None)
        run_records.save_last(tmp_path / "c.pt", model, grid_vocabulary(), optimizer, _quick(), 7, [], facts)
    assert not (tmp_path / "c.pt").exists()


def test_trainer_state_is_typed_and_a_model_file_has_none(tmp_path) -> None:
    """``last.pt``'s training state reads back as a TrainerState; a model.pt (no state) is refused by name."""
    from helpers import tiny

    from trajeglish_env.checkpoint import CheckpointError, TrainerState, load_checkpoint, save_checkpoint

    ckpt = tiny()
    state = TrainerState(7, ({"step": 7, "loss": 1.5},), {"steps": 10})
    save_checkpoint(tmp_path / "last.pt", ckpt.model, ckpt.vocabulary, trainer=state.to_dict())
    assert TrainerState.of(load_checkpoint(tmp_path / "last.pt")) == state
    save_checkpoint(tmp_path / "model.pt", ckpt.model, ckpt.vocabulary)
    with pytest.raises(CheckpointError, match=r"model.pt: holds no training state to resume from"):
        TrainerState.of(load_checkpoint(tmp_path / "model.pt"))


def test_a_checkpoint_with_a_flipped_byte_or_nan_weights_is_refused(tmp_path) -> None:
    """Both loaded silently before: wrong weights (a flipped byte fails its zip member's CRC) or a diverged
    run's NaNs, whose rollouts looked finite."""
    from helpers import tiny

    ckpt = tiny()
    save_checkpoint(tmp_path / "ok.pt", ckpt.model, ckpt.vocabulary)
    data = bytearray((tmp_path / "ok.pt").read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(255 - b for b in data[middle : middle + 64])
    (tmp_path / "flip.pt").write_bytes(bytes(data))
    with pytest.raises(
        CheckpointError, match=r"flip.pt: (corrupt checkpoint: its member .* fails its CRC|not a)"
    ):
        load_checkpoint(tmp_path / "flip.pt")
    model = TrajeglishModel(tiny_config())
    with torch.no_grad():
        next(model.parameters()).fill_(float("nan"))
    save_checkpoint(tmp_path / "nan.pt", model, grid_vocabulary())
    with pytest.raises(CheckpointError, match=r"nan.pt: weights \[.*\] hold NaN or infinite values"):
        load_checkpoint(tmp_path / "nan.pt")


def test_a_warmup_longer_than_half_the_schedule_is_cut_to_half() -> None:
    """--steps 10 --warmup 50 (or a schedule fitted to 36 steps with the default warmup of 100) never peaked
    and never decayed: the learning rate ended at a fifth of the peak."""
    short = TrainConfig(steps=40, lr=1e-3, warmup_steps=100)
    lrs = [short.lr_at(k) for k in range(40)]
    assert max(lrs) == pytest.approx(1e-3) and lrs.index(max(lrs)) == 19
    assert lrs[-1] == pytest.approx(1e-3 / 20)
    # no cliff at warmup = steps: 39 and 40 of 40 warm up alike
    assert TrainConfig(steps=40, warmup_steps=39).lr_at(30) == TrainConfig(steps=40, warmup_steps=40).lr_at(
        30
    )
    normal = TrainConfig(steps=1000, lr=1e-3, warmup_steps=100)  # unchanged where the warmup fits
    assert normal.lr_at(49) == pytest.approx(5e-4) and normal.lr_at(550) == pytest.approx(5e-4)


def test_validation_scenes_that_are_training_scenes_are_warned(
    scenes_dir, tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    from trajeglish_env.training.scene_split import training_scenes, warn_overlap
    from trajeglish_env.training.shard_cache import split_shards

    for cache in (0, 2):
        train_s, val_s = training_scenes(scenes_dir, scenes_dir, 0.05, cache, 8)
        warn_overlap(train_s, val_s)
        assert (
            "4 of the 4 validation scenes (straight-0, straight-1, straight-2) are training scenes too"
            in (capsys.readouterr().err)
        )
    warn_overlap([], [])
    assert capsys.readouterr().err == ""
    # two shards at a held-out share of 1/20: none is held out (the first was: half of the data); from four
    # shards on the first one (19 kept one before and keep it)
    files = [tmp_path / f"{k}.scn.npz" for k in range(20)]
    assert split_shards(files[:2], 0.05) == (files[:2], []) and split_shards(files[:3], 0.05)[1] == []
    assert split_shards(files[:4], 0.05)[1] == [files[0]] and split_shards(files[:19], 0.05)[1] == [files[0]]
    assert split_shards(files, 0.05)[1] == [files[0]]


def test_an_interrupted_run_names_the_step_its_resume_goes_on_from(scenes_dir, tmp_path) -> None:
    import argparse

    from trajeglish_env.cli_args import interrupted_note

    args = argparse.Namespace(command_name="train", out=str(tmp_path / "r"))
    assert "no checkpoint was written yet" in interrupted_note(args)
    train(
        scenes_dir,
        tmp_path / "r",
        tiny_config(),
        _quick(steps=3),
        vocabulary=grid_vocabulary(),
        progress=False,
    )
    assert "train --resume goes on from step 3" in interrupted_note(args)


def test_a_resume_needs_no_flag_but_data_and_out(scenes_dir, tmp_path) -> None:
    """`train --data D --out RUN --resume` was refused for every schedule flag left at its default
    ("batch_size: 4 -> 16, steps: 30 -> 2000, ..."): flags not given now take the run's own settings, and one
    given that differs is still refused."""
    from trajeglish_env.cli_train import default_train_args, train_config_of

    run = tmp_path / "r"
    first = _quick(steps=6)
    cut = train(
        scenes_dir, run, tiny_config(), first, vocabulary=grid_vocabulary(), progress=False, time_limit=0.0
    )
    assert cut["steps"] < 6
    defaults = train_config_of(default_train_args())
    assert defaults.batch_size != first.batch_size and defaults.steps != first.steps
    done = train(
        scenes_dir,
        run,
        tiny_config(),
        defaults,
        vocabulary=grid_vocabulary(),
        progress=False,
        resume=True,
        resume_defaults=defaults,
    )
    assert done["steps"] == 6 and done["resumed_from"] == cut["steps"]
    with pytest.raises(CheckpointError, match=r"batch_size: 4 -> 8\); .*--init .*last.pt and another --out"):
        train(
            scenes_dir,
            run,
            tiny_config(),
            dataclasses.replace(defaults, batch_size=8),
            vocabulary=grid_vocabulary(),
            progress=False,
            resume=True,
            resume_defaults=defaults,
        )


def test_resuming_a_complete_run_keeps_its_model(scenes_dir, tmp_path, capsys) -> None:
    """A resume of a finished run rewrote model.pt with a training time of 0 s, saying nothing."""
    run = tmp_path / "done"
    train(scenes_dir, run, tiny_config(), _quick(steps=3), vocabulary=grid_vocabulary(), progress=False)
    kept = (run / "model.pt").read_bytes()
    again = train(
        scenes_dir,
        run,
        tiny_config(),
        _quick(steps=3),
        vocabulary=grid_vocabulary(),
        progress=False,
        resume=True,
    )
    assert again["steps"] == 3 and (run / "model.pt").read_bytes() == kept
    assert "is complete (step 3 of 3): nothing to train" in capsys.readouterr().err


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="POSIX signals and process groups")
@pytest.mark.parametrize("to", ["group", "process"])
def test_sigterm_with_loader_workers_ends_in_one_line_and_the_run_resumes(scenes_dir, tmp_path, to) -> None:
    """`timeout` or a job scheduler's SIGTERM to the process group also reached the loader's workers, which
    torch ends on a SIGTERM their parent did not send: "DataLoader worker ... killed by signal" followed
    the interrupt (a traceback and exit code 1, or "Exception ignored"). Now they leave it to the trainer."""
    run = tmp_path / "r"
    cli = [sys.executable, "-m", "trajeglish_env.cli", "train", "--data", str(scenes_dir), "--out", str(run)]
    job = subprocess.Popen(
        [*cli, "--preset", "tiny", "--steps", "100000", "--batch-size", "2", "--workers", "2"]
        + ["--checkpoint-every", "1", "--quiet"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a job under `timeout` or a scheduler
    )
    deadline = time.monotonic() + 60
    while job.poll() is None and time.monotonic() < deadline and not (run / "last.pt").is_file():
        time.sleep(0.05)  # a step is checkpointed: the workers are busy filling the loader's queue
    if to == "group":  # `timeout`, `kill -TERM -PGID`: the workers get it too (this failed)
        os.killpg(job.pid, signal.SIGTERM)
    else:  # `kill PID`
        job.send_signal(signal.SIGTERM)
    _, err = job.communicate(timeout=60)
    assert job.returncode == 130, err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("trajeglish train: interrupted;") and "train --resume goes on from step" in last
    step = load_checkpoint(run / "last.pt").trainer["step"]
    assert f"goes on from step {step} " in last
    again = subprocess.run(
        [*cli, "--resume", "--minutes", "0.01", "--workers", "0", "--json", "--quiet"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert again.returncode == 0, again.stderr
    result = json.loads(again.stdout)
    assert result["resumed_from"] == step and result["steps"] > step


def test_a_refitted_schedule_goes_on_from_the_learning_rate_reached() -> None:
    base = TrainConfig(steps=100, lr=1e-3, warmup_steps=10)
    assert base.refitted(5, 300) == dataclasses.replace(base, steps=300)  # in the warmup: its slope kept
    late = base.refitted(50, 80)
    assert late.lr_at(50) == pytest.approx(base.lr_at(50)) and late.lr_at(80) == 0.0
    assert late.lr_at(79) == pytest.approx(base.lr_at(50) / 30)  # linear to 0 at the new end
    again = late.refitted(60, 70)  # refitted again: from the rate the last fit gives at step 60
    assert again.lr_at(60) == pytest.approx(late.lr_at(60)) and again.lr_at(70) == 0.0


def test_a_schedule_fitted_to_the_budget_ends_at_0_when_the_steps_slow_down(
    scenes_dir, tmp_path, monkeypatch
) -> None:
    """`--minutes M --fit-steps` fitted the schedule once, to the step rate of the budget's first tenth: a
    run that slowed down later ran out of time with the learning rate at 10-30 % of its peak. It is refitted
    after every step now, the decay going on from the learning rate reached. A fake clock (steps that
    take ever longer) makes this independent of the machine's speed."""
    import types

    import trajeglish_env.training.train as train_module
    from trajeglish_env.training.loss import TrainingLoss

    clock = types.SimpleNamespace(t=0.0, steps=0)
    clock.perf_counter = lambda: clock.t
    forward = TrainingLoss.forward

    def slowing(self, batch):  # type: ignore[no-untyped-def]
        clock.t += 0.01 * (1 + clock.steps / 50)  # step k takes 10 ms * (1 + k / 50) of the fake clock
        clock.steps += 1
        return forward(self, batch)

    monkeypatch.setattr(train_module, "time", clock)  # the training loop's clock only
    monkeypatch.setattr(TrainingLoss, "forward", slowing)
    cfg = _quick(steps=100_000, warmup_steps=10, checkpoint_every=10)
    kw = dict(vocabulary=grid_vocabulary(), progress=False, fit_steps=True)
    result = train(scenes_dir, tmp_path / "a", tiny_config(), cfg, time_limit=2.0, **kw)  # about 100 steps
    n = result["steps_fitted_to_time"]
    lrs = [row["lr"] for row in load_checkpoint(tmp_path / "a" / "last.pt").trainer["history"]]
    assert len(lrs) == result["steps"] == n and 80 < n < 120 and not result["stopped_by_time_limit"], result
    assert lrs.index(max(lrs)) == 9 and max(lrs) == pytest.approx(cfg.lr)
    assert (np.diff(lrs[9:]) <= 0).all()  # no jump up at a refit
    # the schedule ended with the budget: 0 a step after the last (was 0.35 * lr: fitted once to 149 steps,
    # out of time at 101)
    assert lrs[-1] == pytest.approx(lrs[-2] - lrs[-1]) and lrs[-1] < 0.03 * cfg.lr, lrs[-5:]
    # the same run interrupted after step 70's checkpoint: the resume goes on with the schedule saved there
    real_write = train_module.write_metrics

    def interrupt_at_75(path, history):  # type: ignore[no-untyped-def]
        if history[-1]["step"] == 75:
            raise KeyboardInterrupt
        real_write(path, history)

    clock.t, clock.steps = 0.0, 0
    monkeypatch.setattr(train_module, "write_metrics", interrupt_at_75)
    with pytest.raises(KeyboardInterrupt):
        train(scenes_dir, tmp_path / "b", tiny_config(), cfg, time_limit=2.0, **kw)
    monkeypatch.setattr(train_module, "write_metrics", real_write)
    saved = load_checkpoint(tmp_path / "b" / "last.pt").trainer["train_config"]
    assert saved["decay_from"][0] == 70  # refitted at step 70, and saved with it
    again = train(scenes_dir, tmp_path / "b", tiny_config(), cfg, resume=True, time_limit=100.0, **kw)
    assert again["resumed_from"] == 70 and again["steps"] == again["steps_fitted_to_time"] == saved["steps"]
    resumed = [row["lr"] for row in load_checkpoint(tmp_path / "b" / "last.pt").trainer["history"]]
    assert resumed[:71] == lrs[:71]  # the same learning rate as the uninterrupted run's at step 71
    assert resumed[-1] == pytest.approx(resumed[-2] - resumed[-1]) and resumed[-1] < 0.03 * cfg.lr


def test_a_batch_transfer_cut_by_an_interrupt_prints_no_traceback(monkeypatch: pytest.MonkeyPatch) -> None:
    """multiprocessing's resource_sharer thread reported a batch's fd transfer that the SIGTERM'd trainer cut
    off through sys.excepthook: a ConnectionResetError traceback above the one "interrupted" line (the
    process-group SIGTERM test failed so in a full run, stop 90)."""
    import sys

    from trajeglish_env.training import loader_signals

    seen: list[type[BaseException]] = []
    monkeypatch.setattr(sys, "excepthook", lambda kind, value, tb: seen.append(kind))
    loader_signals.quiet_transfer_errors()
    loader_signals.quiet_transfer_errors()  # idempotent: one filter

    def raised(code: str, filename: str) -> tuple:
        try:
            exec(compile(code, filename, "exec"), {})
        except BaseException as error:  # noqa: BLE001
            return type(error), error, error.__traceback__
        raise AssertionError("no error")

    sharer = "/usr/lib/python3.11/multiprocessing/resource_sharer.py"
    sys.excepthook(*raised("raise ConnectionResetError(104, 'Connection reset by peer')", sharer))
    sys.excepthook(*raised("raise EOFError()", sharer))
    assert seen == []  # dropped
    sys.excepthook(*raised("raise ConnectionResetError(104, 'elsewhere')", "/tmp/user_code.py"))
    sys.excepthook(*raised("raise ValueError('a real error')", sharer))
    assert seen == [ConnectionResetError, ValueError]  # every other error reported as before
