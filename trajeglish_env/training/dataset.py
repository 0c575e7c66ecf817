"""Training windows over scene shards, as in the Trajeglish appendix.

Each item is one window: a random sub-window in time, a random valid agent's state at its first step as
the coordinate frame, up to ``max_agents`` agents nearest to that agent (within ``agent_radius``) in a
random order, and up to ``max_polylines`` map chunks (within ``map_radius``), all padded to fixed shapes
with masks so that the default PyTorch collate stacks them. Item ``i`` of epoch ``e`` is a pure function
of (seed, e, i): results do not depend on DataLoader workers.
"""

from __future__ import annotations

import os
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from trajeglish_env.geometry import to_local
from trajeglish_env.model.config import ModelConfig
from trajeglish_env.model.lanes import road_points_of, window_road_source, window_road_view
from trajeglish_env.model.map_chunks import (
    MapChunks,
    chunk_map,
    nearest_chunks,
    scene_anchors,
    signal_classes,
)
from trajeglish_env.scenario import Scenario
from trajeglish_env.scenario_io import load_scenarios, scenario_files


@dataclass(frozen=True)
class WindowConfig:
    """Shape of a training window (paper defaults: 24 agents within 60 m, 96 map objects within 100 m)."""

    steps: int = 33  # states per window: the initial state + 32 future steps (32 tokens)
    max_agents: int = 24
    agent_radius: float = 60.0
    max_polylines: int = 96
    map_radius: float = 100.0
    points_per_polyline: int = 20  # points per map chunk (about 10-20 m at 0.5-1 m spacing)
    map_select: str = "frame"  # ModelConfig.map_select: chunks nearest the frame agent, or any agent
    map_stride: int = 1  # ModelConfig.map_stride: every map_stride-th point of a polyline in a chunk
    lane_input: bool = False  # ModelConfig.lane_input: windows carry the road around each agent and step

    def __post_init__(self) -> None:
        for name in ("steps", "max_agents", "max_polylines", "points_per_polyline"):
            if getattr(self, name) < (2 if name in ("steps", "points_per_polyline") else 1):
                raise ValueError(f"WindowConfig.{name} is too small: {getattr(self, name)}")


class SceneStore:
    """The scenes of one or more scenario files/directories, loaded on first use and kept in memory."""

    def __init__(self, paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]):
        if isinstance(paths, (str, os.PathLike)):
            paths = [paths]
        self.files: list[Path] = scenario_files(paths)
        self._scenes: list[Scenario] | None = None

    @property
    def scenes(self) -> list[Scenario]:
        if self._scenes is None:
            self._scenes = [s for f in self.files for s in load_scenarios(f)]
        return self._scenes

    def __len__(self) -> int:
        return len(self.scenes)


# Map chunks per live scene: an entry goes with its scene (e.g. a shard dropped from a shard cache), so
# the cache never holds more than the scenes in memory.
_CHUNKS: weakref.WeakKeyDictionary[Scenario, dict[tuple[int, int], MapChunks]] = weakref.WeakKeyDictionary()


def _chunks_for(scene: Scenario, points_per_chunk: int, stride: int) -> MapChunks:
    """Map chunks of a scene, computed once per scene object (Scenarios hash by identity)."""
    per_scene = _CHUNKS.setdefault(scene, {})
    if (points_per_chunk, stride) not in per_scene:
        per_scene[points_per_chunk, stride] = chunk_map(scene, points_per_chunk, stride)
    return per_scene[points_per_chunk, stride]


# the end of the ``source`` of a scene whose agents present at its current step follow a model's own rollout
# after it (``scripts/guarded_rollout_scenes.py``): trained on by the colliding-mass term, its rolled-out
# tokens are not likelihood targets (training/blocked_mass.py)
ROLLOUT_SOURCE = "+rollout"


class WindowDataset(Dataset):
    """PyTorch dataset yielding one training window (a dict of fixed-shape arrays) per scene index.

    Fields: ``agent_xyh [A,S,3]`` float32 in the frame, ``agent_valid [A,S]``, ``agent_size [A,2]``,
    ``agent_kind [A]`` int64, ``agent_mask [A]`` (real vs padding), ``map_points [M,P,2]`` float32,
    ``map_point_mask [M,P]``, ``map_kind [M]`` int64, ``map_mask [M]``, ``map_signal [M]`` int64 (signal
    classes at the window's first step), ``frame [3]`` float64 (the
    global state defining the frame), ``scene [ ]``, ``start [ ]`` and ``logged_targets [ ]`` int64 (the
    leading targets that move between logged states, :func:`logged_targets`). Padding agents come first
    (the order the sampler uses: padding, then agents in acting order).
    """

    def __init__(
        self,
        scenes: SceneStore | Sequence[Scenario] | str | os.PathLike[str],
        config: WindowConfig = WindowConfig(),
        seed: int = 0,
    ):
        if isinstance(scenes, (str, os.PathLike)):
            scenes = SceneStore(scenes)
        self._store = scenes
        self.config = config
        self.seed = int(seed)
        self.epoch = 0

    @property
    def scenes(self) -> Sequence[Scenario]:
        return self._store.scenes if isinstance(self._store, SceneStore) else self._store

    def set_epoch(self, epoch: int) -> None:
        """Change the random draws (window, frame agent, order) for a new epoch."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.scenes)

    def __getitem__(self, index: int) -> dict[str, np.ndarray]:
        rng = np.random.default_rng([self.seed, self.epoch, int(index)])
        return make_window(self.scenes[index], self.config, rng, scene_index=int(index))


def make_window(
    scene: Scenario, config: WindowConfig, rng: np.random.Generator, scene_index: int = 0
) -> dict[str, np.ndarray]:
    """Cut one random training window out of ``scene`` (see :class:`WindowDataset` for the fields)."""
    c = config
    t_total = scene.num_steps
    if t_total < c.steps:
        raise ValueError(
            f"scenario {scene.scenario_id!r} has {t_total} steps, fewer than the window's {c.steps}"
        )
    # Windows must start where some agent is valid: pick a start, then a frame agent valid there.
    starts = np.flatnonzero(scene.valid[:, : t_total - c.steps + 1].any(0))
    if len(starts) == 0:
        raise ValueError(f"scenario {scene.scenario_id!r}: no agent is valid at any window start")
    start = int(rng.choice(starts))
    window = slice(start, start + c.steps)
    alive = np.flatnonzero(scene.valid[:, start])
    frame_agent = int(rng.choice(alive))
    frame = scene.xyh[frame_agent, start].copy()

    # Agents valid at the window start, nearest to the frame agent, within the radius.
    dist = np.linalg.norm(scene.xyh[alive, start, :2] - frame[:2], axis=-1)
    near = alive[dist <= c.agent_radius]
    near = near[np.argsort(np.linalg.norm(scene.xyh[near, start, :2] - frame[:2], axis=-1), kind="stable")]
    chosen = near[: c.max_agents]
    chosen = chosen[rng.permutation(len(chosen))]  # random intra-timestep order
    a = len(chosen)

    xyh = np.zeros((c.max_agents, c.steps, 3), dtype=np.float32)
    valid = np.zeros((c.max_agents, c.steps), dtype=bool)
    size = np.ones((c.max_agents, 2), dtype=np.float32)
    kind = np.zeros(c.max_agents, dtype=np.int64)
    mask = np.zeros(c.max_agents, dtype=bool)
    track = np.full(c.max_agents, -1, dtype=np.int64)
    real = slice(c.max_agents - a, c.max_agents)  # padding first, as when sampling (paper appendix)
    local = to_local(frame, scene.xyh[chosen, window])
    valid[real] = scene.valid[chosen, window]
    xyh[real] = np.where(valid[real, :, None], local, 0.0)
    size[real] = scene.size[chosen]
    kind[real] = scene.kind[chosen]
    mask[real] = True
    track[real] = scene.track_id[chosen]

    chunks = _chunks_for(scene, c.points_per_polyline, c.map_stride)
    signal = signal_classes(scene, chunks, start)
    anchors = scene_anchors(c.map_select, scene, chosen, start)
    pts, pmask, mkind, mmask, msignal = nearest_chunks(
        chunks, frame, c.max_polylines, c.map_radius, signal, anchors
    )
    window_items = {
        "agent_xyh": xyh,
        "agent_valid": valid,
        "agent_size": size,
        "agent_kind": kind,
        "agent_mask": mask,
        "agent_track_id": track,
        "map_points": pts,
        "map_point_mask": pmask,
        "map_kind": mkind,
        "map_mask": mmask,
        "map_signal": msignal,
        "frame": frame.astype(np.float64),
        "scene": np.int64(scene_index),
        "start": np.int64(start),
        "logged_targets": np.int64(logged_targets(scene, start, c.steps - 1)),
    }
    if c.lane_input:  # the road around each agent at each input step, in the window's frame (model.lanes)
        points = road_points_of(scene)
        points = np.concatenate([to_local(frame, points[:, :3]), points[:, 3:]], axis=-1)
        states = np.zeros((c.max_agents, c.steps, 3))  # float64: the same numbers as the sampler's
        states[real] = np.where(valid[real, :, None], local, 0.0)
        road, road_mask = window_road_view(points, states, valid, c.steps - 1)
        window_items["road_points"], window_items["road_mask"] = road, road_mask
        source, source_mask = window_road_source(points, states, valid)  # closed-loop windows read it
        window_items["road_source"], window_items["road_source_mask"] = source, source_mask
    return window_items


def logged_targets(scene: Scenario, start: int, targets: int) -> int:
    """How many leading targets of a window from step ``start`` (``targets`` of them) move between logged
    states: all of them, but in a scene of a model's own rollout (:data:`ROLLOUT_SOURCE` ending its
    source), whose states after its current step are the model's, those up to that step."""
    if not scene.source.endswith(ROLLOUT_SOURCE):
        return targets
    return int(np.clip(scene.current_index - start, 0, targets))


def collate_windows(items: Sequence[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
    """Stack windows into a batch of tensors (the same as PyTorch's default collate, without its overhead)."""
    return {k: torch.from_numpy(np.stack([it[k] for it in items])) for k in items[0]}


def window_config(cfg: ModelConfig) -> WindowConfig:
    """The training window that matches a model's context."""
    return WindowConfig(
        steps=cfg.steps + 1,
        max_agents=cfg.max_agents,
        max_polylines=cfg.max_polylines,
        points_per_polyline=cfg.points_per_polyline,
        map_select=cfg.map_select,
        map_stride=cfg.map_stride,
        lane_input=cfg.lane_input,
    )
