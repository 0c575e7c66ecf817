"""``trajeglish long-rollouts``: do the NPCs stay sane past the log? Rollouts of every agent valid at the
current step, far longer than the log (30 s by default; the agents the log still has at its end are handed
to the model there), and per second of each the rate of new collisions and new off-road excursions per
agent, before and after ``split_s`` (8 s: the WOSAC horizon every model is trained and judged on).

An event is an onset: an agent whose box overlaps another's (the env's collision test) or has a corner
beyond a road edge (vehicles; WOSAC's 0 m threshold) at a step where it did not the step before. The
rate of a window is its onsets per agent-second present; ``ratio`` = after / before (None without an
onset before) and ``within_1_5x`` whether after <= 1.5 x before."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from trajeglish_env.batch_geometry import collision_flags, road_edges
from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.geometry import box_corners
from trajeglish_env.metrics.road_edges import RoadEdges, signed_distance_to_road_edges
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.rollouts import rollout
from trajeglish_env.scenario import AgentKind, Scenario, scenario_seed
from trajeglish_env.scenario_io import atomic_path

EVENTS = ("collision", "offroad")


@dataclass(frozen=True)
class LongRolloutConfig:
    """``seconds`` of rollout after the current step, ``rollouts`` per scene, the window boundary
    ``split_s``; ``guards``: sampled without and/or with guarded sampling; other ``sampling`` settings
    (seeds: ``seed`` + scene index)."""

    seconds: float = 30.0
    rollouts: int = 2
    split_s: float = 8.0
    guards: tuple[bool, ...] = (False, True)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        if not (self.seconds > self.split_s > 0):
            raise ValueError(
                "LongRolloutConfig: need seconds > split_s > 0, got "
                f"seconds={self.seconds}, split_s={self.split_s}"
            )
        if self.rollouts < 1 or not self.guards:
            raise ValueError("LongRolloutConfig: rollouts >= 1 and at least one guard setting are needed")
        if not float(self.split_s).is_integer():  # the rates are per whole second: a split inside one
            raise ValueError(
                f"LongRolloutConfig: split_s must be a whole number of seconds (the onset rates are per "
                f"second), got {self.split_s}"
            )


def event_onsets(
    size: np.ndarray, kind: np.ndarray, edges: RoadEdges | None, xyh: np.ndarray, valid: np.ndarray
) -> dict[str, np.ndarray]:
    """Per event, ``[R, N, T-1]`` onsets at steps 1.. of states ``xyh [R, N, T, 3]`` / ``valid [R, N, T]``
    of agents of ``size [N, 2]`` and ``kind [N]`` on a map with road ``edges`` (an event at step 0 is not
    an onset: it was there when the rollout began)."""
    r, n, t = valid.shape
    flat = xyh.transpose(0, 2, 1, 3).reshape(r * t, n, 3)
    ok = valid.transpose(0, 2, 1).reshape(r * t, n)
    q, a = np.nonzero(ok)
    hit = np.zeros((r * t, n), bool)
    hit[q, a] = collision_flags(flat, ok, np.broadcast_to(size, (r * t, n, 2)), q, a)
    off = np.zeros((r * t, n), bool)
    vehicles = np.flatnonzero(kind == AgentKind.VEHICLE)
    if edges is not None and len(vehicles):
        q, a = np.nonzero(ok[:, vehicles])
        corners = box_corners(flat[q, vehicles[a]], size[vehicles[a]])
        off[q, vehicles[a]] = signed_distance_to_road_edges(corners, edges).max(axis=-1) > 0.0
    out = {}
    for name, flag in (("collision", hit), ("offroad", off)):
        f = flag.reshape(r, t, n).transpose(0, 2, 1)
        out[name] = f[..., 1:] & ~f[..., :-1] & valid[..., :-1]
    return out


def scene_counts(
    ckpt: Checkpoint, scene: Scenario, config: LongRolloutConfig, sampling: SamplingConfig
) -> dict[str, np.ndarray]:
    """Per second of rollout: onsets of each event and agent-seconds present ``[S]``, summed over rollouts."""
    steps_per_s = int(round(1.0 / scene.dt))
    horizon = int(round(config.seconds * steps_per_s))
    out = rollout(ckpt, scene, config.rollouts, horizon, config=sampling)
    cur = scene.current_index
    sim = np.flatnonzero(scene.valid[:, cur])
    xyh, valid = out.xyh[:, sim, cur:], out.valid[:, sim, cur:]
    onsets = event_onsets(scene.size[sim], scene.kind[sim], road_edges(scene), xyh, valid)
    seconds = horizon // steps_per_s
    present = valid[..., 1:].sum(axis=(0, 1))[: seconds * steps_per_s].reshape(seconds, steps_per_s)
    counts = {"agent_seconds": present.sum(axis=1) / steps_per_s}
    for name, flag in onsets.items():
        per_step = flag.sum(axis=(0, 1))[: seconds * steps_per_s]
        counts[name] = per_step.reshape(seconds, steps_per_s).sum(axis=1).astype(np.float64)
    return counts


def long_rollout_rates(
    ckpt: Checkpoint, scenes: list[Scenario], config: LongRolloutConfig, progress: bool = True
) -> dict[str, Any]:
    """Per guard setting: per-second onset rates of each event (``per_second``), the rates of the windows
    before and after ``split_s`` and their ``ratio``."""
    result: dict[str, Any] = {
        "seconds": config.seconds,
        "split_s": config.split_s,
        "rollouts": config.rollouts,
        "scenes": len(scenes),
        "temperature": config.sampling.temperature,
        "methods": {},
    }
    for guard in config.guards:
        total: dict[str, np.ndarray] = {}
        desc = f"long rollouts ({'guard' if guard else 'no guard'})"
        for scene in tqdm(scenes, disable=not progress, file=sys.stderr, desc=desc):
            seed = scenario_seed(config.seed, scene.scenario_id)  # the scene's own, as evaluate's
            sampling = replace(config.sampling, guard=guard, seed=seed)
            for name, value in scene_counts(ckpt, scene, config, sampling).items():
                total[name] = total.get(name, 0) + value
        split = int(round(config.split_s))
        exposure = total["agent_seconds"]
        method: dict[str, Any] = {"agent_seconds": exposure.tolist()}
        for name in EVENTS:
            before = float(total[name][:split].sum() / max(exposure[:split].sum(), 1e-9))
            after = float(total[name][split:].sum() / max(exposure[split:].sum(), 1e-9))
            method[name] = {
                "per_second": (total[name] / np.maximum(exposure, 1e-9)).tolist(),
                "before": before,
                "after": after,
                "ratio": after / before if before > 0 else None,  # None: no onset before the split
                "within_1_5x": after <= 1.5 * before,
            }
        result["methods"]["trajeglish+guard" if guard else "trajeglish"] = method
    return result


def markdown_table(result: dict[str, Any]) -> str:
    """The windows' rates per method as a Markdown table."""
    split = result["split_s"]
    lines = [
        f"Rollouts of {result['seconds']:g} s on {result['scenes']} scenes x {result['rollouts']}; "
        f"onsets per agent-second before / after {split:g} s",
        "",
        "| method | collision before | collision after | ratio | off-road before | off-road after | ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, m in result["methods"].items():
        c, o = m["collision"], m["offroad"]
        lines.append(
            f"| {name} | {c['before']:.4f} | {c['after']:.4f} | {_ratio(c['ratio'])} | {o['before']:.4f} | "
            f"{o['after']:.4f} | {_ratio(o['ratio'])} |"
        )
    return "\n".join(lines) + "\n"


def _ratio(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def plot_rates(result: dict[str, Any], path: Path) -> str:
    """Per-second onset rates of every method and event, the window boundary marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharex=True)
    for ax, event in zip(axes, EVENTS, strict=True):
        for name, m in result["methods"].items():
            rates = m[event]["per_second"]
            ax.plot(np.arange(1, len(rates) + 1), rates, marker=".", label=name)
        ax.axvline(result["split_s"], color="grey", linestyle="--", linewidth=1)
        ax.set_title(f"{'off-road' if event == 'offroad' else event} onsets per agent-second")
        ax.set_xlabel("second of rollout")
        ax.set_ylim(bottom=0.0, top=max(ax.get_ylim()[1], 0.01))  # rates: no negative half when all are 0
    axes[0].legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return str(path)
