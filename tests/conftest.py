"""Shared fixtures: paths of the shared WOMD sample and a small hand-built scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from trajeglish_env.scenario import AgentKind, MapKind, Scenario

REPO = Path(__file__).resolve().parents[1]
# the shared data sits beside the main checkout (../shared) or above a worktree of it (../../shared)
SHARED = next(
    (p / "shared" for p in REPO.parents if (p / "shared" / "data").is_dir()), REPO.parent / "shared"
)
WOMD_TFRECORD = SHARED / "data" / "womd" / "motion_data_one_scenario.tfrecord"
WOMD_SUBMISSION = SHARED / "data" / "womd" / "test_submission.binproto"


def straight_road_scene(num_agents: int = 6, steps: int = 91, seed: int = 0) -> Scenario:
    """A two-lane straight road along +x with vehicles at constant speeds (lanes at y = 0 and y = 3.5)."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * 0.1
    x0 = np.arange(num_agents) * 12.0
    lane = (np.arange(num_agents) % 2) * 3.5
    speed = rng.uniform(5.0, 15.0, num_agents)
    xyh = np.zeros((num_agents, steps, 3))
    xyh[..., 0] = x0[:, None] + speed[:, None] * t[None]
    xyh[..., 1] = lane[:, None]
    valid = np.ones((num_agents, steps), dtype=bool)
    valid[-1, :20] = False  # the last agent enters late
    kinds = np.full(num_agents, AgentKind.VEHICLE)
    kinds[1] = AgentKind.CYCLIST
    xs = np.arange(-50.0, 400.0, 1.0)
    lines = [np.stack([xs, np.full_like(xs, y)], -1) for y in (0.0, 3.5)]
    lines += [np.stack([xs, np.full_like(xs, y)], -1) for y in (-1.75, 5.25)]
    lines += [np.stack([xs, np.full_like(xs, 1.75)], -1)]
    return Scenario.from_arrays(
        xyh,
        valid,
        np.tile([4.5, 2.0], (num_agents, 1)),
        kinds,
        track_id=np.arange(100, 100 + num_agents),
        sdc=0,
        polylines=lines,
        polyline_kinds=[MapKind.LANE_FREEWAY] * 2
        + [MapKind.ROAD_EDGE_BOUNDARY] * 2
        + [MapKind.ROAD_LINE_BROKEN_SINGLE_WHITE],
        scenario_id=f"straight-{seed}",
        source="test",
    )


@pytest.fixture
def straight_scene() -> Scenario:
    return straight_road_scene()


# Tests run in parallel workers (pytest -n 2) on small tensors: one intra-op thread each avoids
# oversubscribing the cores (thread spin-waits made small decodes ~20x slower).
torch.set_num_threads(1)
