"""Tokenized training windows and a deterministic, resumable, rank-sharded batch order.

Sample ``g`` (a global counter over the whole run) is scene ``perm_e[g % N]`` of epoch ``e = g // N``;
its window, agent order and noisy tokens come from ``rng(seed, e, scene)``. Step ``s`` of training uses
samples ``s*B .. s*B+B-1``, and rank ``r`` of ``W`` takes its contiguous ``B/W`` share. So the data of
a run depends only on (seed, step): resuming at step ``k`` and splitting a batch over processes both give
exactly what one uninterrupted process would have seen.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from trajeglish_env.scenario import Scenario
from trajeglish_env.tokenizer.noise import NoiseConfig
from trajeglish_env.tokenizer.tokenize import tokenize
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary
from trajeglish_env.training.dataset import WindowConfig, collate_windows, make_window
from trajeglish_env.training.device_noise import add_noise_fields
from trajeglish_env.training.offroad_mass import OffroadTerm, add_offroad_masks


@dataclass(frozen=True)
class SampleOrder:
    """Maps a global sample counter to (epoch, scene index): a fresh permutation of the scenes per epoch."""

    num_scenes: int
    seed: int

    def __call__(self, g: int) -> tuple[int, int]:
        epoch, pos = divmod(int(g), self.num_scenes)
        perm = np.random.default_rng([self.seed, 7, epoch]).permutation(self.num_scenes)
        return epoch, int(perm[pos])


class TokenizedWindows(Dataset):
    """Training windows with argmin target tokens and (optionally noisy) input tokens, indexed by ``g``.

    Adds ``tokens [A,S-1]`` (targets, -1 unobserved) and ``input_tokens [A,S-1]`` to the window fields.
    """

    def __init__(
        self,
        scenes: Sequence[Scenario],
        window: WindowConfig,
        vocabulary: MotionVocabulary,
        noise: NoiseConfig | None,
        seed: int,
        order: Callable[[int], tuple[int, int]] | None = None,
        history_dropout: float = 0.0,
        noise_on_device: bool = False,
        offroad: OffroadTerm | None = None,
    ):
        if not 0 <= history_dropout < 1:
            raise ValueError(f"TokenizedWindows: history_dropout must be in [0, 1), got {history_dropout}")
        if not len(scenes):
            raise ValueError("TokenizedWindows: no scenes")
        self.scenes = scenes
        self.window = window
        self.vocabulary = vocabulary
        self.noise = noise
        self.seed = seed
        self.order = order or SampleOrder(len(scenes), seed)  # (epoch, scene) of each sample counter
        self.history_dropout = history_dropout
        self.noise_on_device = noise_on_device  # noisy inputs drawn in training (training/device_noise.py)
        self.offroad = offroad  # the off-road term's candidate masks (training/offroad_mass.py)

    def __len__(self) -> int:  # a sampler provides the indices; any g >= 0 is valid
        return len(self.scenes)

    def __getitem__(self, g: int) -> dict[str, np.ndarray]:
        return self.__getitems__([g])[0]

    def __getitems__(self, gs: Sequence[int]) -> list[dict[str, np.ndarray]]:
        """Samples ``gs`` (what a DataLoader's batch fetch calls): the windows are tokenized in one pass,
        each exactly as alone (tokenizing is a loop over time steps, so one pass for a whole batch costs
        the per-step overhead once instead of once per window)."""
        drawn = [self.order(g) for g in gs]
        rngs = [np.random.default_rng([self.seed, epoch, scene]) for epoch, scene in drawn]
        windows = [
            make_window(self.scenes[scene], self.window, rng, scene_index=scene)
            for (_, scene), rng in zip(drawn, rngs, strict=True)
        ]
        with_tokens(windows, self.vocabulary, self.noise, rngs, self.noise_on_device)
        if self.history_dropout:  # its own stream: the windows and noisy tokens stay those of p = 0
            for w, (epoch, scene) in zip(windows, drawn, strict=True):
                drop_histories(w, self.history_dropout, np.random.default_rng([self.seed, epoch, scene, 1]))
        if self.offroad is not None:  # its own stream too
            scenes = [self.scenes[scene] for _, scene in drawn]
            streams = [np.random.default_rng([self.seed, epoch, scene, 2]) for epoch, scene in drawn]
            add_offroad_masks(windows, scenes, self.vocabulary.templates, self.offroad, streams)
        return windows

    def collated(self, start: int, stop: int) -> dict[str, torch.Tensor]:
        """Samples ``start .. stop - 1`` as one batch of tensors (:func:`collate_windows`)."""
        return collate_windows(self.__getitems__(range(start, stop)))


def with_tokens(
    windows: Sequence[dict[str, np.ndarray]],
    vocabulary: MotionVocabulary,
    noise: NoiseConfig | None = None,
    rngs: Sequence[np.random.Generator] | None = None,
    noise_on_device: bool = False,
) -> Sequence[dict[str, np.ndarray]]:
    """``windows`` (of one shape) with ``tokens`` (argmin targets of their real agents' valid steps) and
    ``input_tokens`` (noisy with ``noise``, each window's drawn from its own of ``rngs``) added in place;
    one tokenizing pass for all of them. ``noise_on_device``: ``input_tokens`` are the argmin ones and the
    windows carry what the training device draws the noisy ones from (:mod:`.device_noise`)."""
    if not windows:
        return windows
    later = noise is not None and noise_on_device
    if later:
        noise = None
    stacked = {k: np.stack([w[k] for w in windows]) for k in ("agent_xyh", "agent_valid", "agent_mask")}
    tok = tokenize(
        vocabulary,
        stacked["agent_xyh"].astype(np.float64),
        stacked["agent_valid"] & stacked["agent_mask"][..., None],
        np.stack([w["agent_size"] for w in windows]).astype(np.float64),
        np.stack([w["agent_kind"] for w in windows]),
        noise=noise,
        rng=rngs if noise is not None else None,
    )
    for i, w in enumerate(windows):
        w["tokens"] = tok.tokens[i]
        w["input_tokens"] = tok.input_tokens[i]
    if later:
        add_noise_fields(windows, tok.xyh, rngs or ())
    return windows


def drop_histories(window: dict[str, np.ndarray], p: float, rng: np.random.Generator) -> np.ndarray:
    """Hide the whole motion of each real agent of ``window`` with probability ``p``: its input tokens
    become unobserved (-1) and its targets stay (``TrainConfig.history_dropout``). Such an agent's next
    token can then be told only from what a model with ``neighbour_input`` reads of the current states (its
    own velocity, the agents around it), not from the trend of its own last tokens, which in logged traffic
    predicts a follower's braking once it has begun. Returns the dropped agents ``[A]``."""
    drop = (rng.random(len(window["agent_mask"])) < p) & window["agent_mask"]
    window["input_tokens"][drop] = -1
    return drop


class StepBatchSampler(Sampler[list[int]]):
    """Yields, for steps ``start..stop-1``, this rank's share of each global batch of sample counters."""

    def __init__(self, batch_size: int, start: int, stop: int, rank: int = 0, world: int = 1):
        if batch_size % world:
            raise ValueError(f"batch size {batch_size} must be divisible by the number of processes {world}")
        self.per_rank = batch_size // world
        self.batch_size, self.start, self.stop, self.rank = batch_size, start, stop, rank

    def __iter__(self) -> Iterator[list[int]]:
        for step in range(self.start, self.stop):
            first = step * self.batch_size + self.rank * self.per_rank
            yield list(range(first, first + self.per_rank))

    def __len__(self) -> int:
        return max(0, self.stop - self.start)
