"""Closed-loop rollouts of one scene: full or partial control, any scene size (spatial/temporal sliding
window), optionally split over processes.

A rollout's tokens depend only on its scene, settings and sub-stream (counter-based draws, batch-invariant
inference), so rollouts ``0..R-1`` split into contiguous chunks, each sampled by its own engine (in a
forked process with one torch thread), are exactly the rollouts one engine samples. On a 2-core machine two
processes sample the shared WOMD scene's 32 x 80 rollouts in about 30 s against 49 s in one on a fast
machine (44 s against 68 s on a slower one; the per-call costs of the engine, NumPy's guard geometry and
Python, do not share a core)."""

from __future__ import annotations

import multiprocessing
import numbers
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from trajeglish_env.checkpoint import Checkpoint, load_named
from trajeglish_env.cores import can_fork, others_busy_cores, threads_for, usable_cores
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.scenario import Scenario


@dataclass(frozen=True)
class Rollouts:
    """``xyh [R,N,T,3]`` and ``valid [R,N,T]`` for steps ``0 .. current+horizon`` (history included),
    ``tokens [R,N,T-1]``, which agents the model ``controlled [N]``, and the ``current_index``."""

    xyh: np.ndarray
    valid: np.ndarray
    tokens: np.ndarray
    controlled: np.ndarray
    current_index: int

    @property
    def future(self) -> slice:
        return slice(self.current_index + 1, self.xyh.shape[2])


def rollout(
    ckpt: Checkpoint | str | os.PathLike[str],
    scenario: Scenario,
    rollouts: int = 1,
    horizon: int = 80,
    controlled: np.ndarray | None = None,
    current_index: int | None = None,
    priority: np.ndarray | None = None,
    config: SamplingConfig | None = None,
    processes: int | str = 1,
) -> Rollouts:
    """Sample ``rollouts`` futures of ``horizon`` steps after ``current_index`` (default: the scene's).

    ``controlled [N]`` bool: agents the model drives (default: every agent valid at the current step);
    all others replay the log. ``priority [N]``: lower acts earlier within a timestep (default: the sdc
    first, then by distance to each subset's centre agent). ``processes``: split the rollouts over this
    many processes (``"auto"``: :func:`auto_processes`; forked, so only for a model on the CPU and on
    Linux (:func:`can_fork`), else one); the result is the same. Same seed, same rollout. ``ckpt``: a
    Checkpoint, a checkpoint file or ``"shipped"`` (the pretrained model).
    """
    if isinstance(rollouts, bool) or not isinstance(rollouts, numbers.Integral) or rollouts < 1:
        raise ValueError(f"rollout: rollouts must be an integer >= 1 (futures to sample), got {rollouts!r}")
    rollouts = int(rollouts)
    if isinstance(ckpt, (str, os.PathLike)):
        ckpt = load_named(os.fspath(ckpt))
    if not isinstance(ckpt, Checkpoint):
        raise TypeError(f"rollout: ckpt must be a Checkpoint, a checkpoint file or 'shipped', got {ckpt!r}")
    scenario.validate()  # a user's scene enters here: fail on its field, not deep inside the engine
    current = scenario.current_index if current_index is None else int(current_index)
    if controlled is None:
        controlled = scenario.valid[:, current].copy()
    if priority is None:
        priority = np.zeros(scenario.num_agents)
        priority[scenario.sdc] = -1.0
    job = (
        ckpt,
        scenario,
        horizon,
        np.asarray(controlled, dtype=bool),
        current,
        priority,
        # "auto" resolved for all the rollouts: split over processes, each chunk decodes as one process would
        (config or SamplingConfig()).for_rows(rollouts),
    )
    count = auto_processes(rollouts) if processes == "auto" else _checked_processes(processes)
    on_cpu = next(ckpt.model.parameters()).device.type == "cpu"  # never fork a CUDA context
    if count > 1 and rollouts > 1 and on_cpu and can_fork():
        return _split_rollouts(job, rollouts, count)
    return _sample(job, 0, rollouts)


def auto_processes(rollouts: int) -> int:
    """Processes for ``rollouts`` rollouts: the usable cores that other processes leave free (looked at
    over a quarter of a second), at most one per rollout."""
    if rollouts < 2 or usable_cores() < 2:
        return 1
    return threads_for(others_busy_cores(), rollouts, usable_cores())


def _checked_processes(processes: int | str) -> int:
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"rollout: processes must be a positive int or 'auto', got {processes!r}")
    return processes


_JOB: tuple[Any, ...] | None = None  # the job of the forked workers (set just before they fork)


def _sample(job: tuple[Any, ...], first: int, count: int) -> Rollouts:
    """Rollouts ``first .. first + count - 1`` of ``job`` in this process."""
    ckpt, scenario, horizon, controlled, current, priority, config = job
    engine = RolloutEngine(
        ckpt,
        scenario,
        count,
        horizon,
        controlled,
        current_index=current,
        priority=priority,
        config=config,
        first_rollout=first,
    )
    engine.run()
    return Rollouts(engine.xyh, engine.valid, engine.tokens, engine.controlled, current)


def _worker(conn: Any, first: int, count: int) -> None:
    """A forked worker: samples its chunk with one torch thread and sends it (or its error) back."""
    import torch

    torch.set_num_threads(1)
    try:
        assert _JOB is not None
        conn.send(("ok", _sample(_JOB, first, count)))
    except BaseException as error:  # the parent raises it, naming the chunk
        conn.send(("error", f"{type(error).__name__}: {error}"))
    finally:
        conn.close()


def _split_rollouts(job: tuple[Any, ...], rollouts: int, processes: int) -> Rollouts:
    """The rollouts in ``processes`` contiguous chunks: the first sampled here, the others in forked
    workers, each with one torch thread; concatenated in order."""
    import torch

    global _JOB
    bounds = np.linspace(0, rollouts, min(processes, rollouts) + 1).round().astype(int)
    chunks = [(int(a), int(b - a)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    context = multiprocessing.get_context("fork")
    _JOB = job
    workers = []
    try:
        for first, count in chunks[1:]:
            receive, send = context.Pipe(duplex=False)
            process = context.Process(target=_worker, args=(send, first, count), daemon=True)
            process.start()
            send.close()
            workers.append((process, receive, first, count))
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            parts = [_sample(job, *chunks[0])]
        finally:
            torch.set_num_threads(threads)
        for process, receive, first, count in workers:
            try:
                status, payload = receive.recv()
            except EOFError:
                status, payload = "error", f"the worker exited with code {process.exitcode}"
            process.join()
            if status != "ok":
                raise RuntimeError(f"rollout: rollouts {first}..{first + count - 1} failed: {payload}")
            parts.append(payload)
    finally:
        _JOB = None
        for process, *_ in workers:
            if process.is_alive():
                process.terminate()
    return Rollouts(
        np.concatenate([p.xyh for p in parts]),
        np.concatenate([p.valid for p in parts]),
        np.concatenate([p.tokens for p in parts]),
        parts[0].controlled,
        parts[0].current_index,
    )
