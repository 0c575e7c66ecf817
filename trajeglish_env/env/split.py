"""The batched envs with their scenes split over worker processes: ``B`` scenes in ``P`` contiguous shards,
each a one-process batched env in its own forked worker with its own torch threads
(:mod:`~trajeglish_env.env.shards`), stepped at once. On a machine whose cores are free this outruns one
process of B scenes with several torch threads (decoding calls of B / P rows on one core each scale better
than B rows over P threads, and the guard's NumPy geometry, one core in one process, runs in every shard).

- :class:`SplitEgoEnv`: :class:`~trajeglish_env.env.vector.BatchedEgoEnv`'s Gymnasium ``VectorEnv``.
- :class:`SplitParallelEnv`: :class:`~trajeglish_env.env.vector.BatchedParallelEnv`'s per-scene parallel
  API.

Semantics are the one-process env's, bit for bit: scene ``i`` reset with seed ``s`` plays what scene ``i``
of a one-process batch plays (a scene's results do not depend on the others of its batch). Actions are
checked here before any worker moves. ``apply(fn)`` runs a function on every shard's env where its scenes
live (no copy of the simulations comes back); :class:`SplitEgoEnv`'s ``envs[i]`` reach into scene i's
worker (SB3's ``get_attr`` / ``env_method``). Workers are forked (Linux, :func:`~trajeglish_env.cores.
can_fork`) for a model on the CPU, and spawned for one meant for a GPU (``TrajeglishNPC(device="cuda")``:
each worker puts its copy of the model on the GPU, so the scenes' host work, the guard's geometry and the
env state, runs on as many cores as there are workers while the GPU decodes for all of them).
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.reduction import ForkingPickler
from typing import Any

import gymnasium
import numpy as np

from trajeglish_env.env.actions import check_action
from trajeglish_env.env.batch_api import EgoVectorEnv, ParallelBatchAPI, check_scene_actions
from trajeglish_env.env.config import EnvConfig
from trajeglish_env.env.gym_ego import check_single
from trajeglish_env.env.scenes import scene_set
from trajeglish_env.env.shards import (
    MIN_SCENES_PER_PROCESS,
    CommandLoadError,
    ShardWorkers,
    _Method,
    auto_env_processes,
    auto_gpu_processes,
    checked_processes,
    on_gpu,
    pickled_by_value,
    prepared_config,
    shard_ranges,
    start_method,
    worker_threads,
)
from trajeglish_env.env.vector import BatchedEgoEnv, BatchedParallelEnv

__all__ = [
    "MIN_SCENES_PER_PROCESS",
    "SplitEgoEnv",
    "SplitParallelEnv",
    "auto_env_processes",
    "batched_ego_env",
    "batched_parallel_env",
]


def _count(
    processes: int | str,
    num_envs: int,
    config: EnvConfig | None,
    options: dict[str, Any],
    torch_threads: int | str | None,
) -> int:
    """The process count of a factory: ``"auto"`` gives a model meant for a GPU one spawned GPU worker per
    :data:`~trajeglish_env.env.shards.GPU_SCENES_PER_PROCESS` scenes (:func:`auto_gpu_processes`), and keeps
    in one process an env asked for several torch threads (a worker runs one)."""
    if processes == "auto" and on_gpu(config, options):
        return auto_gpu_processes(int(num_envs))
    if processes == "auto" and torch_threads not in ("auto", None, 1):
        return 1
    return checked_processes(processes, num_envs)


def batched_ego_env(
    num_envs: int,
    scenes: Any = None,
    config: EnvConfig | None = None,
    render_mode: str | None = None,
    torch_threads: int | str | None = "auto",
    processes: int | str = 1,
    **options: Any,
) -> BatchedEgoEnv | SplitEgoEnv:
    """A :class:`BatchedEgoEnv` (``processes`` 1) or a :class:`SplitEgoEnv` of that many worker processes
    (``"auto"``: :func:`auto_env_processes`, one process when that is 1 or when ``torch_threads`` asks for
    several threads; for an NPC model on a GPU, one spawned GPU worker per 64 scenes up to the cores,
    :func:`auto_gpu_processes`; a count for a GPU model spawns that many GPU workers)."""
    count = _count(processes, num_envs, config, options, torch_threads)
    if count == 1:
        return BatchedEgoEnv(num_envs, scenes, config, render_mode, torch_threads, **options)
    return SplitEgoEnv(num_envs, scenes, config, render_mode, torch_threads, processes=count, **options)


def batched_parallel_env(
    num_envs: int,
    scenes: Any = None,
    config: EnvConfig | None = None,
    render_mode: str | None = None,
    torch_threads: int | str | None = "auto",
    processes: int | str = 1,
    **options: Any,
) -> BatchedParallelEnv | SplitParallelEnv:
    """A :class:`BatchedParallelEnv` (``processes`` 1) or a :class:`SplitParallelEnv` (as
    :func:`batched_ego_env`)."""
    count = _count(processes, num_envs, config, options, torch_threads)
    if count == 1:
        return BatchedParallelEnv(num_envs, scenes, config, render_mode, torch_threads, **options)
    return SplitParallelEnv(num_envs, scenes, config, render_mode, torch_threads, processes=count, **options)


@dataclass(frozen=True)
class _ShardEnv:
    """What a worker builds: a one-process batched env (``kind``) of ``num_envs`` scenes. A module-level
    value, so that it pickles for spawned workers."""

    kind: type
    num_envs: int
    scenes: Any
    config: EnvConfig
    render_mode: str | None
    torch_threads: int | str | None

    def __call__(self) -> Any:
        return self.kind(self.num_envs, self.scenes, self.config, self.render_mode, self.torch_threads)


def _ego_spaces(env: BatchedEgoEnv) -> tuple[gymnasium.Space, gymnasium.Space]:
    return env.single_observation_space, env.single_action_space


def _not_loaded(name: str, error: CommandLoadError) -> CommandLoadError:
    """The error of an ``apply`` whose function the workers could not load, with what to do."""
    return CommandLoadError(
        f"apply: {name!r} did not reach the workers: {error}; define it at module level before creating "
        "the env, or in an importable module"
    )


class SplitWorkers:
    """What both split envs share: their workers (started by :meth:`_start`), ``apply`` and stopping."""

    workers: ShardWorkers
    processes: int

    def _start(
        self,
        kind: type,
        num_envs: int,
        processes: int | str,
        shard: tuple[Any, EnvConfig, str | None, int | str | None],
        describe: Callable[[Any], Any],
        method: str,
    ) -> Any:
        """Start the workers (``method``: see :func:`~trajeglish_env.env.shards.start_method`), each with
        an env ``kind(n, *shard)`` of its ``n`` scenes (``shard``: scenes, config, render mode, torch
        threads); ``describe(env)`` of the first shard is returned."""
        owner = f"Split{kind.__name__.removeprefix('Batched')}"
        count = checked_processes(processes, num_envs)
        if not isinstance(num_envs, (int, np.integer)) or num_envs < count:
            raise ValueError(f"{owner}: num_envs must be an int >= processes ({count}), got {num_envs!r}")
        scenes, config, render_mode, torch_threads = shard
        threads = worker_threads(torch_threads, owner)
        shards = shard_ranges(int(num_envs), count)
        builders = [_ShardEnv(kind, len(s), scenes, config, render_mode, threads) for s in shards]
        self.workers = ShardWorkers(shards, builders, describe, owner, method)
        self.num_envs, self.processes, self.shards = int(num_envs), count, shards
        return self.workers.described[0]

    def apply(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> list[Any]:
        """``fn(shard_env, *args, **kwargs)`` in every worker (``shard_env``: the shard's one-process env,
        whose scene ``j`` is scene ``shards[k].start + j`` here); the results, one per shard. ``fn`` goes by
        reference where the workers can load it (a module's function, one of ``__main__`` defined before the
        env: it then runs on the worker's own globals), else by value with cloudpickle (a lambda, a closure,
        a function of ``__main__`` defined after the env forked its workers: a copy of the globals it uses
        at each call). One that pickles neither way is a TypeError here, before any worker moves; one the
        workers still cannot load a ``CommandLoadError`` naming it, and the env goes on."""
        name = getattr(fn, "__qualname__", repr(fn))
        message = ("apply", (fn, args, kwargs))
        try:
            first, by_reference = bytes(ForkingPickler.dumps(message)), True
        except Exception as exc:  # a lambda or a local function: by value, if cloudpickle takes it
            first, by_reference = pickled_by_value(message), False
            if first is None:
                raise TypeError(
                    f"apply: {name!r} and its arguments must pickle to reach the worker processes: {exc}"
                ) from exc
        try:
            return self.workers.all_pickled([first] * self.processes)
        except CommandLoadError as exc:  # the workers lack it (defined after they forked): by value
            again = pickled_by_value(message) if by_reference and exc.nowhere else None
            if again is None:
                raise _not_loaded(name, exc) from exc
        try:
            return self.workers.all_pickled([again] * self.processes)
        except CommandLoadError as exc:
            raise _not_loaded(name, exc) from exc

    def _render(self) -> tuple[Any, ...]:
        return tuple(f for part in self.workers.methods("render", [()] * self.processes) for f in part)

    def __del__(self) -> None:
        if "workers" in self.__dict__:
            self.workers.stop()


class RemoteScene:
    """Scene ``index`` of a :class:`SplitEgoEnv`: attributes are read from (and methods called on) the
    scene in its worker (see :class:`~trajeglish_env.env.vector.EgoScene`); values come back as copies.
    It holds its env weakly, so that dropping the env stops its workers at once."""

    def __init__(self, owner: SplitEgoEnv, index: int):
        object.__setattr__(self, "_ref", weakref.ref(owner))
        object.__setattr__(self, "_index", index)

    @property
    def _owner(self) -> SplitEgoEnv:
        owner = self._ref()
        if owner is None:
            raise RuntimeError("SplitEgoEnv is gone: this scene proxy outlived its env")
        return owner

    @property
    def unwrapped(self) -> RemoteScene:
        return self

    def _ask(self, command: str, *args: Any) -> Any:
        workers, index = self._owner.workers, self._index
        shard = workers.shard_of(index)
        return workers.ask(shard, command, (index - workers.shards[shard].start, *args))

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        value = self._ask("scene_get", name)
        if isinstance(value, _Method):
            return lambda *args, **kwargs: self._ask("scene_call", name, args, kwargs)
        return value

    def __setattr__(self, name: str, value: Any) -> None:
        self._ask("scene_set", name, value)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        """Start this scene's next episode in its worker (the others go on where they are)."""
        obs, info = self._ask("scene_call", "reset", (), {"seed": seed, "options": options})
        self._owner.agents[self._index] = info["agent"]
        return obs, info


class SplitEgoEnv(SplitWorkers, EgoVectorEnv):
    """``num_envs`` single-ego scenes in ``processes`` forked workers (arguments as
    :class:`~trajeglish_env.env.vector.BatchedEgoEnv`; each worker runs one torch thread: ``torch_threads``
    ``"auto"``, None or 1). Same-step autoreset."""

    def __init__(
        self,
        num_envs: int,
        scenes: Any = None,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        torch_threads: int | str | None = "auto",
        processes: int = 2,
        **options: Any,
    ):
        method = start_method(config, options)
        config = prepared_config(config, options, "SplitEgoEnv", num_envs)
        check_single(config)
        shard = (scene_set(scenes), config, render_mode, torch_threads)
        spaces = self._start(BatchedEgoEnv, num_envs, processes, shard, _ego_spaces, method)
        self.render_mode = render_mode
        self._set_spaces(*spaces)
        self.agents = [""] * self.num_envs
        self.envs = [RemoteScene(self, i) for i in range(self.num_envs)]

    def _split(self, values: Sequence[Any]) -> list[tuple[Any, ...]]:
        return [(list(values[s.start : s.stop]),) for s in self.shards]

    def reset_each(
        self,
        seeds: Sequence[int | None],
        options: Sequence[dict[str, Any] | None],
        scenes: Sequence[int] | None = None,
    ) -> tuple[list[np.ndarray], list[dict[str, Any]]]:
        """Reset scene i with ``seeds[i]`` and ``options[i]``, for every i of ``scenes`` (None: all); every
        scene's observation and the reset scenes' infos, in scene order."""
        if len(seeds) != self.num_envs or len(options) != self.num_envs:
            raise ValueError(f"reset_each: expected {self.num_envs} seeds and options (one per scene)")
        chosen = sorted(range(self.num_envs) if scenes is None else scenes)
        args = [
            (
                list(seeds[s.start : s.stop]),
                list(options[s.start : s.stop]),
                [k - s.start for k in chosen if s.start <= k < s.stop],
            )
            for s in self.shards
        ]
        observations, infos = [], []
        for obs, info in self.workers.methods("reset_each", args):
            observations += obs
            infos += info
        for k, info in zip(chosen, infos, strict=True):
            self.agents[k] = info["agent"]
        return observations, infos

    def step_each(self, actions: Any) -> list[tuple[Any, float, bool, bool, dict[str, Any], Any]]:
        """Step every scene (every action checked before any worker moves); per scene ``(obs, reward,
        terminated, truncated, info, final)`` as :meth:`BatchedEgoEnv.step_each`."""
        if len(actions) != self.num_envs:
            raise ValueError(f"step: expected {self.num_envs} actions (one per scene), got {len(actions)}")
        if not all(self.agents):
            raise RuntimeError("call reset() before step()")
        values = [
            check_action(self.single_action_space, a, name)
            for a, name in zip(actions, self.agents, strict=True)
        ]
        results = [r for part in self.workers.methods("step_each", self._split(values)) for r in part]
        self.agents = [
            info["agent"] if final is not None else name
            for name, (*_, info, final) in zip(self.agents, results, strict=True)
        ]
        return results

    def render(self) -> tuple[Any, ...] | None:
        """Frames of every scene (``rgb_array``)."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        return self._render()

    def close_extras(self, **kwargs: Any) -> None:
        """Stop the workers (each closes its env first)."""
        self.workers.stop()


def _parallel_spaces(env: BatchedParallelEnv) -> tuple[gymnasium.Space, tuple[str, int]]:
    return env._observation, env._actions


def _reset_scenes(
    env: BatchedParallelEnv, indices: list[int], seeds: list[int | None], options: dict[str, Any] | None
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[list[str]], list[str | None]]:
    """A shard's ``reset_scenes`` with explicit seeds, and its scenes' agents and scenario ids after it."""
    obs, infos = env.reset_scenes(indices, seeds, options) if indices else ([], [])
    return obs, infos, env.agents, env._scenario_ids


def _step(
    env: BatchedParallelEnv, actions: list[dict[str, Any]]
) -> tuple[tuple[list[Any], ...], list[list[str]]]:
    """A shard's ``step``, and its scenes' agents after it."""
    return env.step(actions), env.agents


class SplitParallelEnv(SplitWorkers, ParallelBatchAPI):
    """``num_envs`` multi-agent scenes in ``processes`` forked workers, with
    :class:`~trajeglish_env.env.vector.BatchedParallelEnv`'s API (lists with one entry per scene; arguments
    as it, one torch thread per worker as in :class:`SplitEgoEnv`)."""

    def __init__(
        self,
        num_envs: int,
        scenes: Any = None,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        torch_threads: int | str | None = "auto",
        processes: int = 2,
        **options: Any,
    ):
        method = start_method(config, options)
        config = prepared_config(config, options, "SplitParallelEnv", num_envs)
        shard = (scene_set(scenes), config, render_mode, torch_threads)
        start = self._start(BatchedParallelEnv, num_envs, processes, shard, _parallel_spaces, method)
        self._observation, self._actions = start
        self.render_mode = render_mode
        self.agents: list[list[str]] = [[] for _ in range(self.num_envs)]
        self.episode_agents: list[set[str]] = [set() for _ in range(self.num_envs)]  # live or finished
        self._scenario_ids: list[str | None] = [None] * self.num_envs  # named in action errors

    def _reset_scenes(
        self, indices: list[int], seeds: list[int | None], options: dict[str, Any] | None
    ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        """The listed scenes restarted in their workers (see :meth:`ParallelBatchAPI.reset_scenes`)."""
        per_shard: list[tuple[list[int], list[int | None]]] = [([], []) for _ in self.shards]
        for i, s in zip(indices, seeds, strict=True):
            k = self.workers.shard_of(i)
            per_shard[k][0].append(i - self.shards[k].start)
            per_shard[k][1].append(s)
        args = [(_reset_scenes, (local, shard_seeds, options), {}) for local, shard_seeds in per_shard]
        answers = self.workers.all("apply", args)
        found: dict[int, tuple[dict[str, Any], dict[str, Any]]] = {}
        for k, (obs, infos, agents, ids) in enumerate(answers):
            start = self.shards[k].start
            self.agents[start : start + len(agents)] = [list(a) for a in agents]
            self._scenario_ids[start : start + len(ids)] = ids
            for j, local in enumerate(per_shard[k][0]):
                found[start + local] = (obs[j], infos[j])
        for i in indices:
            self.episode_agents[i] = set(self.agents[i])
        return [found[i][0] for i in indices], [found[i][1] for i in indices]

    def step(self, actions: Sequence[dict[str, Any]]) -> tuple[list[dict[str, Any]], ...]:
        """One timestep of every scene that has agents (every action checked here before any worker
        moves); per-scene lists of observations, rewards, terminations, truncations and infos."""
        check_scene_actions(self.agents, actions, self.action_space, self.episode_agents, self._scenario_ids)
        args = [(_step, (list(actions[s.start : s.stop]),), {}) for s in self.shards]
        out: tuple[list[dict[str, Any]], ...] = ([], [], [], [], [])
        for k, (results, agents) in enumerate(self.workers.all("apply", args)):
            for column, part in zip(out, results, strict=True):
                column.extend(part)
            start = self.shards[k].start
            self.agents[start : start + len(agents)] = [list(a) for a in agents]
        return out

    def render(self) -> tuple[Any, ...] | None:
        """Frames of every scene (``rgb_array``; None for a finished scene)."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        return self._render()

    def close(self) -> None:
        """Stop the workers (each closes its env first)."""
        self.workers.stop()
