"""The arithmetic a training step runs in (``TrainConfig.precision``).

On CUDA: bfloat16 autocast, always. On a CPU that multiplies bfloat16 natively (AVX512-BF16 / AMX,
:func:`~trajeglish_env.cores.native_bfloat16`) ``"auto"`` is bfloat16 autocast too: the linear layers'
products (forward and backward) run in bfloat16 with float32 weights, optimizer state and accumulation,
and attention stays in float32 (:meth:`~trajeglish_env.model.layers.Attention.attend`), whose CPU kernel's
backward is slower in bfloat16. Elsewhere, and with ``"float32"``, the step is float32 throughout.
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from typing import TYPE_CHECKING

from trajeglish_env.cores import native_bfloat16

if TYPE_CHECKING:  # importing this module loads no torch (the CLI's choices come from here)
    import torch

PRECISIONS = ("auto", "float32", "bfloat16")


def check_precision(name: str) -> str:
    """``name`` if it is one of :data:`PRECISIONS`, else a ValueError naming the choices."""
    if name not in PRECISIONS:
        raise ValueError(f"TrainConfig.precision must be one of {PRECISIONS}, got {name!r}")
    return name


def step_dtype(name: str, device: torch.device) -> torch.dtype:
    """The dtype a training step's products run in on ``device`` under precision ``name``."""
    import torch

    check_precision(name)
    if device.type == "cuda":
        return torch.bfloat16
    if name == "bfloat16" or (name == "auto" and native_bfloat16()):
        return torch.bfloat16
    return torch.float32


def step_autocast(name: str, device: torch.device) -> AbstractContextManager[object]:
    """The autocast context of a training step's forward pass (a null context for float32)."""
    import torch

    if step_dtype(name, device) == torch.float32:
        return nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)
