"""Reactivity test (``trajeglish brake-test``): an ego brakes hard to a stop in front of NPCs that follow it
in its lane; how often does an NPC rear-end it?

Episodes are found in the scenes: at the current step, a vehicle moving at ``min_speed`` m/s or more (the
ego) with another vehicle behind it in its lane, heading the same way, at most ``max_gap`` m bumper to
bumper (the follower). The ego is the env's single external agent (``EgoEnv``, acting first in each step,
so that NPCs see its move), with the continuous action [-1, 0] (full braking, no steering) at every step:
it stops and holds. An episode is a rear-end when the box of an agent behind the ego and heading its way
(within 45 degrees) overlaps the ego's. Every NPC policy plays the same episodes: when there are fewer
candidates than episodes, they are played again with other seeds.

No rear-end is not enough: a follower that holds its speed to the last step and then stops in 0.1 s never
hits the ego but is no driver (guarded NPCs did, at up to -186 m/s^2, before the guard's following rule).
So each episode also records the follower's hardest braking (m/s^2, over one step, and averaged over
:data:`SMOOTH_STEPS` steps: a token follower's one-step figure carries the tokens' speed levels) and its
smallest gap to the ego, and each policy the share of episodes whose follower brakes harder than
:data:`HARSH_BRAKING` (over one step, and over 0.5 s).
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from trajeglish_env.geometry import to_local
from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.scenario_io import atomic_path

NPCS = ("trajeglish", "trajeglish+guard", "idm", "replay", "constant_velocity")
SAME_LANE = 1.0  # m: the follower's centre within this of the ego's axis
SAME_WAY = 0.35  # rad: the follower's heading within this of the ego's
BEHIND_WAY = np.pi / 4  # rad: an agent hitting the ego from behind heads its way within this
# m/s^2: braking harder than this over a step is beyond any car's grip (the env's limit: 8.5 m/s^2)
HARSH_BRAKING = 10.0
# steps (0.5 s) over which braking is also averaged: the motion tokens' speeds come in levels about 0.4-0.6
# m/s apart at 3-5 m/s (the shipped vocabulary), so a token follower's one-step braking reads 4-6 m/s^2 at
# any change of level and 10 where it skips one (a guarded follower: 5.12 -> 4.09 m/s, 10.2 m/s^2 in 0.1 s,
# 2.9 m/s^2 over the 0.5 s around it); IDM's speed changes continuously
SMOOTH_STEPS = 5


@dataclass(frozen=True)
class BrakeTestConfig:
    """What the test plays: NPC policies ``npcs`` (:data:`NPCS`; ``trajeglish`` samples the model without
    the guard, ``trajeglish+guard`` with it, both otherwise with ``sampling``), ``episodes`` per policy of
    ``steps`` steps, the episode search (``max_gap`` m, ``min_speed`` m/s) and the ``seed``."""

    npcs: tuple[str, ...] = ("trajeglish", "trajeglish+guard", "idm", "replay")
    episodes: int = 22
    steps: int = 60
    max_gap: float = 25.0
    min_speed: float = 5.0
    seed: int = 0
    sampling: SamplingConfig = field(default_factory=SamplingConfig)

    def __post_init__(self) -> None:
        unknown = [n for n in self.npcs if n not in NPCS]
        if not self.npcs or unknown:
            raise ValueError(f"BrakeTestConfig.npcs: expected some of {NPCS}, got {list(self.npcs)}")
        if self.episodes < 1 or self.steps < 1:
            raise ValueError(
                f"BrakeTestConfig: episodes and steps must be >= 1, got {self.episodes}, {self.steps}"
            )
        if not (self.max_gap > 0 and self.min_speed >= 0):
            raise ValueError(
                "BrakeTestConfig: max_gap must be > 0 and min_speed >= 0, "
                f"got {self.max_gap}, {self.min_speed}"
            )


@dataclass(frozen=True)
class Candidate:
    """An ego with a follower: indices in ``scene``, their bumper-to-bumper ``gap`` (m), the ego's
    ``speed`` and the follower's (m/s)."""

    scene: Scenario
    ego: int
    follower: int
    gap: float
    speed: float
    follower_speed: float


def followers(scene: Scenario, max_gap: float, min_speed: float) -> list[Candidate]:
    """Each moving vehicle of the scene with its nearest follower (see the module docstring)."""
    c = scene.current_index
    xyh, speed = scene.xyh[:, c], scene.speed()[:, c]
    vehicle = scene.valid[:, c] & (scene.kind == AgentKind.VEHICLE)
    rel = to_local(xyh[:, None], xyh[None])  # [i,j]: agent j in agent i's frame
    length = scene.size[:, 0]
    gap = -rel[..., 0] - (length[:, None] + length[None]) / 2
    follows = (
        vehicle[:, None] & vehicle[None] & (speed[:, None] >= min_speed) & (speed[None] > 0.5 * min_speed)
    )
    follows &= (
        (np.abs(rel[..., 1]) < SAME_LANE) & (np.abs(rel[..., 2]) < SAME_WAY) & (gap > 0) & (gap <= max_gap)
    )
    out = []
    for i in np.flatnonzero(follows.any(axis=1)):
        j = int(np.argmin(np.where(follows[i], gap[i], np.inf)))
        out.append(Candidate(scene, int(i), j, float(gap[i, j]), float(speed[i]), float(speed[j])))
    return out


def peak_braking(speeds: np.ndarray, dt: float, steps: int) -> float:
    """The hardest braking (m/s^2, >= 0) of a speed series ``speeds [T]`` (m/s, ``dt`` s apart) averaged
    over ``steps`` steps (the whole series where it is shorter)."""
    k = min(steps, len(speeds) - 1)
    if k < 1:
        return 0.0
    return float(max(0.0, (speeds[:-k] - speeds[k:]).max()) / (k * dt))


def rear_ended(xyh: np.ndarray, present: np.ndarray, size: np.ndarray, ego: int) -> bool:
    """Whether an agent behind the ego and heading its way overlaps it (states ``xyh [N,3]``)."""
    rel = to_local(xyh[ego], xyh)
    behind = present & (rel[:, 0] < 0) & (np.abs(rel[:, 2]) < BEHIND_WAY)
    behind[ego] = False
    others = np.flatnonzero(behind)
    return bool(box_collisions(xyh[ego], size[ego], xyh[others], size[others]).any())


def npc_spec(name: str, checkpoint: Any, sampling: SamplingConfig) -> Any:
    """The env's ``npc`` setting of a policy name of :data:`NPCS`."""
    if not name.startswith("trajeglish"):
        return name
    from dataclasses import replace

    from trajeglish_env.env.config import TrajeglishNPC

    return TrajeglishNPC(checkpoint, replace(sampling, guard=name.endswith("+guard")))


def play(candidate: Candidate, npc: Any, steps: int, seed: int) -> dict[str, Any]:
    """One episode: the ego brakes to a stop and holds; the first step of a rear-end (None if none) and
    whether the ego collided at all."""
    from trajeglish_env.env import EgoEnv, RewardConfig

    sc = candidate.scene
    keep_going = RewardConfig(
        terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False
    )
    env = EgoEnv(
        [sc], external=(int(sc.track_id[candidate.ego]),), npc=npc, max_cycles=steps, reward=keep_going
    )
    env.reset(seed=seed)
    ego = env.aec.agent_index(env.agent)
    brake = np.array([-1.0, 0.0], np.float32)
    hit, collided = None, False
    follower = candidate.follower
    speeds, gaps = [candidate.follower_speed], [candidate.gap]
    for k in range(steps):
        _, _, terminated, truncated, info = env.step(brake)
        collided |= bool(info.get("collision", False))
        view = env.aec.sim.view()
        now, before = view.xyh[:, view.t], view.xyh[:, view.t - 1]
        if view.valid[follower, view.t] and view.valid[follower, view.t - 1]:
            speeds.append(float(np.hypot(*(now[follower, :2] - before[follower, :2]))) / sc.dt)
            along = to_local(now[ego], now[follower][None])[0, 0]
            gaps.append(float(-along - (sc.size[ego, 0] + sc.size[follower, 0]) / 2))
        if rear_ended(view.xyh[:, view.t], view.valid[:, view.t], sc.size, ego):
            hit = k + 1
            break
        if terminated or truncated:
            break
    env.close()
    return {
        "scenario_id": sc.scenario_id,
        "ego_track": int(sc.track_id[candidate.ego]),
        "follower_track": int(sc.track_id[candidate.follower]),
        "gap_m": round(candidate.gap, 2),
        "ego_speed_mps": round(candidate.speed, 2),
        "follower_speed_mps": round(candidate.follower_speed, 2),
        "seed": seed,
        "rear_end": hit is not None,
        "rear_end_step": hit,
        "collision": collided or hit is not None,
        "follower_peak_braking_mps2": round(peak_braking(np.array(speeds), sc.dt, 1), 2),
        "follower_peak_braking_05s_mps2": round(peak_braking(np.array(speeds), sc.dt, SMOOTH_STEPS), 2),
        "follower_min_gap_m": round(min(gaps), 2),
    }


def brake_test(
    scenes: Sequence[Scenario],
    config: BrakeTestConfig = BrakeTestConfig(),
    checkpoint: Any = None,
    out_dir: str | os.PathLike[str] | None = "out/brake_test",
    progress: bool = True,
) -> dict[str, Any]:
    """Play the test for every NPC policy; the rear-end rate of each, the episodes, a table and a plot."""
    candidates = [c for sc in scenes for c in followers(sc, config.max_gap, config.min_speed)]
    if not candidates:
        raise ValueError(
            f"brake-test: no scene has a vehicle at >= {config.min_speed} m/s with a follower within "
            f"{config.max_gap} m in its lane"
        )
    plan = [(candidates[k % len(candidates)], config.seed + k) for k in range(config.episodes)]
    if len(candidates) < config.episodes:
        print(
            f"brake-test: warning: {len(candidates)} ego(s) with a follower for {config.episodes} episodes: "
            "each is played again with other seeds, so deterministic NPCs (idm, replay) repeat the same "
            "episode; "
            "give more scenes (--data) for more distinct ones",
            file=sys.stderr,
        )
    if any(n.startswith("trajeglish") for n in config.npcs) and checkpoint is None:
        from trajeglish_env.checkpoint import load_pretrained

        checkpoint = load_pretrained()
    bar = tqdm(total=len(plan) * len(config.npcs), disable=not progress, file=sys.stderr, desc="brake-test")
    records, summary = [], {}
    for name in config.npcs:
        spec = npc_spec(name, checkpoint, config.sampling)
        runs = []
        for candidate, seed in plan:
            runs.append({"npc": name, **play(candidate, spec, config.steps, seed)})
            bar.update(1)
        records += runs
        summary[name] = {
            "episodes": len(runs),
            "rear_ends": sum(r["rear_end"] for r in runs),
            "rear_end_rate": round(float(np.mean([r["rear_end"] for r in runs])), 4),
            "collision_rate": round(float(np.mean([r["collision"] for r in runs])), 4),
            "harsh_braking_rate": round(
                float(np.mean([r["follower_peak_braking_mps2"] > HARSH_BRAKING for r in runs])), 4
            ),
            "median_peak_braking_mps2": round(
                float(np.median([r["follower_peak_braking_mps2"] for r in runs])), 2
            ),
            "max_peak_braking_mps2": round(max(r["follower_peak_braking_mps2"] for r in runs), 2),
            "harsh_braking_05s_rate": round(
                float(np.mean([r["follower_peak_braking_05s_mps2"] > HARSH_BRAKING for r in runs])), 4
            ),
            "median_peak_braking_05s_mps2": round(
                float(np.median([r["follower_peak_braking_05s_mps2"] for r in runs])), 2
            ),
        }
    bar.close()
    result: dict[str, Any] = {
        "scenes": len(scenes),
        "candidates": len(candidates),
        "episodes": config.episodes,
        "steps": config.steps,
        "npcs": summary,
        "records": records,
    }
    if out_dir is not None:
        result.update(_write(result, Path(out_dir)))
    return result


def markdown_table(result: dict[str, Any]) -> str:
    """The rear-end rate of each NPC policy as a Markdown table."""
    lines = [
        f"Brake test: {result['episodes']} episodes of {result['steps']} steps per NPC policy "
        f"({result['candidates']} egos with a follower in {result['scenes']} scenes)",
        "",
        "| NPCs | rear-end rate | rear-ends | ego collision rate | follower braking > "
        f"{HARSH_BRAKING:g} m/s^2 in 0.1 s / 0.5 s | follower peak braking in 0.1 s, median / max | "
        "in 0.5 s, median (m/s^2) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, s in result["npcs"].items():
        counts = f"{s['rear_ends']}/{s['episodes']}"
        braking = f"{s['median_peak_braking_mps2']:.1f} / {s['max_peak_braking_mps2']:.1f}"
        harsh = f"{s['harsh_braking_rate']:.3f} / {s['harsh_braking_05s_rate']:.3f}"
        lines.append(
            f"| {name} | {s['rear_end_rate']:.3f} | {counts} | {s['collision_rate']:.3f} | "
            f"{harsh} | {braking} | {s['median_peak_braking_05s_mps2']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def _write(result: dict[str, Any], out: Path) -> dict[str, str]:
    """The JSON, the Markdown table and a bar plot of the rear-end rates under ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    paths = {"table": str(out / "brake_test.md"), "plot": str(out / "brake_test.png")}
    with atomic_path(out / "brake_test.md") as tmp:
        tmp.write_text(markdown_table(result))
    names = list(result["npcs"])
    fig, ax = plt.subplots(figsize=(1.6 * len(names) + 2, 3.5))
    bars = ax.bar(names, [result["npcs"][n]["rear_end_rate"] for n in names], color="tab:red")
    counts = [f"{result['npcs'][n]['rear_ends']}/{result['npcs'][n]['episodes']}" for n in names]
    ax.bar_label(bars, labels=counts, padding=2)  # a 0/40 bar is a label, not an empty slot
    ax.set_ylabel("share of episodes with a rear-end")
    ax.set_ylim(0, 1)
    ax.set_title(f"ego brakes to a stop ({result['episodes']} episodes each)")
    fig.tight_layout()
    with atomic_path(out / "brake_test.png") as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
    with atomic_path(out / "brake_test.json") as tmp:
        tmp.write_text(json.dumps({**result, **paths}, indent=2))
    return paths
