"""What the tests share (not a test module): the one tiny-model builder, bundled and hand-built scenes, and
the shared WOMD files. Nothing heavy runs at import: models and scenes are built on first use (cached)."""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from trajeglish_env.checkpoint import Checkpoint
from trajeglish_env.env import TrajeglishNPC
from trajeglish_env.env.scenes import load_bundle
from trajeglish_env.model import ModelConfig, SceneInputs, TrajeglishModel, preset
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


def random_scene_inputs(cfg: ModelConfig, g: torch.Generator) -> SceneInputs:
    """Encoder inputs of one window of random agents and map points filling a model's whole context."""
    a, m, p = cfg.max_agents, cfg.max_polylines, cfg.points_per_polyline
    return SceneInputs(
        agent_xyh=torch.randn(1, a, 3, generator=g),
        agent_size=torch.ones(1, a, 2) * 4,
        agent_kind=torch.zeros(1, a, dtype=torch.long),
        agent_mask=torch.ones(1, a, dtype=torch.bool),
        map_points=torch.randn(1, m, p, 2, generator=g),
        map_point_mask=torch.ones(1, m, p, dtype=torch.bool),
        map_kind=torch.zeros(1, m, dtype=torch.long),
        map_mask=torch.ones(1, m, dtype=torch.bool),
        map_signal=torch.zeros(1, m, dtype=torch.long),
    )


def assert_batched_ego_env_equals_separate_envs(
    kw: dict, steps: int = 9, seed: int = 11, scenes: int = 2
) -> None:
    """A BatchedEgoEnv of ``scenes`` scenes, stepped with random actions through ends and auto-resets, gives
    each scene what a separate EgoEnv gives (observations, rewards, flags and the final step's info)."""
    from trajeglish_env.env import EgoEnv
    from trajeglish_env.env.vector import BatchedEgoEnv

    venv = BatchedEgoEnv(scenes, **kw)
    obs, _ = venv.reset(seed=seed)
    rng = np.random.default_rng(3)
    actions = [rng.uniform(-1, 1, (scenes, 2)).astype(np.float32) for _ in range(steps)]
    batched = [venv.step(a) for a in actions]
    assert sum(int((r[2] | r[3]).sum()) for r in batched) >= scenes  # scenes ended and restarted
    for i in range(scenes):
        env = EgoEnv(**kw)
        o, _ = env.reset(seed=seed + i)
        assert np.array_equal(o, obs[i])
        for a, (b_obs, b_rew, b_term, b_trunc, b_info) in zip(actions, batched, strict=True):
            o, r, term, trunc, info = env.step(a[i])
            assert (r, term, trunc) == (b_rew[i], b_term[i], b_trunc[i])
            if term or trunc:
                final = b_info["final_info"]
                assert np.array_equal(o, b_info["final_obs"][i])
                assert all(final[k][i] == info[k] for k in ("collision", "offroad", "progress_m"))
                o, _ = env.reset()
            assert np.array_equal(o, b_obs[i])


@dataclasses.dataclass
class GreedyWindow:
    """A greedy rollout's first window, as training would see it: the recorded encoder inputs, the input
    tokens ``[1,A,T]`` and the model's states ``xyh [A,S,3]`` / ``valid [A,S]`` / ``size [A,2]`` of its
    slots; ``checked(logits)`` compares the rollout's decided tokens with the argmax of teacher forcing."""

    engine: object
    scene: SceneInputs
    inputs: torch.Tensor
    xyh: np.ndarray
    valid: np.ndarray
    size: np.ndarray
    slots: np.ndarray
    controlled: np.ndarray
    s0: int
    t0: int
    horizon: int

    def checked(self, logits: torch.Tensor) -> int:
        """Asserts each controlled slot's decided tokens are the greedy ones of ``logits [T,A,V]``; returns
        how many tokens were compared."""
        greedy, checked = logits.argmax(-1).numpy(), 0
        for j, agent in enumerate(self.slots):
            if agent >= 0 and self.controlled[agent]:
                decided = self.engine.tokens[0, agent, self.t0 : self.t0 + self.horizon]
                assert np.array_equal(
                    decided, greedy[self.t0 - self.s0 : self.t0 - self.s0 + self.horizon, j]
                )
                checked += len(decided)
        return checked


def greedy_window(ckpt: Checkpoint, monkeypatch: pytest.MonkeyPatch, sc: Scenario) -> GreedyWindow:
    """Roll ``sc`` out greedily (5 agents, two replayed) for one window's horizon and collect that window."""
    from trajeglish_env.sampler.config import SamplingConfig
    from trajeglish_env.sampler.engine import RolloutEngine

    model = ckpt.model
    controlled = np.array([True, False, True, True, False])
    scenes = record_encoded(monkeypatch, model)
    config = SamplingConfig(temperature=0.0, prime_steps=3, guard=False)
    horizon = config.every(model.cfg.steps)
    engine = RolloutEngine(ckpt, sc, 1, horizon, controlled, config=config)
    engine.run()
    w, a = engine.windows[0], model.cfg.max_agents
    s0 = int(w.start[0])
    slots = w.slots[0]
    real = slots >= 0
    idx = np.where(real, slots, 0)
    steps = np.arange(s0, s0 + model.cfg.steps)
    inside = steps < engine.T - 1
    inputs = np.full((a, len(steps)), -1)
    inputs[:, inside] = np.where(real[:, None], engine.tokens[0][idx][:, steps[inside]], -1)
    states = np.arange(s0, s0 + model.cfg.steps + 1).clip(max=engine.T - 1)
    return GreedyWindow(
        engine,
        scenes[0].rows(slice(0, 1)),
        torch.from_numpy(inputs)[None],
        engine.mxyh[0][idx][:, states],
        engine.valid[0][idx][:, states] & real[:, None],
        engine.size[0][idx],
        slots,
        controlled,
        s0,
        sc.current_index,
        horizon,
    )


def extended_tiny_checkpoint(added: str) -> Checkpoint:
    """The tiny model extended with the input ``added`` (a ModelConfig flag: ``neighbour_input``,
    ``lane_input``), the added encoder's output layer random so that it matters."""
    from trajeglish_env.checkpoint import check_init, load_into

    base = tiny_checkpoint()
    cfg = dataclasses.replace(base.model.cfg, **{added: True})
    check_init(base, cfg, base.vocabulary)
    model = TrajeglishModel(cfg)
    load_into(model, base, base.vocabulary)
    torch.manual_seed(1)
    encoder = {"neighbour_input": model.neighbours, "lane_input": model.lanes}[added]
    torch.nn.init.normal_(encoder.out[1].weight, std=0.5)
    return Checkpoint(model=model.eval(), vocabulary=base.vocabulary, training={})
