"""Ranks of a ``torchrun`` job, shared by training, conversion, submission export and evaluation.

``torchrun --nproc_per_node G [--nnodes M ...] -m trajeglish_env.cli COMMAND`` starts ``G x M`` copies of
a command; each reads its rank from the environment (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``), takes its
share of the work (:func:`my_share`: every ``world``-th item, so shares differ by at most one item) and
the main rank merges what the others report (:func:`gather`). Without ``torchrun`` there is one rank and
nothing here touches ``torch.distributed``. On CUDA machines each rank uses GPU ``LOCAL_RANK``
(:func:`rank_device`) and the process group runs on NCCL, elsewhere on gloo.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

T = TypeVar("T")

__all__ = ["Ranks", "barrier", "gather", "init_ranks", "my_share", "rank_device"]


@dataclass(frozen=True)
class Ranks:
    """This process's place in the job: ``rank`` of ``world`` processes, ``local_rank`` on its machine."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """The rank that merges results, prints them and writes shared files."""
        return self.rank == 0


def rank_device() -> Any:
    """This rank's torch device: GPU ``LOCAL_RANK`` when CUDA is available, else the CPU."""
    import torch

    if torch.cuda.is_available():
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
        return device
    return torch.device("cpu")


def init_ranks(device: Any = None) -> Ranks:
    """Join the ``torchrun`` job (if any) and return this process's ranks.

    The process group is created once (NCCL for a CUDA ``device``, gloo otherwise); without
    ``WORLD_SIZE > 1`` in the environment this is a single-process run.
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Ranks()
    import torch.distributed as dist

    if not dist.is_initialized():
        cuda = device is not None and getattr(device, "type", "cpu") == "cuda"
        dist.init_process_group(backend="nccl" if cuda else "gloo")
    return Ranks(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")))


def my_share(items: Sequence[T], ranks: Ranks) -> list[T]:
    """This rank's items: every ``world``-th one starting at ``rank`` (balanced, order kept)."""
    return list(items[ranks.rank :: ranks.world])


def gather(value: T, ranks: Ranks) -> list[T]:
    """Every rank's ``value`` (picklable), in rank order, on every rank."""
    if ranks.world == 1:
        return [value]
    import torch.distributed as dist

    out: list[Any] = [None] * ranks.world
    dist.all_gather_object(out, value)
    return out


def barrier(ranks: Ranks) -> None:
    """Wait until every rank gets here (e.g. before merging files the others write)."""
    if ranks.world > 1:
        import torch.distributed as dist

        dist.barrier()
