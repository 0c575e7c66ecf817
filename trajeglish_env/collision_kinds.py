"""Who collides with whom, and how: each simulated agent-rollout's first collision by the agent's class, its
partner's class and the geometry of the contact (``evaluate``'s ``collisions_by_class``).

A collision rate says how often agents collide, not what to fix: a cyclist riding into the back of a car
that waits at a light and two vehicles meeting in a junction are different failures of a model. At an
agent's first overlapping step its partner is the nearest agent it overlaps there, and the contact is
classed by the partner's heading relative to the agent's (within :data:`SAME_DIRECTION` radians: the same
direction, then ahead of or behind the agent's centre; beyond ``pi -`` that: head-on; else crossing).
Partners that were already overlapping the agent at the current (last logged) step are counted apart:
those boxes overlap in the log itself.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from trajeglish_env.metrics import box_collisions
from trajeglish_env.scenario import AgentKind, Scenario

SAME_DIRECTION = np.pi / 6  # radians of relative heading that still count as travelling the same way
STOPPED_SPEED = 0.5  # m/s: a partner slower than this at the contact is standing
GEOMETRIES = ("into_agent_ahead", "from_behind", "crossing", "head_on")
CLASSES = tuple(k.name.lower() for k in AgentKind)
# columns of the per-class count array, in order: the agent-rollouts, those that collide, the partner's
# class, the geometry, then two flags of the contact
FIELDS = (
    "agent_rollouts",
    "collided",
    *(f"partner_{c}" for c in CLASSES),
    *GEOMETRIES,
    "into_stopped_agent_ahead",
    "already_overlapping",
)


def pair_hits(scene: Scenario, fut: np.ndarray, sim: np.ndarray) -> tuple[np.ndarray, ...]:
    """The overlapping pairs of simulated agents ``sim [N]`` (scene indices) in rollouts ``fut [R,N,H,3]``:
    ``(rollout, i, j, step)`` arrays, ``i < j`` indexing ``sim``. Only pairs whose bounding circles touch
    are tested (the rest cannot overlap)."""
    size = scene.size[sim]
    i, j = np.triu_indices(len(sim), k=1)
    reach = (np.linalg.norm(size[i], axis=-1) + np.linalg.norm(size[j], axis=-1)) / 2
    near = np.linalg.norm(fut[:, i, :, :2] - fut[:, j, :, :2], axis=-1) < reach[None, :, None]  # [R,P,H]
    r, p, h = np.nonzero(near)
    hit = box_collisions(fut[r, i[p], h], size[i[p]], fut[r, j[p], h], size[j[p]])
    return r[hit], i[p[hit]], j[p[hit]], h[hit]


def collision_kinds(scene: Scenario, fut: np.ndarray, sim: np.ndarray) -> np.ndarray:
    """Counts ``[len(AgentKind), len(FIELDS)]`` of the simulated agents ``sim`` over rollouts ``fut
    [R,N,H,3]`` (future steps after the scene's current one), by the class of the agent (rows)."""
    out = np.zeros((len(AgentKind), len(FIELDS)), dtype=np.int64)
    rollouts, n = fut.shape[:2]
    kind = scene.kind[sim].astype(np.int64)
    np.add.at(out[:, 0], kind, rollouts)
    r, i, j, h = pair_hits(scene, fut, sim)
    if len(r) == 0:
        return out
    # both sides of every overlap, then each agent-rollout's first step and its nearest partner there
    r, a, b, h = (
        np.concatenate([r, r]),
        np.concatenate([i, j]),
        np.concatenate([j, i]),
        np.concatenate([h, h]),
    )
    gap = np.linalg.norm(fut[r, a, h, :2] - fut[r, b, h, :2], axis=-1)
    order = np.lexsort((gap, h, a, r))  # by agent-rollout, then step, then distance
    first = order[np.unique(r[order] * n + a[order], return_index=True)[1]]
    r, a, b, h = r[first], a[first], b[first], h[first]
    now = scene.xyh[sim, scene.current_index]
    before = np.where((h > 0)[:, None], fut[r, b, np.maximum(h - 1, 0)], now[b])
    partner, own = fut[r, b, h], fut[r, a, h]
    turn = np.abs((partner[:, 2] - own[:, 2] + np.pi) % (2 * np.pi) - np.pi)
    ahead = (partner[:, 0] - own[:, 0]) * np.cos(own[:, 2]) + (partner[:, 1] - own[:, 1]) * np.sin(
        own[:, 2]
    ) > 0
    same = turn <= SAME_DIRECTION
    geometry = np.where(same, np.where(ahead, 0, 1), np.where(turn >= np.pi - SAME_DIRECTION, 3, 2))
    stopped = np.linalg.norm(partner[:, :2] - before[:, :2], axis=-1) / scene.dt < STOPPED_SPEED
    overlapping = box_collisions(now[a], scene.size[sim][a], now[b], scene.size[sim][b])
    classes = len(AgentKind)
    np.add.at(out[:, 1], kind[a], 1)
    np.add.at(out, (kind[a], 2 + kind[b]), 1)
    np.add.at(out, (kind[a], 2 + classes + geometry), 1)
    np.add.at(out[:, -2], kind[a], (geometry == 0) & stopped)
    np.add.at(out[:, -1], kind[a], overlapping)
    return out


def collision_table(counts: np.ndarray) -> dict[str, dict[str, Any]]:
    """``{class: {agent_rollouts, collided, rate, partner: {class: n}, geometry: {kind: n},
    into_stopped_agent_ahead, already_overlapping}}`` from :func:`collision_kinds` counts (summed over
    scenes)."""
    table: dict[str, dict[str, Any]] = {}
    k = len(CLASSES)
    for name, row in zip(CLASSES, np.asarray(counts, dtype=np.int64), strict=True):
        table[name] = {
            "agent_rollouts": int(row[0]),
            "collided": int(row[1]),
            "rate": float(row[1] / max(row[0], 1)),
            "partner": {c: int(v) for c, v in zip(CLASSES, row[2 : 2 + k], strict=True)},
            "geometry": {
                g: int(v) for g, v in zip(GEOMETRIES, row[2 + k : 2 + k + len(GEOMETRIES)], strict=True)
            },
            "into_stopped_agent_ahead": int(row[-2]),
            "already_overlapping": int(row[-1]),
        }
    return table
