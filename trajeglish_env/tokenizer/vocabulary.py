"""A motion vocabulary: one set of template actions ``(dx, dy, dh)`` per agent class, with metadata.

Templates are expressed in the local frame of the current state (x forward, y left, heading change in
radians). All classes share the vocabulary size ``V`` so that a model has one output head; token ``i``
means template ``i`` of the agent's own class. The object is embedded in model checkpoints through
:meth:`MotionVocabulary.to_state` / :meth:`MotionVocabulary.from_state`, and has its own versioned file
format (``save`` / ``load``) so a fitted vocabulary can be shared on its own.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from trajeglish_env.scenario import AgentKind
from trajeglish_env.scenario_io import atomic_path, load_failure
from trajeglish_env.tokenizer.nearest import SearchTable

FORMAT_NAME = "trajeglish_env.tokenizer"
FORMAT_VERSION = 1
KIND_NAMES = tuple(k.name.lower() for k in AgentKind)


class VocabularyError(ValueError):
    """A vocabulary (or a file or checkpoint entry holding one) is malformed; the message says where."""


@dataclass(frozen=True, eq=False)
class MotionVocabulary:
    """Template actions ``templates [num_kinds, V, 3]`` (float64 dx, dy in m, dh in rad) per AgentKind.

    ``method`` names how they were made (``k-disks``, ``xyh-grid``, ``xy-grid``, ``k-means``); ``metadata``
    is a JSON-able dict (fitting settings, data, per-class transition counts, classes that borrowed another
    class's templates, ...).
    """

    templates: np.ndarray
    method: str = "k-disks"
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    @property
    def size(self) -> int:
        """Number of templates per class (the token vocabulary size)."""
        return int(self.templates.shape[1])

    @property
    def num_kinds(self) -> int:
        """Number of agent classes (one template set each)."""
        return int(self.templates.shape[0])

    def for_kind(self, kind: int | AgentKind) -> np.ndarray:
        """Templates ``[V,3]`` of one agent class."""
        return self.templates[int(kind)]

    @cached_property
    def search_tables(self) -> tuple[SearchTable, ...]:
        """Precomputed nearest-template search tables, one per class."""
        return tuple(SearchTable.build(t) for t in self.templates)

    def validate(self, where: str = "vocabulary") -> MotionVocabulary:
        """Check shape, dtype and finiteness; raise VocabularyError naming ``where`` and the problem."""
        t = self.templates
        if not isinstance(t, np.ndarray) or t.ndim != 3 or t.shape[0] != len(AgentKind) or t.shape[2] != 3:
            shape = getattr(t, "shape", type(t).__name__)
            raise VocabularyError(
                f"{where}: templates must be an array [{len(AgentKind)} classes, V, 3 (dx, dy, dh)], "
                f"got {shape}"
            )
        if t.dtype != np.float64:
            object.__setattr__(self, "templates", t.astype(np.float64))
            t = self.templates
        if t.shape[1] < 1:
            raise VocabularyError(f"{where}: vocabulary is empty (V = 0)")
        if not np.isfinite(t).all():
            kind, index = np.argwhere(~np.isfinite(t).all(-1))[0]
            raise VocabularyError(
                f"{where}: template {index} of class {KIND_NAMES[kind]} is not finite: {t[kind, index]}"
            )
        if not isinstance(self.method, str) or not self.method:
            raise VocabularyError(f"{where}: method must be a non-empty string, got {self.method!r}")
        try:
            json.dumps(self.metadata)
        except (TypeError, ValueError) as exc:
            raise VocabularyError(f"{where}: metadata must be JSON-serialisable: {exc}") from exc
        return self

    # ------------------------------------------------------------------ checkpoint embedding
    def to_state(self) -> dict[str, np.ndarray | str | int]:
        """Plain arrays/strings/ints describing this vocabulary (for a model checkpoint)."""
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "templates": self.templates.copy(),
            "kinds": ",".join(KIND_NAMES),
            "method": self.method,
            "metadata": json.dumps(self.metadata, sort_keys=True),
        }

    @classmethod
    def from_state(cls, state: dict[str, Any], where: str = "checkpoint") -> MotionVocabulary:
        """Inverse of :meth:`to_state`; unknown formats or versions fail naming ``where``."""
        if not isinstance(state, dict):
            raise VocabularyError(f"{where}: tokenizer state must be a dict, got {type(state).__name__}")
        missing = [
            k for k in ("format", "version", "templates", "kinds", "method", "metadata") if k not in state
        ]
        if missing:
            raise VocabularyError(f"{where}: tokenizer state lacks {missing}")
        if str(state["format"]) != FORMAT_NAME:
            raise VocabularyError(
                f"{where}: not a trajeglish_env tokenizer (format {str(state['format'])!r})"
            )
        try:
            version = int(state["version"])
        except (TypeError, ValueError) as exc:
            raise VocabularyError(f"{where}: tokenizer version {state['version']!r} is not a number") from exc
        if version != FORMAT_VERSION:
            raise VocabularyError(
                f"{where}: tokenizer format version {version} is not supported "
                f"(this build reads {FORMAT_VERSION})"
            )
        kinds = str(state["kinds"]).split(",")
        if tuple(kinds) != KIND_NAMES:
            raise VocabularyError(
                f"{where}: tokenizer classes {kinds} do not match this build's {list(KIND_NAMES)}"
            )
        try:
            metadata = json.loads(str(state["metadata"]))
        except json.JSONDecodeError as exc:
            raise VocabularyError(f"{where}: tokenizer metadata is not valid JSON: {exc}") from exc
        templates = np.asarray(state["templates"])
        vocab = cls.__new__(cls)
        object.__setattr__(vocab, "templates", templates)
        object.__setattr__(vocab, "method", str(state["method"]))
        object.__setattr__(vocab, "metadata", metadata)
        return vocab.validate(where)

    # ------------------------------------------------------------------ own file format
    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write this vocabulary to ``path`` (``.npz``) atomically; returns the path."""
        path = Path(path)
        state = self.to_state()
        arrays = {k: np.asarray(v) for k, v in state.items()}
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> MotionVocabulary:
        """Read a file written by :meth:`save`; a missing, corrupt or unknown-version file fails naming it."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such tokenizer file")
        try:
            data = np.load(path, allow_pickle=False)
            if isinstance(data, np.ndarray):  # a bare .npy array, not an archive of fields
                raise VocabularyError(
                    f"{path}: not a readable tokenizer file (a single array, not an archive)"
                )
            with data:
                if any(not name.endswith(".npy") for name in data.zip.namelist()):  # a torch checkpoint...
                    raise VocabularyError(
                        f"{path}: not a readable tokenizer file (a zip of other files: a checkpoint? a "
                        "vocabulary is a tokenizer .npz, as `trajeglish tokenizer fit` writes)"
                    )
                state = {k: data[k] for k in data.files}
        except VocabularyError:
            raise
        except (zipfile.BadZipFile, EOFError, OSError, ValueError, zlib.error) as exc:
            raise VocabularyError(
                f"{path}: not a readable tokenizer file (truncated or corrupt?): {load_failure(exc)}"
            ) from exc
        state = {k: (v.item() if v.ndim == 0 else v) for k, v in state.items()}
        return cls.from_state(state, where=str(path))

    def equals(self, other: MotionVocabulary) -> bool:
        """Exact equality of templates, method and metadata."""
        return (
            self.templates.shape == other.templates.shape
            and np.array_equal(self.templates, other.templates)
            and self.method == other.method
            and self.metadata == other.metadata
        )


def default_tokenizer_path(vocab_size: int = 384) -> Path:
    """Path of the shipped vocabulary of ``vocab_size`` templates (inside the package's assets)."""
    return Path(str(resources.files("trajeglish_env") / "assets" / f"tokenizer_v{vocab_size}.npz"))


def load_default_tokenizer(vocab_size: int = 384) -> MotionVocabulary:
    """The shipped k-disks vocabulary (fitted on generated scenes; see its ``metadata`` for provenance)."""
    path = default_tokenizer_path(vocab_size)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no shipped tokenizer with {vocab_size} templates (only V=384 is shipped)"
        )
    return MotionVocabulary.load(path)
