"""The arithmetic a training step runs in (``TrainConfig.precision``).

On CUDA: bfloat16 autocast, always. On a CPU that multiplies bfloat16 natively (AVX512-BF16 / AMX,
:func:`~trajeglish_env.cores.native_bfloat16`) ``"auto"`` is bfloat16 autocast too for models at least
:data:`AUTO_BFLOAT16_WIDTH` wide: the linear layers' products (forward and backward) run in bfloat16 with
float32 weights, optimizer state and accumulation, and attention stays in float32
(:meth:`~trajeglish_env.model.layers.Attention.attend`), whose CPU kernel's backward is slower in
bfloat16. Elsewhere, and with ``"float32"``, the step is float32 throughout.
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from typing import TYPE_CHECKING

from trajeglish_env.cores import native_bfloat16

if TYPE_CHECKING:  # importing this module loads no torch (the CLI's choices come from here)
    import torch

PRECISIONS = ("auto", "float32", "bfloat16")
# below this width (d_model) the casts cost more than bfloat16's products save: a step of the tiny preset
# (32 wide) takes 34 ms in bfloat16 against 17 ms in float32, one of 64 wide 420 ms against 442 ms, the
# small preset (128) 754 ms against 1,046 ms (8 random full windows, one thread, AVX512-BF16)
AUTO_BFLOAT16_WIDTH = 64


def check_precision(name: str) -> str:
    """``name`` if it is one of :data:`PRECISIONS`, else a ValueError naming the choices."""
    if name not in PRECISIONS:
        raise ValueError(f"TrainConfig.precision must be one of {PRECISIONS}, got {name!r}")
    return name


def step_dtype(name: str, device: torch.device, width: int) -> torch.dtype:
    """The dtype a training step's products run in on ``device`` under precision ``name``, for a model
    ``width`` (d_model) wide."""
    import torch

    check_precision(name)
    if device.type == "cuda":
        return torch.bfloat16
    if name == "bfloat16" or (name == "auto" and width >= AUTO_BFLOAT16_WIDTH and native_bfloat16()):
        return torch.bfloat16
    return torch.float32


def step_autocast(name: str, device: torch.device, width: int) -> AbstractContextManager[object]:
    """The autocast context of a training step's forward pass (a null context for float32)."""
    import torch

    if step_dtype(name, device, width) == torch.float32:
        return nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)
