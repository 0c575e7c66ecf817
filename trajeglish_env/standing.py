"""How often simulated agents stand still, per class and scene kind, against the log (``evaluate``'s
``standing_by_kind``): frozen traffic is what a realism mean hides and a planner trained among the NPCs
sees first (guarded vehicles that stop at a bend or a roundabout entry and stay stopped;
docs/evaluation.md, stop 57).

An agent stands at a future step when it moves less than :data:`STANDING_SPEED` m/s over the step
before it (the current state counts as the first one's start), the speed every WOSAC kinematic feature
is built from, differenced once."""

from __future__ import annotations

import numpy as np

from trajeglish_env.scenario import AgentKind, Scenario

STANDING_SPEED = 0.5  # m/s: under it an agent stands (the collision kinds' "standing" threshold too)


def standing_counts(scene: Scenario, fut: np.ndarray, sim: np.ndarray) -> np.ndarray:
    """``[K, 2]`` per agent class (AgentKind order): the future agent-steps at which simulated agents ``sim
    [N]`` of rollouts ``fut [R, N, H, 3]`` stand, and all their future agent-steps."""
    now = np.broadcast_to(scene.xyh[sim, scene.current_index, None, :2], (fut.shape[0], len(sim), 1, 2))
    xy = np.concatenate([now, fut[..., :2]], axis=2)
    speed = np.linalg.norm(np.diff(xy, axis=2), axis=-1) / scene.dt  # [R, N, H]
    stands = (speed < STANDING_SPEED).sum(axis=(0, 2))  # per agent
    kind = scene.kind[sim]
    out = np.zeros((len(AgentKind), 2), dtype=np.int64)
    for k in AgentKind:
        mine = kind == k
        out[k] = stands[mine].sum(), int(mine.sum()) * speed.shape[0] * speed.shape[2]
    return out


def standing_table(counts: np.ndarray) -> dict[str, dict[str, float]]:
    """``{class: {standing, steps, share}}`` from :func:`standing_counts` summed over scenes (classes
    without agents are left out)."""
    return {
        k.name.lower(): {"standing": int(c[0]), "steps": int(c[1]), "share": float(c[0] / c[1])}
        for k, c in zip(AgentKind, counts, strict=True)
        if c[1]
    }
