"""What the tests share (not a test module): the one tiny-model builder, bundled and hand-built scenes, and
the shared WOMD files. Nothing heavy runs at import: models and scenes are built on first use (cached)."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.env import TrajeglishNPC
from trajeglish_env.env.scenes import load_bundle
from trajeglish_env.model import ModelConfig, TrajeglishModel, preset
from trajeglish_env.scenario import AgentKind, MapKind, Scenario
from trajeglish_env.tokenizer.baselines import xyh_grid_templates
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

REPO = Path(__file__).resolve().parents[1]
MERGE = "highway-merge-999000"  # 5 vehicles: fits in one context of the tiny model
SMALL = (MERGE, "highway-two-way-999000", "highway-highway-999000")


# ------------------------------------------------------------------------------------------ the tiny model
@functools.cache
def grid_vocabulary(size: int = 128) -> MotionVocabulary:
    """A grid vocabulary of ``size`` templates for every class (no fitting needed)."""
    return MotionVocabulary(np.stack([xyh_grid_templates(size)] * 3), method="xyh-grid")


def tiny_config(variant: str = "trajeglish", vocab_size: int = 128) -> ModelConfig:
    """The tiny preset for the grid vocabulary."""
    return preset("tiny", vocab_size=grid_vocabulary(vocab_size).size, variant=variant)


def tiny_checkpoint(variant: str = "trajeglish", vocab_size: int = 128) -> Checkpoint:
    """A fresh randomly initialised tiny model (6 agents x 8 steps of context, seed 0), grid vocabulary."""
    vocab = grid_vocabulary(vocab_size)
    torch.manual_seed(0)
    model = TrajeglishModel(tiny_config(variant, vocab_size)).eval()
    return Checkpoint(model=model, vocabulary=vocab, training={})


@functools.cache
def tiny() -> Checkpoint:
    """The tiny trajeglish model shared by tests that only run it (never train it in place)."""
    return tiny_checkpoint()


def record_encoded(monkeypatch: pytest.MonkeyPatch, model: TrajeglishModel) -> list:
    """Make ``model.encode_into`` record every scene it encodes; returns the list it fills."""
    scenes: list = []
    encode = model.encode_into

    def spy(cache, scene):  # type: ignore[no-untyped-def]
        scenes.append(scene)
        return encode(cache, scene)

    monkeypatch.setattr(model, "encode_into", spy)
    return scenes


def tiny_kwargs(**overrides: object) -> dict:
    """Env keyword arguments for Trajeglish NPCs of the tiny model, 8-step episodes."""
    return {"npc": TrajeglishNPC(tiny()), "max_cycles": 8, **overrides}


# ---------------------------------------------------------------------------------------------- scenes
def bundle_scene(name: str) -> Scenario:
    """A bundled scene by scenario_id."""
    bundle = load_bundle()
    return bundle.get(bundle.index_of(name))


def small_scenes() -> list[Scenario]:
    """Three small bundled highway scenes."""
    return [bundle_scene(name) for name in SMALL]


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


def queue_scene(n: int = 6, steps: int = 30) -> Scenario:
    """``n`` cars in one lane along +x, 6.5 m apart (2 m gaps) at 10 m/s, between two road edges 2 m from
    the lane's centre (the road on their left)."""
    t = np.arange(steps) * 0.1
    xyh = np.zeros((n, steps, 3))
    xyh[..., 0] = np.arange(n)[:, None] * 6.5 + 10.0 * t
    xs = np.arange(-20.0, 120.0, 1.0)
    edges = [np.stack([xs, np.full_like(xs, -2.0)], -1), np.stack([xs[::-1], np.full_like(xs, 2.0)], -1)]
    return Scenario.from_arrays(
        xyh, np.ones((n, steps), bool), np.tile([4.5, 2.0], (n, 1)), np.zeros(n, np.int64), sdc=n - 1,
        polylines=edges, polyline_kinds=[MapKind.ROAD_EDGE_BOUNDARY] * 2, scenario_id="queue",
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------- shared files
def shared_dir() -> Path:
    """The shared data folder: ``$TRAJEGLISH_SHARED``, else ``shared/`` beside the checkout (or above a
    git worktree of it)."""
    if os.environ.get("TRAJEGLISH_SHARED"):
        return Path(os.environ["TRAJEGLISH_SHARED"])
    found = (p / "shared" for p in REPO.parents if (p / "shared" / "data").is_dir())
    return next(found, REPO.parent / "shared")


def shared_file(relative: str) -> Path:
    """A file of the shared data; a missing one fails the test (never skips it), saying where it looked."""
    path = shared_dir() / relative
    if not path.is_file():
        pytest.fail(
            f"shared test file missing: {path} (the tests need the shared folder beside the checkout, "
            "or TRAJEGLISH_SHARED pointing at it)",
            pytrace=False,
        )
    return path


def womd_tfrecord() -> Path:
    """The shared real WOMD scenario (Scenario proto in TFRecord framing)."""
    return shared_file("data/womd/motion_data_one_scenario.tfrecord")


def womd_submission() -> Path:
    """The shared official-format 32-rollout submission for it."""
    return shared_file("data/womd/test_submission.binproto")


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

    ((_, data),) = list(read_tfrecord(womd_tfrecord()))
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
