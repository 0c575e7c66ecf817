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


def write_tfrecord(path: Path, records: list[bytes]) -> Path:
    """A TFRecord file of the given records (length, masked CRCs, data), as TensorFlow writes one."""
    from trajeglish_env.sources.womd_tfrecord import masked_crc32c

    with open(path, "wb") as fh:
        for data in records:
            length = len(data).to_bytes(8, "little")
            fh.write(length + masked_crc32c(length).to_bytes(4, "little"))
            fh.write(data + masked_crc32c(data).to_bytes(4, "little"))
    return path


def small_womd_records(keep: int = 8) -> list[bytes]:
    """Two WOMD Scenario records cut from the shared sample: the sdc, the tracks to predict and the tracks
    nearest the sdc at the current step (``keep`` sim agents in all; the others' states invalidated, so the
    reader drops them), the second one renamed (``...-b``). Real format, small enough for quick rollouts."""
    from trajeglish_env.sources.womd_proto import ScenarioProto
    from trajeglish_env.sources.womd_tfrecord import read_tfrecord

    ((_, data),) = list(read_tfrecord(WOMD_TFRECORD))
    proto = ScenarioProto.FromString(data)
    now = int(proto.current_time_index)
    sdc = proto.tracks[proto.sdc_track_index].states[now]
    required = {int(proto.sdc_track_index)} | {int(r.track_index) for r in proto.tracks_to_predict}
    live = [i for i, t in enumerate(proto.tracks) if t.states[now].valid]
    dist = {
        i: np.hypot(t.states[now].center_x - sdc.center_x, t.states[now].center_y - sdc.center_y)
        for i, t in enumerate(proto.tracks)
        if i in live
    }
    kept = required | set(
        sorted((i for i in live if i not in required), key=dist.get)[: keep - len(required)]
    )
    for i, track in enumerate(proto.tracks):
        if i not in kept:
            for state in track.states:
                state.valid = False
    first = proto.SerializeToString()
    proto.scenario_id = proto.scenario_id + "-b"
    return [first, proto.SerializeToString()]
