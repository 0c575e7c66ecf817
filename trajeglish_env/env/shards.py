"""Scenes of a batched env in forked worker processes: contiguous shards of the scenes, each a batched env
(:class:`~trajeglish_env.env.vector.BatchedEgoEnv` or :class:`~trajeglish_env.env.vector.BatchedParallelEnv`)
in its own process, driven over a pipe by the split envs of :mod:`~trajeglish_env.env.split`.

A worker answers each command with ``("ok", result)`` or ``("error", exception)``: the exception keeps its
type when it pickles and carries the worker's traceback as a note, and the caller adds which scenes the
worker holds. A command the worker cannot unpickle (say a function of ``__main__`` defined after it forked)
is answered with a :class:`CommandLoadError`, and the worker goes on.
The caller counts the answers it has not read yet (a command interrupted by Ctrl-C, an
error in another worker) and reads them before its next command, and pickles every worker's command
before it sends any, so the pipes stay in step; a worker that dies is an error naming its scenes, not a
hang. Workers are forked (Linux, :func:`~trajeglish_env.cores.can_fork`), so they share the caller's
loaded model and scenes, unless the model is meant for a GPU: a CUDA context cannot fork, so they are then
spawned, get a pickled CPU copy of the model and scenes, and each moves its model to the GPU
(:func:`start_method`). They run one torch thread each (OpenMP is not fork-safe: a forked child that
uses several threads after its parent did can hang), ignore Ctrl-C (the caller handles it), and end when
the caller's pipe closes or the caller dies.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import replace
from multiprocessing.reduction import ForkingPickler
from typing import Any

import numpy as np

from trajeglish_env.cores import can_fork, others_busy_cores, threads_for, usable_cores
from trajeglish_env.env.config import EnvConfig
from trajeglish_env.env.scene_batch import load_npc_checkpoint, trajeglish_settings
from trajeglish_env.worker_pool import die_with_parent

__all__ = [
    "MIN_SCENES_PER_PROCESS",
    "CommandLoadError",
    "ShardWorkers",
    "auto_env_processes",
    "checked_processes",
    "prepared_config",
]

# "auto" gives each process at least this many scenes (measured, 2 cores, 24-agent scenes, guarded NPCs:
# two processes beat one with 2 threads by 11 % at B = 8, 18 % at 16, 32 % at 32, 23 % at 128)
MIN_SCENES_PER_PROCESS = 4
# A GPU worker (spawned, with its own CUDA context and model copy) pays off from this many scenes: measured on
# an H200 at B = 1,024, 16 workers of 64 scenes ran 3.6x one process (28,661 against 7,956 agent-steps/s).
GPU_SCENES_PER_PROCESS = 64


def auto_env_processes(num_envs: int) -> int:
    """Processes for ``num_envs`` scenes: the usable cores other processes leave free (looked at over a
    quarter of a second), at most one per :data:`MIN_SCENES_PER_PROCESS` scenes; 1 where workers cannot be
    forked."""
    most = num_envs // MIN_SCENES_PER_PROCESS
    if most < 2 or usable_cores() < 2 or not can_fork():
        return 1
    return threads_for(others_busy_cores(), most, usable_cores())


def auto_gpu_processes(num_envs: int) -> int:
    """Spawned GPU workers for ``num_envs`` scenes of a model on a GPU: one per
    :data:`GPU_SCENES_PER_PROCESS` scenes, at most one per usable core (the host work of the guard and the
    env is what they spread); 1 below two workers' worth."""
    return max(1, min(num_envs // GPU_SCENES_PER_PROCESS, usable_cores()))


def checked_processes(processes: int | str, num_envs: int) -> int:
    """A process count: a positive int, or ``"auto"`` resolved by :func:`auto_env_processes`."""
    if processes == "auto":
        return auto_env_processes(int(num_envs))
    if isinstance(processes, bool) or not isinstance(processes, (int, np.integer)) or processes < 1:
        raise ValueError(f"processes must be a positive int or 'auto', got {processes!r}")
    return int(processes)


def on_gpu(config: EnvConfig | None, options: dict[str, Any]) -> bool:
    """Whether the env's NPC model is meant for a device other than the CPU (``TrajeglishNPC.device``, or a
    loaded checkpoint already there): such a model never forks."""
    import torch

    settings = trajeglish_settings(options.get("npc", (config or EnvConfig()).npc))
    if settings is None:
        return False
    if settings.device is not None:
        return torch.device(settings.device).type != "cpu"
    model = getattr(settings.checkpoint, "model", None)
    return model is not None and next(model.parameters()).device.type != "cpu"


def start_method(config: EnvConfig | None, options: dict[str, Any]) -> str:
    """How the workers of an env start: ``"spawn"`` (fresh interpreters, each putting the model on its
    GPU) for a model meant for a GPU, since a CUDA context cannot fork; else ``"fork"`` (the workers share
    the caller's loaded model and scenes)."""
    return "spawn" if on_gpu(config, options) else "fork"


def prepared_config(
    config: EnvConfig | None, options: dict[str, Any], where: str, num_envs: int
) -> EnvConfig:
    """The env's config with its NPC model loaded (and checked) here, once. Forked workers share it; for a
    model meant for a GPU the copy sent to the spawned workers is a CPU one (nothing here touches the GPU)
    and ``TrajeglishNPC.device`` names the GPU, so each worker moves the model there itself. The sampling's
    ``compute_dtype="auto"`` is resolved for all ``num_envs`` scenes, so that every shard decodes as one
    process of them would (:meth:`~trajeglish_env.sampler.config.SamplingConfig.for_rows`)."""
    import torch

    gpu = on_gpu(config, options)
    config = (config or EnvConfig()).with_overrides(**options)
    settings = trajeglish_settings(config.npc)
    if settings is None:
        return config
    device = settings.device
    if gpu and device is None:  # a loaded checkpoint already on a GPU: the workers use that device
        device = str(next(settings.checkpoint.model.parameters()).device)
    if gpu and torch.device(device).type != "cuda":
        raise RuntimeError(
            f"{where}: workers put the NPC model on a CUDA device or keep it on the CPU, got {device!r}"
        )
    if gpu and not torch.cuda.is_available():
        raise RuntimeError(f"{where}: the NPC model's device {device!r} needs CUDA, which this machine lacks")
    checkpoint = load_npc_checkpoint(settings.checkpoint, "cpu" if gpu else device)
    sampling = settings.sampling.for_rows(num_envs)
    npc = replace(settings.with_checkpoint(checkpoint), device=device, sampling=sampling)
    return config.with_overrides(npc=npc)


class CommandLoadError(RuntimeError):
    """A worker could not unpickle a command sent to it (e.g. a reference to a function its ``__main__``
    lacks): the command did not run, and the worker goes on. ``nowhere``: no worker of the call ran it."""

    nowhere = False


def pickled_by_value(message: Any) -> bytes | None:
    """``message`` pickled by cloudpickle, which sends functions and classes of ``__main__`` (even ones
    defined after the workers forked), lambdas and closures by value with the globals they use; None where
    cloudpickle is not installed or cannot take it."""
    try:
        import cloudpickle
    except ImportError:
        return None
    try:
        return bytes(cloudpickle.dumps(message))
    except Exception:
        return None


class _Method:
    """What a worker answers for a scene attribute that is a method: the proxy then calls it remotely."""


def _portable(error: BaseException) -> BaseException:
    """The error itself if it survives pickling (so the caller raises the same type), else a RuntimeError
    with its text; either way carrying the worker's traceback as a note."""
    text = "".join(traceback.format_exception(error))
    try:
        pickle.loads(pickle.dumps(error))
        portable = error
    except Exception:
        portable = RuntimeError(f"{type(error).__name__}: {error}")
    portable.__notes__ = [*getattr(portable, "__notes__", []), f"in the worker process:\n{text}"]
    return portable


def _run(env: Any, command: str, args: tuple[Any, ...]) -> Any:
    """One command of the caller on a shard's env."""
    if command == "method":  # a method of the shard's env
        name, call_args, kwargs = args
        return getattr(env, name)(*call_args, **kwargs)
    if command == "apply":  # a function of the caller's on the shard's env
        fn, call_args, kwargs = args
        return fn(env, *call_args, **kwargs)
    target = env.envs[args[0]]  # one scene (ego envs)
    if command == "scene_get":
        value = getattr(target, args[1])
        return _Method() if callable(value) else value
    if command == "scene_call":
        return getattr(target, args[1])(*args[2], **args[3])
    if command == "scene_set":
        setattr(target, args[1], args[2])
        return None
    raise ValueError(f"unknown worker command {command!r}")


def _serve(
    conn: Any,
    build: Callable[[], Any],
    describe: Callable[[Any], Any],
    inherited: Sequence[Any],
    parent: int | None,
) -> None:
    """A shard's loop in its worker: build the env, answer with ``describe(env)``, then run commands until
    ``close`` (an error is sent back and the worker goes on). ``inherited``: the caller's ends of the
    pipes, closed here so that the worker sees the caller go; ``parent``: see
    :func:`~trajeglish_env.worker_pool.die_with_parent`."""
    import torch

    for other in inherited:
        other.close()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent(parent)
    torch.set_num_threads(1)
    try:
        env = build()
        conn.send(("ok", describe(env)))
    except BaseException as error:
        conn.send(("error", _portable(error)))
        conn.close()
        return
    while True:
        try:
            data = conn.recv_bytes()
        except (EOFError, KeyboardInterrupt, OSError):  # the caller closed its end, or is gone (killed)
            break
        try:  # unpickled apart, so that a command this process cannot load is its error, not the worker's end
            command, args = pickle.loads(data)
        except Exception as error:
            if not _reply(conn, ("error", CommandLoadError(f"{type(error).__name__}: {error}"))):
                break
            continue
        if command == "close":
            env.close()
            _reply(conn, ("ok", None))
            break
        try:
            reply = ("ok", _run(env, command, args))
        except BaseException as error:  # the command's own error (an OSError too) goes back to the caller
            reply = ("error", _portable(error))
        if not _reply(conn, reply):
            break
    conn.close()


def _reply(conn: Any, message: tuple[str, Any]) -> bool:
    """Send ``message``; a result that does not pickle is sent as its error instead. False where the caller
    is gone (its end of the pipe broke: the worker leaves quietly, without a traceback)."""
    try:
        conn.send(message)
    except (BrokenPipeError, ConnectionError, EOFError):
        return False
    except Exception as error:  # pickling the result failed: nothing was written
        try:
            conn.send(("error", _portable(error)))
        except (BrokenPipeError, ConnectionError, EOFError):
            return False
    return True


class ShardWorkers:
    """``len(builders)`` workers, worker ``k`` serving the env ``builders[k]()`` for the scenes
    ``shards[k]``; ``described[k]`` is ``describe(env)`` of each (e.g. its spaces). ``owner`` names the
    split env in errors. ``method``: ``"fork"``, or ``"spawn"`` (see :func:`start_method`; the builders
    and ``describe`` must then pickle, and a script that makes the env needs an ``if __name__ ==
    "__main__":`` guard, as for any spawned process)."""

    def __init__(
        self,
        shards: Sequence[range],
        builders: Sequence[Callable[[], Any]],
        describe: Callable[[Any], Any],
        owner: str,
        method: str = "fork",
    ):
        if method not in ("fork", "spawn"):
            raise ValueError(f"{owner}: start method must be 'fork' or 'spawn', got {method!r}")
        if method == "fork" and not can_fork():
            raise RuntimeError(f"{owner} forks its workers, which needs Linux; use the one-process env")
        self.shards, self.owner, self.method = list(shards), owner, method
        context = multiprocessing.get_context(method)
        self.conns: list[Any] = []
        self.workers: list[Any] = []
        self.pending: list[int] = []  # answers sent but not read yet, per worker
        self.stopped = False
        main = threading.current_thread() is threading.main_thread()
        try:
            for build in builders:
                parent, child = context.Pipe()
                inherited = [*self.conns, parent] if method == "fork" else []  # spawn inherits none
                args = (child, build, describe, inherited, os.getpid() if main else None)
                worker = context.Process(target=_serve, args=args, daemon=True)
                worker.start()
                child.close()
                self.conns.append(parent)
                self.workers.append(worker)
                self.pending.append(1)  # its description
            self.described = [self.receive(k) for k in range(len(self.shards))]
        except BaseException:
            self.stop()
            raise

    def __len__(self) -> int:
        return len(self.shards)

    def name(self, shard: int) -> str:
        scenes = self.shards[shard]
        return f"the worker of scenes {scenes.start}..{scenes.stop - 1}"

    def shard_of(self, scene: int) -> int:
        """The shard holding scene ``scene``."""
        for k, scenes in enumerate(self.shards):
            if scene in scenes:
                return k
        raise IndexError(f"{self.owner}: scene {scene} out of range for {self.shards[-1].stop} scenes")

    def _died(self, shard: int) -> RuntimeError:
        worker = self.workers[shard]
        worker.join(timeout=1.0)
        return RuntimeError(f"{self.owner}: {self.name(shard)} died (exit code {worker.exitcode})")

    def _send_bytes(self, shard: int, message: bytes) -> None:
        """Send a pickled command, after reading (and dropping) the answers left unread before."""
        if self.stopped:
            raise RuntimeError(f"{self.owner} is closed")
        while self.pending[shard]:
            self._read(shard)
        try:
            self.conns[shard].send_bytes(message)
        except (BrokenPipeError, OSError):
            raise self._died(shard) from None
        self.pending[shard] += 1

    def send(self, shard: int, command: str, args: tuple[Any, ...]) -> None:
        self._send_bytes(shard, bytes(ForkingPickler.dumps((command, args))))

    def _read(self, shard: int) -> tuple[str, Any]:
        """The next answer of ``shard``'s worker. Waiting can be interrupted (Ctrl-C) and reads nothing;
        once an answer arrives it is read whole with SIGINT held back, and counted before it is unpickled,
        so the pipe stays in step whatever happens."""
        conn = self.conns[shard]
        try:
            conn.poll(None)
            held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
            try:
                data = conn.recv_bytes()
                self.pending[shard] -= 1
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, held)
        except (EOFError, OSError):
            raise self._died(shard) from None
        return ForkingPickler.loads(data)

    def receive(self, shard: int) -> Any:
        """The answer of ``shard``'s worker; its error raised here, naming the shard's scenes."""
        if not self.pending[shard]:
            raise RuntimeError(f"{self.owner}: no command is waiting for {self.name(shard)}")
        status, payload = self._read(shard)
        if status == "error":
            if isinstance(payload, CommandLoadError):  # nothing ran: the scenes go in the message itself
                raise CommandLoadError(f"{self.owner}: {self.name(shard)} could not load it: {payload}")
            payload.add_note(f"{self.owner}: raised by {self.name(shard)}")
            raise payload
        return payload

    def ask(self, shard: int, command: str, args: tuple[Any, ...]) -> Any:
        """One command to one worker, and its answer."""
        self.send(shard, command, args)
        return self.receive(shard)

    def all(self, command: str, per_shard: Sequence[tuple[Any, ...]]) -> list[Any]:
        """``command`` to every worker (its own arguments each; all pickled before any is sent), run at
        once; their answers in order."""
        return self.all_pickled([bytes(ForkingPickler.dumps((command, args))) for args in per_shard])

    def all_pickled(self, messages: Sequence[bytes]) -> list[Any]:
        """A pickled command (``(command, args)``) to every worker, its own each, run at once; their
        answers in order."""
        for k, message in enumerate(messages):
            self._send_bytes(k, message)
        answers, errors = [], []
        for k in range(len(self.shards)):  # every answer is read after an error (Ctrl-C stops at once: the
            try:  # answers left are read before the next command)
                answers.append(self.receive(k))
            except Exception as exc:
                errors.append(exc)
        if errors:
            if len(errors) == len(self.shards) and all(isinstance(e, CommandLoadError) for e in errors):
                errors[0].nowhere = True  # no worker ran it: the caller may send it again another way
            raise errors[0]
        return answers

    def methods(self, name: str, per_shard: Sequence[tuple[Any, ...]]) -> list[Any]:
        """Method ``name`` of every shard's env, with its own positional arguments each."""
        return self.all("method", [(name, args, {}) for args in per_shard])

    def stop(self, wait_s: float = 5.0) -> None:
        """Close every shard's env and end its worker (idempotent): the answers still coming are read and
        dropped, and a worker that has not ended after ``wait_s`` is terminated."""
        if self.stopped:
            return
        self.stopped = True
        for conn in self.conns:
            try:
                conn.send(("close", ()))
            except (BrokenPipeError, OSError):
                pass
        deadline = time.monotonic() + wait_s
        for conn, worker in zip(self.conns, self.workers, strict=False):
            try:
                while worker.is_alive() and time.monotonic() < deadline:
                    if conn.poll(0.05):  # a worker blocked on a full pipe could not end
                        conn.recv_bytes()
            except Exception:
                pass
            finally:
                worker.join(timeout=max(0.0, deadline - time.monotonic()))
                if worker.is_alive():
                    worker.terminate()
                    worker.join()
                conn.close()


def shard_ranges(num_envs: int, processes: int) -> list[range]:
    """``processes`` contiguous, near-equal ranges of the scenes ``0 .. num_envs - 1``."""
    bounds = np.linspace(0, num_envs, processes + 1).round().astype(int)
    return [range(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def worker_threads(torch_threads: int | str | None, owner: str) -> int:
    """Each worker's torch threads: one (``"auto"``, None or 1); more is refused, since OpenMP is not
    fork-safe (a forked child using several threads after its parent did can hang)."""
    if torch_threads in ("auto", None, 1):
        return 1
    raise ValueError(
        f"{owner}: torch_threads must be 'auto', None or 1 (each worker runs one torch thread: OpenMP is not "
        f"fork-safe), got {torch_threads!r}; use more processes, or the one-process env for more threads"
    )
