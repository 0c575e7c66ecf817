"""What the AEC order means (who sees whose move), determinism, episode ends and refused inputs."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch
from helpers import MERGE, bundle_scene, small_scenes, straight_road_scene, tiny, tiny_checkpoint

import trajeglish_env
import trajeglish_env.sampler.engine as engine_module
from trajeglish_env.checkpoint import Checkpoint, CheckpointError
from trajeglish_env.env import (
    EgoEnv,
    EnvConfig,
    ObservationConfig,
    RandomAgents,
    RewardConfig,
    TrajeglishNPC,
    parallel_env,
    raw_env,
)
from trajeglish_env.env.observations import EGO_FEATURES, NEIGHBOUR_FEATURES
from trajeglish_env.env.vector import BatchedEgoEnv
from trajeglish_env.geometry import to_local
from trajeglish_env.sampler.config import SamplingConfig

WIDE = ObservationConfig(radius=500.0)
KEEP_GOING = RewardConfig(terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False)


def neighbours(obs: np.ndarray, k: int = 8) -> np.ndarray:
    return obs[EGO_FEATURES : EGO_FEATURES + NEIGHBOUR_FEATURES * k].reshape(k, NEIGHBOUR_FEATURES)


@pytest.mark.parametrize("npc", ["tiny", "idm"])
def test_external_acting_last_observes_the_npcs_moves_and_acting_first_observes_none(npc: str) -> None:
    scene = bundle_scene(MERGE)  # 5 vehicles: one model context
    spec = TrajeglishNPC(tiny()) if npc == "tiny" else npc
    for order, moved in (("last", 1.0), ("first", 0.0)):
        e = raw_env([scene], npc=spec, order=order, max_cycles=5, reward=KEEP_GOING, obs=WIDE)
        e.reset(seed=0)
        sim = e.sim
        t, ego = sim.t, int(sim.external_index[0])
        near = neighbours(e.observe(e.agent_selection))
        shown = near[near[:, 0] == 1]
        assert len(shown) == 4  # the 4 NPCs, all within the 500 m radius
        np.testing.assert_array_equal(shown[:, 9], moved)
        step = t + 1 if order == "last" else t  # where the NPCs are shown: after or before their move
        others = np.flatnonzero(np.arange(scene.num_agents) != ego)
        local = to_local(sim.driver.xyh[ego, t], sim.driver.xyh[others, step])[:, :2] / WIDE.radius
        order_shown = np.argsort(np.hypot(local[:, 0], local[:, 1]), kind="stable")
        np.testing.assert_allclose(shown[:, 1:3], local[order_shown], atol=1e-6)
        if npc == "tiny":  # the engine's own record: the NPC tokens of this step are decided (or not) yet
            assert sim.driver.engine.known[0, others, t].all() == (order == "last")


def _npc_logits(monkeypatch: pytest.MonkeyPatch, order: str, action: list[float]) -> list[torch.Tensor]:
    """Logits of every NPC token sampled while the ego takes ``action`` for two steps."""
    seen: list[torch.Tensor] = []
    original = engine_module.sample_with_uniform

    def spy(logits: torch.Tensor, *args: object, **kwargs: object) -> np.ndarray:
        seen.append(logits.clone())
        return original(logits, *args, **kwargs)

    monkeypatch.setattr(engine_module, "sample_with_uniform", spy)
    # the spy sits on the engine's own draw, one call per sampled agent when decoding sequentially
    unguarded = TrajeglishNPC(tiny(), SamplingConfig(guard=False, intra_step="sequential"))
    e = raw_env([bundle_scene(MERGE)], npc=unguarded, order=order, max_cycles=3, reward=KEEP_GOING)
    e.reset(seed=0)
    for _ in range(2):
        e.step(np.array(action, dtype=np.float32))
    monkeypatch.setattr(engine_module, "sample_with_uniform", original)
    return seen


def test_npcs_after_the_external_condition_on_its_move(monkeypatch: pytest.MonkeyPatch) -> None:
    # first: the 4 NPCs of the first step decode after the ego's token -> their logits depend on its action
    fast = _npc_logits(monkeypatch, "first", [1.0, 0.5])
    slow = _npc_logits(monkeypatch, "first", [-1.0, -0.5])
    assert len(fast) == len(slow) == 8
    assert not any(torch.equal(a, b) for a, b in zip(fast[:4], slow[:4], strict=True))
    # last: they decode before it -> identical logits whatever the ego does; later steps see its past move
    fast = _npc_logits(monkeypatch, "last", [1.0, 0.5])
    slow = _npc_logits(monkeypatch, "last", [-1.0, -0.5])
    assert len(fast) == len(slow) == 12  # the env also decodes the NPCs of the next step before the ego
    assert all(torch.equal(a, b) for a, b in zip(fast[:4], slow[:4], strict=True))
    assert not any(torch.equal(a, b) for a, b in zip(fast[4:8], slow[4:8], strict=True))


def test_order_first_holds_across_model_contexts_with_several_external_agents() -> None:
    scene = bundle_scene("sumo-random-999000-0-0")  # ~30 agents: five contexts of the tiny model
    e = raw_env([scene], npc=TrajeglishNPC(tiny()), external=RandomAgents(3), order="first", max_cycles=2)
    e.reset(seed=1)
    sim = e.sim
    t = sim.t
    listed = list(e.agents)
    assert len(listed) == 3
    for agent in listed:
        assert e.agent_selection == agent  # externals act in the configured order
        npcs = np.flatnonzero(sim.npc)
        assert not sim.driver.moved()[npcs].any()  # ... before every NPC of every context
        e.step(np.zeros(2, dtype=np.float32))
    assert sim.t == t + 1 and sim.driver.valid[np.flatnonzero(sim.npc), t + 1].all()
    assert len(sim.driver.engine.plan[0].centres) > 1  # the NPCs were decoded in several model contexts


def test_explicit_order_puts_the_named_agents_first() -> None:
    scene = bundle_scene(MERGE)
    names = [f"vehicle_{i}" for i in scene.track_id]
    ego = names[scene.sdc]
    leader = names[(scene.sdc + 2) % scene.num_agents]
    e = raw_env([scene], npc=TrajeglishNPC(tiny()), order=(leader, ego), max_cycles=3)
    e.reset(seed=0)
    moved = e.sim.driver.moved()
    assert moved[names.index(leader)] and moved.sum() == 1  # only the named NPC acted before the ego
    with pytest.raises(ValueError, match=r"order: unknown agent name\(s\) \['vehicle_999999'\]"):
        raw_env([scene], npc="replay", order=("vehicle_999999",)).reset(seed=0)


def test_parallel_env_is_deterministic_over_many_steps() -> None:
    def play(seed: int) -> tuple[list[np.ndarray], list[float]]:
        scene = bundle_scene(MERGE)
        two = tuple(int(i) for i in scene.track_id[:2])  # two external agents, three Trajeglish NPCs
        par = parallel_env([scene], npc=TrajeglishNPC(tiny()), external=two, max_cycles=6, reward=KEEP_GOING)
        obs, _ = par.reset(seed=seed)
        rng = np.random.default_rng(0)
        seen, rewards = [], []
        while par.agents:
            actions = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in sorted(par.agents)}
            obs, rew, _, _, _ = par.step(actions)
            seen += [obs[a] for a in sorted(obs)]
            rewards += [rew[a] for a in sorted(rew)]
        return seen, rewards

    a, b, c = play(5), play(5), play(6)
    assert len(a[0]) == 6 * 2  # 6 steps x 2 agents
    assert all(np.array_equal(x, y) for x, y in zip(a[0], b[0], strict=True)) and a[1] == b[1]
    assert not all(np.array_equal(x, y) for x, y in zip(a[0], c[0], strict=True))


def test_reset_picks_scenes_by_seed_index_or_id() -> None:
    e = raw_env(small_scenes(), npc="replay")
    e.reset(seed=0, options={"scene": "highway-two-way-999000"})
    assert e.scenario.scenario_id == "highway-two-way-999000"
    e.reset(seed=0, options={"scene": 2})
    assert e.scenario.scenario_id == "highway-highway-999000"
    picks = set()
    for seed in range(12):
        e.reset(seed=seed)
        picks.add(e.scenario.scenario_id)
        again = raw_env(small_scenes(), npc="replay")
        again.reset(seed=seed)
        assert again.scenario.scenario_id == e.scenario.scenario_id
    assert len(picks) == 3
    with pytest.raises(KeyError, match="no scene with scenario_id 'nope'"):
        e.reset(options={"scene": "nope"})
    with pytest.warns(UserWarning, match=r"reset options: 'scnee' ignored; the env reads only 'scene'"):
        e.reset(seed=0, options={"scnee": 1})  # a misspelt option is said (PettingZoo's tests pass others)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        e.reset(seed=0, options={})  # what vectorized envs pass without options: no warning
    assert e.scenario.scenario_id in picks


def test_reset_infos_hold_the_step_info_keys() -> None:
    """The first ``env.last()`` of an AEC loop (and a parallel reset) already has every info key."""
    from trajeglish_env.env import parallel_env

    e = raw_env(small_scenes(), npc="replay")
    e.reset(seed=0)
    *_, info = e.last()
    assert info == {
        "collision": False, "offroad": False, "goal": False, "has_goal": True, "progress_m": 0.0,
        "route_fraction": 0.0,
        "collision_steps": 0, "offroad_steps": 0, "goal_reached": False,
    }  # fmt: skip
    e.step(e.action_space(e.agent_selection).sample())
    assert set(e.infos[e.possible_agents[0]]) == set(info)
    _, infos = parallel_env(small_scenes(), npc="replay").reset(seed=0)
    assert all(v == info for v in infos.values())


def test_collision_terminates_and_the_agent_leaves_the_scene() -> None:
    scene = straight_road_scene(num_agents=4, steps=91)  # agent 2 drives 24 m ahead of the sdc, same lane
    e = raw_env([scene], npc="replay", action="delta", max_cycles=40)
    e.reset(seed=0)
    agent = e.agent_selection
    rewards = []
    while not e.terminations[agent]:
        e.step(np.array([5.0, 0.0, 0.0], dtype=np.float32))  # 50 m/s: rams the car ahead
        rewards.append(e.rewards[agent])
    info = e.infos[agent]
    assert info["collision"] and not info["offroad"] and not e.truncations[agent]
    assert len(rewards) < 10 and rewards[-1] < -0.9
    assert all(type(r) is float for r in rewards) and type(e.terminations[agent]) is bool
    t = e.sim.t
    e.step(None)  # the dead step removes it
    assert e.agents == [] and e.sim.driver.valid[scene.sdc, t]


def test_offroad_and_goal_end_the_episode() -> None:
    scene = bundle_scene("highway-highway-999000")
    e = raw_env([scene], npc="replay", action="delta")
    e.reset(seed=0)
    agent = e.agent_selection
    while not e.terminations[agent]:
        e.step(np.array([1.0, -1.0, 0.0], dtype=np.float32))  # drift right, off the road
    assert e.infos[agent]["offroad"] and not e.infos[agent]["collision"]
    # the logged route, driven with the exact logged displacements, ends the episode at its goal
    from policies import ReplayPolicy, play_episode

    result = play_episode(raw_env([scene], npc="replay", action="delta"), ReplayPolicy(), seed=0)
    assert result.goal[agent] and result.route_fraction[agent] > 0.95 and not result.collision[agent]


def test_bad_inputs_are_refused_with_clear_errors(tmp_path: object) -> None:
    scene = bundle_scene(MERGE)
    with pytest.raises(ValueError, match=r"unknown agent id\(s\) \[123456\] in the external"):
        raw_env([scene], npc="replay", external=(123456,)).reset(seed=0)
    e = raw_env([scene], npc="replay")
    e.reset(seed=0)
    with pytest.raises(ValueError, match=r"action \[2.0, 0.0\] is outside the action space bounds"):
        e.step(np.array([2.0, 0.0], dtype=np.float32))
    with pytest.raises(ValueError, match=r"must be a finite array of shape \(2,\)"):
        e.step(np.zeros(3, dtype=np.float32))
    tok = raw_env([scene], npc=TrajeglishNPC(tiny()), action="token")
    tok.reset(seed=0)
    n = tok.action_space(tok.agent_selection).n
    with pytest.raises(ValueError, match=f"action {n} is outside the action space Discrete"):
        tok.step(n)
    with pytest.raises(ValueError, match=r"action 1.5 \(float\) is not an integer scalar; expected an int"):
        tok.step(1.5)
    with pytest.raises(ValueError, match=r"action True \(bool\) is not an integer scalar"):
        tok.step(True)  # was taken as token 1
    with pytest.raises(ValueError, match=r"array\(\[3\]\) \(ndarray of shape \(1,\)\) is not an integer"):
        tok.step(np.array([3]))
    with pytest.raises(ValueError, match="is complex; expected real numbers"):
        e.step(np.array([0.5j, 0.0]))
    gone = scene.valid.copy()
    gone[scene.sdc, scene.current_index] = False
    no_sdc = dataclasses.replace(scene, valid=gone)
    with pytest.raises(ValueError, match="its sdc .* is not present at the current step 10"):
        raw_env([no_sdc], npc="replay").reset(seed=0)
    mismatched = Checkpoint(
        model=tiny_checkpoint(vocab_size=128).model,
        vocabulary=tiny_checkpoint(vocab_size=256).vocabulary,
        training={},
    )
    with pytest.raises(
        CheckpointError, match="vocabulary has 3 classes x 294 templates but the model expects 3 x 144"
    ):
        raw_env([scene], npc=TrajeglishNPC(mismatched))
    with pytest.raises(TypeError, match=r"unknown environment option\(s\) \['max_cycle'\]"):
        raw_env([scene], npc="replay", max_cycle=3)
    with pytest.raises(ValueError, match="EnvConfig.order: expected one of"):
        EnvConfig(order="sometimes")


def test_an_unknown_option_lists_every_accepted_one_and_the_closest() -> None:
    """``scene=`` (for ``scenes=``) listed the valid options without ``scenes``, ``render_mode`` and
    ``config``, and no hint."""
    with pytest.raises(TypeError, match=r"\['scene'\] \(did you mean 'scenes'\?\); valid options: ") as err:
        trajeglish_env.env(scene="data/womd", npc="replay")
    assert all(f"'{name}'" in str(err.value) for name in ("scenes", "render_mode", "config", "max_cycles"))
    with pytest.raises(TypeError, match=r"\['zzz'\]; valid options: "):  # no close match: no hint
        EnvConfig().with_overrides(zzz=1)


def test_render_size_is_one_positive_int() -> None:
    """A ``render_size`` of (H, W) was a TypeError comparing a tuple with an int."""
    square = r"render_size: expected a positive int \(the square picture's side in pixels\), got \(320, 240\)"
    with pytest.raises(TypeError, match=square):
        trajeglish_env.env(npc="replay", render_size=(320, 240))
    assert EnvConfig(render_size=np.int64(64)).render_size == 64


def test_missing_shipped_model_names_the_alternatives(
    monkeypatch: pytest.MonkeyPatch, tmp_path: object
) -> None:
    import trajeglish_env.checkpoint as checkpoint_module

    monkeypatch.setattr(checkpoint_module, "pretrained_path", lambda: tmp_path / "absent.pt")  # type: ignore[operator]
    with pytest.raises(
        CheckpointError, match=r"missing from this installation\. Trajeglish NPCs need a model.*npc='idm'"
    ):
        raw_env()


def test_human_mode_shows_the_reset_and_every_step() -> None:
    """Gymnasium's human render mode renders at reset and at every step (the window itself is pygame's)."""
    e = raw_env(small_scenes(), npc="replay", render_mode="human", max_cycles=2)
    shown: list[int] = []
    e.render = lambda: shown.append(e.sim.t)  # type: ignore[method-assign]
    e.reset(seed=0)
    assert shown == [e.scenario.current_index]
    e.step(e.action_space(e.agent_selection).sample())
    assert len(shown) == 2


def test_the_drift_warning_names_the_agent_as_the_env_does() -> None:
    """An external agent driven faster than the vocabulary follows is named ``vehicle_<track>`` with its
    scene (the warning said "external agent 2 (track 7) of row 0")."""
    env = raw_env([bundle_scene(MERGE)], npc=TrajeglishNPC(tiny()), action="delta", max_cycles=3)
    env.reset(seed=0)
    agent = env.agent_selection
    with pytest.warns(UserWarning, match=rf"external agent {agent} of scene 'highway-merge-999000' \(batch"):
        env.step(np.array([5.0, 0.0, 0.0], np.float32))
        env.step(np.array([5.0, 0.0, 0.0], np.float32))


def test_the_goal_reward_is_paid_once_when_the_episode_goes_on() -> None:
    """With ``terminate_on_goal=False`` an agent that reached its goal and stays there collected the bonus
    at every step (a return of 65 for one route); it is paid once, while ``info["goal"]`` still says
    where the agent is."""
    from policies import ReplayPolicy, play_episode
    from trajeglish_env.env import RewardConfig

    results = [
        play_episode(
            raw_env(npc="idm", action="delta", reward=RewardConfig(goal=bonus, terminate_on_goal=False)),
            ReplayPolicy(),
            seed=0,
            options={"scene": 18},
        )
        for bonus in (0.0, 1.0)
    ]
    (agent,) = results[1].returns
    assert results[1].goal[agent] and results[1].steps == 80  # the goal is reached early, the episode goes on
    assert results[1].returns[agent] - results[0].returns[agent] == pytest.approx(1.0)  # one bonus


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("comfort_accel", 0.0, "comfort_accel must be > 0"),
        ("progress", float("nan"), "progress must be a finite number"),
        ("goal_tolerance", -1.0, "goal_tolerance must be >= 0 m"),
        ("terminate_on_goal", 1, "terminate_on_goal must be a bool"),
    ],
)
def test_reward_config_refuses_values_that_would_poison_the_rewards(field, value, message) -> None:
    from trajeglish_env.env import RewardConfig

    with pytest.raises(ValueError, match=message):
        RewardConfig(**{field: value})


def test_random_agents_can_keep_the_sdc_and_take_what_a_small_scene_has() -> None:
    """Your ego plus k - 1 others over any scene set (track ids are per scene; RandomAgents(k) could leave
    the sdc out or fail on a scene with fewer agents)."""
    import trajeglish_env
    from trajeglish_env.env import RandomAgents

    env = trajeglish_env.parallel_env(
        npc="constant_velocity", external=RandomAgents(8, with_sdc=True, at_most=True)
    )
    for seed in range(12):
        env.reset(seed=seed)
        raw = env.unwrapped
        sc = raw.scenario
        present = int(sc.valid[:, sc.current_index].sum())
        assert len(env.agents) == min(8, present)
        assert raw.sim.names[sc.sdc] in env.agents
    with pytest.raises(ValueError, match=r"RandomAgents\(k=40\) but only .* at_most=True"):
        trajeglish_env.parallel_env(npc="constant_velocity", external=RandomAgents(40)).reset(seed=0)


def test_an_episode_counts_a_goal_reached_at_any_step() -> None:
    """With the episode going on past the goal, an agent that reached it and drove back off was reported
    as not reaching it (the last step's flag)."""
    from policies import play_episode
    from trajeglish_env.env import RewardConfig

    class ToTheEndAndBack:
        def reset(self, env, agent):
            self.back = False

        def act(self, env, agent, obs):
            self.seen = env.unwrapped.infos[agent]
            self.back |= self.seen["goal"]
            return np.array([-1.0 if self.back else 5.0, 0.0, 0.0], np.float32)

    reward = RewardConfig(terminate_on_goal=False, terminate_on_offroad=False, terminate_on_collision=False)
    env = raw_env([bundle_scene(MERGE)], npc="replay", action="delta", max_cycles=70, reward=reward)
    policy = ToTheEndAndBack()
    result = play_episode(env, policy, seed=0)
    (agent,) = result.returns
    assert policy.back and not policy.seen["goal"] and policy.seen["goal_reached"]  # left the goal again
    assert result.goal[agent]


def test_an_npc_policy_object_is_copied_per_scene_and_rule_based_envs_pickle() -> None:
    """One ReplayNPC / IDMNPC object given to a batch of scenes, or to two envs, was shared: each reset
    overwrote another scene's episode state, so NPCs replayed another scene's log (observations 2.0
    apart on [-1, 1] features). And an env with rule-based NPCs did not pickle (a lambda)."""
    import pickle

    from trajeglish_env.env import IDMNPC, EgoEnv, ReplayNPC
    from trajeglish_env.env.vector import BatchedEgoEnv

    scenes = small_scenes()[:2]
    zero = np.zeros((2, 2), np.float32)
    for obj, name in ((ReplayNPC(), "replay"), (IDMNPC(), "idm")):
        shared = [EgoEnv(scenes, npc=obj, max_cycles=6) for _ in range(2)]
        alone = [EgoEnv(scenes, npc=name, max_cycles=6) for _ in range(2)]
        got = [e.reset(seed=0, options={"scene": k})[0] for k, e in enumerate(shared)]
        want = [e.reset(seed=0, options={"scene": k})[0] for k, e in enumerate(alone)]
        for _ in range(4):  # interleaved: each env's reset and steps between the other's
            got += [e.step(zero[0])[0] for e in shared]
            want += [e.step(zero[0])[0] for e in alone]
        np.testing.assert_array_equal(np.stack(got), np.stack(want))
        batch = BatchedEgoEnv(2, scenes, npc=obj, max_cycles=6)
        ref = BatchedEgoEnv(2, scenes, npc=name, max_cycles=6)
        a, b = batch.reset(seed=3)[0], ref.reset(seed=3)[0]
        for _ in range(3):
            a, b = batch.step(zero)[0], ref.step(zero)[0]
            np.testing.assert_array_equal(a, b)
        batch.close(), ref.close()
    env = EgoEnv(scenes, npc="idm", max_cycles=6)
    env.reset(seed=1)
    copy = pickle.loads(pickle.dumps(env))
    np.testing.assert_array_equal(copy.step(zero[0])[0], env.step(zero[0])[0])


def test_config_fields_take_numpy_integers_and_refuse_bools_and_fractions() -> None:
    """`max_cycles=np.int64(5)` was refused and `max_cycles=True` taken as 1; `neighbours=2.5` failed
    later inside Gymnasium, `neighbours='3'` with a bare TypeError; `bev_resolution=1e-3` ran out of memory
    at reset (22 GB); a single env refused `torch_threads="auto"` with a bare TypeError."""
    from trajeglish_env.env.config import EnvConfig, ObservationConfig

    assert EnvConfig(max_cycles=np.int64(5)).max_cycles == 5
    assert type(ObservationConfig(neighbours=np.int64(3)).neighbours) is int
    for kw, field in (
        ({"neighbours": 2.5}, "neighbours must be an int >= 1"),
        ({"neighbours": True}, "neighbours must be an int >= 1"),
        ({"bev_size": "8"}, "bev_size must be an int >= 1"),
        ({"signals": -1}, "signals must be an int >= 0"),
        ({"radius": True}, "radius must be a number > 0"),
        ({"bev_resolution": 1e-3}, "bev_resolution must be >= 0.05 m per pixel"),
    ):
        with pytest.raises(ValueError, match=f"ObservationConfig.{field}"):
            ObservationConfig(**kw)
    with pytest.raises(ValueError, match="max_cycles must be a positive integer or None, got True"):
        EnvConfig(max_cycles=True)
    with pytest.raises(ValueError, match="torch_threads must be 'auto', None or an integer >= 1, got 'x'"):
        EnvConfig(torch_threads="x")
    env = raw_env(small_scenes(), npc="idm", torch_threads="auto", max_cycles=2)
    env.reset(seed=0)


def test_the_ego_envs_infos_have_the_same_keys_at_reset_and_every_step() -> None:
    """EgoEnv's reset info held `agent` and `scenario_id` only, its step info neither (the AEC and
    parallel envs keep one set of keys); BatchedEgoEnv the same."""
    from trajeglish_env.env import EgoEnv
    from trajeglish_env.env.vector import BatchedEgoEnv

    env = EgoEnv(small_scenes(), npc="idm", max_cycles=3)
    _, first = env.reset(seed=0)
    later = env.step(np.zeros(2, np.float32))[4]
    assert set(first) == set(later) >= {"agent", "scenario_id", "collision", "route_fraction"}
    assert later["agent"] == first["agent"] and first["collision"] is False
    batch = BatchedEgoEnv(2, small_scenes(), npc="idm", max_cycles=3)
    keys = {k for k in batch.reset(seed=0)[1] if not k.startswith("_")}
    assert (
        keys
        == set(first)
        == {k for k in batch.step(np.zeros((2, 2), np.float32))[4] if not k.startswith("_")}
    )
    batch.close()


def test_the_first_slot_plays_the_users_npc_object_and_an_uncopyable_one_is_shared_with_a_warning() -> None:
    """Copying for every slot broke what worked: an object's own counters never saw an episode, and one
    holding a lock could not be used at all."""
    import gc
    import threading

    from trajeglish_env.env import EgoEnv, ReplayNPC

    class Counting(ReplayNPC):
        def __init__(self) -> None:
            super().__init__()
            self.resets = 0

        def reset(self, *args, **kwargs):
            self.resets += 1
            return super().reset(*args, **kwargs)

    mine = Counting()
    first = EgoEnv(small_scenes(), npc=mine, max_cycles=3)
    first.reset(seed=0)
    first.reset(seed=1)
    assert mine.resets == 2  # the object itself plays the first env's episodes
    second = EgoEnv(small_scenes(), npc=mine, max_cycles=3)
    second.reset(seed=0)
    assert mine.resets == 2  # the second env plays a copy
    del first, second
    gc.collect()
    third = EgoEnv(small_scenes(), npc=mine, max_cycles=3)  # the first env gone: the object plays again
    third.reset(seed=0)
    assert mine.resets == 3

    class Locked(ReplayNPC):
        def __init__(self) -> None:
            super().__init__()
            self.lock = threading.Lock()

    from trajeglish_env.env.vector import BatchedEgoEnv

    with pytest.warns(UserWarning, match="Locked: cannot be copied"):
        batch = BatchedEgoEnv(2, small_scenes(), npc=Locked(), max_cycles=3)
        batch.reset(seed=0)
    batch.close()


def test_the_ego_env_takes_every_form_of_one_random_agent() -> None:
    """`RandomAgents(1, with_sdc=True)` (the sdc) and `RandomAgents(1, at_most=True)` mean one agent, yet
    EgoEnv refused them."""
    from trajeglish_env.env import EgoEnv, RandomAgents

    for external in (RandomAgents(1, with_sdc=True), RandomAgents(1, at_most=True)):
        env = EgoEnv(small_scenes(), npc="idm", external=external, max_cycles=3)
        _, info = env.reset(seed=0)
        assert info["agent"] and np.isfinite(env.step(np.zeros(2, np.float32))[1])
    sdc = EgoEnv(small_scenes(), npc="idm", external=RandomAgents(1, with_sdc=True), max_cycles=3)
    sdc.reset(seed=0)
    assert sdc.aec.sim.external_index.tolist() == [sdc.aec.scenario.sdc]
    with pytest.raises(ValueError, match="EgoEnv controls exactly one agent"):
        EgoEnv(small_scenes(), npc="idm", external=RandomAgents(2))


def test_a_named_scene_plays_the_episode_its_seed_plays_when_it_draws_that_scene() -> None:
    """Naming the scene a seed draws replays that episode (the scene draw was skipped when a scene was
    named, which shifted the episode's generator: other NPC draws), in any env holding that scene;
    numpy integer seeds are seeds."""

    def play(env, **kwargs) -> np.ndarray:
        env.reset(**kwargs)
        for _ in range(12):
            done = env.terminations[env.agent_selection] or env.truncations[env.agent_selection]
            env.step(None if done else np.zeros(2, np.float32))
        return env.unwrapped.sim.driver.xyh.copy()

    env = trajeglish_env.env(scenes=small_scenes()[:3], npc=TrajeglishNPC(tiny()))
    drawn = play(env, seed=5)
    scene = env.unwrapped.scenario.scenario_id
    assert np.array_equal(play(env, seed=5, options={"scene": scene}), drawn)
    assert np.array_equal(play(env, seed=np.int64(5)), drawn)
    # an env holding that scene alone plays the same episode (a one-scene env drew nothing for the scene:
    # its NPCs drew other numbers; the ego audit of stop 82), and so does one holding it among others
    one = next(s for s in small_scenes()[:3] if s.scenario_id == scene)
    assert np.array_equal(play(trajeglish_env.env(scenes=[one], npc=TrajeglishNPC(tiny())), seed=5), drawn)
    more = trajeglish_env.env(scenes=[*small_scenes(), one][::-1], npc=TrajeglishNPC(tiny()))
    assert np.array_equal(play(more, seed=5, options={"scene": scene}), drawn)
    ego = EgoEnv(scenes=small_scenes()[:3], npc=TrajeglishNPC(tiny()))
    assert np.array_equal(ego.reset(seed=np.int64(2))[0], ego.reset(seed=2)[0])


def test_a_refused_batched_reset_restarts_no_scene() -> None:
    """`BatchedEgoEnv(2).reset(seed=[5, -1])` restarted scene 0 with seed 5, then refused scene 1 with a
    Gymnasium error that named no scene."""
    batch = BatchedEgoEnv(2, scenes=small_scenes()[:3], npc="idm")
    batch.reset(seed=0)
    batch.step(np.zeros((2, 2), np.float32))
    before = [s.t for s in batch.core.batch.sims]
    with pytest.raises(ValueError, match="scene 1's seed must be a non-negative integer"):
        batch.reset(seed=[5, -1])
    assert [s.t for s in batch.core.batch.sims] == before
    batch.reset(seed=[np.int64(5), 6])


def test_a_scenario_given_as_the_scene_option_is_named_by_its_id() -> None:
    """`reset(options={"scene": scenario})` put the Scenario's whole repr (11,320 characters) in the error."""
    env = raw_env(small_scenes()[:2], npc="replay")
    scene = small_scenes()[1]
    with pytest.raises(TypeError, match="got the Scenario .* itself: pass options=") as err:
        env.reset(seed=0, options={"scene": scene})
    assert len(str(err.value)) < 400


def test_a_custom_npc_returning_nan_is_named_and_save_scenarios_names_swapped_arguments(tmp_path) -> None:
    """A custom NPC returning NaN got "must return finite next states [11,3] ... got (11, 3) / (11,)": the
    shapes it printed matched and it named no agent; save_scenarios with its arguments swapped failed with
    an AttributeError from inside (the RL audit of stop 82)."""
    from trajeglish_env import save_scenarios
    from trajeglish_env.env import EgoEnv, ReplayNPC

    class Broken(ReplayNPC):
        def act(self, view, agents):
            nxt, ok = super().act(view, agents)
            nxt = np.array(nxt, dtype=np.float64)
            nxt[0, 0] = np.nan
            return nxt, ok

    env = EgoEnv(small_scenes()[:1], npc=Broken(), max_cycles=3)
    env.reset(seed=0)
    with pytest.raises(
        ValueError, match=r"Broken.act returned a non-finite next state \[nan, .* for \w+_\d+ at step"
    ):
        env.step(np.zeros(2, np.float32))
    with pytest.raises(TypeError, match=r"got list and str \(swapped\?\)"):
        save_scenarios(small_scenes()[:1], str(tmp_path / "x.scn.npz"))


def test_agents_without_a_goal_earn_no_progress_reward() -> None:
    """The reset warning says so; they were paid up to route length / 10 m (QA, stop 90: a pedestrian
    2 m along its 4 m path earned +0.13)."""
    import trajeglish_env
    from trajeglish_env.env import RandomAgents

    env = trajeglish_env.parallel_env(
        npc="idm", external=RandomAgents(40, at_most=True), max_cycles=30, reward=RewardConfig(comfort=0.0)
    )
    with pytest.warns(UserWarning, match="no goal and no progress reward"):
        _, infos = env.reset(seed=0, options={"scene": "sumo-random-999000-0-0"})
    idle = [a for a in env.agents if not infos[a]["has_goal"]]
    moved = dict.fromkeys(idle, 0.0)
    paid = dict.fromkeys(idle, 0.0)
    for _ in range(30):
        if not env.agents:
            break
        out = env.step({a: np.array([1.0, 0.0], np.float32) for a in env.agents})  # full throttle
        for a in idle:
            if a in out[1]:
                paid[a] += out[1][a] if not (out[4][a]["collision"] or out[4][a]["offroad"]) else 0.0
                moved[a] = out[4][a]["progress_m"]
    assert len(idle) >= 3 and max(moved.values()) > 1.0  # they do move along their short paths
    assert all(v == 0.0 for v in paid.values()), paid
