"""Batched envs play every intra-timestep order exactly as separate envs do; a step validates every
scene's actions before anything moves; SB3's vector env keeps the final step's info."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import MERGE, assert_batched_ego_env_equals_separate_envs, tiny
from stable_baselines3.common.vec_env import DummyVecEnv

from trajeglish_env.env import EgoEnv, RewardConfig, TrajeglishNPC, parallel_env
from trajeglish_env.env.config import RandomAgents
from trajeglish_env.env.sb3 import SB3VecEnv
from trajeglish_env.env.vector import BatchedParallelEnv
from trajeglish_env.sampler.config import SamplingConfig

KEEP_GOING = RewardConfig(terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False)
RING = "highway-roundabout-999001"
FLOAT32 = SamplingConfig(compute_dtype="float32")  # a batch multiplies as one env (see the README)


def same_dicts(got: dict, want: dict) -> bool:
    """Equal keys and values (arrays compared exactly)."""
    return got.keys() == want.keys() and all(np.array_equal(got[k], want[k]) for k in got)


@pytest.mark.parametrize("order", ["last", "random"])
def test_batched_parallel_env_equals_separate_envs_for_every_order(order: str) -> None:
    kw = {"npc": TrajeglishNPC(tiny()), "external": "all", "order": order, "max_cycles": 4}
    penv = BatchedParallelEnv(2, **kw)
    options = [{"scene": MERGE}, {"scene": RING}]
    refs = [parallel_env(**kw) for _ in range(2)]
    obs = [penv.reset_scenes([i], seed=7 + i, options=o)[0][0] for i, o in enumerate(options)]
    for i, ref in enumerate(refs):
        assert same_dicts(obs[i], ref.reset(seed=7 + i, options=options[i])[0])
    for _ in range(5):
        actions = [{a: penv.action_space(a).sample() for a in agents} for agents in penv.agents]
        out = penv.step(actions)
        for i, ref in enumerate(refs):
            if not ref.agents:
                assert out[0][i] == {} and penv.agents[i] == []
                continue
            want = ref.step(actions[i])
            assert same_dicts(out[0][i], want[0])  # observations, where the next step's first agent acts
            assert out[1][i] == pytest.approx(dict(want[1]))
            assert out[2][i] == want[2] and out[3][i] == want[3] and out[4][i] == want[4]
            assert penv.agents[i] == ref.agents


def test_batched_ego_env_acting_last_equals_separate_envs_with_autoreset() -> None:
    assert_batched_ego_env_equals_separate_envs(
        {"npc": TrajeglishNPC(tiny()), "order": "last", "max_cycles": 5}
    )


@pytest.mark.parametrize("order", ["last", "random"])
def test_five_scenes_with_the_ego_later_in_the_step_equal_separate_envs(order: str) -> None:
    """Each row stands at its own ego when observed, whatever subset of its step the ego comes in and
    wherever the other rows wait: with five scenes restarting at different steps (their clocks apart), rows
    whose egos come in different subsets share the engine's steps (each row has its own subset cursor)."""
    assert_batched_ego_env_equals_separate_envs(
        {"npc": TrajeglishNPC(tiny(), FLOAT32), "order": order, "max_cycles": 9},
        steps=24,
        seed=3,
        scenes=5,
    )


@pytest.mark.parametrize("order", ["last", "random"])
def test_three_external_agents_in_five_scenes_equal_separate_envs_through_staggered_restarts(
    order: str,
) -> None:
    """Three external agents per scene, anywhere in their step (``RandomAgents(3)``), five scenes restarted
    one at a time at different steps (the others' unfinished step undone and redone) and when their episodes
    end: every observation, reward and agent list equals that of five separate parallel envs."""
    kw = {"npc": TrajeglishNPC(tiny(), FLOAT32), "external": RandomAgents(3), "order": order, "max_cycles": 6}
    n, restarts = 5, {3: 1, 5: 3, 8: 0, 11: 4}
    penv = BatchedParallelEnv(n, **kw)
    refs = [parallel_env(**kw) for _ in range(n)]
    seeds = [20 + i for i in range(n)]

    def restart(i: int, seed: int) -> None:
        seeds[i] = seed
        assert same_dicts(penv.reset_scenes([i], seed=seed)[0][0], refs[i].reset(seed=seed)[0])

    for i in range(n):
        restart(i, seeds[i])
    rng = np.random.default_rng(0)
    ended = 0
    for k in range(16):
        if k in restarts:
            restart(restarts[k], seeds[restarts[k]] + 100)
        actions = [{a: rng.uniform(-1, 1, 2).astype(np.float32) for a in agents} for agents in penv.agents]
        out = penv.step(actions)
        for i, ref in enumerate(refs):
            want = ref.step(actions[i])
            assert same_dicts(out[0][i], want[0]) and out[1][i] == pytest.approx(dict(want[1]))
            assert penv.agents[i] == ref.agents
            if not ref.agents:
                ended += 1
                restart(i, seeds[i] + 1000)
    assert ended >= n  # every scene's episode also ended and restarted


def test_a_bad_action_in_one_scene_changes_nothing_and_a_retry_plays_on() -> None:
    kw = {"npc": "idm", "external": "all", "max_cycles": 6, "reward": KEEP_GOING}
    penv = BatchedParallelEnv(2, **kw)
    penv.reset(seed=[3, 4], options={"scene": MERGE})
    refs = [parallel_env(**kw) for _ in range(2)]
    for ref, s in zip(refs, [3, 4], strict=True):
        ref.reset(seed=s, options={"scene": MERGE})
    steps = [penv.core.sim(i).t for i in range(2)]
    states = [penv.core.sim(i).driver.xyh.copy() for i in range(2)]
    good = [{a: np.zeros(2, np.float32) for a in agents} for agents in penv.agents]
    bad = [dict(good[0]), dict(good[1])]
    last = penv.agents[1][-1]
    bad[1][last] = np.array([5.0, 0.0], np.float32)
    with pytest.raises(ValueError, match=f"agent {last}: action .* outside the action space"):
        penv.step(bad)
    unknown = [dict(good[0]), {**good[1], "vehicle_999999": np.zeros(2, np.float32)}]
    with pytest.raises(KeyError, match="scene 1 has no live agent"):
        penv.step(unknown)
    assert [penv.core.sim(i).t for i in range(2)] == steps
    assert all(np.array_equal(penv.core.sim(i).driver.xyh, s) for i, s in enumerate(states))
    out = penv.step(good)  # the retry plays exactly what separate envs play
    for i, ref in enumerate(refs):
        want = ref.step(good[i])
        assert same_dicts(out[0][i], want[0]) and out[1][i] == pytest.approx(dict(want[1]))


def test_the_unbatched_parallel_env_checks_every_action_before_any_agent_acts() -> None:
    env = parallel_env(npc="idm", external="all", max_cycles=4)
    env.reset(seed=0, options={"scene": MERGE})
    raw = env.aec_env.unwrapped
    t, agents = raw.sim.t, list(env.agents)
    actions = {a: np.zeros(2, np.float32) for a in agents}
    with pytest.raises(KeyError, match=f"no action for agent\\(s\\) \\['{agents[-1]}'\\]"):
        env.step({a: actions[a] for a in agents[:-1]})
    with pytest.raises(KeyError, match="no live agent"):
        env.step({**actions, "vehicle_123456789": np.zeros(2, np.float32)})
    with pytest.raises(ValueError, match=f"agent {agents[-1]}: action"):
        env.step({**actions, agents[-1]: np.array([0.0, 9.0], np.float32)})
    assert raw.sim.t == t and raw.agent_selection == agents[0]
    env.step(actions)
    assert raw.sim.t == t + 1


def test_sb3_vec_env_reports_the_final_steps_info_at_an_episode_end() -> None:
    kw = {"npc": "idm", "max_cycles": 3}
    vec = SB3VecEnv(2, **kw)
    ref = DummyVecEnv([lambda: EgoEnv(**kw) for _ in range(2)])
    vec.seed(5)
    ref.seed(5)
    vec.reset(), ref.reset()
    for _ in range(3):
        got, want = vec.step(np.zeros((2, 2), np.float32)), ref.step(np.zeros((2, 2), np.float32))
    assert got[2].all() and want[2].all()  # the episodes ended at this step
    for g, w in zip(got[3], want[3], strict=True):
        assert {"collision", "offroad", "goal", "progress_m", "route_fraction"} <= g.keys()
        assert np.array_equal(g.pop("terminal_observation"), w.pop("terminal_observation"))
        assert g == w


def test_actions_for_finished_agents_are_ignored_and_unknown_names_refused() -> None:
    """PettingZoo's parallel envs ignore actions for agents that have finished (a loop over the last step's
    observations passes them); a name the episode never had is still a KeyError naming it."""
    from gymnasium import spaces

    from trajeglish_env.env.batch_api import check_scene_actions

    box = spaces.Box(-1.0, 1.0, (2,), np.float32)
    zero = np.zeros(2, np.float32)
    checked = check_scene_actions([["a"]], [{"a": zero, "b": zero}], lambda name: box, [{"a", "b"}])
    assert len(checked) == 1 and len(checked[0]) == 1  # only the live agent's action is played
    with pytest.raises(KeyError, match=r"scene 0 has no live agent\(s\) \['c'\]"):
        check_scene_actions([["a"]], [{"a": zero, "c": zero}], lambda name: box, [{"a", "b"}])
    with pytest.raises(KeyError, match="no live agent"):
        check_scene_actions([["a"]], [{"a": zero, "b": zero}], lambda name: box)


def two_scenes() -> BatchedParallelEnv:
    """Scene 0 on the merge, scene 1 on the roundabout, every agent external (IDM NPCs: fast)."""
    penv = BatchedParallelEnv(2, npc="idm", external="all", max_cycles=6, reward=KEEP_GOING)
    for i, scene in enumerate([MERGE, RING]):
        penv.reset_scenes([i], seed=i, options={"scene": scene})
    return penv


def test_one_dict_for_a_batch_is_a_type_error_naming_the_expected_list() -> None:
    """PettingZoo's single-env format (one dict) on a batch: a TypeError, not a bare ``KeyError: 0`` (or,
    with one key, a count that reads like a wrong number of scenes)."""
    penv = two_scenes()
    t = [penv.core.sim(i).t for i in range(2)]
    zero = np.zeros(2, np.float32)
    expected = r"step: expected a list of 2 action dicts \(one per scene\), got a dict"
    with pytest.raises(TypeError, match=expected):
        penv.step({a: zero for a in penv.agents[0][:2]})
    with pytest.raises(TypeError, match=expected):
        penv.step({penv.agents[0][0]: zero})
    not_a_dict = r"scene 1's actions must be a dict agent name -> action, got ndarray"
    with pytest.raises(TypeError, match=not_a_dict):
        penv.step([{a: zero for a in penv.agents[0]}, np.zeros((len(penv.agents[1]), 2), np.float32)])
    assert [penv.core.sim(i).t for i in range(2)] == t  # nothing moved
    penv.step(tuple({a: zero for a in agents} for agents in penv.agents))  # a tuple of dicts is a list
    assert [penv.core.sim(i).t for i in range(2)] == [s + 1 for s in t]


def test_a_bad_action_names_its_scene_and_scenario_as_agent_names_repeat_across_scenes() -> None:
    penv = two_scenes()
    actions = [{a: np.zeros(2, np.float32) for a in agents} for agents in penv.agents]
    agent = penv.agents[1][0]
    actions[1][agent] = np.zeros(3, np.float32)
    named = f"step: scene 1 \\({RING}\\): agent {agent}: action"
    with pytest.raises(ValueError, match=named + r" .* must be a finite array of shape \(2,\)"):
        penv.step(actions)
    actions[1][agent] = np.array([0.0, 4.0], np.float32)
    with pytest.raises(ValueError, match=named + " .* outside the action space"):
        penv.step(actions)


def test_reset_scenes_refuses_bools_floats_a_lone_int_out_of_range_and_repeated_indices() -> None:
    penv = two_scenes()
    penv.step([{a: np.zeros(2, np.float32) for a in agents} for agents in penv.agents])
    t = [penv.core.sim(i).t for i in range(2)]
    with pytest.raises(TypeError, match=r"reset_scenes: scene index True \(bool\) is not an integer; "):
        penv.reset_scenes([True])  # was scene 1
    with pytest.raises(TypeError, match=r"scene index 0\.0 \(float\) is not an integer; expected integers"):
        penv.reset_scenes([0.0])  # was scene 0
    with pytest.raises(TypeError, match=r"expected a sequence of scene indices \(integers in \[0, 2\)\)"):
        penv.reset_scenes(1)
    with pytest.raises(ValueError, match=r"scene indices \[2\] out of range for 2 scenes"):
        penv.reset_scenes([0, 2])
    with pytest.raises(ValueError, match=r"reset_scenes: scene indices \[0\] listed more than once"):
        penv.reset_scenes([0, 1, 0], seed=7)  # was scene 0 restarted twice, two copies of its observations
    assert [penv.core.sim(i).t for i in range(2)] == t  # nothing restarted
    obs, _ = penv.reset_scenes(np.array([1]), seed=5)  # NumPy integers are indices
    assert len(obs) == 1 and penv.core.sim(1).t < t[1] and penv.core.sim(0).t == t[0]


def test_a_batched_parallel_env_shows_each_scenes_simulation_to_a_centralised_critic() -> None:
    """README "Several learned agents in one scene": ``penv.sim(i).view()`` (there is no ``unwrapped``)."""
    penv = two_scenes()
    for i, scene in enumerate([MERGE, RING]):
        view = penv.sim(i).view()
        assert view.scenario.scenario_id == scene and view.t == penv.core.sim(i).t
        sim = penv.core.sim(i)
        assert penv.sim(i) is sim and view.xyh.shape[0] == view.scenario.num_agents
        assert {sim.names[a] for a in np.flatnonzero(view.external)} >= set(penv.agents[i])
