"""The measurements of ``trajeglish bench``: each returns a dict of
figures (wall-clock rates; best of repeats where the machine may be shared)."""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from trajeglish_env.benchmark.workloads import (
    benchmark_scenes,
    model_checkpoint,
    noisy_rollouts,
    random_inputs,
    ring_scene,
)
from trajeglish_env.model import TrajeglishModel, preset
from trajeglish_env.model.masks import teacher_inputs
from trajeglish_env.training.precision import step_autocast

GUARDED = {"trajeglish": False, "trajeglish_guard": True}  # model NPCs of the env runs: guarded sampling?
MAX_ROUNDS = 32  # timed rounds of one env measurement at most (see env_speed's min_seconds)


def peak_rss_mb() -> float:
    """Peak resident memory of this process image so far (MB): VmHWM, which, unlike ``ru_maxrss``, does
    not inherit the parent's peak across fork + exec."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine() -> dict[str, Any]:
    """Cores and load: context for every figure."""
    return {"cpu_count": os.cpu_count(), "load_average_1min": round(os.getloadavg()[0], 2)}


def tokenizer_speed(
    agents: int = 20000,
    steps: int = 51,
    threads: Sequence[int] = (1, 2),
    repeats: int = 3,
    noise_agents: int = 2000,
    data: str | None = None,
) -> dict[str, Any]:
    """Tokenization agent-steps/s (exact argmin over the shipped 384 templates), per thread count, and
    of noisy tokenization; synthetic smooth trajectories of all classes unless ``data`` is given."""
    from trajeglish_env.scenario import AgentKind
    from trajeglish_env.tokenizer import NoiseConfig, load_default_tokenizer, tokenize
    from trajeglish_env.tokenizer.synthetic import synthetic_trajectories

    vocab = load_default_tokenizer()
    if data:
        from trajeglish_env.tokenizer.data import load_trajectories

        rows = load_trajectories(data)
        reps, take = -(-agents // rows.num_rows), slice(0, agents)
        xyh = np.tile(rows.xyh, (reps, 1, 1))[take]
        valid = np.tile(rows.valid, (reps, 1))[take]
        size = np.tile(rows.size, (reps, 1))[take]
        kind = np.tile(rows.kind, reps)[take]
    else:
        rng = np.random.default_rng(0)
        xyh, valid, size, kind = synthetic_trajectories(
            agents, steps, rng, kinds=tuple(AgentKind), max_speed=20.0
        )
    transitions = int((valid[:, 1:] & valid[:, :-1]).sum())
    result: dict[str, Any] = {
        "vocab_size": vocab.size,
        "agents": int(len(xyh)),
        "agent_steps": transitions,
        "threads": {},
    }
    for n in threads:
        walls, cpus = [], []
        for _ in range(repeats):
            wall0, cpu0 = time.perf_counter(), time.process_time()
            tokenize(vocab, xyh, valid, size, kind, threads=n)
            walls.append(time.perf_counter() - wall0)
            cpus.append(time.process_time() - cpu0)
        best = int(np.argmin(walls))
        result["threads"][str(n)] = {
            "seconds": round(walls[best], 3),
            "agent_steps_per_s": round(transitions / walls[best]),
            "agent_steps_per_cpu_s": round(transitions / cpus[best]),
        }
    k = min(noise_agents, len(xyh))
    wall0 = time.perf_counter()
    tokenize(vocab, xyh[:k], valid[:k], size[:k], kind[:k], noise=NoiseConfig(), rng=np.random.default_rng(0))
    noisy = int((valid[:k, 1:] & valid[:k, :-1]).sum())
    result["noisy_agent_steps_per_s"] = round(noisy / (time.perf_counter() - wall0))
    result["agent_steps_per_s"] = max(r["agent_steps_per_s"] for r in result["threads"].values())
    return result


def dataset_speed(data: Path, windows: int = 2000, batch: int = 32, workers: int = 2) -> dict[str, Any]:
    """Training windows per second of WindowDataset: one process, and through a DataLoader."""
    from torch.utils.data import DataLoader

    from trajeglish_env.training.dataset import WindowConfig, WindowDataset, collate_windows

    ds = WindowDataset(data, WindowConfig(), seed=0)
    n_scenes = len(ds)
    for i in range(n_scenes):  # warm the per-scene map-chunk cache, as an epoch of training does
        ds[i]
    start = time.perf_counter()
    for i in range(windows):
        ds.set_epoch(1 + i // n_scenes)
        ds[i % n_scenes]
    single = windows / (time.perf_counter() - start)
    result: dict[str, Any] = {"scenes": n_scenes, "windows_per_s_single_process": round(single, 1)}
    if workers > 0:
        loader = DataLoader(
            ds,
            batch_size=batch,
            num_workers=workers,
            collate_fn=collate_windows,
            persistent_workers=True,
            shuffle=True,
        )
        next(iter(loader))  # start the workers
        start, count = time.perf_counter(), 0
        for _ in range(max(1, windows // n_scenes)):
            for item in loader:
                count += item["agent_xyh"].shape[0]
        result[f"windows_per_s_dataloader_{workers}_workers"] = round(
            count / (time.perf_counter() - start), 1
        )
    return result


def training_speed(name: str = "small", batch: int = 8, steps: int = 5, precision: str = "float32") -> float:
    """Training tokens per second (forward, backward, AdamW step) of a preset on random full windows, in a
    training precision (:mod:`~trajeglish_env.training.precision`)."""
    cfg = preset(name)
    model = TrajeglishModel(cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    scene, tokens = random_inputs(cfg, batch)
    autocast = step_autocast(precision, torch.device("cpu"), cfg.d_model)
    with autocast:
        loss, _ = model.loss(scene, tokens, tokens)  # warm-up
    loss.backward()
    start = time.perf_counter()
    for _ in range(steps):
        with autocast:
            loss, n = model.loss(scene, tokens, tokens)
        loss.backward()
        opt.step()
        opt.zero_grad()
    return steps * n / (time.perf_counter() - start)


@torch.no_grad()
def decoding_speed(name: str = "small", probes: int = 32) -> dict[str, float]:
    """Decoding tokens/s of a 24-agent x 32-step sequence with the key/value cache, and without it (a
    full forward pass per token, timed at ``probes`` evenly spaced positions)."""
    cfg = preset(name, max_agents=24, steps=32)
    model = TrajeglishModel(cfg).eval()
    scene, tokens = random_inputs(cfg, 1)
    a, length = cfg.max_agents, cfg.max_agents * cfg.steps
    ids = model.global_ids(tokens, scene.agent_kind[:, :, None]).transpose(1, 2).reshape(1, -1)
    carried, own = teacher_inputs(cfg.variant, ids, a)
    one = np.ones(1, dtype=np.int64)
    start = time.perf_counter()
    cache = model.empty_cache(1, model.start.dtype)
    agents = model.encode_into(cache, scene)
    for p in range(length):
        hidden = model.decode_at(cache, agents, carried[:, p : p + 1], own[:, p : p + 1], p * one, one)
        model.class_logits(hidden, scene.agent_kind[:, [p % a]])
    cached = length / (time.perf_counter() - start)
    positions = torch.linspace(0, length - 1, probes).long().tolist()
    start = time.perf_counter()
    for p in positions:
        model(scene, tokens[:, :, : p // a + 1])  # the sequence up to the timestep of position p
    uncached = len(positions) / (time.perf_counter() - start)
    return {
        "decode_tokens_per_s_cached": round(cached, 1),
        "decode_tokens_per_s_uncached": round(uncached, 2),
        "cache_speedup": round(cached / uncached, 1),
    }


def metrics_time(
    agents: int = 128,
    rollouts: int = 32,
    evaluated: Sequence[int] = (8, 0),
    repeats: int = 3,
    config: str = "2025",
) -> dict[str, Any]:
    """Seconds to score ``rollouts`` rollouts of a synthetic ring-road scene with the realism metrics,
    for each number of scored agents (0: all)."""
    from trajeglish_env.metrics import score_rollouts

    scenario = ring_scene(agents)
    samples = noisy_rollouts(scenario, rollouts)
    result: dict[str, Any] = {"agents": agents, "rollouts": rollouts, "future_steps": int(samples.shape[2])}
    for n in evaluated:
        chosen = replace(scenario, tracks_to_predict=np.arange(1, n, dtype=np.int64))
        walls, cpus = [], []
        for _ in range(repeats):
            wall0, cpu0 = time.perf_counter(), time.process_time()
            scores = score_rollouts(chosen, samples, chosen.track_id, config)
            walls.append(time.perf_counter() - wall0)
            cpus.append(time.process_time() - cpu0)
        best = int(np.argmin(walls))
        result[f"{n}_evaluated" if n else "all_evaluated"] = {
            "evaluated_agents": scores.num_evaluated,
            "seconds": round(walls[best], 3),
            "cpu_seconds": round(cpus[best], 3),
            "metametric": round(scores.metametric, 6),
            "collision_rate": round(scores.collision_rate, 4),
            "offroad_rate": round(scores.offroad_rate, 4),
        }
    return result


def dtype_name(dtype: Any) -> str:
    """``torch.bfloat16`` -> ``"bfloat16"``."""
    return str(dtype).rsplit(".", 1)[-1]


def rollout_speed(ckpt: Any, scene: Any, rollouts: int, horizon: int, processes: int = 1) -> dict[str, Any]:
    """Simulated agent-steps/s of ``rollouts`` closed-loop rollouts of a scene (full control), split over
    ``processes`` processes (see :func:`~trajeglish_env.sampler.rollouts.rollout`)."""
    from trajeglish_env.sampler import SamplingConfig, rollout

    agents = int(scene.valid[:, scene.current_index].sum())
    config = SamplingConfig(seed=0)
    start = time.perf_counter()
    rollout(ckpt, scene, rollouts, horizon, config=config, processes=processes)
    seconds = time.perf_counter() - start
    return {
        "compute_dtype": dtype_name(config.torch_compute_dtype(rows=rollouts)),
        "agents": agents,
        "seconds": round(seconds, 2),
        "agent_steps_per_s": round(agents * horizon * rollouts / seconds, 1),
    }


def env_speed(
    num_envs: int,
    npc: str = "trajeglish",
    steps: int | None = None,
    agents: int = 24,
    warmup: int = 3,
    torch_threads: int | str | None = "auto",
    cache_dtype: str = "bfloat16",
    subsets: str = "overlap",
    compute_dtype: str = "auto",
    processes: int | str = 1,
    device: str = "cpu",
    checkpoint: Any = None,
    min_seconds: float = 0.0,
) -> dict[str, Any]:
    """Stepping speed of the batched ego env: ``num_envs`` scenes of ``agents`` agents (the bundled
    SUMO scenes cut to the sdc and its nearest neighbours), one ego each replaying its log through
    continuous actions, episodes that never end early. Times ``env.step`` only (the actions are
    computed outside the timed region) and reports peak memory of the process (with its env workers).
    ``npc``: ``"replay"``, ``"trajeglish"`` (unguarded sampling) or ``"trajeglish_guard"`` (guarded
    sampling); ``processes``: the env's worker processes (1: one :class:`BatchedEgoEnv`, else a
    :class:`~trajeglish_env.env.split.SplitEgoEnv`; ``"auto"``: its automatic count); ``device``: where
    the NPC model decodes (``"cuda"``: also the peak GPU memory); ``checkpoint``: the NPCs' model (default:
    the shipped one).

    ``steps`` None: Trajeglish NPCs are timed over one whole window cycle of the model (its
    ``recompute_every`` steps, one of which re-encodes and re-primes every scene's windows), so the
    figure is the long-run rate; replay NPCs over 40 steps. ``min_seconds``: the timed run is repeated in
    rounds (each from a reset with the next seed, its warm-up untimed) until the timed steps add up to at
    least that long (at most :data:`MAX_ROUNDS` rounds): one window cycle of a single scene lasts about
    0.3 s, too short a window for a rate that holds from run to run."""
    from trajeglish_env.env import RewardConfig, TrajeglishNPC
    from trajeglish_env.env.split import SplitEgoEnv, batched_ego_env
    from trajeglish_env.sampler.config import SamplingConfig

    rss0 = peak_rss_mb()
    never_end = RewardConfig(
        terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False
    )
    scenes = benchmark_scenes(agents)
    build0 = time.perf_counter()
    npc_spec: Any = npc
    model = npc in GUARDED
    if model:
        ckpt = model_checkpoint()[0] if checkpoint is None else checkpoint
        sampling = SamplingConfig(
            cache_dtype=cache_dtype, subsets=subsets, guard=GUARDED[npc], compute_dtype=compute_dtype
        )
        npc_spec = TrajeglishNPC(ckpt, sampling, device=device)
        if steps is None:  # one window cycle
            steps = npc_spec.sampling.every(ckpt.model.cfg.steps)
    steps = 40 if steps is None else steps
    venv = batched_ego_env(
        num_envs,
        scenes,
        npc=npc_spec,
        reward=never_end,
        max_cycles=steps + warmup + 1,
        torch_threads=torch_threads,
        processes=processes,
    )
    try:
        venv.reset(seed=0)
        build = time.perf_counter() - build0
        elapsed, rebuilds, rounds = 0.0, 0, 0
        while rounds == 0 or (elapsed < min_seconds and rounds < MAX_ROUNDS):
            if rounds:
                venv.reset(seed=rounds)
            rounds += 1
            for k in range(steps + warmup):
                actions = np.concatenate(venv.apply(_log_actions))
                before = venv.apply(_window_steps)
                start = time.perf_counter()
                venv.step(actions)
                if k >= warmup:
                    elapsed += time.perf_counter() - start
                    after = venv.apply(_window_steps)
                    rebuilds += int(any((a != b).any() for a, b in zip(after, before, strict=True)))
        threads = venv.apply(_torch_threads)
        shards = venv.apply(_engine_shards)
        split = isinstance(venv, SplitEgoEnv)  # peaks of the caller and its workers (shared pages in each)
        peak = peak_rss_mb() + (sum(venv.apply(_peak_rss)) if split else 0.0)
    finally:
        venv.close()
    rate = steps * rounds / elapsed
    return {
        "num_envs": num_envs,
        "npc": npc,
        "agents_per_scene": agents,
        "processes": len(threads),
        "torch_threads": threads[0],
        "engine_shards": shards[0],
        "device": device if model else None,
        "peak_gpu_mb": _peak_gpu_mb(device) if model else None,
        "cache_dtype": cache_dtype if model else None,
        "compute_dtype": dtype_name(sampling.torch_compute_dtype(device, rows=num_envs)) if model else None,
        "subsets": subsets if model else None,
        "guard": GUARDED[npc] if model else None,
        "timed_steps": steps,
        "rounds": rounds,
        "timed_seconds": round(elapsed, 3),
        "window_rebuild_steps": rebuilds if model else None,
        "env_steps_per_s": round(rate, 3),
        "scene_steps_per_s": round(rate * num_envs, 2),
        "agent_steps_per_s": round(rate * num_envs * agents, 1),
        "setup_seconds": round(build, 2),
        "peak_rss_mb": round(peak, 1),
        "rss_growth_mb": round(peak - rss0, 1),
    }


def _log_actions(venv: Any) -> np.ndarray:
    """The continuous actions bringing each scene's ego of a batched env closest to its logged next state."""
    return np.stack([log_action(env, env.agent) for env in venv.envs])


def _peak_gpu_mb(device: str) -> float | None:
    """Peak GPU memory allocated by torch in this process (None on the CPU)."""
    if torch.device(device).type != "cuda":
        return None
    return round(torch.cuda.max_memory_allocated(torch.device(device)) / 2**20, 1)


def _window_steps(venv: Any) -> np.ndarray:
    """The window steps of a batched env's Trajeglish engine (empty for rule-based NPCs)."""
    rows = venv.core.batch.rows
    engines = getattr(rows, "engines", [rows.engine] if hasattr(rows, "engine") else [])
    return np.concatenate([np.zeros(0)] + [engine.window_step for engine in engines])


def _engine_shards(venv: Any) -> int:
    """The engines a batched env's rows run as (2: :class:`~trajeglish_env.env.engine_shards.
    ShardedEngineRows` in threads; 1: one engine, or rule-based NPCs)."""
    return len(getattr(venv.core.batch.rows, "engines", [None]))


def _torch_threads(venv: Any) -> int:
    """The torch threads of a batched env's model calls (the env applies its count only inside them)."""
    return venv.core.batch.model_threads or torch.get_num_threads()


def _peak_rss(venv: Any) -> float:
    return peak_rss_mb()


def log_action(env: Any, agent: str) -> np.ndarray:
    """The continuous action bringing external ``agent`` of an env (AEC or one batched scene) closest to
    its logged next state (its last logged state past the log's end)."""
    i = env.agent_index(agent)
    sc = env.scenario
    return np.asarray(env.action_towards(agent, sc.xyh[i, min(env.sim.t + 1, sc.num_steps - 1)]))


def highway_env_speed(vehicles: int = 40, steps: int = 300, kind: str = "intersection") -> dict[str, Any]:
    """highway-env's own env at 10 Hz (one IDM step per env step, no rendering, the ego idling): steps/s,
    mean vehicles on the road and simulated agent-steps/s. ``kind="intersection"``: it removes arrived
    vehicles, so it starts with ``vehicles`` to keep about half of them on the road; ``kind="highway"``:
    ``highway-v0`` with exactly ``vehicles`` vehicles (the ego included) on 4 lanes. Resets are not timed
    (they were until stop 81: 1 s of intersection-v0's 10, its rate 1.06-1.21x low)."""
    from highway_env.envs.highway_env import HighwayEnv
    from highway_env.envs.intersection_env import IntersectionEnv

    config: dict[str, Any] = {"simulation_frequency": 10, "policy_frequency": 10, "duration": 10_000}
    if kind == "intersection":
        config |= {"initial_vehicle_count": vehicles, "spawn_probability": 0.6, "offroad_terminal": False}
        env: Any = IntersectionEnv(config=config)
    elif kind == "highway":
        config |= {"vehicles_count": vehicles - 1, "lanes_count": 4, "vehicles_density": 1.0}
        env = HighwayEnv(config=config)
    else:
        raise ValueError(f"highway_env_speed: kind must be 'intersection' or 'highway', got {kind!r}")
    env.reset(seed=0)
    counts, elapsed, episodes = [], 0.0, 0
    for _ in range(steps):  # only the steps are timed, as the Trajeglish envs' runs time theirs
        start = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(1)  # IDLE: the ego keeps its lane and speed
        elapsed += time.perf_counter() - start
        counts.append(len(env.road.vehicles))
        if terminated or truncated:  # the idling ego crashes or arrives (intersection-v0: ~4 in 300)
            episodes += 1
            env.reset(seed=episodes)
    rate = steps / elapsed
    mean = float(np.mean(counts))
    return {
        "env": f"{kind}-v0",
        "steps_per_s": round(rate, 2),
        "mean_vehicles": round(mean, 1),
        "agent_steps_per_s": round(rate * mean, 1),
    }
