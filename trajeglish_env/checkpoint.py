"""Self-describing, versioned model checkpoints: config + vocabulary + weights + training metadata.

One ``torch.save`` file holding only tensors and plain Python values, read back with
``torch.load(weights_only=True)`` (no pickled code runs on load). Wrong, corrupt, truncated or
mismatched files fail with a :class:`CheckpointError` that names the file and the problem.
"""

from __future__ import annotations

import dataclasses
import os
import zipfile
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch

from trajeglish_env.model.config import ModelConfig, Variant
from trajeglish_env.model.encoder import SIGNAL_PARAMS
from trajeglish_env.model.lanes import LANE_PARAMS
from trajeglish_env.model.neighbours import NEIGHBOUR_PARAMS
from trajeglish_env.model.network import TrajeglishModel
from trajeglish_env.scenario_io import atomic_path, load_failure
from trajeglish_env.tokenizer.extend import embedding_sources, is_extension
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary, VocabularyError

FORMAT_NAME = "trajeglish_env.checkpoint"
FORMAT_VERSION = 1
PRETRAINED_ASSET = "trajeglish_small.pt"


class CheckpointError(ValueError):
    """A checkpoint file is missing, corrupt, of another format/version, or inconsistent."""


class CheckpointNotFoundError(CheckpointError, FileNotFoundError):
    """No checkpoint file at the path (a directory is not one): both a CheckpointError and a
    FileNotFoundError, so either ``except`` catches it."""


@dataclass(frozen=True)
class TrainerState:
    """What a run's ``last.pt`` records to resume from: the step reached, its metrics history and its
    ``TrainConfig`` (as a dict: older runs lack newer fields)."""

    step: int
    history: tuple[dict[str, Any], ...] = ()
    train_config: dict[str, Any] = dataclasses.field(default_factory=dict)

    @classmethod
    def of(cls, ckpt: Checkpoint) -> TrainerState:
        """The checkpoint's training state; a CheckpointError when it holds none (a ``model.pt``)."""
        raw = ckpt.trainer
        step = raw.get("step") if isinstance(raw, dict) else None
        if not isinstance(step, int) or step < 0:
            raise CheckpointError(
                f"{ckpt.path}: holds no training state to resume from (no 'trainer' step; a model.pt, "
                "not a run's last.pt?)"
            )
        assert isinstance(raw, dict)
        return cls(step, tuple(raw.get("history") or ()), dict(raw.get("train_config") or {}))

    def to_dict(self) -> dict[str, Any]:
        """The form a checkpoint file stores."""
        return {"step": self.step, "history": list(self.history), "train_config": self.train_config}


@dataclass
class Checkpoint:
    """A loaded checkpoint: the model (eval mode), its vocabulary and what training recorded."""

    model: TrajeglishModel
    vocabulary: MotionVocabulary
    training: dict[str, Any]
    path: Path | None = None
    optimizer: dict[str, Any] | None = None
    trainer: dict[str, Any] | None = None

    @property
    def config(self) -> ModelConfig:
        return self.model.cfg


def _to_plain(state: dict[str, Any]) -> dict[str, Any]:
    """NumPy arrays -> tensors so the file loads with ``weights_only=True``."""
    return {
        k: torch.from_numpy(np.ascontiguousarray(v)) if isinstance(v, np.ndarray) else v
        for k, v in state.items()
    }


def _from_plain(state: dict[str, Any]) -> dict[str, Any]:
    return {k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in state.items()}


def _plain_config(cfg: ModelConfig) -> dict[str, Any]:
    """A config as plain values (the variant by its name), as stored in checkpoint files."""
    config = dataclasses.asdict(cfg)
    config["variant"] = cfg.variant.value
    return config


def save_checkpoint(
    path: str | os.PathLike[str],
    model: TrajeglishModel,
    vocabulary: MotionVocabulary,
    training: dict[str, Any] | None = None,
    optimizer: dict[str, Any] | None = None,
    trainer: dict[str, Any] | None = None,
) -> Path:
    """Write a checkpoint atomically (a crash never leaves a half-written file in place)."""
    check_compatible(model.cfg, vocabulary, where=str(path))
    config = _plain_config(model.cfg)
    payload = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "config": config,
        "vocabulary": _to_plain(vocabulary.to_state()),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "training": training or {},
        "optimizer": optimizer,
        "trainer": trainer,
    }
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def on_device(ckpt: Checkpoint, device: str | torch.device) -> Checkpoint:
    """``ckpt`` with its model on ``device``: itself when it is there already, else a copy (the caller's
    model is not moved); a CUDA device on a machine without one is refused with one clear line."""
    target = torch.device(device)
    if target.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(
            f"device {str(device)!r}: CUDA is not available on this machine (torch "
            f"{torch.__version__}); use device='cpu'"
        )
    here = next(ckpt.model.parameters()).device
    if here.type == target.type and (target.index is None or here.index == target.index):
        return ckpt
    model = TrajeglishModel(ckpt.model.cfg)  # built on the CPU, so the source device never holds two copies
    model.load_state_dict(ckpt.model.state_dict())
    return dataclasses.replace(ckpt, model=model.to(target).eval())


def check_compatible(cfg: ModelConfig, vocabulary: MotionVocabulary, where: str) -> None:
    """The vocabulary must have the model's size and number of classes."""
    if vocabulary.size != cfg.vocab_size or vocabulary.num_kinds != cfg.num_kinds:
        raise CheckpointError(
            f"{where}: vocabulary has {vocabulary.num_kinds} classes x {vocabulary.size} templates but the "
            "model "
            f"expects {cfg.num_kinds} x {cfg.vocab_size}"
        )


def check_init(ckpt: Checkpoint, cfg: ModelConfig, vocabulary: MotionVocabulary) -> None:
    """A run started from ``ckpt`` (fine-tuning) must keep its config (but may add the signal or neighbour
    input, or choose its windows' map chunks another way), vocabulary (or extend it: ``tokenizer.extend``,
    with ``vocab_size`` and ``token_bias`` to match) and finite weights; otherwise raise a
    :class:`CheckpointError` naming what differs."""
    where = f"--init {ckpt.path or 'checkpoint'}"
    theirs_cfg, ours_cfg = _plain_config(ckpt.config), _plain_config(cfg)
    for added in (
        "signal_input",
        "neighbour_input",
        "lane_input",
    ):  # added inputs (their weights start at zero)
        if getattr(cfg, added) and not getattr(ckpt.config, added):
            theirs_cfg[added] = True
    theirs_cfg["map_select"] = cfg.map_select  # which chunks a window holds, and their points: inputs,
    theirs_cfg["map_stride"] = cfg.map_stride  # not weights
    extended = is_extension(ckpt.vocabulary, vocabulary)
    if extended:  # added tokens: their embeddings and biases, see load_into
        theirs_cfg["vocab_size"] = vocabulary.size
        theirs_cfg["token_bias"] = True
    theirs, ours = ckpt.vocabulary.templates, vocabulary.templates
    if not extended and (theirs.shape != ours.shape or not np.array_equal(theirs, ours)):
        same = theirs.shape == ours.shape
        how = (
            f"the same shape {list(ours.shape)}, templates up to {np.abs(theirs - ours).max():.3g} apart"
            if same
            else f"{list(theirs.shape)} vs {list(ours.shape)}"
        )
        raise CheckpointError(
            f"{where}: the vocabulary differs from the checkpoint's ({ckpt.vocabulary.method} vs "
            f"{vocabulary.method}, {how}; leave --vocab out to use the checkpoint's, or pass one that "
            "extends it: trajeglish tokenizer extend)"
        )
    diffs = [
        f"{name} {theirs_cfg[name]} (checkpoint) vs {ours_cfg[name]} (requested)"
        for name in theirs_cfg
        if theirs_cfg[name] != ours_cfg[name]
    ]
    if diffs:
        raise CheckpointError(
            f"{where}: the model config differs from the checkpoint's: {'; '.join(diffs)} "
            "(leave --preset/--variant out to use the checkpoint's)"
        )
    bad = [name for name, p in ckpt.model.named_parameters() if not torch.isfinite(p).all()]
    if bad:
        raise CheckpointError(f"{where}: weights {bad[:3]} are not finite")


def load_into(model: TrajeglishModel, ckpt: Checkpoint, vocabulary: MotionVocabulary | None = None) -> None:
    """Load ``ckpt``'s weights into ``model``, whose config is ``ckpt``'s or extends it with the signal or
    neighbour input (:func:`check_init`): the added weights keep their initial values (their output zero).
    With ``vocabulary`` extending the checkpoint's (``tokenizer.extend``), each added token starts as a copy
    of the nearest old template of its class, and the bias of each old token and its copies is ``-log`` of
    their number (plus the old bias): the extended model gives every old token's group the old token's
    probability."""
    state = ckpt.model.state_dict()
    if vocabulary is not None and is_extension(ckpt.vocabulary, vocabulary):
        if not model.cfg.token_bias:
            raise CheckpointError(
                f"--init {ckpt.path or 'checkpoint'}: an extended vocabulary needs token_bias"
            )
        sources = torch.from_numpy(embedding_sources(ckpt.vocabulary, vocabulary))  # [K, V']
        kinds = torch.arange(len(sources))[:, None]
        old = state["token.weight"].view(ckpt.config.num_kinds, ckpt.config.vocab_size, -1)
        state["token.weight"] = old[kinds, sources].reshape(-1, old.shape[-1])
        copies = torch.stack([torch.bincount(row, minlength=ckpt.config.vocab_size) for row in sources])
        bias = -torch.log(copies[kinds, sources].to(old.dtype))
        if "token_bias" in state:
            bias = bias + state["token_bias"].view(ckpt.config.num_kinds, -1)[kinds, sources]
        state["token_bias"] = bias.reshape(-1)
    missing, unexpected = model.load_state_dict(state, strict=False)
    signal = [k for k in missing if k.startswith(SIGNAL_PARAMS)]
    neighbours = [k for k in missing if k.startswith(NEIGHBOUR_PARAMS)]
    lanes = [k for k in missing if k.startswith(LANE_PARAMS)]
    if (
        unexpected
        or len(signal) + len(neighbours) + len(lanes) != len(missing)
        or (signal and not model.cfg.signal_input)
        or (neighbours and not model.cfg.neighbour_input)
        or (lanes and not model.cfg.lane_input)
    ):
        raise CheckpointError(
            f"--init {ckpt.path or 'checkpoint'}: weights do not fit the model (missing {missing[:3]}, "
            f"unexpected {unexpected[:3]})"
        )


def load_checkpoint(path: str | os.PathLike[str], map_location: str | torch.device = "cpu") -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint`; the model is returned in eval mode."""
    path = Path(path)
    if not path.is_file():
        what = "a directory, not a checkpoint file" if path.is_dir() else "no such checkpoint file"
        raise CheckpointNotFoundError(f"{path}: {what}")
    _check_archive(path)
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt/truncated/foreign files
        # a checkpoint is a zip archive: torch's legacy reader's error for any other file means nothing
        reason = load_failure(exc, "a checkpoint") if zipfile.is_zipfile(path) else "not a zip archive"
        raise CheckpointError(
            f"{path}: not a readable checkpoint (not written by trajeglish, truncated or corrupt?): {reason}"
        ) from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT_NAME:
        raise CheckpointError(f"{path}: not a trajeglish_env checkpoint (no '{FORMAT_NAME}' header)")
    if payload.get("version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {payload.get('version')} is not supported "
            f"(this build reads {FORMAT_VERSION})"
        )
    try:
        raw = dict(payload["config"])
        raw["variant"] = Variant(raw["variant"])
        known = {f.name for f in dataclasses.fields(ModelConfig)}
        unknown = sorted(set(raw) - known)
        if unknown:
            raise CheckpointError(
                f"{path}: config has unknown fields {unknown} (written by a newer version?)"
            )
        cfg = ModelConfig(**raw)
        vocabulary = MotionVocabulary.from_state(_from_plain(payload["vocabulary"]), where=str(path))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, CheckpointError):
            raise
        if isinstance(exc, VocabularyError):
            raise CheckpointError(str(exc)) from exc
        if isinstance(exc, KeyError):
            raise CheckpointError(f"{path}: malformed checkpoint: no {exc.args[0]!r} entry") from exc
        stored = {
            k: v for k, v in dict(payload.get("config") or {}).items() if not isinstance(v, (int, float))
        }
        raise CheckpointError(
            f"{path}: malformed checkpoint config: {exc} (its non-numeric fields: {stored})"
        ) from exc
    check_compatible(cfg, vocabulary, where=str(path))
    model = TrajeglishModel(cfg)
    try:
        model.load_state_dict(payload["state_dict"])
    except (RuntimeError, KeyError) as exc:
        raise CheckpointError(f"{path}: weights do not match the stored config: {exc}") from exc
    broken = [name for name, value in model.state_dict().items() if not torch.isfinite(value).all()]
    if broken:
        raise CheckpointError(f"{path}: weights {broken[:3]} hold NaN or infinite values (a diverged run?)")
    if cfg.drawn < cfg.vocab_size:
        _check_sources(model.token_source, cfg.drawn, str(path))
    model.eval()
    return Checkpoint(
        model=model,
        vocabulary=vocabulary,
        training=dict(payload.get("training") or {}),
        path=path,
        optimizer=payload.get("optimizer"),
        trainer=payload.get("trainer"),
    )


def _check_archive(path: Path) -> None:
    """A checkpoint is a zip archive: each member's CRC is checked (a flipped byte in the weights would
    otherwise load as wrong numbers, silently); a file that is no zip is left to ``torch.load``'s error."""
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
            names = set(archive.namelist())
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, RuntimeError):
        return
    if {"templates.npy", "kinds.npy"} <= names:  # a motion vocabulary (tokenizer .npz), not a model
        raise CheckpointError(
            f"{path}: a motion vocabulary (tokenizer file), not a model checkpoint: pass it as --vocab "
            "(TrajeglishNPC and --ckpt take a checkpoint .pt)"
        )
    if "__format__.npy" in names:
        raise CheckpointError(f"{path}: a scenario shard, not a model checkpoint")
    if names and all(name.endswith(".npy") for name in names):
        raise CheckpointError(f"{path}: a NumPy .npz archive, not a model checkpoint")
    if bad is not None:
        raise CheckpointError(f"{path}: corrupt checkpoint: its member {bad!r} fails its CRC check")


def _check_sources(sources: torch.Tensor, drawn: int, where: str) -> None:
    """A reading extension's ``token_source [K, V]`` must name drawn tokens, each drawn one itself."""
    identity = torch.arange(drawn)
    if (sources < 0).any() or (sources >= drawn).any() or not bool((sources[:, :drawn] == identity).all()):
        raise CheckpointError(
            f"{where}: token_source must map every token to one of the {drawn} drawn ones and each of those "
            "to itself (a corrupt reading extension?)"
        )


def pretrained_path() -> Path:
    """Path of the checkpoint shipped inside the package."""
    return Path(str(resources.files("trajeglish_env") / "assets" / PRETRAINED_ASSET))


def load_pretrained(map_location: str | torch.device = "cpu") -> Checkpoint:
    """The shipped pretrained model and its tokenizer (no download: it lives in the package)."""
    path = pretrained_path()
    if not path.is_file():
        raise CheckpointError(f"{path}: the shipped pretrained checkpoint is missing from this installation")
    return load_checkpoint(path, map_location)


def load_named(name: str, map_location: str | torch.device = "cpu") -> Checkpoint:
    """The checkpoint a command's argument names: ``"shipped"`` (the pretrained model) or a file."""
    return load_pretrained(map_location) if name == "shipped" else load_checkpoint(name, map_location)
