"""Policies for external agents and the episode runner."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from helpers import MERGE, bundle_scene, small_scenes, tiny

from policies import (
    ConstantVelocityPolicy,
    IDMPolicy,
    RandomPolicy,
    ReplayPolicy,
    SB3Policy,
    TrajeglishPolicy,
    evaluate,
    play_episode,
    policy_for,
    summarize,
)
from trajeglish_env.env import TrajeglishNPC, raw_env

HIGHWAY = "highway-highway-999000"


def test_rule_based_egos_follow_their_route() -> None:
    for policy in (ReplayPolicy(), IDMPolicy()):
        env = raw_env([bundle_scene(HIGHWAY)], npc="idm")
        result = play_episode(env, policy, seed=0)
        (agent,) = result.returns
        assert (
            result.route_fraction[agent] > 0.9 and not result.collision[agent] and not result.offroad[agent]
        )
        assert result.goal[agent] and result.steps <= 80
    cv = play_episode(
        raw_env([bundle_scene(HIGHWAY)], npc="idm", max_cycles=20), ConstantVelocityPolicy(), seed=0
    )
    (agent,) = cv.returns
    speed = bundle_scene(HIGHWAY).speed()[bundle_scene(HIGHWAY).sdc, 10]
    assert cv.steps == 20 and cv.progress_m[agent] == pytest.approx(20 * 0.1 * speed, rel=0.05)


def test_random_policy_is_seeded_and_stays_in_the_space() -> None:
    env = raw_env(small_scenes(), npc="replay", max_cycles=10)
    a = play_episode(env, RandomPolicy(seed=3), seed=1)
    b = play_episode(env, RandomPolicy(seed=3), seed=1)
    c = play_episode(env, RandomPolicy(seed=4), seed=1)
    assert a == b and a.returns != c.returns


class _ConstantModel:
    """Stands in for an SB3 model: ``predict`` returns the same action for every observation."""

    def __init__(self, action: np.ndarray):
        self.action = action
        self.calls = 0

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        self.calls += 1
        batch = obs.shape[:-1]
        return np.broadcast_to(self.action, (*batch, *self.action.shape)).copy(), None


def test_sb3_policy_drives_one_or_many_agents() -> None:
    model = _ConstantModel(np.array([0.5, 0.0], dtype=np.float32))
    policy = SB3Policy(model)
    env = raw_env([bundle_scene(MERGE)], npc="replay", external="all", max_cycles=4)
    result = play_episode(env, lambda agent: policy, seed=0)  # a factory: the same policy for all agents
    assert len(result.returns) == 5 and model.calls > 0
    batch = policy.act_many({"a": np.zeros(300, np.float32), "b": np.ones(300, np.float32)})
    assert set(batch) == {"a", "b"} and batch["b"].tolist() == [0.5, 0.0]
    token = SB3Policy(_ConstantModel(np.array(7)))
    assert token.act(None, "x", np.zeros(3)) == 7


def test_trajeglish_policy_drives_an_external_agent() -> None:
    env = raw_env([bundle_scene(MERGE)], npc=TrajeglishNPC(tiny()), action="token", max_cycles=5)
    policy = TrajeglishPolicy(tiny())
    a = play_episode(env, policy, seed=0)
    b = play_episode(env, TrajeglishPolicy(tiny()), seed=0)
    assert a.steps >= 1 and a.returns == b.returns
    other = raw_env([bundle_scene(MERGE)], npc="idm", action="token")  # the shipped model's vocabulary
    other.reset(seed=0)
    shipped = raw_env([bundle_scene(MERGE)], action="token")  # as with the shipped model's NPCs: one V
    assert other.action_space(other.agent_selection) == shipped.action_space(other.agent_selection)
    assert other.action_space(other.agent_selection).n == 2048
    with pytest.raises(
        ValueError, match="checkpoint's vocabulary .* does not match the env's token vocabulary"
    ):
        policy.reset(other, other.agent_selection)


def test_runner_maps_agents_and_summarises() -> None:
    env = raw_env([bundle_scene(MERGE)], npc="replay", external="all", max_cycles=3)
    env.reset(seed=0)
    names = list(env.agents)
    mapping = {name: (ReplayPolicy() if k % 2 else ConstantVelocityPolicy()) for k, name in enumerate(names)}
    result = play_episode(env, mapping, seed=0)
    assert sorted(result.returns) == sorted(names) and result.steps == 3
    with pytest.raises(KeyError, match="no policy for agent"):
        policy_for({"someone": ReplayPolicy()}, names[0])
    summary = summarize([result, result])
    assert summary["episodes"] == 2 and summary["agents"] == 10
    assert summary["collision_rate"] == np.mean(list(result.collision.values()))
    assert summary["mean_progress_m"] == pytest.approx(np.mean(list(result.progress_m.values())))
    several = evaluate(raw_env(small_scenes(), npc="idm", max_cycles=5), IDMPolicy(), 3, scenes=[0, 1, 2])
    assert several["episodes"] == 3 and several["mean_steps"] == 5


class _RamAhead:
    """vehicle_7 stands; every other external agent drives 4 m a step along y = 0 (into it)."""

    def reset(self, env, agent) -> None:
        return None

    def act(self, env, agent, obs):
        raw = env.unwrapped
        if agent == "vehicle_7":
            return np.zeros(3, np.float32)
        x = raw.sim.driver.xyh[raw.agent_index(agent), raw.sim.t]
        return raw.action_towards(agent, np.array([x[0] + 4.0, 0.0, 0.0]))


def test_an_episode_counts_a_collision_at_any_step_not_only_the_last() -> None:
    """With collisions not ending the episode, the agents that ran into each other mid-episode and drove
    apart are still counted (the flags of the last step alone said 0)."""
    from trajeglish_env.env import RewardConfig

    reward = RewardConfig(terminate_on_collision=False, terminate_on_offroad=False)
    env = raw_env(npc="replay", action="delta", external=(5, 7), max_cycles=60, reward=reward)
    result = play_episode(env, _RamAhead(), seed=0, options={"scene": 0})
    assert result.collision == {"vehicle_5": True, "vehicle_7": True}
    assert summarize([result])["collision_rate"] == 1.0


def test_a_policy_object_played_again_plays_the_same_episode() -> None:
    """``reset`` starts each episode afresh: an IDM or Trajeglish policy reused on the same seed and scene
    gives what a new one gives (before, the IDM kept its path state and the model its draw counter)."""
    env = raw_env(npc="idm")
    idm = IDMPolicy()
    runs = [play_episode(env, p, seed=0, options={"scene": 15}) for p in (idm, idm, IDMPolicy())]
    assert runs[0] == runs[1] == runs[2]
    env = raw_env([bundle_scene(MERGE)], npc=TrajeglishNPC(tiny()), action="token", max_cycles=4)
    model = TrajeglishPolicy(tiny())
    runs = [play_episode(env, p, seed=s) for p, s in ((model, 0), (model, 0), (TrajeglishPolicy(tiny()), 0))]
    assert runs[0] == runs[1] == runs[2]
    assert play_episode(env, model, seed=1).progress_m != runs[0].progress_m  # the episode seed drives it


def test_policy_mistakes_are_named() -> None:
    from policies import FunctionPolicy

    env = raw_env([bundle_scene(HIGHWAY)], npc="idm", max_cycles=3)
    with pytest.raises(TypeError, match="is the class IDMPolicy, not an object of it: pass IDMPolicy()"):
        play_episode(env, IDMPolicy, seed=0)
    with pytest.raises(TypeError, match="a function observation -> action is not a policy.*FunctionPolicy"):
        play_episode(env, lambda obs: np.zeros(2, np.float32), seed=0)
    with pytest.raises(TypeError, match=r"\(object\) has no reset and no act method"):
        play_episode(env, object(), seed=0)
    result = play_episode(env, FunctionPolicy(lambda obs: np.zeros(2, np.float32)), seed=0)
    assert result.steps == 3


def test_a_random_policy_played_again_plays_the_same_episode() -> None:
    """Its draws were seeded by how many agents the object had seen: the same seed and scene gave another
    episode the second time."""
    env = raw_env(npc="constant_velocity", max_cycles=10)
    policy = RandomPolicy(seed=0)
    runs = [play_episode(env, policy, seed=0, options={"scene": 0}) for _ in range(2)]
    play_episode(env, policy, seed=0, options={"scene": 1})
    runs.append(play_episode(env, policy, seed=0, options={"scene": 0}))
    assert (
        runs[0] == runs[1] == runs[2] == play_episode(env, RandomPolicy(seed=0), seed=0, options={"scene": 0})
    )
    assert play_episode(env, RandomPolicy(seed=1), seed=0, options={"scene": 0}).returns != runs[0].returns


def test_the_idm_ego_pulls_away_from_a_stop_beside_its_curving_path() -> None:
    """A roundabout where the IDM ego stopped 0.15-0.2 m beside its path with the road ahead free: its
    throttle came from the target's distance ahead in the car's frame, and the next centimetre of a
    curving path lay behind its nose, so it stood for the last 59 steps (8 m driven); the throttle is
    IDM's own acceleration now."""
    import trajeglish_env
    from trajeglish_env.sources.highway import generate_scene

    env = trajeglish_env.env(scenes=[generate_scene("roundabout", seed=512415398)], npc="idm")
    env.reset(seed=0)
    policy = IDMPolicy()
    policy.reset(env, env.agents[0])
    standing = 0
    for agent in env.agent_iter():
        obs, _, done, cut, info = env.last()
        if done or cut:
            env.step(None)
            continue
        env.step(policy.act(env, agent, obs))
        standing += env.unwrapped.sim.kin.speed[env.unwrapped.agent_index(agent)] < 0.05
    assert standing == 0 and info["progress_m"] > 30.0


def test_one_idm_policy_drives_two_envs_at_once_as_it_drives_one() -> None:
    """The controller kept one episode's state: driving two envs in lockstep rebuilt it at every switch
    and both egos left the road (53 m driven against 151 m); its state is per env now, and it pickles
    without the simulation it last drove (437 KB before, with IDM NPCs)."""
    import pickle

    import trajeglish_env

    def drive(envs: list, policy: IDMPolicy) -> list[float]:
        for k, env in enumerate(envs):
            env.reset(seed=k, options={"scene": 0})
        policy.reset(envs[0], envs[0].agents[0])
        while any(env.agents for env in envs):
            for env in envs:
                if not env.agents:
                    continue
                obs, _, done, cut, _ = env.last()
                env.step(None if done or cut else policy.act(env, env.agent_selection, obs))
        return [float(env.unwrapped.sim.progress[0]) for env in envs]

    alone = drive([trajeglish_env.env(npc="idm")], IDMPolicy())
    shared = IDMPolicy()
    together = drive([trajeglish_env.env(npc="idm") for _ in range(2)], shared)
    assert together == pytest.approx([alone[0]] * 2) and alone[0] > 100.0
    assert len(pickle.dumps(shared)) < 1000


def test_an_ego_parked_in_the_log_is_named_and_not_counted_as_missing_its_goal() -> None:
    """The shared WOMD scene's sdc is parked (a 0 m route): its info read route_fraction 0 while its
    observation read 1, nothing said it had no reward to earn, and the goal rate counted it as a failure
    (replaying every agent's log: goal rate 0.40, 28 of 50 agents with no goal)."""
    from helpers import womd_tfrecord

    import trajeglish_env
    from policies import ReplayPolicy, play_episode, summarize
    from trajeglish_env.sources.womd import read_womd

    scene = next(read_womd(womd_tfrecord()))
    with pytest.warns(UserWarning, match=r"external agent\(s\) vehicle_2406 move less than .* no goal"):
        env = trajeglish_env.env(scenes=[scene], npc="replay", max_cycles=5)
        env.reset(seed=0)
    obs, *_, info = env.last()
    assert info["has_goal"] is False and info["route_fraction"] == 1.0 == obs[5]
    result = play_episode(env, ReplayPolicy(), seed=0)
    assert result.has_goal == {"vehicle_2406": False}
    summary = summarize([result])
    assert summary["agents_with_goal"] == 0.0 and summary["goal_rate"] is None  # no goal: undefined
    assert summary["mean_route_fraction"] is None
    json.loads(json.dumps(summary, allow_nan=False))  # strict JSON, as the result of play_episode
    json.loads(json.dumps(dataclasses.asdict(result), allow_nan=False))


@pytest.mark.parametrize("make", [IDMPolicy, ReplayPolicy, RandomPolicy])
def test_the_policies_drive_the_ego_of_a_gymnasium_ego_env(make) -> None:
    """`IDMPolicy().act(EgoEnv(...), ...)` failed with "'EgoEnv' object has no attribute 'sim'" and
    RandomPolicy called the Box it got as env.action_space; a policy drives an EgoEnv's ego now, as
    the AEC env's (IDM: the same episode)."""
    from trajeglish_env.env import EgoEnv

    ego = EgoEnv(small_scenes()[:2], npc="idm", max_cycles=15)
    obs, _ = ego.reset(seed=3)
    policy = make()
    policy.reset(ego, ego.agent)
    done = cut = False
    while not (done or cut):
        action = policy.act(ego, ego.agent, obs)
        assert ego.action_space.contains(action)
        obs, _, done, cut, info = ego.step(action)
    if make is IDMPolicy:
        env = raw_env(small_scenes()[:2], npc="idm", max_cycles=15)
        result = play_episode(env, IDMPolicy(), seed=3)
        assert info["progress_m"] == pytest.approx(result.progress_m[info["agent"]])


def test_a_function_given_as_policies_and_a_bad_video_path_fail_before_the_episode(tmp_path) -> None:
    """A plain function observation -> action passed as ``policies`` is called as a factory with the agent
    name: its error is named as that (it was an IndexError from inside the function); a video path of the
    wrong kind is refused before the episode plays (it was refused after the whole episode)."""
    env = raw_env(small_scenes()[:1], max_cycles=3)

    def lane_keeper(observation):
        return np.array([observation[0] * 0.0, 0.0])

    with pytest.raises(TypeError, match="lane_keeper was called with the agent name .* FunctionPolicy"):
        play_episode(env, lane_keeper, seed=0)
    with pytest.raises(ValueError, match=r"x\.avi: expected a \.gif or \.mp4 output path"):
        play_episode(env, ReplayPolicy(), seed=0, video=tmp_path / "x.avi")


def test_play_episode_plays_an_ego_envs_aec_env_and_refuses_other_objects() -> None:
    import gymnasium

    import trajeglish_env  # noqa: F401 (registers the ids)
    from policies import ConstantVelocityPolicy, play_episode

    ego = gymnasium.make("trajeglish_env/EgoIDM-v0", max_cycles=5)  # wrapped (OrderEnforcing, PassiveChecker)
    result = play_episode(ego, ConstantVelocityPolicy(), seed=0)
    assert result.steps == 5 and [a[:8] for a in result.returns] == ["vehicle_"]  # its ego alone
    with pytest.raises(TypeError, match="a PettingZoo AEC env .* or an EgoEnv .*, got dict"):
        play_episode({}, ConstantVelocityPolicy())
