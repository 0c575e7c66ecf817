"""Realism evaluation of traffic models on held-out scenes (``trajeglish evaluate``).

Methods compared on the same scenes and seeds: the log itself (upper bound), constant velocity, the log
snapped to each model's motion vocabulary (``tokenized_log``: the realism a perfect model of those tokens
would reach, so the vocabulary's own cost shows), and any number of model checkpoints (e.g. the
marginal, no-intra and trajeglish variants) at one or more sampling temperatures, each without and with
guarded sampling (``NAME@T=t`` and ``NAME+guard@T=t``). Every scene's rollouts are scored with the
WOSAC-style metrics; results are averaged over scenes and written as JSON, a Markdown table and plots
(collision rate over time, speed/acceleration histograms of log vs rollouts, per-feature scores).
Partial control: one agent driven by the model, everyone else replaying the log, with the controlled agent
placed first versus last in the intra-timestep order.
"""

from __future__ import annotations

import json
import os
import sys
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.collision_kinds import collision_kinds, collision_table, pair_hits
from trajeglish_env.distributed import Ranks, gather, my_share
from trajeglish_env.evaluation_methods import (  # noqa: F401 (re-exported: evaluate's public names)
    Method,
    constant_velocity_method,
    departed_filled,
    horizon,
    log_method,
    parked,
    simulated,
    spread_indices,
    submission_method,
    tokenized_log_method,
    tokenized_log_methods,
    with_details,
)
from trajeglish_env.evaluation_plots import plot_evaluation, plot_feature_scores
from trajeglish_env.evaluation_tables import markdown_table
from trajeglish_env.metrics import LogDetails, RealismScores, mean_scores, score_rollouts
from trajeglish_env.metrics.collision_fault import collisions_by_fault
from trajeglish_env.metrics.log_details_io import details_for_files
from trajeglish_env.metrics.traffic_lights import red_light_violations
from trajeglish_env.sampler import rollout
from trajeglish_env.sampler.config import DEFAULT_TEMPERATURE, SamplingConfig
from trajeglish_env.sampler.guard_signals import SceneSignals
from trajeglish_env.scenario import AgentKind, Scenario, scenario_seed, scene_kind
from trajeglish_env.scenario_io import atomic_path
from trajeglish_env.standing import standing_counts, standing_table
from trajeglish_env.training.dataset import SceneStore


@dataclass(frozen=True)
class EvalConfig:
    """What to evaluate: scenes, rollouts per scene, the model's ``sampling`` (the env's NPC defaults
    unless changed) at each of ``temperatures`` (default: the sampling's own) and each of ``guards``
    (guarded sampling off and on; the partial-control experiment keeps ``sampling.guard``), metrics and
    seed (a scene's rollouts draw with ``scenario.scenario_seed(seed, scenario_id)``: they do not
    depend on which other scenes are selected, or in what order)."""

    rollouts: int = 8
    scenes: int = 16  # evenly spaced over the data (so every source and kind is represented)
    temperatures: tuple[float, ...] = (DEFAULT_TEMPERATURE,)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    metrics: str = "2025"
    seed: int = 0
    guards: tuple[bool, ...] = (False, True)
    # processes each scene's model rollouts are split over (rollout(..., processes=...): the same rollouts)
    rollout_processes: int = 1

    def __post_init__(self) -> None:
        if not self.guards or not all(isinstance(g, bool) for g in self.guards):
            raise ValueError(f"EvalConfig.guards must be a non-empty tuple of bools, got {self.guards!r}")
        if isinstance(self.rollout_processes, bool) or not (
            isinstance(self.rollout_processes, int) and self.rollout_processes >= 1
        ):
            raise ValueError(
                f"EvalConfig.rollout_processes must be a positive int, got {self.rollout_processes!r}"
            )


def method_name(model: str, temperature: float, guard: bool) -> str:
    """The table's name of a model sampled at ``temperature``, with or without the guard."""
    return f"{model}{'+guard' if guard else ''}@T={temperature:g}"


def model_method(ckpt: Checkpoint, sampling: SamplingConfig, processes: int = 1) -> Method:
    """Full-control rollouts of a checkpoint (every simulated agent driven by the model), each scene's
    split over ``processes`` processes."""

    def run(scene: Scenario, rollouts: int, seed: int) -> np.ndarray:
        config = replace(sampling, seed=seed)
        out = rollout(ckpt, scene, rollouts, horizon(scene), config=config, processes=processes)
        return out.xyh[:, simulated(scene), scene.current_index + 1 :]

    return run


def check_unique_ids(scenes: Sequence[Scenario], data: object) -> None:
    """Refuse scenes that share a scenario id (the same shard passed twice?): they would count twice."""
    counts = Counter(s.scenario_id for s in scenes)
    twice = sorted(sid for sid, n in counts.items() if n > 1)
    if twice:
        raise ValueError(
            f"{data}: scenario id(s) {twice[:5]} appear more than once among the scenes to evaluate (the "
            "same shard passed twice, or converted twice?): each would be counted twice"
        )


def collisions_over_time(scene: Scenario, fut: np.ndarray) -> np.ndarray:
    """Per rollout and future step, the fraction of simulated agents overlapping another agent ``[R,H]``.

    Non-simulated agents are absent; simulated agents are present at every future step.
    """
    sim = simulated(scene)
    r, i, j, h = pair_hits(scene, fut, sim)
    agent_hit = np.zeros((fut.shape[0], len(sim), fut.shape[2]), dtype=bool)
    agent_hit[r, i, h] = True
    agent_hit[r, j, h] = True
    return agent_hit.mean(axis=1)


def red_light_runs(scene: Scenario, fut: np.ndarray) -> np.ndarray:
    """``[K, 2]`` per agent class (AgentKind order): simulated agent-rollouts that cross the stop fence of a
    red signal on their lane at least once (WOSAC's rule, applied to every simulated agent, not only the
    evaluated ones), and all simulated agent-rollouts of scenes with signals (zeros without)."""
    out = np.zeros((len(AgentKind), 2), dtype=np.int64)
    signals = SceneSignals.of(scene)
    if signals is None:
        return out
    sim = simulated(scene)
    now = np.broadcast_to(scene.xyh[sim, scene.current_index, None, :2], (fut.shape[0], len(sim), 1, 2))
    xy = np.concatenate([now, fut[..., :2]], axis=2)
    away = parked(scene, xy)
    moved = ~away
    moved[..., 1:] &= ~away[..., :-1]  # neither the jump onto a parking spot nor back from it is a move
    ran = red_light_violations(signals.signals, xy, moved, scene.current_index).any(-1)
    kind = scene.kind[sim]
    for k in AgentKind:
        out[k] = ran[:, kind == k].sum(), ran.shape[0] * int((kind == k).sum())
    return out


def _kinematics(scene: Scenario, fut: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    speed = np.linalg.norm(np.diff(fut[..., :2], axis=2), axis=-1) / scene.dt
    accel = np.diff(speed, axis=2) / scene.dt
    return speed.ravel(), accel.ravel()


def evaluate_methods(
    scenes: Sequence[Scenario],
    methods: dict[str, Method],
    config: EvalConfig,
    progress: bool = True,
    details: Sequence[LogDetails | None] | None = None,
    ranks: Ranks | None = None,
) -> dict[str, Any]:
    """Score every method on every scene; returns per-method mean scores, curves and samples.

    ``details``: raw WOMD log values per scene (official-value parity; None: planar). Under ``torchrun``
    the ranks share the scenes and every rank returns the merged (one-process) result.
    """
    ranks = ranks or Ranks()
    mine = my_share(range(len(scenes)), ranks)
    bar = tqdm(total=len(mine) * len(methods), disable=not progress, file=sys.stderr, desc="evaluate")
    rows: dict[str, list] = {name: [] for name in methods}
    for name, method in methods.items():
        for k in mine:
            rows[name].append(_score_scene(scenes[k], k, method, config, details))
            bar.update(1)
    bar.close()
    merged = gather(rows, ranks)
    results: dict[str, Any] = {}
    for name in methods:
        per_scene = sorted((row for part in merged for row in part[name]), key=lambda row: row[0])
        index, scores, curves, speeds, accels, red, pairs, stand = (
            list(x) for x in zip(*per_scene, strict=True)
        )
        mean = mean_scores(scores)
        kinds = [scene_kind(scenes[k]) for k in index]
        results[name] = {
            "scores": mean.to_dict(),
            "collision_rate_over_time": np.mean(curves, axis=0).tolist(),
            "collision_rate_over_time_by_kind": {
                kind: np.mean([c for c, g in zip(curves, kinds, strict=True) if g == kind], axis=0).tolist()
                for kind in sorted(set(kinds))
            },
            "red_light_runs_by_kind": _red_light_table(np.sum(red, axis=0)),
            "collisions_by_class": collision_table(np.sum(pairs, axis=0)),
            "scores_by_kind": {
                kind: _kind_scores([r for r, g in zip(scores, kinds, strict=True) if g == kind])
                for kind in sorted(set(kinds))
            },
            "standing_by_kind": {
                kind: standing_table(
                    np.sum([c for c, g in zip(stand, kinds, strict=True) if g == kind], axis=0)
                )
                for kind in sorted(set(kinds))
            },
            "_speed": np.concatenate(speeds),
            "_accel": np.concatenate(accels),
        }
    return results


def _kind_scores(scores: list[RealismScores]) -> dict[str, float]:
    """The headline figures of one scene kind's scenes (plain means over them, as for all scenes)."""
    mean = mean_scores(scores)
    return {
        "scenes": len(scores),
        "metametric": mean.metametric,
        "collision_rate": mean.collision_rate,
        "offroad_rate": mean.offroad_rate,
    }


def _red_light_table(counts: np.ndarray) -> dict[str, dict[str, float]]:
    """``{class: {runs, agent_rollouts, rate}}`` from :func:`red_light_runs` counts summed over scenes."""
    return {
        k.name.lower(): {"runs": int(c[0]), "agent_rollouts": int(c[1]), "rate": float(c[0] / max(c[1], 1))}
        for k, c in zip(AgentKind, counts, strict=True)
    }


def _score_scene(
    scene: Scenario, k: int, method: Method, config: EvalConfig, details: Sequence[LogDetails | None] | None
) -> tuple[int, RealismScores, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(index, scores, collision curve, speeds, accelerations, red-light runs, collision kinds, standing
    counts) of one method on scene ``k``."""
    fut, z = _split(method(scene, config.rollouts, scenario_seed(config.seed, scene.scenario_id)))
    ids = scene.track_id[simulated(scene)]
    detail = details[k] if details is not None else None
    scores = score_rollouts(scene, fut, ids, config.metrics, rollouts_z=z, details=detail)
    speed, accel = _kinematics(scene, fut)
    curve, red = collisions_over_time(scene, fut).mean(0), red_light_runs(scene, fut)
    sim = simulated(scene)
    return (
        k,
        scores,
        curve,
        speed,
        accel,
        red,
        collision_kinds(scene, fut, sim),
        standing_counts(scene, fut, sim),
    )


def _split(out: np.ndarray | tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray | None]:
    """A method's rollouts ``[R,N,H,3]`` and their z ``[R,N,H]`` if it gives them (submissions do)."""
    return out if isinstance(out, tuple) else (out, None)


def partial_control(
    ckpt: Checkpoint,
    scenes: Sequence[Scenario],
    config: EvalConfig,
    progress: bool = True,
    ranks: Ranks | None = None,
) -> dict[str, dict[str, float]]:
    """The sdc driven by the model, all others replaying the log; the sdc acts first vs last (ranks
    share the scenes; the merged result is the one-process one). Per placement: ADE, the share of
    rollouts with a collision, and that share split at each rollout's first collision into the sdc moving
    into another agent (``at_fault_rate``) and other agents moving into the sdc (``struck_rate``: the
    logged agents do not react to it), see :mod:`~trajeglish_env.metrics.collision_fault`."""
    ranks = ranks or Ranks()
    out: dict[str, dict[str, float]] = {}
    for place in ("first", "last"):
        ades, cols, faults = [], [], []
        mine = my_share(range(len(scenes)), ranks)
        for k in tqdm(mine, disable=not progress, file=sys.stderr, desc=f"partial ({place})"):
            scene = scenes[k]
            controlled = np.zeros(scene.num_agents, bool)
            controlled[scene.sdc] = True
            priority = np.zeros(scene.num_agents)
            priority[scene.sdc] = -1.0 if place == "first" else 1.0
            res = rollout(
                ckpt,
                scene,
                config.rollouts,
                horizon(scene),
                controlled,
                priority=priority,
                config=replace(
                    config.sampling,
                    temperature=config.temperatures[0],
                    seed=scenario_seed(config.seed, scene.scenario_id),
                ),
                processes=config.rollout_processes,
            )
            fut = slice(scene.current_index + 1, scene.num_steps)
            log_ok = scene.valid[scene.sdc, fut]
            err = np.linalg.norm(res.xyh[:, scene.sdc, fut, :2] - scene.xyh[scene.sdc, fut, :2], axis=-1)
            ades.append((k, float(err[:, log_ok].mean())))
            hit, at_fault = collisions_by_fault(
                res.xyh, res.valid, scene.size, scene.sdc, scene.current_index
            )
            cols.append((k, float(hit.mean())))
            faults.append((k, float(at_fault.mean())))
        ades, cols, faults = (
            sorted(x for part in gather(values, ranks) for x in part) for values in (ades, cols, faults)
        )
        collided, fault = float(np.mean([c for _, c in cols])), float(np.mean([f for _, f in faults]))
        out[place] = {
            "ade": float(np.mean([a for _, a in ades])),
            "collision_rate": collided,
            "at_fault_rate": fault,
            "struck_rate": collided - fault,
        }
    return out


def evaluate(
    data: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    checkpoints: dict[str, Checkpoint],
    config: EvalConfig = EvalConfig(),
    out_dir: str | os.PathLike[str] = "out/evaluate",
    partial: str | None = None,
    progress: bool = True,
    submission: str | os.PathLike[str] | None = None,
    ranks: Ranks | None = None,
) -> dict[str, Any]:
    """The evaluation table (JSON + Markdown + plots) for the log, constant velocity, checkpoints and
    a ``submission`` file's rollouts (row ``submission``). WOMD shards with raw log details are scored
    with them (official values). Under ``torchrun`` the ranks share the scenes and the main rank writes
    the files; every rank returns the merged result."""
    ranks = ranks or Ranks()
    store = SceneStore(data)
    every = store.scenes
    chosen = spread_indices(len(every), config.scenes)  # every source represented
    scenes = [every[k] for k in chosen]
    if not scenes:
        raise ValueError(f"{data}: no scenes to evaluate")
    check_unique_ids(scenes, data)
    all_details = details_for_files(store.files)
    details = [all_details[k] for k in chosen]
    womd_without = [
        s.scenario_id for s, d in zip(scenes, details, strict=True) if d is None and s.source == "womd"
    ]
    if womd_without and ranks.main:  # scored all the same (planar), never silently
        print(
            f"evaluate: warning: {len(womd_without)} WOMD scene(s) ({', '.join(womd_without[:3])}) have no "
            "raw log details beside their shard (NAME.details.npz): they are scored with planar "
            "values, not as the official scorer does; convert them again with `trajeglish convert-womd`",
            file=sys.stderr,
        )
    by_id = {s.scenario_id: d for s, d in zip(scenes, details, strict=True)}
    methods: dict[str, Method] = {
        "log": with_details(log_method, by_id),
        "constant_velocity": constant_velocity_method,
    }
    if submission is not None:
        methods["submission"] = submission_method(submission, [s.scenario_id for s in scenes])
    methods.update({k: with_details(m, by_id) for k, m in tokenized_log_methods(checkpoints).items()})
    for name, ckpt in checkpoints.items():
        for temp in config.temperatures:
            for guard in config.guards:
                sampling = replace(config.sampling, temperature=temp, guard=guard)
                methods[method_name(name, temp, guard)] = model_method(
                    ckpt, sampling, config.rollout_processes
                )
    raw = evaluate_methods(scenes, methods, config, progress and ranks.main, details, ranks)
    if partial is not None:
        pc = partial_control(checkpoints[partial], scenes, config, progress and ranks.main, ranks)
    if not ranks.main:
        return {"scenes": len(scenes), "rank": ranks.rank}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plots = plot_evaluation(raw, scenes[0].dt, out)
    table = {name: {k: v for k, v in r.items() if not k.startswith("_")} for name, r in raw.items()}
    plots.append(plot_feature_scores(table, out / "feature_scores.png", config.metrics))
    best = {}
    for name in checkpoints:
        for guard in config.guards:
            key = f"{name}+guard" if guard else name
            cands = {
                t: table[method_name(name, t, guard)]["scores"]["metametric"] for t in config.temperatures
            }
            best[key] = max(cands, key=cands.get)  # type: ignore[arg-type]
    result: dict[str, Any] = {
        "data": [str(d) for d in data] if isinstance(data, (list, tuple)) else str(data),
        "scenes": len(scenes),
        "rollouts": config.rollouts,
        "metrics_config": config.metrics,
        "log_details": all(d is not None for d in details),
        "processes": ranks.world,
        "rollout_processes": config.rollout_processes,
        "guards": list(config.guards),
        "methods": table,
        "best_temperature": best,
        "plots": plots,
    }
    if partial is not None:
        result["partial_control"] = {"model": partial, **pc}
    md = markdown_table(result)
    with atomic_path(out / "evaluation.md") as tmp:
        tmp.write_text(md)
    with atomic_path(out / "evaluation.json") as tmp:
        tmp.write_text(json.dumps(result, indent=2))
    result["markdown"] = str(out / "evaluation.md")
    return result
