"""Typed configuration of the Trajeglish model: the variant and the size presets."""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import Enum


class Variant(str, Enum):
    """Decoder masking variants of the paper's ablation (same code path, different attention masks)."""

    TRAJEGLISH = "trajeglish"  # full intra-timestep attention (causal over the flattened sequence)
    NO_INTRA = "no-intra"  # a token may not attend to tokens of its own timestep
    MARGINAL = "marginal"  # only its own agent's past tokens
    NO_MAP = "no-map"  # marginal, and no map encoder

    @property
    def uses_map(self) -> bool:
        """Whether the variant encodes the map."""
        return self is not Variant.NO_MAP


MAP_SELECT = ("frame", "agents", "ahead")  # see ModelConfig.map_select


@dataclass(frozen=True)
class ModelConfig:
    """Model hyper-parameters. ``steps`` is the number of future tokens per agent in a training window.

    ``signal_input``: map chunks of a signal-controlled lane carry the state of its signal (none, stop,
    caution, go) at the window's first step, a learned embedding added to the chunk's; its weights start
    at zero, so a model extended with it (``train --init CKPT --signal-input``) starts as ``CKPT`` did.

    ``map_select``: which ``max_polylines`` map chunks a window holds: ``"frame"`` those nearest the
    window's frame agent (the default; 64 chunks of 20 points at 0.5 m reach only 26-49 m, so
    agents farther away see no map), ``"agents"`` those nearest to any of the window's agents, ``"ahead"``
    those nearest to any of them or to where each would be 0.8, 1.6 and 2.4 s on at its speed and turn
    rate of the window's first step (:func:`~trajeglish_env.model.map_chunks.ahead_anchors`: the same
    chunks spent on the road the agents drive onto; a median vehicle's next 2.4 s on highway-env lie on
    shown lanes 0.90 of the way against 0.47).

    ``map_stride``: a chunk takes every ``map_stride``-th point of its polyline (and its last): 1 (the
    shipped model's) gives 20 points at the maps' 0.5 m, a chunk 9.5 m long, so 64 chunks show a vehicle
    its lane for a median 0.3-1.7 s ahead on highway-env scenes; 4 makes chunks 38 m long (3-8 s ahead;
    ``docs/evaluation.md``, "What the model sees of the road").

    ``token_bias``: the tied output head adds a learned bias per token. A model whose vocabulary was
    extended (``tokenizer.extend``) gets it: each added token starts as a copy of the nearest old one, and
    the bias (``-log`` of the copies) keeps every old token's probability, now shared by its copies, as it
    was, so the extended model starts as the trained one did.

    ``neighbour_input``: every decoder position also reads its agent's velocity and its nearest neighbours'
    states relative to it at the step it moves from (:mod:`~trajeglish_env.model.neighbours`); the added
    weights' output starts at zero, so a model extended with it (``train --init CKPT --neighbour-input``)
    starts as ``CKPT`` did.

    ``lane_input``: every decoder position also reads the lane centres and road edges around its agent, in
    the agent's frame at the step it moves from (:mod:`~trajeglish_env.model.lanes`); zero-initialized like
    ``neighbour_input`` (``train --init CKPT --lane-input``).

    ``drawn_size``: how many of each class's tokens the model draws (0: all ``vocab_size``). A model whose
    vocabulary was extended for reading only (:func:`~trajeglish_env.checkpoint.reading_extension`) reads
    every token of the finer vocabulary (the ego, logged and external agents are tracked within 5 cm) but
    draws only its first ``drawn_size``, the ones it was trained on: each token it cannot draw counts as
    the drawn one it was copied from (``token_source``)."""

    d_model: int = 512
    num_heads: int = 8
    map_layers: int = 2
    encoder_layers: int = 2
    decoder_layers: int = 6
    latent_queries: int = 64
    max_agents: int = 24
    max_polylines: int = 96
    points_per_polyline: int = 20
    steps: int = 32
    vocab_size: int = 384
    num_kinds: int = 3
    num_map_kinds: int = 20
    ff_mult: int = 4
    dropout: float = 0.0
    variant: Variant = Variant.TRAJEGLISH
    signal_input: bool = False
    map_select: str = "frame"
    map_stride: int = 1
    token_bias: bool = False
    neighbour_input: bool = False
    drawn_size: int = 0
    lane_input: bool = False

    def __post_init__(self) -> None:
        if self.d_model % self.num_heads:
            raise ValueError(
                f"ModelConfig: d_model {self.d_model} must be divisible by num_heads {self.num_heads}"
            )
        for name in (
            "d_model",
            "num_heads",
            "decoder_layers",
            "latent_queries",
            "max_agents",
            "steps",
            "vocab_size",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"ModelConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not isinstance(self.variant, Variant):
            object.__setattr__(self, "variant", Variant(self.variant))
        if not isinstance(self.token_bias, bool):
            raise TypeError(f"ModelConfig.token_bias must be a bool, got {self.token_bias!r}")
        for name in ("signal_input", "neighbour_input", "lane_input"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"ModelConfig.{name} must be a bool, got {getattr(self, name)!r}")
        if isinstance(self.drawn_size, bool) or not isinstance(self.drawn_size, int):
            raise TypeError(f"ModelConfig.drawn_size must be an int, got {self.drawn_size!r}")
        if not 0 <= self.drawn_size <= self.vocab_size:
            raise ValueError(
                f"ModelConfig.drawn_size must be in [0, vocab_size {self.vocab_size}], got {self.drawn_size}"
            )
        if isinstance(self.map_stride, bool) or not isinstance(self.map_stride, int) or self.map_stride < 1:
            raise ValueError(f"ModelConfig.map_stride must be an int >= 1, got {self.map_stride!r}")
        if self.map_select not in MAP_SELECT:
            raise ValueError(f"ModelConfig.map_select must be one of {MAP_SELECT}, got {self.map_select!r}")

    @property
    def reads_states(self) -> bool:
        """Whether decoder positions read the states of their step (neighbours or road around them): a
        position can then be decoded only once its step's states are known."""
        return self.neighbour_input or self.lane_input

    @property
    def drawn(self) -> int:
        """Tokens per class the model draws (its logits' width): ``drawn_size``, or the whole vocabulary."""
        return self.drawn_size or self.vocab_size

    def with_variant(self, variant: Variant | str) -> ModelConfig:
        """This config with another ablation variant."""
        return replace(self, variant=Variant(variant))


PRESETS: dict[str, ModelConfig] = {
    # seconds on CPU: unit tests
    "tiny": ModelConfig(
        d_model=32,
        num_heads=2,
        map_layers=1,
        encoder_layers=1,
        decoder_layers=2,
        latent_queries=8,
        max_agents=6,
        max_polylines=16,
        points_per_polyline=10,
        steps=8,
    ),
    # the shipped model: trainable on a 2-core CPU in about an hour
    "small": ModelConfig(
        d_model=128,
        num_heads=4,
        map_layers=1,
        encoder_layers=1,
        decoder_layers=4,
        latent_queries=32,
        max_agents=24,
        max_polylines=64,
        points_per_polyline=20,
        steps=24,
    ),
    # the paper's WOMD model (appendix "Training hyperparameters")
    "paper": ModelConfig(),
}


def preset(name: str, **overrides: object) -> ModelConfig:
    """A preset by name (``tiny``, ``small``, ``paper``), optionally with fields overridden."""
    if name not in PRESETS:
        raise ValueError(f"unknown model preset {name!r}; expected one of {sorted(PRESETS)}")
    return replace(PRESETS[name], **overrides)  # type: ignore[arg-type]
