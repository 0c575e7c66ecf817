"""Traffic signals in the vector observation (``ObservationConfig.signals``): an RL ego on SUMO scenes saw
no light at all; now it can see the nearest stop points with their state, exactly where the scene has them."""

from __future__ import annotations

import numpy as np
import pytest

import trajeglish_env
from trajeglish_env.env import ObservationConfig
from trajeglish_env.env.signal_features import SIGNAL_FEATURES
from trajeglish_env.env.vector import BatchedParallelEnv
from trajeglish_env.geometry import to_local
from trajeglish_env.scenario import SignalState


@pytest.fixture(scope="module")
def lit_scene():
    from trajeglish_env.sources import sumo

    try:
        (scene,) = sumo.generate_shard(("grid",), 0, 0, 1)
    except sumo.SumoNotAvailableError as error:
        pytest.skip(str(error))
    assert len(scene.signal_xy) > 0
    return scene


def test_the_nearest_signals_are_shown_where_they_are_with_their_state(lit_scene) -> None:
    config = ObservationConfig(signals=4)
    env = trajeglish_env.parallel_env(scenes=[lit_scene], npc="replay", external="all", obs=config)
    obs, _ = env.reset(seed=0)
    agent = env.agents[0]
    space = env.observation_space(agent)
    assert space.shape == (300 + 4 * SIGNAL_FEATURES,) and all(space.contains(o) for o in obs.values())
    block = obs[agent][-4 * SIGNAL_FEATURES :].reshape(4, SIGNAL_FEATURES)
    i, t = env.unwrapped.agent_index(agent), lit_scene.current_index
    own = lit_scene.xyh[i, t]
    dist = np.linalg.norm(lit_scene.signal_xy - own[:2], axis=1)
    nearest = np.argsort(dist, kind="stable")[:4]
    shown = dist[nearest] <= config.radius
    assert np.array_equal(block[:, 0], shown.astype(np.float32))
    points = np.concatenate([lit_scene.signal_xy[nearest], np.zeros((4, 1))], axis=1)
    want = to_local(own[None], points)[:, :2] / config.radius
    np.testing.assert_allclose(block[shown, 1:3], want[shown], atol=1e-5)
    state = lit_scene.signal_state[t, nearest]
    red = np.isin(state, [SignalState.STOP, SignalState.ARROW_STOP, SignalState.FLASHING_STOP])
    green = np.isin(state, [SignalState.GO, SignalState.ARROW_GO])
    assert np.array_equal(block[shown, 3] == 1, red[shown]) and np.array_equal(
        block[shown, 5] == 1, green[shown]
    )
    default = trajeglish_env.parallel_env(scenes=[lit_scene], npc="replay", external="all")
    assert default.observation_space(agent).shape == (300,)  # off by default: trained policies keep theirs


def test_signal_features_are_the_same_in_a_batch_and_refused_when_negative(lit_scene) -> None:
    config = ObservationConfig(signals=3)
    single = trajeglish_env.parallel_env(scenes=[lit_scene], npc="replay", external="all", obs=config)
    alone, _ = single.reset(seed=0)
    batch = BatchedParallelEnv(2, scenes=[lit_scene], npc="replay", external="all", obs=config)
    together, _ = batch.reset(seed=0)
    assert all(np.array_equal(together[0][a], o) for a, o in alone.items())
    with pytest.raises(ValueError, match="ObservationConfig.signals must be an int >= 0"):
        ObservationConfig(signals=-1)
