"""Training loop (paper appendix "Training hyperparameters"), one process or many through ``torchrun``.

Random time window, random agent's frame, random agent order, noisy input tokens (sigma 0.008, nucleus
0.95) with argmin targets, AdamW with warmup and linear decay, gradient clipping. On CUDA: bf16 autocast
(attention runs through SDPA, i.e. flash attention where available); on CPU: bf16 autocast where the CPU
multiplies bfloat16 natively, else float32 (``TrainConfig.precision``, :mod:`.precision`). Progress bar with
loss and tokens/s, CSV metrics, periodic validation NLL, atomic checkpoints, exact ``--resume``.
Under ``torchrun`` each process takes its share of every global batch (DistributedDataParallel); the
loss is normalised by the global token count so that W processes compute exactly the one-process update.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import DataLoader
from tqdm import tqdm

from trajeglish_env.checkpoint import (
    Checkpoint,
    TrainerState,
    check_compatible,
    check_init,
    load_checkpoint,
    load_into,
    save_checkpoint,
)
from trajeglish_env.checkpoint_reading import training_start
from trajeglish_env.distributed import init_ranks, rank_device
from trajeglish_env.model.config import ModelConfig
from trajeglish_env.model.encoder import SIGNAL_PARAMS
from trajeglish_env.model.network import TrajeglishModel
from trajeglish_env.tokenizer.noise import NoiseConfig
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary, load_default_tokenizer
from trajeglish_env.training.budget import ScheduleFit, out_of_time
from trajeglish_env.training.closed_loop import ClosedLoopConfig, closed_loop_batch
from trajeglish_env.training.curves import plot_curve, write_metrics
from trajeglish_env.training.dataset import collate_windows, window_config
from trajeglish_env.training.device_noise import DeviceTemplates, device_input_tokens
from trajeglish_env.training.kind_repeat import window_order
from trajeglish_env.training.loader_signals import loader_batches, quiet_worker
from trajeglish_env.training.loss import TrainingLoss
from trajeglish_env.training.mass_term_checks import check_mass_terms
from trajeglish_env.training.offroad_mass import OffroadTerm
from trajeglish_env.training.precision import check_precision, step_autocast
from trajeglish_env.training.run_records import (
    TrainingDiverged,
    check_resumed_inputs,
    check_run_folder,
    clear_old_run,
    diverged_note,
    resumed_config,
    run_facts,
    save_last,
    training_info,
)
from trajeglish_env.training.scene_split import training_scenes, warn_overlap
from trajeglish_env.training.term_sources import collision_scenes, scene_source_list
from trajeglish_env.training.training_data import StepBatchSampler, TokenizedWindows
from trajeglish_env.training.validation import batch_to, validation_nll

MAX_UNSTABLE_STEPS = 10  # consecutive non-finite-gradient steps skipped before training stops
SHOWN = ("loss", "val_nll", "tokens_per_s", "data_wait")  # the progress bar's figures of a logged row


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (paper: lr 5e-4, 500 warmup steps, linear decay, AdamW, batch 96)."""

    steps: int = 2000
    batch_size: int = 16
    lr: float = 5e-4
    warmup_steps: int = 100
    weight_decay: float = 0.01
    grad_clip: float = 1.0
    noise_sigma: float = 0.008
    noise_top_p: float = 0.95
    noisy_inputs: bool = True
    seed: int = 0
    val_fraction: float = 0.05
    val_windows: int = 64
    val_every: int = 200
    log_every: int = 10
    checkpoint_every: int = 200
    num_workers: int = 1
    shard_cache: int = 0  # 0: every scene in memory; K: at most K shards per loading process (shard_cache.py)
    # learning-rate multiplier of the signal embedding (ModelConfig.signal_input): it starts at zero inside
    # an already trained model (train --init CKPT --signal-input) and must catch up with the rest
    signal_lr_scale: float = 1.0
    repeat: tuple[tuple[str, int], ...] = ()  # scene kinds drawn N times an epoch (training/kind_repeat.py)
    # CAT-K closed-loop fine-tuning (training/closed_loop.py): 0 = teacher forcing; K = every window rolled
    # out with the model's top-K tokens nearest the log, trained to return to it (recovery, max_drift)
    closed_loop_top_k: int = 0
    closed_loop_recovery: float = 0.2
    closed_loop_along_recovery: float = 0.2
    closed_loop_max_drift: float = 2.0
    closed_loop_teacher_forced: bool = True
    # loss weight of the tokens of agents closing in on the agent ahead (training/interaction_weights.py):
    # 1 = plain likelihood; the logged training loss is then the weighted mean, validation NLL stays plain
    interaction_weight: float = 1.0
    # loss weight of the tokens where the lane ahead turns away from an agent's current motion
    # (training/bend_weights.py; needs lane_input): 1 = plain likelihood
    bend_weight: float = 1.0
    # colliding-mass term (training/blocked_mass.py): W * -log(1 - m) per target with colliding candidates (0:
    # off; "+rollout" scenes train by it alone after their current step); candidates kept up H steps;
    # rolled_out_only: the term on those rolled-out targets alone (the logged ones keep plain likelihood)
    collision_weight: float = 0.0
    collision_horizon: int = 1
    collision_rolled_out_only: bool = False
    # the term on the windows of these scene sources alone (a model's own rollouts of a source count as it;
    # empty: every window): highway-env's IDM logs keep gaps the term teaches against (docs/evaluation.md)
    collision_sources: tuple[str, ...] = ()
    collision_form: str = "mass"  # or "versus_target": W * log(1 + m / p), p the target's (blocked_mass.py)
    # off-road-mass term (training/offroad_mass.py): W * -log(1 - m) at `offroad_positions` vehicle targets
    # per window, m the probability on candidates the guard's road-edge rule masks (0: off)
    offroad_weight: float = 0.0
    offroad_positions: int = 32
    offroad_horizon: int = 1  # candidates kept up this many steps (a constant turn) must stay on the road
    offroad_form: str = "mass"  # or "versus_target": W * log(1 + m / p), as collision_form
    # share of each window's agents whose input tokens are all hidden (training_data.drop_histories): their
    # next tokens must be told from the current states a neighbour_input model reads, not their own trend
    history_dropout: float = 0.0
    noise_on_device: bool = False  # noisy inputs drawn on the model's device (training/device_noise.py; GPU)
    # the arithmetic of a step on CPU (training/precision.py): "auto" (bfloat16 autocast where the CPU has
    # native bfloat16, else float32), "float32" or "bfloat16"; CUDA always autocasts to bfloat16
    precision: str = "auto"
    # (step a, fraction f) of a schedule refitted to a time budget (train --fit-steps, training/budget.py):
    # from step a on the learning rate decays linearly from f * lr to 0 at `steps`; () for none
    decay_from: tuple[int, float] = ()

    def __post_init__(self) -> None:
        if not self.signal_lr_scale > 0:
            raise ValueError(f"TrainConfig.signal_lr_scale must be > 0, got {self.signal_lr_scale}")
        if not self.interaction_weight >= 1:
            raise ValueError(f"TrainConfig.interaction_weight must be >= 1, got {self.interaction_weight}")
        if not self.bend_weight >= 1:
            raise ValueError(f"TrainConfig.bend_weight must be >= 1, got {self.bend_weight}")
        check_mass_terms(self)
        if not 0 <= self.history_dropout < 1:
            raise ValueError(f"TrainConfig.history_dropout must be in [0, 1), got {self.history_dropout}")
        check_precision(self.precision)
        self.closed_loop()  # ClosedLoopConfig checks its settings

    def closed_loop(self) -> ClosedLoopConfig | None:
        """The CAT-K settings, or None for teacher forcing."""
        if not self.closed_loop_top_k:
            return None
        return ClosedLoopConfig(
            self.closed_loop_top_k,
            self.closed_loop_recovery,
            self.closed_loop_along_recovery,
            self.closed_loop_max_drift,
            self.closed_loop_teacher_forced,
        )

    def lr_at(self, step: int) -> float:
        """Learning rate at ``step``: linear warmup, then linear decay to 0 at ``steps``; a warmup longer than
        half the schedule (a short run, or one fitted to a small budget) is cut to half of it, so the
        learning rate still peaks and reaches 0. A refitted schedule decays from ``decay_from`` on."""
        if self.decay_from and step >= self.decay_from[0]:
            start, share = self.decay_from
            return self.lr * share * max(0.0, (self.steps - step) / max(1, self.steps - start))
        warm = self.warm()
        if step < warm:
            return self.lr * (step + 1) / warm
        return self.lr * max(0.0, (self.steps - step) / max(1, self.steps - warm))

    def warm(self) -> int:
        """The warmup's length: ``warmup_steps``, at most half the schedule."""
        return min(self.warmup_steps, self.steps // 2)

    def decaying(self, step: int) -> bool:
        """Whether ``step`` is past the warmup (a refitted schedule always is)."""
        return bool(self.decay_from) or step >= self.warm()

    def refitted(self, step: int, steps: int) -> TrainConfig:
        """The schedule ending at ``steps`` instead; once past the warmup, its learning rate goes on from
        ``step``'s without a jump, linearly to 0."""
        new = dataclasses.replace(self, steps=steps)
        if self.decay_from or step >= min(self.warm(), new.warm()):
            new = dataclasses.replace(new, decay_from=(step, self.lr_at(step) / self.lr))
        return new


def _param_groups(model: TrajeglishModel, config: TrainConfig) -> list[dict[str, Any]]:
    """AdamW groups: matrices with weight decay, vectors without, and the signal embedding (when the model
    has it) with its own learning-rate scale (``lr_scale``, read each step) and weight decay."""
    groups: dict[str, dict[str, Any]] = {
        "decay": {"params": [], "weight_decay": config.weight_decay},
        "no_decay": {"params": [], "weight_decay": 0.0},
        "signal": {"params": [], "weight_decay": config.weight_decay, "lr_scale": config.signal_lr_scale},
    }
    for name, p in model.named_parameters():
        key = "signal" if name.startswith(SIGNAL_PARAMS) else "decay" if p.ndim >= 2 else "no_decay"
        groups[key]["params"].append(p)
    return [g for g in groups.values() if g["params"]]


def train(
    data: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    model_config: ModelConfig,
    config: TrainConfig = TrainConfig(),
    vocabulary: MotionVocabulary | None = None,
    val_data: str | os.PathLike[str] | None = None,
    resume: bool = False,
    progress: bool = True,
    init: str | os.PathLike[str] | Checkpoint | None = None,
    time_limit: float | None = None,
    fit_steps: bool = False,
    overwrite: bool = False,
    resume_defaults: TrainConfig | None = None,
) -> dict[str, Any]:
    """Train (or resume) a model on scene shards; writes ``last.pt``, ``model.pt`` and ``metrics.csv``.

    ``init``: a trained checkpoint to start from (fine-tuning, e.g. adapting a model to WOMD); its config
    and vocabulary must be the run's, or the vocabulary one that extends the checkpoint's (new tokens start
    from the nearest old one's embedding; :func:`check_init`). A ``resume`` from ``last.pt`` takes precedence.
    ``time_limit``: seconds after this call starts when no further step is taken (a wall-clock budget,
    e.g. a lent machine's): the step reached is validated and checkpointed like the last one, and a later
    ``resume`` continues the same schedule (``config.steps``, which the limit does not change).
    ``fit_steps`` (with ``time_limit``, a new run): the step rate sets the schedule's length, refitted as it
    changes (:mod:`.budget`), so the learning rate reaches 0 as the budget ends (``config.steps`` is then the
    most); the fitted schedule is saved, and a ``resume`` keeps it. A new run into a folder with a
    ``last.pt`` needs ``overwrite`` (:func:`check_run_folder`). ``resume_defaults``: the settings a flag left
    unset means (the CLI's defaults); on a resume each field ``config`` leaves at them takes the run's own
    value.
    """
    if fit_steps and time_limit is None:
        raise ValueError("train: fit_steps needs a time_limit (train --fit-steps needs --minutes)")
    if config.history_dropout and not model_config.neighbour_input:
        raise ValueError(
            "train: history_dropout needs a model that reads its agents' neighbours (--neighbour-input): "
            "without it a dropped agent's motion is known only at the window's first step"
        )
    if config.bend_weight != 1 and not model_config.lane_input:
        raise ValueError(
            "train: bend_weight finds the bends in the lane points the model reads: it needs a model "
            "with lane_input (train --lane-input)"
        )
    deadline = None if time_limit is None else time.perf_counter() + time_limit
    out = Path(out)
    check_run_folder(out, resume, overwrite)
    device = rank_device()
    dd = init_ranks(device)
    start_ckpt = load_checkpoint(init) if isinstance(init, (str, os.PathLike)) else init
    start_ckpt, vocabulary = training_start(start_ckpt, vocabulary)
    if model_config.drawn < model_config.vocab_size:  # a reading extension's own config: draw all it reads
        model_config = dataclasses.replace(model_config, drawn_size=0, token_bias=True)
    vocabulary = vocabulary or (
        start_ckpt.vocabulary if start_ckpt else load_default_tokenizer(model_config.vocab_size)
    )
    if start_ckpt is not None:
        check_init(start_ckpt, model_config, vocabulary)
    check_compatible(model_config, vocabulary, where="train: --vocab")
    train_scenes, val_scenes = training_scenes(
        data, val_data, config.val_fraction, config.shard_cache, config.val_windows
    )
    if dd.main:
        warn_overlap(train_scenes, val_scenes)
    if overwrite:  # the inputs loaded: now the old run's files go (every rank: missing_ok)
        clear_old_run(out)
    if not val_scenes and dd.main:  # no held-out NLL (curves stay empty): say so, never silently
        print(
            f"train: warning: no validation scenes (the held-out share {config.val_fraction} of "
            f"{len(train_scenes)} training scenes' shards or scenes is none); pass --val-data DIR for a "
            "held-out NLL",
            file=sys.stderr,
        )

    facts = run_facts(train_scenes, val_scenes, dd.world, start_ckpt)
    torch.manual_seed(config.seed)
    model = TrajeglishModel(model_config).to(device)
    optimizer = torch.optim.AdamW(_param_groups(model, config), lr=config.lr, betas=(0.9, 0.95))
    start_step, history = 0, []
    last = out / "last.pt"
    if resume and last.is_file():
        ckpt = load_checkpoint(last, map_location=device)
        trainer = TrainerState.of(ckpt)
        note = (lambda text: print(text, file=sys.stderr)) if dd.main else None
        config = resumed_config(
            last, ckpt.config, model_config, trainer, config, fit_steps, resume_defaults, note
        )
        note = check_resumed_inputs(last, ckpt, vocabulary, facts)
        if note and dd.main:
            print(note, file=sys.stderr)
        model.load_state_dict(ckpt.model.state_dict())
        optimizer.load_state_dict(ckpt.optimizer or {})
        start_step, history = trainer.step, list(trainer.history)
    else:
        if resume and dd.main:
            print(f"train: no {last} to resume from; starting from scratch", file=sys.stderr)
        if start_ckpt is not None:
            load_into(model, start_ckpt, vocabulary)

    drawn = vocabulary.templates[:, : model.cfg.drawn]
    term_scenes = collision_scenes(scene_source_list(train_scenes), config.collision_sources)
    loss_module: nn.Module = TrainingLoss(model, config, drawn, term_scenes)
    if dd.world > 1:
        loss_module = nn.parallel.DistributedDataParallel(
            loss_module, device_ids=[device.index] if device.type == "cuda" else None
        )
    noise = NoiseConfig(config.noise_sigma, config.noise_top_p) if config.noisy_inputs else None
    templates = DeviceTemplates.of(vocabulary, device)
    order = window_order(train_scenes, config.repeat, config.shard_cache, config.seed)
    dataset = TokenizedWindows(
        train_scenes,
        window_config(model_config),
        vocabulary,
        noise,
        config.seed,
        order,
        config.history_dropout,
        config.noise_on_device,
        OffroadTerm(config.offroad_positions, model.cfg.drawn, horizon=config.offroad_horizon)
        if config.offroad_weight
        else None,
    )
    sampler = StepBatchSampler(config.batch_size, start_step, config.steps, dd.rank, dd.world)
    loader = DataLoader(
        dataset,
        batch_sampler=sampler,
        num_workers=config.num_workers,
        collate_fn=collate_windows,
        persistent_workers=False,
        worker_init_fn=quiet_worker,
        pin_memory=device.type == "cuda",
    )
    autocast = step_autocast(config.precision, device, model_config.d_model)
    out.mkdir(parents=True, exist_ok=True)
    metrics_path = out / "metrics.csv"
    bar = tqdm(
        total=config.steps,
        initial=start_step,
        disable=not (progress and dd.main),
        file=sys.stderr,
        desc="train",
        unit="step",
    )
    model.train()
    step, t0, tokens_seen, last_log = start_step, time.perf_counter(), 0, time.perf_counter()
    unstable = 0  # consecutive steps whose gradients were not finite
    window_tokens, window_loss = 0.0, 0.0
    stopped = False  # the time limit ended the run before config.steps
    # a new run's schedule fitted to the budget from the step rate, and refitted as the rate changes
    fit: ScheduleFit | None = None
    if fit_steps and start_step == 0 and deadline is not None and time_limit is not None:
        fit = ScheduleFit(deadline, time_limit, config.steps)
    closed_loop = config.closed_loop()
    # seconds spent waiting for the loaders' next batch (a share near 1: data, not the model, sets the pace)
    data_wait, window_wait, asked = 0.0, 0.0, time.perf_counter()
    with bar, loader_batches(loader) as batches:  # the workers leave interrupts to this process
        for batch in batches:
            waited = time.perf_counter() - asked
            data_wait, window_wait = data_wait + waited, window_wait + waited
            batch = batch_to(batch, device)
            if config.noise_on_device and noise is not None:
                batch["input_tokens"] = device_input_tokens(batch, templates, noise)
            if closed_loop is not None:  # inputs: the model's own rollout; targets: the way back to the log
                batch = closed_loop_batch(model, batch, vocabulary, closed_loop)
            step_lr = config.lr_at(step)
            for group in optimizer.param_groups:
                group["lr"] = step_lr * group.get("lr_scale", 1.0)
            with autocast:
                loss_sum, n = loss_module(batch)
            global_n = n.detach().clone()
            if dd.world > 1:
                dist.all_reduce(global_n)
            # DDP averages gradients over W processes, hence the factor W: the update equals one process's.
            (loss_sum * dd.world / global_n.clamp(min=1)).backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            finite = bool(torch.isfinite(grad_norm))  # the norm of the reduced gradients: same on every rank
            if finite:
                optimizer.step()
                unstable = 0
            else:  # skip the update rather than poison the weights (and the next checkpoint) with NaN
                unstable += 1
                if dd.main:
                    bar.write(
                        f"train: non-finite gradients at step {step + 1}; update skipped", file=sys.stderr
                    )
                if unstable > MAX_UNSTABLE_STEPS:
                    raise TrainingDiverged(diverged_note(last, unstable, step + 1))
            optimizer.zero_grad(set_to_none=True)
            step += 1
            if fit is not None:
                config = fit.after_step(config, step, time.perf_counter(), device, dd.world)
                bar.total = config.steps
            batch_loss = torch.stack([loss_sum.detach().float(), n.float()])
            if dd.world > 1:
                dist.all_reduce(batch_loss)
            if finite:
                window_loss += float(batch_loss[0])
                window_tokens += float(batch_loss[1])
            tokens_seen += int(batch_loss[1])
            stopped = out_of_time(deadline, time.perf_counter(), device, dd.world) and step < config.steps
            final = step == config.steps or stopped
            if dd.main:
                row: dict[str, Any] = {}
                if step % config.log_every == 0 or final:
                    now = time.perf_counter()
                    row = {
                        "step": step,
                        "loss": window_loss / max(window_tokens, 1),
                        "lr": step_lr,
                        "grad_norm": float(grad_norm),
                        "tokens_per_s": window_tokens / max(now - last_log, 1e-9),
                        "data_wait": window_wait / max(now - last_log, 1e-9),
                    }
                    window_loss, window_tokens, window_wait, last_log = 0.0, 0.0, 0.0, now
                if val_scenes and (step % config.val_every == 0 or final):
                    row.setdefault("step", step)
                    row["val_nll"] = validation_nll(
                        model, val_scenes, vocabulary, config.val_windows, config.seed, device
                    )
                if row:
                    history.append(row)
                    write_metrics(metrics_path, history)
                    bar.set_postfix({k: f"{v:.3g}" for k, v in row.items() if k in SHOWN})
                if step % config.checkpoint_every == 0 or final:
                    save_last(
                        last,
                        model,
                        vocabulary,
                        optimizer,
                        config,
                        step,
                        history,
                        facts,
                    )
            bar.update(1)
            if final:
                break
            asked = time.perf_counter()
    elapsed = time.perf_counter() - t0
    result: dict[str, Any] = {"out": str(out), "steps": step, "resumed_from": start_step}
    if time_limit is not None:
        result["stopped_by_time_limit"] = stopped
    if fit_steps:
        result["steps_fitted_to_time"] = config.steps
    if dd.main:
        final = out / "model.pt"
        finished_before = start_step >= config.steps and final.is_file()
        if finished_before:  # a resume of a complete run: its model.pt (and its training time) stay
            print(
                f"train: {out} is complete (step {start_step} of {config.steps}): nothing to train",
                file=sys.stderr,
            )
        else:
            info = training_info(config, step, history, facts)
            info["seconds"] = round(elapsed, 1)
            save_checkpoint(final, model, vocabulary, training=info)
            plot_curve(history, out / "training_curve.png")
        vals = [h["val_nll"] for h in history if "val_nll" in h]
        result.update(
            checkpoint=str(final),
            train_loss=next((h["loss"] for h in reversed(history) if "loss" in h), math.nan),
            val_nll=vals[-1] if vals else None,
            tokens_per_second=round(tokens_seen / max(elapsed, 1e-9), 1),
            data_wait_share=round(data_wait / max(elapsed, 1e-9), 3),
            seconds=round(elapsed, 1),
            device=str(device),
            processes=dd.world,
        )
    if dd.world > 1:
        dist.barrier()
    return result
