"""Warnings shown at the user's line: the first frame outside this package and the RL libraries that call
it (PettingZoo's and Gymnasium's wrappers), not an internal line of the env."""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

import gymnasium
import pettingzoo

_LIBRARIES = tuple(
    str(Path(m.__file__).parent) + os.sep for m in (sys.modules[__package__], gymnasium, pettingzoo)
)


def warn_at_caller(message: str, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn`` attributed to the nearest caller outside trajeglish_env, PettingZoo and Gymnasium
    (the outermost frame when there is none, as under the command line)."""
    frame, level = sys._getframe(1), 1
    while frame.f_back is not None and frame.f_code.co_filename.startswith(_LIBRARIES):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level + 1)
