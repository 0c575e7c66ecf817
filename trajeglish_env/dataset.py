"""Deprecated alias of :mod:`trajeglish_env.training.dataset` (the module moved with the training stage)."""

import warnings

from trajeglish_env.training.dataset import *  # noqa: F403
from trajeglish_env.training.dataset import WindowConfig, WindowDataset

warnings.warn(
    "trajeglish_env.dataset moved to trajeglish_env.training.dataset; the old name will be removed",
    DeprecationWarning,
    stacklevel=2,
)

__all__ = ["WindowConfig", "WindowDataset"]
