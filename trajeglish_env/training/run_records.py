"""What a training run's checkpoints record: its data and setup (:class:`RunFacts`), the training info
stored with every checkpoint, and the atomic save of ``last.pt`` (weights, optimizer, schedule, history)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from trajeglish_env.checkpoint import Checkpoint, save_checkpoint
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
    trainer = {"train_config": dataclasses.asdict(config), "step": step, "history": history}
    info = training_info(config, step, history, facts)
    save_checkpoint(path, model, vocabulary, training=info, optimizer=optimizer.state_dict(), trainer=trainer)
