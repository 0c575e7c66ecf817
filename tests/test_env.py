"""Conformance of the environments: PettingZoo's API, parallel API, seed, max-cycles and render tests,
Gymnasium's and SB3's env checkers, the registries and SubprocVecEnv (spawn)."""

from __future__ import annotations

import os
import warnings

import numpy as np
from helpers import small_scenes, tiny, tiny_kwargs

from trajeglish_env.env import EgoEnv, RewardConfig, TrajeglishNPC, env, parallel_env, raw_env

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # the "human" render mode opens a pygame window


def test_pettingzoo_api_test_with_every_agent_external() -> None:
    from pettingzoo.test import api_test

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # api_test warns about e.g. observations that are not all zeros
        api_test(env(small_scenes(), **tiny_kwargs(external="all")), num_cycles=20)


def test_pettingzoo_parallel_api_test() -> None:
    from pettingzoo.test import parallel_api_test

    parallel_api_test(
        parallel_env(small_scenes(), **tiny_kwargs(external="all", order="last")), num_cycles=20
    )


def test_pettingzoo_seed_test() -> None:
    from pettingzoo.test import seed_test

    seed_test(lambda: env(small_scenes(), **tiny_kwargs(external="all", order="random")), num_cycles=6)


NEVER_TERMINATE = RewardConfig(
    terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False
)


class _Module:
    """What ``max_cycles_test`` expects: a module with ``env`` and ``parallel_env`` taking ``max_cycles``
    (random actions would end episodes early by collision or off-road, so only truncation ends them)."""

    @staticmethod
    def env(**kwargs: object) -> object:
        return env(small_scenes()[:1], npc=TrajeglishNPC(tiny()), reward=NEVER_TERMINATE, **kwargs)

    @staticmethod
    def parallel_env(**kwargs: object) -> object:
        return parallel_env(small_scenes()[:1], npc=TrajeglishNPC(tiny()), reward=NEVER_TERMINATE, **kwargs)


def test_pettingzoo_max_cycles_test() -> None:
    from pettingzoo.test import max_cycles_test

    max_cycles_test(_Module)


def test_pettingzoo_render_test_in_both_modes() -> None:
    from pettingzoo.test import render_test

    def make(render_mode: str | None = None) -> object:
        return env(small_scenes()[:1], npc="replay", render_mode=render_mode, render_size=64)

    render_test(make)
    e = make("rgb_array")
    e.reset(seed=0)
    frame = e.render()
    assert frame.shape == (64, 64, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 3  # map and agents drawn, not a blank image


def test_gymnasium_and_sb3_check_env() -> None:
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(EgoEnv(small_scenes(), **tiny_kwargs()))
        sb3_check_env(EgoEnv(small_scenes(), **tiny_kwargs(observation="bev", action="token")))
        check_env(EgoEnv(small_scenes(), **tiny_kwargs(action="delta")))


def test_registered_with_gymnasium_and_pettingzoo() -> None:
    import gymnasium
    import pettingzoo

    import trajeglish_env

    ego = gymnasium.make("trajeglish_env/EgoIDM-v0", scenes=small_scenes(), max_cycles=3)
    obs, info = ego.reset(seed=0)
    assert obs.shape == ego.observation_space.shape and info["agent"].startswith("vehicle_")
    # make_vec's vector entry point: the batched env (one model call for all scenes)
    from trajeglish_env.env.vector import BatchedEgoEnv

    venv = gymnasium.make_vec(
        "trajeglish_env/EgoIDM-v0",
        3,
        vectorization_mode="vector_entry_point",
        scenes=small_scenes(),
        max_cycles=3,
    )
    assert isinstance(venv, BatchedEgoEnv) and venv.spec.id == "trajeglish_env/EgoIDM-v0"
    assert venv.reset(seed=0)[0].shape == (3, *ego.observation_space.shape)
    aec = pettingzoo.make("aec", "trajeglish_env/Traffic-v0", scenes=small_scenes(), npc="replay")
    aec.reset(seed=0)
    assert aec.agents == [aec.agent_selection]
    par = pettingzoo.make("parallel", "trajeglish_env/Traffic-v0", scenes=small_scenes(), npc="idm")
    assert len(par.reset(seed=0)[0]) == 1
    # trajeglish_env.env is both the env subpackage and PettingZoo's env() factory
    wrapped = trajeglish_env.env(small_scenes(), npc="replay")
    assert isinstance(wrapped.unwrapped, raw_env)


def test_subproc_vec_env_with_spawn() -> None:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    vec = make_vec_env(
        EgoEnv,
        n_envs=2,
        seed=3,
        env_kwargs={"scenes": small_scenes(), "npc": "idm", "max_cycles": 4},
        vec_env_cls=SubprocVecEnv,
        vec_env_kwargs={"start_method": "spawn"},
    )
    try:
        obs = vec.reset()
        assert obs.shape == (2, *vec.observation_space.shape)
        dones = np.zeros(2, dtype=bool)
        for _ in range(5):
            obs, rewards, done, infos = vec.step(np.zeros((2, 2), dtype=np.float32))
            dones |= done
            assert np.isfinite(rewards).all() and np.isfinite(obs).all()
        assert dones.all()  # every worker finished (truncated at 4 steps or terminated) and auto-reset
    finally:
        vec.close()
