"""What a training run's checkpoints record: its data and setup (:class:`RunFacts`), the training info
stored with every checkpoint, and the atomic save of ``last.pt`` (weights, optimizer, schedule, history);
the checks that keep a run folder from being overwritten or resumed with other settings by mistake."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from trajeglish_env.checkpoint import Checkpoint, CheckpointError, TrainerState, save_checkpoint
from trajeglish_env.model.config import ModelConfig
from trajeglish_env.model.network import TrajeglishModel
from trajeglish_env.scenario import Scenario
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary
from trajeglish_env.training.shard_cache import ShardedScenes

if TYPE_CHECKING:
    from trajeglish_env.training.train import TrainConfig


@dataclass(frozen=True)
class RunFacts:
    """What a run's checkpoints record about its data and setup (computed once)."""

    train_scenes: int
    val_scenes: int
    sources: tuple[str, ...]
    processes: int
    init: str | None


def run_facts(
    train: Sequence[Scenario], val: Sequence[Scenario], world: int, init: Checkpoint | None
) -> RunFacts:
    sources = tuple(
        train.all_sources() if isinstance(train, ShardedScenes) else sorted({s.source for s in train})
    )
    path = None if init is None else str(init.path or "checkpoint")
    return RunFacts(len(train), len(val), sources, world, path)


def training_info(config: TrainConfig, step: int, history: list[dict], facts: RunFacts) -> dict[str, Any]:
    info = {
        "train_config": dataclasses.asdict(config),
        "step": step,
        "train_scenes": facts.train_scenes,
        "val_scenes": facts.val_scenes,
        "sources": list(facts.sources),
        "processes": facts.processes,
        "val_nll": next((h["val_nll"] for h in reversed(history) if "val_nll" in h), None),
        "torch": str(torch.__version__),
        "device": "cuda" if torch.cuda.is_available() else "cpu",
    }
    if facts.init is not None:
        info["init"] = facts.init
    return info


def save_last(
    path: Path,
    model: TrajeglishModel,
    vocabulary: MotionVocabulary,
    optimizer: torch.optim.Optimizer,
    config: TrainConfig,
    step: int,
    history: list[dict],
    facts: RunFacts,
) -> None:
    bad = [name for name, p in model.named_parameters() if not torch.isfinite(p).all()]
    if bad:
        raise RuntimeError(f"train: weights {bad[:3]} are not finite at step {step}; {path} not overwritten")
    trainer = TrainerState(step, tuple(history), dataclasses.asdict(config)).to_dict()
    info = training_info(config, step, history, facts)
    save_checkpoint(path, model, vocabulary, training=info, optimizer=optimizer.state_dict(), trainer=trainer)


RUN_FILES = ("last.pt", "model.pt", "metrics.csv", "training_curve.png")


def check_run_folder(out: Path, resume: bool, overwrite: bool) -> None:
    """A new run into a folder that holds one (``last.pt`` or ``model.pt``) would overwrite it: refused unless
    ``resume`` (go on with it) or ``overwrite`` (start again: :func:`clear_old_run` removes the old run's
    files once the new run's inputs have loaded). A ``resume`` of a folder with a ``model.pt`` and no
    ``last.pt`` (a finished model kept alone) is refused too: it would train a new model over it."""
    if resume and overwrite:
        raise ValueError(
            "pass one of --resume (go on with the run) and --overwrite (start it again), not both"
        )
    held = [f for f in ("last.pt", "model.pt") if (out / f).is_file()]
    if overwrite:
        return  # the old files go once the new run's inputs have loaded (clear_old_run)
    if resume and held == ["model.pt"]:
        raise FileExistsError(
            f"{out} holds a model (model.pt) but no last.pt to resume from: resuming would train a new model "
            f"over it; fine-tune it with --init {out / 'model.pt'} and another --out, or pass --overwrite"
        )
    if held and not resume:
        raise FileExistsError(
            f"{out} holds a run ({', '.join(held)}): pass --resume to continue it, --overwrite to "
            "start it again, or another --out"
        )


class TrainingDiverged(ValueError):
    """Training stopped on non-finite gradients: the run's settings (its learning rate) are the cause, so
    the CLI reports it in one line, as bad input."""


def diverged_note(last: Path, unstable: int, step: int) -> str:
    """What stopped a diverging run and what to do: a lower ``--lr`` is another schedule, so a new run."""
    kept = resume_point(last.parent)
    where = (
        f"{last} keeps the weights of step {kept}"
        if kept is not None
        else f"no checkpoint was written before it (no {last.name})"
    )
    return (
        f"{unstable} steps in a row up to step {step} had non-finite gradients, so training stopped "
        f"({where}); train again with a lower --lr: from it with --init {last} and another --out, or "
        "from the start with --overwrite"
        if kept is not None
        else f"({where}); train again with a lower --lr and --overwrite (or another --out)"
    )


def clear_old_run(out: Path) -> None:
    """``--overwrite``: remove the old run's files, once the new run's inputs have loaded (a typo in the
    new command must not cost the old model), so the folder never mixes two runs' files."""
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)


def resume_point(out: Path) -> int | None:
    """The step a ``train --resume`` of ``out`` goes on from (its ``last.pt``'s), None without one."""
    from trajeglish_env.checkpoint import load_checkpoint

    last = out / "last.pt"
    if not last.is_file():
        return None
    try:
        return TrainerState.of(load_checkpoint(last)).step
    except (CheckpointError, OSError, ValueError):
        return None


def differences(saved: dict[str, Any], requested: dict[str, Any]) -> str:
    """The fields where two settings differ, ``name: saved -> requested`` (an error message's)."""
    names = sorted(set(saved) | set(requested))
    return ", ".join(
        f"{k}: {saved.get(k, '(unset)')!r} -> {requested.get(k, '(unset)')!r}"
        for k in names
        if saved.get(k) != requested.get(k)
    )


def resumed_config(
    last: Path,
    saved_model: ModelConfig,
    model: ModelConfig,
    trainer: TrainerState,
    config: TrainConfig,
    fit_steps: bool,
    defaults: TrainConfig | None = None,
    note: Callable[[str], None] | None = None,
) -> TrainConfig:
    """The settings a resumed run goes on with: the requested ones, which must be the run's own (a
    CheckpointError naming the fields that differ otherwise), with the schedule's fitted length kept.
    With ``defaults`` (what flags left unset mean), every field the request leaves at its default takes
    the run's own value, so ``train --resume`` needs no flag but ``--data`` and ``--out``."""
    if saved_model != model:
        raise CheckpointError(
            f"{last}: its model config differs from the requested one ("
            f"{differences(dataclasses.asdict(saved_model), dataclasses.asdict(model))})"
        )
    saved = {**dataclasses.asdict(type(config)()), **trainer.train_config}  # older runs lack new fields
    # loader processes do not change the batches (items are pure functions of seed and index), so a run
    # may go on on a machine with another number of cores
    saved["num_workers"] = config.num_workers
    saved["noise_on_device"] = config.noise_on_device  # the same draws either way (up to rounding)
    saved["precision"] = config.precision  # arithmetic, not the schedule: a run may go on on another CPU
    saved["repeat"] = tuple((str(k), int(n)) for k, n in saved["repeat"])  # lists once serialized
    saved["collision_sources"] = tuple(str(k) for k in saved["collision_sources"])
    saved["decay_from"] = tuple(saved["decay_from"])  # where a fitted schedule's decay goes on from
    config = dataclasses.replace(config, decay_from=saved["decay_from"])  # a record, never a request
    if fit_steps:  # the schedule's length was fitted to the first call's budget
        config = dataclasses.replace(config, steps=int(saved["steps"]))
    if defaults is not None:
        unset = dataclasses.asdict(defaults)
        asked = dataclasses.asdict(config)
        taken = {
            k: saved[k] for k, v in asked.items() if k in saved and v == unset.get(k, v) and saved[k] != v
        }
        config = dataclasses.replace(config, **taken)
        if taken and note is not None:  # visible: a flag given at its default value is taken as not given
            note(
                f"train: resuming {last.parent} with its own settings where the flags are at their defaults: "
                + ", ".join(f"{k} {v!r}" for k, v in sorted(taken.items()))
            )
    if saved != dataclasses.asdict(config):
        raise CheckpointError(
            f"{last}: it was trained with other settings than requested now ("
            f"{differences(saved, dataclasses.asdict(config))}); resume with its own, or train it further on "
            f"another schedule as a fine-tune: --init {last} and another --out"
        )
    return config


def check_resumed_inputs(
    last: Path, ckpt: Checkpoint, vocabulary: MotionVocabulary, facts: RunFacts
) -> str | None:
    """A resumed run must read the vocabulary it was trained with (a CheckpointError otherwise: its
    weights would go on learning other token meanings); other training data than recorded is allowed,
    and returned as a warning to print."""
    if not ckpt.vocabulary.equals(vocabulary):
        have, want = ckpt.vocabulary, vocabulary
        raise CheckpointError(
            f"{last}: the run was trained with another vocabulary ({have.size} templates per class, "
            f"{have.method}) than the one given now ({want.size}, {want.method}): resuming would train its "
            "weights on other token meanings; pass the run's own (the same --vocab / --init as its start)"
        )
    recorded = (ckpt.training.get("train_scenes"), list(ckpt.training.get("sources") or []))
    now = (facts.train_scenes, list(facts.sources))
    if recorded[0] is not None and recorded != now:
        return (
            f"train: warning: {last} was trained on {recorded[0]} scenes of {recorded[1]}, this resume reads "
            f"{now[0]} of {now[1]}: the schedule goes on with other data"
        )
    return None
