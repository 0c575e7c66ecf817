"""The NPC rows of a big batch decoded as shards in threads of one process.

On a CPU where the ``"auto"`` thread policy would give a batch of :data:`THREADED_MIN_SCENES` or more
scenes two torch threads, the batch instead runs two engines over the two halves of its rows, each
advanced in its own Python thread with one torch thread. Torch and most of NumPy release the GIL, so the
halves decode side by side without the barrier of every multi-threaded kernel call (many of a step's
calls are too small to split well): measured at B = 128 on 2 cores (`trajeglish bench`, docs/speed.md)
about +25 % over one engine on two threads, and beside one busy process faster than one engine on one
thread (where two threads of one engine collapse). Below about 96 scenes the GIL makes it slower.

A row's numbers do not depend on the other rows of its engine (the engines' invariant), so a sharded
batch samples exactly what one engine of all its rows samples, bit for bit.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from trajeglish_env.env.drivers import EngineRows, RowView, Waiting
from trajeglish_env.env.threads import auto_threads

__all__ = ["THREADED_MIN_SCENES", "ShardedEngineRows", "engine_shards"]

THREADED_MIN_SCENES = 96  # from here two shards in threads beat one engine on two threads (B = 64: not)


def engine_shards(
    num_scenes: int,
    torch_threads: int | str | None,
    device: str,
    cores: int | None = None,
) -> int:
    """How many engine shards a batch of ``num_scenes`` runs: 2 on the CPU under ``torch_threads="auto"``
    where the policy would give the batch exactly two threads (a 2-core machine) and it holds at least
    :data:`THREADED_MIN_SCENES` scenes, else 1 (more shards on more cores are not measured: the GIL).
    Any intra-timestep order: each row of an engine walks the agent subsets of its step with its own
    cursor, so where a row's external agents come in its step never depends on the engine's other rows."""
    if torch_threads != "auto" or not str(device).startswith("cpu") or num_scenes < THREADED_MIN_SCENES:
        return 1
    return 2 if auto_threads(num_scenes, cores) == 2 else 1


class ShardedEngineRows:
    """:class:`~trajeglish_env.env.drivers.EngineRows` of ``num_rows`` rows split into ``shards``
    contiguous shards, each an engine of its own (``make_engine(rows)``), advanced in threads."""

    def __init__(
        self,
        make_engine: Callable[[int], object],
        num_rows: int,
        shards: int,
        externals_first: bool,
        entering: bool = False,
    ):
        if not 1 <= shards <= num_rows:
            raise ValueError(f"ShardedEngineRows: shards must be in 1..{num_rows} (the rows), got {shards}")
        self.bounds = np.linspace(0, num_rows, shards + 1).round().astype(np.int64)
        self.parts = [
            EngineRows(make_engine(int(b - a)), externals_first, entering)
            for a, b in zip(self.bounds[:-1], self.bounds[1:], strict=True)
        ]
        self._pool: ThreadPoolExecutor | None = None
        self._pid = -1

    @property
    def engines(self) -> list[Any]:
        """The shards' engines, in row order."""
        return [part.engine for part in self.parts]

    def _part(self, row: int) -> tuple[EngineRows, int]:
        k = int(np.searchsorted(self.bounds, row, side="right")) - 1
        return self.parts[k], row - int(self.bounds[k])

    def start(
        self,
        row: int,
        scenario: Any,
        external: np.ndarray,
        horizon: int,
        priority: np.ndarray,
        seed: int,
    ) -> RowView:
        """(Re)start row ``row`` (see :meth:`EngineRows.start`)."""
        part, local = self._part(row)
        return part.start(local, scenario, external, horizon, priority, seed)

    def stop(self, row: int) -> None:
        part, local = self._part(row)
        part.stop(local)

    def advance(self) -> Waiting | None:
        """Every shard's :meth:`EngineRows.advance`, the busy ones side by side in threads (each with this
        thread's grad mode: the layers' inference path depends on it); the rows that wait, in row order."""
        import torch

        busy = [k for k, part in enumerate(self.parts) if part.engine.stepping.any()]
        grad = torch.is_grad_enabled()

        def run(k: int) -> Waiting | None:
            with torch.set_grad_enabled(grad):
                return self.parts[k].advance()

        if len(busy) > 1:
            results = list(self._executor().map(run, busy))
        else:
            results = [run(k) for k in busy]
        rows = [got[0] + self.bounds[k] for k, got in zip(busy, results, strict=True) if got is not None]
        agents = [got[1] for got in results if got is not None]
        return (np.concatenate(rows), np.concatenate(agents)) if rows else None

    def supply(self, rows: np.ndarray, agents: np.ndarray, next_xyh: np.ndarray, valid: np.ndarray) -> None:
        """Set the next states of external agents (see :meth:`EngineRows.supply`), shard by shard."""
        shard = np.searchsorted(self.bounds, rows, side="right") - 1
        for k in np.unique(shard).tolist():
            pick = shard == k
            self.parts[k].supply(rows[pick] - self.bounds[k], agents[pick], next_xyh[pick], valid[pick])

    def _executor(self) -> ThreadPoolExecutor:
        """The shards' thread pool, made on first use and again in a forked child (threads do not fork)."""
        if self._pool is None or self._pid != os.getpid():
            self._pool = ThreadPoolExecutor(len(self.parts), thread_name_prefix="trajeglish-shard")
            self._pid = os.getpid()
        return self._pool

    def close(self) -> None:
        """Stop the threads (they also end with the process)."""
        if self._pool is not None and self._pid == os.getpid():
            self._pool.shutdown(wait=False)
        self._pool = None
