"""The methods ``evaluate`` compares, as functions ``(scene, rollouts, seed) -> rollouts`` (the module
``evaluation`` runs and scores them): the log (departed agents held or parked, raw log values where a
shard has its details), the log snapped to a vocabulary, constant velocity and a submission file's
rollouts; and which agents a scene simulates and for how many steps."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.metrics import LogDetails
from trajeglish_env.metrics.features import evaluated_agents
from trajeglish_env.metrics.submission import iter_submission
from trajeglish_env.scenario import Scenario
from trajeglish_env.tokenizer.tokenize import tokenize_scenario
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

# (scene, rollouts, seed) -> [R, N_sim, H, 3], or with the rollouts' z [R, N_sim, H] (submissions)
Method = Callable[[Scenario, int, int], np.ndarray | tuple[np.ndarray, np.ndarray]]


def simulated(scene: Scenario) -> np.ndarray:
    """Indices of the agents simulated in a scene: those valid at the current step."""
    return np.flatnonzero(scene.valid[:, scene.current_index])


def spread_indices(n: int, k: int) -> list[int]:
    """``min(n, k)`` indices evenly spread over ``range(n)`` (index ``j * n // k`` for j < k): scenes of
    several sources or shards, listed one after the other, are each represented (a stride ``n // k``
    dropped the last source whenever ``k < n < 2k``); every ``n / k``-th where ``k`` divides ``n``, as
    before."""
    return sorted({j * n // k for j in range(k)}) if k < n else list(range(n))


def horizon(scene: Scenario) -> int:
    return scene.num_steps - scene.current_index - 1


def departed_filled(
    scene: Scenario, xyh: np.ndarray, valid: np.ndarray, details: LogDetails | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The future ``[N_sim, H, 3]`` of the simulated agents' logged ``xyh [N, T, 3]`` where ``valid [N, T]``,
    and their z ``[N_sim, H]`` (from ``details``, else None). Where an agent has no logged state, an
    evaluated agent keeps the raw log's value where ``details`` exist (as the official scorer replays the
    log) and else holds its last state (it is scored: its departure must not read as off-road or a jump);
    any other agent, an obstacle only, is parked far beyond the scene, each at its own spot, so the agents
    still driving do not collide with the ghost of one that left (WOMD's own placeholders pile up at (0, 0),
    where they overlap one another)."""
    sim = simulated(scene)
    c = scene.current_index
    raw = details is not None
    if raw:
        xyh = np.concatenate([details.xyz[..., :2], details.heading[..., None]], axis=-1)
    xyh, valid = xyh[sim], valid[sim]
    if not raw:
        last = np.maximum.accumulate(np.where(valid, np.arange(scene.num_steps), 0), axis=1)
        xyh = np.take_along_axis(xyh, last[..., None], axis=1)
    park = np.zeros((len(sim), 3))
    park[:, 0] = scene_extent(scene) + PARK_GAP + PARK_SPACING * np.arange(len(sim))
    park[:, 1] = scene_extent(scene) + PARK_GAP
    kept = valid | np.isin(sim, evaluated_agents(scene, sim))[:, None]
    filled = np.where(kept[..., None], xyh, park[:, None, :])[:, c + 1 :]
    return filled, (details.xyz[sim, c + 1 :, 2] if raw else None)


PARK_GAP, PARK_SPACING = 1000.0, 100.0  # m: where departed obstacles are parked, beyond the scene, apart


def scene_extent(scene: Scenario) -> float:
    """The largest |x| or |y| of the scene's logged agents and map points (m)."""
    agents = np.abs(scene.xyh[scene.valid, :2]).max(initial=0.0)
    return float(max(agents, np.abs(scene.map_points).max(initial=0.0)))


def parked(scene: Scenario, xy: np.ndarray) -> np.ndarray:
    """Where positions ``xy [..., 2]`` are parking spots of :func:`departed_filled` (beyond the scene): the
    diagnostics that read every simulated agent's moves leave those steps out (a jump to a spot is no
    move: it crossed red stop lines)."""
    return np.abs(np.asarray(xy)).max(axis=-1) > scene_extent(scene) + PARK_GAP / 2


def _repeated(
    future: tuple[np.ndarray, np.ndarray | None], rollouts: int
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """One future ``(xyh, z)`` as ``rollouts`` identical rollouts (z only where known)."""
    xyh, z = future
    rep = np.broadcast_to(xyh, (rollouts, *xyh.shape)).copy()
    return rep if z is None else (rep, np.broadcast_to(z, (rollouts, *z.shape)).copy())


def log_method(
    scene: Scenario, rollouts: int, seed: int, details: LogDetails | None = None
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The logged future repeated (:func:`departed_filled`: departed agents held or parked); with the
    scene's raw log ``details``, the raw values and their z (the official replayed-log scores)."""
    return _repeated(departed_filled(scene, scene.xyh, scene.valid, details), rollouts)


def with_details(method: Callable[..., Any], details: dict[str, LogDetails | None]) -> Method:
    """``method`` given each scene's raw log details (by scenario id) as its ``details`` argument."""

    def run(scene: Scenario, rollouts: int, seed: int) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        return method(scene, rollouts, seed, details=details.get(scene.scenario_id))

    return run


def tokenized_log_method(
    vocab: MotionVocabulary,
) -> Callable[..., np.ndarray | tuple[np.ndarray, np.ndarray]]:
    """The log as the vocabulary's argmin tokens render it (the model's training targets): every simulated
    agent's logged future snapped to the templates, departed agents held or parked as in
    :func:`log_method` (z from ``details`` where given). Its scores are the ceiling of any model that
    speaks this vocabulary."""

    def run(
        scene: Scenario, rollouts: int, seed: int, details: LogDetails | None = None
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        tok = tokenize_scenario(vocab, scene)
        xyh, z = departed_filled(scene, tok.xyh, tok.valid)
        if details is not None:
            z = departed_filled(scene, scene.xyh, scene.valid, details)[1]
        return _repeated((xyh, z), rollouts)

    return run


def tokenized_log_methods(checkpoints: dict[str, Checkpoint]) -> dict[str, Callable[..., Any]]:
    """One :func:`tokenized_log_method` per distinct vocabulary of ``checkpoints``: ``tokenized_log`` when
    they all share one, else ``tokenized_log[NAME]`` for the first checkpoint of each vocabulary."""
    distinct: dict[str, MotionVocabulary] = {}
    for name, ckpt in checkpoints.items():
        if not any(np.array_equal(v.templates, ckpt.vocabulary.templates) for v in distinct.values()):
            distinct[name] = ckpt.vocabulary
    if len(distinct) == 1:
        return {"tokenized_log": tokenized_log_method(next(iter(distinct.values())))}
    return {f"tokenized_log[{name}]": tokenized_log_method(v) for name, v in distinct.items()}


def constant_velocity_method(scene: Scenario, rollouts: int, seed: int) -> np.ndarray:
    """Each agent keeps its current velocity (from the last two logged steps) and heading."""
    sim = simulated(scene)
    c = scene.current_index
    now = scene.xyh[sim, c]
    prev_ok = scene.valid[sim, c - 1] if c > 0 else np.zeros(len(sim), bool)
    vel = np.where(prev_ok[:, None], (now[:, :2] - scene.xyh[sim, max(c - 1, 0), :2]) / scene.dt, 0.0)
    steps = np.arange(1, horizon(scene) + 1) * scene.dt
    fut = np.empty((len(sim), len(steps), 3))
    fut[..., :2] = now[:, None, :2] + vel[:, None, :] * steps[None, :, None]
    fut[..., 2] = now[:, None, 2]
    return np.broadcast_to(fut, (rollouts, *fut.shape)).copy()


def submission_method(path: str | os.PathLike[str], scenario_ids: Sequence[str]) -> Method:
    """The rollouts (and z) a submission file holds for the given scenarios, as a method."""
    wanted = set(scenario_ids)
    held = {item.scenario_id: item for _, item in iter_submission(path) if item.scenario_id in wanted}
    absent = sorted(wanted - set(held))
    if absent:
        raise ValueError(f"{path}: no rollouts for scenarios {absent[:3]} ({len(absent)} of {len(wanted)})")

    def run(scene: Scenario, rollouts: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        item = held[scene.scenario_id]
        ids = scene.track_id[simulated(scene)]
        sorter = np.argsort(item.object_id)
        order = sorter[np.searchsorted(item.object_id, ids, sorter=sorter).clip(max=len(sorter) - 1)]
        if (
            len(ids) != len(order)
            or len(ids) != len(item.object_id)
            or not np.array_equal(item.object_id[order], ids)
        ):
            missing, extra = np.setdiff1d(ids, item.object_id), np.setdiff1d(item.object_id, ids)
            raise ValueError(
                f"{path}: scenario {scene.scenario_id!r} must hold exactly its {len(ids)} simulated agents "
                f"(those valid at the current step), it holds {len(item.object_id)}: missing object id(s) "
                f"{missing.tolist()[:10]}, not simulated {extra.tolist()[:10]}"
            )
        return item.xyh[:, order].astype(np.float64), item.z[:, order].astype(np.float64)

    return run
