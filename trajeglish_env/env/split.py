"""A batched ego env whose scenes are split over worker processes: ``B`` scenes in ``P`` contiguous shards,
each a :class:`~trajeglish_env.env.vector.BatchedEgoEnv` in its own forked process with its own torch
threads, stepped at once. On a machine whose cores are free this outruns one process of B scenes with
several torch threads (decoding calls of B / P rows on one core each scale better than B rows over P
threads, and the NumPy geometry of the guard, one core in one process, runs in every shard at once).

Semantics are :class:`BatchedEgoEnv`'s, bit for bit: scene ``i`` reset with seed ``s`` plays what scene
``i`` of a one-process batch plays (a scene's results do not depend on the others of its batch). Per-scene
tools (``envs[i].agent``, ``envs[i].action_towards(...)``, SB3's ``get_attr`` / ``env_method``) reach into
the scene's worker; :meth:`SplitEgoEnv.apply` runs a function on every shard where its scenes live (no copy
of the simulations comes back). Workers are forked, so this needs Linux
(:func:`~trajeglish_env.cores.can_fork`) and a model on the CPU.
"""

from __future__ import annotations

import multiprocessing
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium
import numpy as np

from trajeglish_env.cores import can_fork, others_busy_cores, threads_for, usable_cores
from trajeglish_env.env.actions import check_action
from trajeglish_env.env.config import EnvConfig
from trajeglish_env.env.gym_ego import check_single
from trajeglish_env.env.scene_batch import load_npc_checkpoint, trajeglish_settings
from trajeglish_env.env.scenes import scene_set
from trajeglish_env.env.vector import BatchedEgoEnv, EgoVectorEnv

__all__ = ["MIN_SCENES_PER_PROCESS", "SplitEgoEnv", "auto_env_processes", "batched_ego_env"]

# "auto" gives each process at least this many scenes (measured, 2 cores, 24-agent scenes, guarded NPCs:
# two processes beat one with 2 threads by 11 % at B = 8, 18 % at 16, 32 % at 32, 23 % at 128)
MIN_SCENES_PER_PROCESS = 4


def auto_env_processes(num_envs: int) -> int:
    """Processes for ``num_envs`` scenes: the usable cores other processes leave free (looked at over a
    quarter of a second), at most one per :data:`MIN_SCENES_PER_PROCESS` scenes; 1 where workers cannot be
    forked."""
    most = num_envs // MIN_SCENES_PER_PROCESS
    if most < 2 or usable_cores() < 2 or not can_fork():
        return 1
    return threads_for(others_busy_cores(), most, usable_cores())


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
    (``"auto"``: :func:`auto_env_processes`, one process when that is 1 or the NPC model is on a GPU)."""
    settings = trajeglish_settings(options.get("npc", (config or EnvConfig()).npc))
    if processes == "auto" and settings is not None and settings.device not in (None, "cpu"):
        processes = 1  # a model on another device decodes every scene in one process
    count = _checked_processes(processes, num_envs)
    if count == 1:
        return BatchedEgoEnv(num_envs, scenes, config, render_mode, torch_threads, **options)
    return SplitEgoEnv(num_envs, scenes, config, render_mode, torch_threads, processes=count, **options)


def _checked_processes(processes: int | str, num_envs: int) -> int:
    if processes == "auto":
        return auto_env_processes(int(num_envs))
    if isinstance(processes, bool) or not isinstance(processes, (int, np.integer)) or processes < 1:
        raise ValueError(f"processes must be a positive int or 'auto', got {processes!r}")
    return int(processes)


class _Method:
    """What a worker answers for an attribute that is a method: the proxy then calls it remotely."""


def _serve(conn: Any, build: Callable[[], BatchedEgoEnv]) -> None:
    """A shard's loop in its worker: build the env, answer ``ready`` with its spaces, then run commands
    until ``close`` (an error is sent back with its traceback, and the worker goes on)."""
    try:
        env = build()
        conn.send(("ok", (env.single_observation_space, env.single_action_space)))
    except BaseException as error:
        conn.send(("error", _portable(error)))
        conn.close()
        return
    while True:
        try:
            command, args = conn.recv()
        except (EOFError, KeyboardInterrupt):
            break
        if command == "close":
            env.close()
            conn.send(("ok", None))
            break
        try:
            conn.send(("ok", _run(env, command, args)))
        except BaseException as error:
            conn.send(("error", _portable(error)))
    conn.close()


def _run(env: BatchedEgoEnv, command: str, args: tuple[Any, ...]) -> Any:
    """One command of the parent on a shard's env."""
    if command == "reset_each":
        return env.reset_each(*args)
    if command == "step_each":
        return env.step_each(*args)
    if command == "render":
        return env.render()
    if command == "apply":
        fn, fn_args, fn_kwargs = args
        return fn(env, *fn_args, **fn_kwargs)
    scene, name = args[0], args[1]
    target = env.envs[scene]
    if command == "getattr":
        value = getattr(target, name)
        return _Method() if callable(value) else value
    if command == "call":
        return getattr(target, name)(*args[2], **args[3])
    if command == "setattr":
        setattr(target, name, args[2])
        return None
    raise ValueError(f"unknown worker command {command!r}")


def _portable(error: BaseException) -> BaseException:
    """The error itself if it survives pickling (so the parent raises the same type), else a RuntimeError
    with its text; either way carrying the worker's traceback as a note."""
    import pickle

    text = "".join(traceback.format_exception(error))
    try:
        pickle.loads(pickle.dumps(error))
        portable = error
    except Exception:
        portable = RuntimeError(f"{type(error).__name__}: {error}")
    portable.__notes__ = [*getattr(portable, "__notes__", []), f"in the worker process:\n{text}"]
    return portable


class RemoteScene:
    """Scene ``index`` of a :class:`SplitEgoEnv`: attributes are read from (and methods called on) the
    scene in its worker (see :class:`~trajeglish_env.env.vector.EgoScene`); values come back as copies."""

    def __init__(self, owner: SplitEgoEnv, index: int):
        object.__setattr__(self, "_owner", owner)
        object.__setattr__(self, "_index", index)

    @property
    def unwrapped(self) -> RemoteScene:
        return self

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        owner, index = self._owner, self._index
        value = owner._scene_command("getattr", index, name)
        if isinstance(value, _Method):
            return lambda *args, **kwargs: owner._scene_command("call", index, name, args, kwargs)
        return value

    def __setattr__(self, name: str, value: Any) -> None:
        self._owner._scene_command("setattr", self._index, name, value)


class SplitEgoEnv(EgoVectorEnv):
    """``num_envs`` single-ego scenes in ``processes`` forked workers (arguments as
    :class:`~trajeglish_env.env.vector.BatchedEgoEnv`; ``torch_threads`` is each worker's: ``"auto"`` gives
    a worker the usable cores divided among the workers, at least one). Same-step autoreset."""

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
        count = _checked_processes(processes, num_envs)
        if not isinstance(num_envs, (int, np.integer)) or num_envs < count:
            raise ValueError(f"SplitEgoEnv: num_envs must be an int >= processes ({count}), got {num_envs!r}")
        if not can_fork():
            raise RuntimeError("SplitEgoEnv forks its workers, which needs Linux; use BatchedEgoEnv")
        config = (config or EnvConfig()).with_overrides(**options)
        check_single(config)
        settings = trajeglish_settings(config.npc)
        if settings is not None:  # load (and check) the model once, here: the workers share its memory
            checkpoint = load_npc_checkpoint(settings.checkpoint, settings.device)
            if next(checkpoint.model.parameters()).device.type != "cpu":
                raise ValueError("SplitEgoEnv: the NPC model must be on the CPU (a CUDA context cannot fork)")
            config = config.with_overrides(npc=settings.with_checkpoint(checkpoint))
        scene_source = scene_set(scenes)
        if torch_threads == "auto":
            torch_threads = max(1, usable_cores() // count)
        self.num_envs, self.processes = int(num_envs), count
        self.render_mode = render_mode
        bounds = np.linspace(0, self.num_envs, count + 1).round().astype(int)
        self.shards = [range(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
        context = multiprocessing.get_context("fork")
        self._conns: list[Any] = []
        self._workers: list[Any] = []
        self._stopped = False
        try:
            for shard in self.shards:
                parent, child = context.Pipe()

                def build(n: int = len(shard)) -> BatchedEgoEnv:
                    return BatchedEgoEnv(n, scene_source, config, render_mode, torch_threads)

                worker = context.Process(target=_serve, args=(child, build), daemon=True)
                worker.start()
                child.close()
                self._conns.append(parent)
                self._workers.append(worker)
            spaces = [self._receive(k) for k in range(count)]
        except BaseException:
            self._stop()
            raise
        self._set_spaces(*spaces[0])
        self.agents = [""] * self.num_envs
        self.envs = [RemoteScene(self, i) for i in range(self.num_envs)]

    # ------------------------------------------------------------------ the workers
    def _name(self, shard: int) -> str:
        scenes = self.shards[shard]
        return f"the worker of scenes {scenes.start}..{scenes.stop - 1}"

    def _died(self, shard: int) -> RuntimeError:
        worker = self._workers[shard]
        worker.join(timeout=1.0)
        return RuntimeError(f"SplitEgoEnv: {self._name(shard)} died (exit code {worker.exitcode})")

    def _send(self, shard: int, command: str, args: tuple[Any, ...]) -> None:
        if self._stopped:
            raise RuntimeError("SplitEgoEnv is closed")
        try:
            self._conns[shard].send((command, args))
        except (BrokenPipeError, OSError):
            raise self._died(shard) from None

    def _receive(self, shard: int) -> Any:
        """The answer of ``shard``'s worker; its error raised here, naming the shard's scenes."""
        try:
            status, payload = self._conns[shard].recv()
        except (EOFError, OSError):
            raise self._died(shard) from None
        if status == "error":
            payload.add_note(f"SplitEgoEnv: raised by {self._name(shard)}")
            raise payload
        return payload

    def _all(self, command: str, per_shard: Sequence[tuple[Any, ...]]) -> list[Any]:
        """Send ``command`` to every worker (its own arguments each), then gather their answers in order."""
        for k, args in enumerate(per_shard):
            self._send(k, command, args)
        answers, error = [], None
        for k in range(self.processes):  # every answer is read, so the pipes stay in step after an error
            try:
                answers.append(self._receive(k))
            except BaseException as exc:
                error = error or exc
        if error is not None:
            raise error
        return answers

    def _scene_command(self, command: str, scene: int, *args: Any) -> Any:
        """One command on scene ``scene`` in its worker."""
        shard = next(k for k, s in enumerate(self.shards) if scene in s)
        self._send(shard, command, (scene - self.shards[shard].start, *args))
        return self._receive(shard)

    def _split(self, values: Sequence[Any]) -> list[tuple[Any, ...]]:
        return [(list(values[s.start : s.stop]),) for s in self.shards]

    def apply(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> list[Any]:
        """``fn(shard_env, *args, **kwargs)`` in every worker (``shard_env``: the shard's BatchedEgoEnv,
        whose scene ``j`` is scene ``shards[k].start + j`` here); the results, one per shard. ``fn`` must
        pickle (a module-level function)."""
        return self._all("apply", [(fn, args, kwargs)] * self.processes)

    # ------------------------------------------------------------------ the VectorEnv API
    def reset_each(
        self, seeds: Sequence[int | None], options: Sequence[dict[str, Any] | None]
    ) -> tuple[list[np.ndarray], list[dict[str, Any]]]:
        """Reset scene i with ``seeds[i]`` and ``options[i]``; per-scene observations and infos."""
        if len(seeds) != self.num_envs or len(options) != self.num_envs:
            raise ValueError(f"reset_each: expected {self.num_envs} seeds and options (one per scene)")
        args = [(list(seeds[s.start : s.stop]), list(options[s.start : s.stop])) for s in self.shards]
        observations, infos = [], []
        for obs, info in self._all("reset_each", args):
            observations += obs
            infos += info
        self.agents = [info["agent"] for info in infos]
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
        results = [r for part in self._all("step_each", self._split(values)) for r in part]
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
        return tuple(frame for part in self._all("render", [()] * self.processes) for frame in part)

    def close_extras(self, **kwargs: Any) -> None:
        """Stop the workers (each closes its env first)."""
        self._stop()

    def _stop(self) -> None:
        if self._stopped:
            return
        self._stopped = True
        for conn in self._conns:
            try:
                conn.send(("close", ()))
            except (BrokenPipeError, OSError):
                pass
        for conn, worker in zip(self._conns, self._workers, strict=False):
            try:
                if conn.poll(5.0):
                    conn.recv()
            except (EOFError, OSError):
                pass
            worker.join(timeout=5.0)
            if worker.is_alive():
                worker.terminate()
                worker.join()
            conn.close()

    def __del__(self) -> None:
        if "_stopped" in self.__dict__:
            self._stop()
