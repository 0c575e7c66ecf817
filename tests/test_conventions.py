"""PettingZoo's and Gymnasium's conventions to the letter: fixed ``possible_agents`` by slot names (the stock
wrappers then work), ``parallel_to_aec`` giving the order-enforced env back, ``np_random`` as the generator
the env draws from, and the vector envs' seeded ``np_random`` and ``reset_mask``."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
from helpers import MERGE
from pettingzoo.test import api_test, parallel_api_test
from pettingzoo.utils.conversions import aec_to_parallel, parallel_to_aec
from pettingzoo.utils.wrappers import OrderEnforcingWrapper

import trajeglish_env
from trajeglish_env.env import EgoEnv, EnvConfig, RandomAgents
from trajeglish_env.env.split import SplitEgoEnv
from trajeglish_env.env.vector import BatchedEgoEnv
from trajeglish_env.scenario import agent_name


def _slots(**kw: object) -> trajeglish_env.env.aec.raw_env:
    return trajeglish_env.env.aec.raw_env(npc="idm", agent_names="slot", max_cycles=6, **kw)


def test_slot_names_keep_possible_agents_for_the_envs_life() -> None:
    env = _slots(external=RandomAgents(3, with_sdc=True, at_most=True))
    fixed = ["agent_0", "agent_1", "agent_2"]
    assert env.possible_agents == fixed and env.max_num_agents == 3
    tracks = set()
    for seed in range(4):  # other scenes, other agents: the same names
        env.reset(seed=seed)
        assert env.possible_agents == fixed and set(env.agents) <= set(fixed)
        sdc = env.sim.sc.sdc
        assert env.agent_index("agent_0") == sdc  # with_sdc: the sdc takes the first slot
        tracks.add(env.agent_track("agent_0"))
        assert env.agent_track("agent_0") == agent_name(env.scenario.kind[sdc], env.scenario.track_id[sdc])
    assert len(tracks) > 1  # the slot's car changes with the scene, its name does not
    # the stock wrapper copies possible_agents once: with slot names its API test passes
    parallel_api_test(aec_to_parallel(_slots(external=RandomAgents(2, at_most=True))), num_cycles=20)
    api_test(OrderEnforcingWrapper(_slots(external=RandomAgents(2, at_most=True))), num_cycles=20)


def test_with_track_names_each_episode_has_its_own_possible_agents() -> None:
    env = trajeglish_env.env.aec.raw_env(npc="idm", max_cycles=3)
    seen = set()
    for seed in range(4):
        env.reset(seed=seed)
        assert env.possible_agents == env.agents and env.agents[0].startswith("vehicle_")
        seen.add(env.agents[0])
    assert len(seen) > 1


def test_slot_names_take_an_order_by_slot_and_ignore_absent_slots_actions() -> None:
    env = trajeglish_env.parallel_env(
        npc="idm",
        agent_names="slot",
        external=RandomAgents(9, at_most=True),
        max_cycles=3,
        order=("agent_1",),
    )
    obs, _ = env.reset(seed=0, options={"scene": MERGE})  # 5 vehicles: slots 5 to 8 stay empty
    assert env.possible_agents == [f"agent_{j}" for j in range(9)] and sorted(obs) == sorted(env.agents)
    assert len(env.agents) == 5
    raw = env.aec_env.unwrapped
    assert raw.agents[0] == "agent_1"  # the explicit order names slots
    actions = {a: np.zeros(2, np.float32) for a in env.possible_agents}  # a library acting for every slot
    out = env.step(actions)
    assert sorted(out[0]) == sorted(env.agents) and raw.sim.t == raw.scenario.current_index + 1
    with pytest.raises(KeyError, match="no live agent"):
        env.step({**actions, "agent_9": np.zeros(2, np.float32)})


def test_slot_names_refuse_external_all_and_unknown_styles() -> None:
    with pytest.raises(ValueError, match=r"RandomAgents\(k, at_most=True\)"):
        EnvConfig(external="all", agent_names="slot")
    with pytest.raises(ValueError, match=r"agent_names: expected one of \('track', 'slot'\), got 'slots'"):
        EnvConfig(agent_names="slots")
    assert EnvConfig(external=(3, 7), agent_names="slot").slot_names == ["agent_0", "agent_1"]
    assert EnvConfig().slot_names is None


def test_parallel_to_aec_gives_the_order_enforced_env_back() -> None:
    par = trajeglish_env.parallel_env(npc="idm", max_cycles=3)
    aec = parallel_to_aec(par)
    assert isinstance(aec, OrderEnforcingWrapper)
    with pytest.raises(Exception, match="reset"):  # the wrapper's check: step before reset
        aec.step(np.zeros(2, np.float32))


def test_ego_env_np_random_is_the_generator_it_draws_scenes_from() -> None:
    env = EgoEnv(npc="idm", max_cycles=3)
    env.reset(seed=11)
    assert env.np_random is env.aec.unwrapped.np_random and env.np_random_seed == 11
    before = env.np_random.bit_generator.state
    env.reset()  # an unseeded reset draws from it
    assert env.np_random.bit_generator.state != before

    def scenes(gen: np.random.Generator) -> list[str]:
        env.np_random = gen
        assert env.np_random_seed == -1  # Gymnasium's mark of a generator set by hand
        return [env.reset()[1]["scenario_id"] for _ in range(6)]

    first = scenes(np.random.default_rng(3))
    assert scenes(np.random.default_rng(3)) == first  # the generator set is the one drawn from
    assert scenes(np.random.default_rng(4)) != first


@pytest.mark.parametrize("split", [False, True])
def test_vector_envs_seed_np_random_and_reset_only_the_masked_scenes(split: bool) -> None:
    kw = dict(npc="idm", max_cycles=20)
    venv = SplitEgoEnv(3, processes=2, **kw) if split else BatchedEgoEnv(3, **kw)
    try:
        venv.reset(seed=5)
        first = venv.np_random.integers(10**9)
        venv.reset(seed=5)
        assert venv.np_random_seed == 5 and venv.np_random.integers(10**9) == first
        for _ in range(3):
            obs, *_ = venv.step(np.zeros((3, 2), np.float32))
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the mask is read, not passed on as an unknown option
            again, infos = venv.reset(seed=50, options={"reset_mask": np.array([False, True, False])})
        assert infos["_agent"].tolist() == [False, True, False]
        assert np.array_equal(again[[0, 2]], obs[[0, 2]])  # the other scenes go on where they were
        fresh, _ = BatchedEgoEnv(3, **kw).reset(seed=50)
        assert np.array_equal(again[1], fresh[1])  # scene 1 with its seed of the list, 50 + 1
        for bad, error in [
            ([True, False, False], TypeError),
            (np.array([1, 0, 0]), TypeError),
            (np.array([True, False]), ValueError),
            (np.zeros(3, bool), ValueError),
        ]:
            with pytest.raises(error, match="reset_mask"):
                venv.reset(options={"reset_mask": bad})
    finally:
        venv.close()


def test_env_warnings_point_at_the_callers_line_and_name_slots_with_their_car() -> None:
    env = trajeglish_env.env(
        npc="idm", agent_names="slot", external=RandomAgents(40, at_most=True), max_cycles=3
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env.reset(
            seed=0, options={"scene": "sumo-random-999000-0-0", "sceen": 1}
        )  # through PettingZoo's wrapper
    assert [w.filename for w in caught] == [__file__, __file__]  # not a line inside the env or PettingZoo
    options, goal = (str(w.message) for w in caught)
    assert "'sceen' ignored" in options
    slot = re.search(r"external agent\(s\) (agent_\d+) \(((vehicle|pedestrian|cyclist)_\d+)\)", goal)
    assert slot is not None and env.unwrapped.agent_track(slot.group(1)) == slot.group(2)


def test_slot_names_give_a_fixed_size_global_state() -> None:
    from pettingzoo.test import state_test

    kw = dict(
        npc="idm", agent_names="slot", external=RandomAgents(3, with_sdc=True, at_most=True), max_cycles=8
    )
    state_test(trajeglish_env.env(**kw), trajeglish_env.parallel_env(**kw), num_cycles=10)  # PettingZoo's
    env = trajeglish_env.parallel_env(**kw)
    obs, _ = env.reset(seed=0, options={"scene": MERGE})
    state = env.state()
    d = env.observation_space("agent_0").shape[0]
    assert state.shape == env.state_space.shape == (3 * d,)
    for j in range(3):  # each slot's observation in its place
        assert np.array_equal(state[j * d : (j + 1) * d], obs[f"agent_{j}"])
    raw = trajeglish_env.raw_env(npc="idm", max_cycles=3)  # track names: no fixed size
    raw.reset(seed=0)
    assert not hasattr(raw, "state_space")
    with pytest.raises(NotImplementedError, match="agent_names='slot'"):
        raw.state()
