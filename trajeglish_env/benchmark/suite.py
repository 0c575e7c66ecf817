"""``trajeglish bench``: the whole benchmark suite in one run, as one JSON document.

Sections: tokenization agent-steps/s, dataset windows/s, training tokens/s, decoding tokens/s with and
without the key/value cache, closed-loop rollout agent-steps/s (a bundled scene of about 24 agents and a
200-agent grid scene), realism-metric scoring time, a real WOMD scene with all its agents (rollouts and
the AEC env, :mod:`~trajeglish_env.benchmark.womd`), the batched ego env (Trajeglish and replay NPCs) for
each batch size, each in a fresh process so that its peak memory is its own, and highway-env's own
stepping speed measured in the same run, before and after the batched envs (their mean is the baseline),
and the batched env idle and beside one busy process (:mod:`~trajeglish_env.benchmark.busy`). Ratios to
highway-env make the figures comparable across noisy runs. JSON layout: see docs/speed.md ("Benchmarks").
"""

from __future__ import annotations

import copy
import json
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

# 2: env figures over a whole window cycle; highway-env measured before and after; 3: guarded sampling's
# env runs (env.trajeglish_guard) and its cost (guard_cost), the rollout section; 4: the womd and busy
# sections and their ratios; 5: split env runs (env.<npc>_split, busy "<B>_split") and env runs' processes;
# 6: ``complete`` (False in the documents written after each run while the suite goes on); 11: busy "aec";
# 12: ``aec_interleaved``, the AEC env and intersection-v0 timed in turn
SCHEMA_VERSION = 12
AEC_ROUNDS = 3  # turns of the AEC env and intersection-v0 in the env section (schema 12)
SECTIONS = ("tokenizer", "dataset", "training", "decoding", "rollout", "metrics", "womd", "env", "busy")


@dataclass(frozen=True)
class BenchConfig:
    """What the suite measures and how long: ``batches`` scene counts of the batched env, ``agents`` per
    scene, timed env steps per run (after ``warmup``; repeated in rounds from resets until they last
    ``env_min_seconds``), highway-env steps, torch threads for the batched
    env (``"auto"``: see :class:`trajeglish_env.env.threads.AdaptiveThreads`), the NPC cache dtype, the
    Trajeglish NPCs' ``guards`` (guarded sampling off and/or on: env runs ``trajeglish`` and
    ``trajeglish_guard``), the sections to run (``quick`` shrinks every workload for a smoke run), the
    ``womd`` section's scenario file (None: the shared one, see :func:`~trajeglish_env.benchmark.womd.
    locate_womd`) and ``split``: whether the env and busy sections also run the default NPCs' env with its
    scenes split over worker processes (``processes="auto"``, :class:`~trajeglish_env.env.split.
    SplitEgoEnv`) at the batch sizes that split (:func:`split_batches`); ``device``: the torch device the
    env runs' NPC model decodes on (``"cuda"``: a GPU; the split runs then stay in one process unless
    ``split_processes`` is a count: the env section's split runs' processes, spawned GPU workers)."""

    batches: tuple[int, ...] = (1, 8, 32, 128, 256)
    agents: int = 24
    env_steps: int | None = None  # None: one window cycle of the model (see measure.env_speed)
    # each env run is timed in rounds until its timed steps last this long (quick: one round)
    env_min_seconds: float = 2.0
    replay_steps: int = 40
    highway_steps: int = 300
    torch_threads: str | int = "auto"
    cache_dtype: str = "bfloat16"
    compute_dtype: str = "auto"
    sections: tuple[str, ...] = SECTIONS
    quick: bool = False
    guards: tuple[bool, ...] = (False, True)
    womd: str | None = None
    split: bool = True
    device: str = "cpu"
    split_processes: int | str = "auto"

    def __post_init__(self) -> None:
        unknown = sorted(set(self.sections) - set(SECTIONS))
        if unknown:
            raise ValueError(f"bench: unknown section(s) {unknown}; expected some of {list(SECTIONS)}")
        if not self.batches or min(self.batches) < 1:
            raise ValueError(f"bench: batch sizes must be positive, got {list(self.batches)}")
        if not self.guards or not all(isinstance(g, bool) for g in self.guards):
            raise ValueError(f"bench: guards must be a non-empty tuple of bools, got {self.guards!r}")
        _check_device(self.device)
        if self.split_processes != "auto" and not (
            isinstance(self.split_processes, int) and self.split_processes >= 2
        ):
            wrong = self.split_processes
            raise ValueError(f"bench: split processes must be 'auto' or an int >= 2, got {wrong!r}")
        if (self.env_steps is not None and self.env_steps < 1) or min(
            self.replay_steps, self.highway_steps
        ) < 1:
            raise ValueError("bench: step counts must be >= 1")
        if not (self.env_min_seconds >= 0):
            raise ValueError(f"bench: env min seconds must be >= 0, got {self.env_min_seconds}")


def _check_device(device: str) -> None:
    """A torch device name the env runs can use here (one clear line otherwise)."""
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, TypeError) as exc:
        raise ValueError(
            f"bench: --device must name a torch device (cpu, cuda, cuda:1), got {device!r}"
        ) from exc
    if kind == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"bench: --device {device}: CUDA is not available on this machine")
    if kind not in ("cpu", "cuda"):
        raise ValueError(f"bench: --device {device}: expected a cpu or cuda device")


def run_suite(
    config: BenchConfig,
    progress: bool = True,
    on_update: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Run the configured sections (with a progress bar on stderr) and return the JSON document.
    ``on_update`` gets the document of the runs done so far after each run (``complete`` False), so a
    suite stopped early (a lent machine's time limit) keeps what it measured."""
    from tqdm import tqdm

    from trajeglish_env.benchmark import measure

    q = config.quick
    cores = measure.machine()["cpu_count"] or 1
    jobs: list[tuple[str, Callable[[], Any]]] = []
    if "tokenizer" in config.sections:
        jobs.append(
            ("tokenizer", lambda: measure.tokenizer_speed(2000 if q else 20000, repeats=1 if q else 2))
        )
    if "dataset" in config.sections:
        jobs.append(("dataset", lambda: _dataset(200 if q else 1000)))
    if "training" in config.sections:
        jobs.append(("training", lambda: _threads(cores, _training, 1 if q else 3)))
    if "decoding" in config.sections:  # single token calls: one thread is fastest
        jobs.append(("decoding", lambda: _threads(1, measure.decoding_speed, "small", 4 if q else 16)))
    if "rollout" in config.sections:  # full-control rollouts, batched over rollouts: one thread
        jobs.append(("rollout", lambda: _threads(1, _rollouts, 2 if q else 8, 10 if q else 40)))
    if "metrics" in config.sections:
        jobs.append(("metrics", lambda: measure.metrics_time(32 if q else 128, 8 if q else 32, (8,), 1)))
    if "womd" in config.sections:
        jobs.append(("womd", _womd_job(config)))
    if "env" in config.sections:
        hw_steps = 60 if q else config.highway_steps
        baselines = [
            ("highway_env", lambda: measure.highway_env_speed(40, hw_steps)),
            ("highway_env_highway", lambda: measure.highway_env_speed(config.agents, hw_steps, "highway")),
        ]
        jobs += [(f"{name}/before", job) for name, job in baselines]
        jobs.append(("aec", lambda: _aec(q)))
        jobs.append(("aec_interleaved", lambda: _aec_interleaved(q, hw_steps)))
        models = [name for name, guard in measure.GUARDED.items() if guard in config.guards]
        for npc in (*models, "replay"):
            for b in config.batches:
                jobs.append((f"env/{npc}/{b}", _env_job(config, npc, b)))
        if config.split:  # the default NPCs with the scenes split over worker processes
            for b in split_batches(config.batches):
                job = _env_job(config, default_npc(), b, config.split_processes)
                jobs.append((f"env/{default_npc()}_split/{b}", job))
        jobs += [(f"{name}/after", job) for name, job in baselines]  # the machine's load drifts
    if "busy" in config.sections:
        jobs.append(("busy", lambda: _busy(config)))
    result: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "machine": measure.machine(),
        "config": asdict(config),
    }
    if q:  # what the quick runs really use (config keeps what was asked for)
        result["quick_overrides"] = {
            "env_steps": 3,
            "replay_steps": 3,
            "env_min_seconds": 0.0,
            "highway_steps": 60,
            "rollouts": 2,
        }
    start = time.perf_counter()
    for name, job in tqdm(jobs, desc="bench", unit="run", disable=not progress, file=sys.stderr):
        value = job()
        if name.startswith("env/"):
            _, npc, b = name.split("/")
            result.setdefault("env", {}).setdefault(npc, {})[b] = value
        elif name.endswith(("/before", "/after")):
            result.setdefault(name.split("/")[0], {"runs": []})["runs"].append(value)
        else:
            result[name] = value
        if on_update is not None and len(result) > 3:
            on_update(_document(result, start, complete=False))
    return _document(result, start, complete=True)


def _document(result: dict[str, Any], start: float, complete: bool) -> dict[str, Any]:
    """The suite's JSON document from its runs so far: highway-env's runs averaged, ratios, guard cost."""
    doc = copy.deepcopy(result)
    for key in ("highway_env", "highway_env_highway"):
        if key in doc:
            doc[key] = _mean_run(doc[key]["runs"])
    doc["ratios"] = ratios(doc)
    if "trajeglish" in doc.get("env", {}) and "trajeglish_guard" in doc["env"]:
        doc["guard_cost"] = guard_cost(doc["env"])
    doc["seconds"] = round(time.perf_counter() - start, 1)
    doc["complete"] = complete
    return doc


def _mean_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """highway-env's figures averaged over its runs (before and after the batched-env runs), with them."""
    mean = {
        key: round(sum(r[key] for r in runs) / len(runs), 2)
        for key in ("steps_per_s", "mean_vehicles", "agent_steps_per_s")
    }
    return {"env": runs[0]["env"], **mean, "runs": runs}


def _threads(n: int, fn: Callable[..., Any], *args: Any) -> Any:
    """Run ``fn`` with ``n`` torch threads (restored afterwards)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        return fn(*args)
    finally:
        torch.set_num_threads(before)


def _rollouts(rollouts: int, horizon: int) -> dict[str, Any]:
    """Closed-loop rollout speed of the model on the bundled scene nearest 24 agents and a 200-agent grid."""
    import numpy as np

    from trajeglish_env.benchmark.measure import rollout_speed
    from trajeglish_env.benchmark.workloads import grid_scene, model_checkpoint
    from trajeglish_env.env.scenes import load_bundle

    ckpt, model = model_checkpoint()
    bundle = load_bundle()
    scenes = [bundle.get(i) for i in range(len(bundle))]
    count = np.array([int(s.valid[:, s.current_index].sum()) for s in scenes])
    small = scenes[int(np.argmin(np.abs(count - 24)))]
    return {
        "model": model,
        "rollouts": rollouts,
        "horizon": horizon,
        "scene_small": rollout_speed(ckpt, small, rollouts, horizon),
        "scene_200": rollout_speed(ckpt, grid_scene(200), rollouts, horizon),
    }


def _training(steps: int) -> dict[str, Any]:
    """Training tokens/s at the default precision (``train --precision auto``) and in float32."""
    import torch

    from trajeglish_env.benchmark.measure import training_speed
    from trajeglish_env.model import preset
    from trajeglish_env.training.precision import step_dtype

    default = step_dtype("auto", torch.device("cpu"), preset("small").d_model)
    return {
        "preset": "small",
        "batch": 8,
        "torch_threads": torch.get_num_threads(),
        "precision": str(default).removeprefix("torch."),
        "tokens_per_s": round(training_speed("small", 8, steps, "auto"), 1),
        "tokens_per_s_float32": round(training_speed("small", 8, steps, "float32"), 1),
    }


def _dataset(windows: int) -> dict[str, Any]:
    from trajeglish_env.benchmark.measure import dataset_speed
    from trajeglish_env.env.scenes import load_bundle

    bundle = load_bundle()
    return dataset_speed([bundle.get(i) for i in range(len(bundle))], windows, workers=0)  # type: ignore[arg-type]


def _womd_job(config: BenchConfig) -> Callable[[], dict[str, Any]]:
    """The womd section's job; the scenario is located and read now, so that a corrupt file fails the
    run before anything is timed. No file found: the section reports ``{"skipped": reason}``."""
    from trajeglish_env.benchmark.womd import load_womd, locate_womd, womd_section

    found = locate_womd(config.womd)
    if not isinstance(found, Path):
        return lambda: {"skipped": found}
    scene = load_womd(found)
    return lambda: womd_section(found, scene, config.quick)


def _aec(quick: bool) -> dict[str, Any]:
    """The env section's AEC run: the lead API on the bundled 24-agent scenes (quick: 3 steps each)."""
    from trajeglish_env.benchmark.aec import AEC_STEPS, AEC_WARMUP, QUICK_AEC_STEPS, aec_scenes_speed

    return aec_scenes_speed(24, QUICK_AEC_STEPS if quick else AEC_STEPS, 1 if quick else AEC_WARMUP)


def _aec_interleaved(quick: bool, highway_steps: int) -> dict[str, Any]:
    """The env section's AEC env and ``intersection-v0`` in turn (3 rounds; quick: 1 of 3 steps each)."""
    from trajeglish_env.benchmark.aec import AEC_STEPS, AEC_WARMUP, QUICK_AEC_STEPS, aec_interleaved

    if quick:
        return aec_interleaved(1, highway_steps, QUICK_AEC_STEPS, 1)
    return aec_interleaved(AEC_ROUNDS, highway_steps, AEC_STEPS, AEC_WARMUP)


def default_npc() -> str:
    """The env run of the env's default NPCs (default sampling: guarded or not)."""
    from trajeglish_env.sampler.config import SamplingConfig

    return "trajeglish_guard" if SamplingConfig().guard else "trajeglish"


def split_batches(batches: tuple[int, ...]) -> tuple[int, ...]:
    """The batch sizes whose scenes ``processes="auto"`` may split (two processes' worth of scenes)."""
    from trajeglish_env.env.split import MIN_SCENES_PER_PROCESS

    return tuple(b for b in batches if b >= 2 * MIN_SCENES_PER_PROCESS)


def _busy(config: BenchConfig) -> dict[str, Any]:
    """The busy section: the batched env with the env's default NPCs (default sampling) at the default
    thread setting, idle and beside one busy process, through the env worker process; with ``split``, also
    its scenes over ``processes="auto"`` worker processes (keys ``"{B}_split"``); and the AEC env (key
    ``"aec"``: :func:`_aec`, which takes a second core only once it finds one free)."""
    from trajeglish_env.benchmark.busy import busy_batches, busy_section

    npc, auto = default_npc(), replace(config, torch_threads="auto")
    batches = busy_batches(config.batches, config.quick)
    out = busy_section(batches, lambda b: _env_job(auto, npc, b)())
    if "skipped" in out:
        return out
    if config.split:
        split = busy_section(split_batches(batches), lambda b: _env_job(auto, npc, b, "auto")())
        out.update({f"{b}_split": run for b, run in split.items() if b != "skipped"})
    out["aec"] = busy_section((1,), lambda _: _aec(config.quick))["1"]
    return out


def _env_job(
    config: BenchConfig, npc: str, batch: int, processes: int | str = 1
) -> Callable[[], dict[str, Any]]:
    """Run one batched-env measurement in a fresh Python process (its own peak memory, with that of its
    env workers when ``processes`` is not 1)."""

    def job() -> dict[str, Any]:
        steps = config.replay_steps if npc == "replay" else config.env_steps
        if config.quick:
            steps = 3
        spec = {
            "num_envs": batch,
            "npc": npc,
            "steps": steps,
            "agents": config.agents,
            "torch_threads": config.torch_threads,
            "cache_dtype": config.cache_dtype,
            "compute_dtype": config.compute_dtype,
            "processes": processes,
            "device": config.device,
            "min_seconds": 0.0 if config.quick else config.env_min_seconds,
        }
        cmd = [sys.executable, "-m", "trajeglish_env.benchmark.worker", json.dumps(spec)]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise RuntimeError(f"bench: the env run {spec} failed:\n{done.stderr[-2000:]}")
        return json.loads(done.stdout.strip().splitlines()[-1])

    return job


def ratios(result: dict[str, Any]) -> dict[str, Any]:
    """Simulated agent-steps/s of each batched-env run divided by highway-env's (same run): the
    intersection env (``..._to_highway_env``) and highway-v0 at the same agent count
    (``..._to_highway_env_highway``); the WOMD scene's AEC env steps/s over ``intersection-v0``'s
    (``womd_env_to_highway_env``); busy over idle agent-steps/s per batch size (``busy_B{B}_to_idle``)."""
    from trajeglish_env.benchmark.womd import womd_ratio

    out: dict[str, Any] = {}
    for key in ("highway_env", "highway_env_highway"):
        base = result.get(key, {}).get("agent_steps_per_s")
        if not base:
            continue
        for npc, runs in result.get("env", {}).items():
            for b, run in runs.items():
                out[f"{npc}_B{b}_to_{key}"] = round(run["agent_steps_per_s"] / base, 3)
    base_steps = result.get("highway_env", {}).get("steps_per_s")
    if "aec" in result and base_steps:
        out["aec_env_to_highway_env"] = round(result["aec"]["env_steps_per_s"] / base_steps, 3)
    if "aec_interleaved" in result:
        out["aec_env_to_highway_env_interleaved"] = result["aec_interleaved"]["median_ratio"]
    if (womd := womd_ratio(result.get("womd", {}))) is not None:
        out["womd_env_to_highway_env"] = womd
    for b, run in result.get("busy", {}).items():
        if isinstance(run, dict):
            out["busy_aec_to_idle" if b == "aec" else f"busy_B{b}_to_idle"] = run["busy_to_idle"]
    return out


def guard_cost(env: dict[str, Any]) -> dict[str, Any]:
    """Per batch size, the batched env's agent-steps/s with Trajeglish NPCs sampled without and with the
    guard, and the slowdown the guard costs (off / on)."""
    out = {}
    for b, off in env["trajeglish"].items():
        on = env["trajeglish_guard"].get(b)
        if on:
            off_rate, on_rate = off["agent_steps_per_s"], on["agent_steps_per_s"]
            out[b] = {"off": off_rate, "on": on_rate, "slowdown": round(off_rate / on_rate, 3)}
    return out


def summary_lines(result: dict[str, Any]) -> list[str]:
    """A human-readable digest of a suite result."""
    lines = [f"machine: {result['machine']}"]
    if "tokenizer" in result:
        lines.append(f"tokenizer: {result['tokenizer']['agent_steps_per_s']:,} agent-steps/s")
    if "dataset" in result:
        lines.append(f"dataset: {result['dataset']['windows_per_s_single_process']} windows/s")
    if "training" in result:
        t = result["training"]
        lines.append(
            f"training (small preset): {t['tokens_per_s']} tokens/s in {t['precision']}, "
            f"{t['tokens_per_s_float32']} in float32"
        )
    if "decoding" in result:
        d = result["decoding"]
        lines.append(
            f"decoding: {d['decode_tokens_per_s_cached']} tokens/s cached, "
            f"{d['decode_tokens_per_s_uncached']} uncached ({d['cache_speedup']}x)"
        )
    if "metrics" in result:
        lines.append(f"metrics: {result['metrics']['8_evaluated']['seconds']} s per scene of 32 rollouts")
    for key in ("highway_env", "highway_env_highway"):
        if key in result:
            h = result[key]
            lines.append(
                f"highway-env {h.get('env', '')}: {h['steps_per_s']} steps/s x {h['mean_vehicles']} "
                f"vehicles = {h['agent_steps_per_s']} agent-steps/s"
            )
    if "aec" in result:
        a = result["aec"]
        lines.append(
            f"AEC env, {a['agents']} agents (sdc replays its log, {len(a['scenes'])} bundled scenes): "
            f"{a['env_steps_per_s']} steps/s "
            f"({result['ratios'].get('aec_env_to_highway_env')}x intersection-v0)"
        )
    if "aec_interleaved" in result:
        t = result["aec_interleaved"]
        lines.append(
            f"AEC env and intersection-v0 in turn ({t['rounds']} rounds): {t['median_ratio']}x (median of "
            f"{', '.join(str(r) for r in t['ratios'])})"
        )
    for npc, runs in result.get("env", {}).items():
        for b, run in runs.items():
            ratio = result["ratios"].get(f"{npc}_B{b}_to_highway_env")
            ratio_hw = result["ratios"].get(f"{npc}_B{b}_to_highway_env_highway")
            lines.append(
                f"env {npc:>10} B={b:>4}: {run['scene_steps_per_s']:>8} scene-steps/s "
                f"{run['agent_steps_per_s']:>10} agent-steps/s ({ratio}x intersection, {ratio_hw}x highway), "
                f"{_parallelism(run)}, peak {run['peak_rss_mb']} MB"
            )
    for b, cost in result.get("guard_cost", {}).items():
        lines.append(f"guarded sampling B={b:>4}: {cost['slowdown']}x slower ({cost['off']} -> {cost['on']})")
    lines += _womd_lines(result) + _busy_lines(result)
    lines.append(f"total {result['seconds']} s")
    if result.get("complete") is False:
        lines.append("incomplete: the suite stopped before its last run (these are the runs it finished)")
    return lines


def _womd_lines(result: dict[str, Any]) -> list[str]:
    """The womd section's digest: rollout time and rate, the AEC env's steps/s and its ratio."""
    if "womd" not in result:
        return []
    w = result["womd"]
    if "skipped" in w:
        return [f"womd: skipped ({w['skipped']})"]
    r, e, split = w["rollouts"], w["env"], w.get("rollouts_split", {})
    over = f"; over {split['processes']} processes in {split['seconds']} s" if "seconds" in split else ""
    return [
        f"womd {w['scenario_id']} ({w['agents']} agents): {r['rollouts']} rollouts x {r['horizon']} steps "
        f"in {r['seconds']} s = {r['agent_steps_per_s']} agent-steps/s{over}",
        f"womd AEC env (sdc replays its log): {e['env_steps_per_s']} steps/s "
        f"({result['ratios'].get('womd_env_to_highway_env')}x intersection-v0 at "
        f"{w['highway_env']['steps_per_s']} steps/s)",
    ]


def _busy_lines(result: dict[str, Any]) -> list[str]:
    """The busy section's digest: idle and busy agent-steps/s and their ratio per batch size."""
    busy = result.get("busy", {})
    if "skipped" in busy:
        return [f"busy: skipped ({busy['skipped']})"]
    return [
        f"busy machine {'AEC env' if b == 'aec' else f'B={b:>4}'}: {run['idle_agent_steps_per_s']} "
        "agent-steps/s idle, "
        f"{run['busy_agent_steps_per_s']} beside one busy process ({run['busy_to_idle']}x; "
        f"{_parallelism(run['idle'])} -> {_parallelism(run['busy'])})"
        for b, run in busy.items()
    ]


def _parallelism(run: dict[str, Any]) -> str:
    """How an env run used the cores: its torch threads, and its worker processes when split."""
    processes, device = run.get("processes", 1), run.get("device")
    if device not in (None, "cpu"):
        return f"model on {device}"
    threads = f"threads {run.get('torch_threads')}"
    if run.get("engine_shards", 1) > 1:  # big batches on 2 cores: engines over parts of the rows, in threads
        threads = f"{run['engine_shards']} engine shards in threads x {threads}"
    return threads if processes == 1 else f"{processes} processes x {threads}"
