"""Episodes longer than the log: learned and constant-velocity NPCs drive on, the log's late agents are
handed to them where the log ends, and log-bound NPC policies refuse such episodes."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import tiny

from trajeglish_env.env import EgoEnv, RewardConfig, TrajeglishNPC
from trajeglish_env.env.aec import raw_env
from trajeglish_env.env.vector import BatchedEgoEnv
from trajeglish_env.sampler.config import SamplingConfig

KEEP_GOING = RewardConfig(terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False)
CROSSING = "highway-intersection-999001"  # 7 agents at the current step, 4 more enter later


def play(env: raw_env) -> int:
    """Play the episode with a braking-free zero action; the number of env steps taken."""
    steps = 0
    for _ in env.agent_iter():
        _, _, term, trunc, _ = env.last()
        env.step(None if term or trunc else np.zeros(2, np.float32))
        steps += 1
    return steps


@pytest.mark.parametrize("npc", ["tiny", "constant_velocity"])
def test_an_episode_runs_past_the_log_and_its_agents_drive_on(npc: str) -> None:
    spec = TrajeglishNPC(tiny()) if npc == "tiny" else npc
    env = raw_env(npc=spec, max_cycles=150, reward=KEEP_GOING)
    env.reset(seed=0, options={"scene": CROSSING})
    sc, sim = env.scenario, env.sim
    log_end = sc.num_steps - 1
    play(env)
    assert sim.steps == 150 and sim.t == sc.current_index + 150 > log_end
    xyh, valid = sim.driver.xyh, sim.driver.valid
    assert np.isfinite(xyh[valid]).all()
    at_end = np.flatnonzero(sc.valid[:, log_end])
    late = at_end[~sc.valid[at_end, sc.current_index]]
    assert len(late) == 4  # agents the log brought in after the current step
    assert valid[at_end, log_end:].all()  # everyone present at the log's end stays, the late ones too
    moved = np.linalg.norm(xyh[late, -1, :2] - xyh[late, log_end, :2], axis=-1)
    assert (moved > 1.0).any()  # and they keep driving after it


@pytest.mark.parametrize("drive", [True, False])
def test_agents_entering_later_enter_as_logged_then_the_model_drives_them(drive: bool) -> None:
    env = raw_env(npc=TrajeglishNPC(tiny(), drive_entering=drive), reward=KEEP_GOING)
    env.reset(seed=0, options={"scene": CROSSING})
    sc, sim = env.scenario, env.sim
    play(env)
    xyh, valid = sim.driver.xyh, sim.driver.valid
    cur = sc.current_index
    late = np.flatnonzero(~sc.valid[:, cur] & sc.valid[:, cur + 1 :].any(axis=1))
    entry = np.argmax(sc.valid[late], axis=1)
    assert len(late) == 4 and (entry > cur).all()
    rows = np.arange(len(late))
    assert not valid[late, cur].any()  # absent before they enter
    np.testing.assert_allclose(xyh[late, entry], sc.xyh[late, entry])  # they enter where the log has them
    after = entry + 5
    ok = after < sc.num_steps
    gap = np.linalg.norm(xyh[late[ok], after[ok], :2] - sc.xyh[late[ok], after[ok], :2], axis=-1)
    if drive:  # the untrained model, not the log, drives them after that
        assert (gap > 0.05).all() and valid[late[rows], -1].all()
    else:
        assert (gap == 0).all()


@pytest.mark.parametrize("leaves", [20, None])
def test_an_agent_entering_onto_another_waits_until_its_place_is_clear(leaves: int | None) -> None:
    from trajeglish_env.sampler.config import SamplingConfig
    from trajeglish_env.sampler.engine import BatchEngine, RowSpec
    from trajeglish_env.scenario import AgentKind, Scenario

    steps, cur = 40, 10
    xyh = np.zeros((3, steps, 3))
    valid = np.zeros((3, steps), bool)
    valid[0, : leaves or steps] = True  # a parked car (replayed) at x = 0, gone at step `leaves`
    xyh[1, :, 0] = 8.0 * (np.arange(steps) - 15) * 0.1  # enters at step 15 at x = 0, onto the parked car
    valid[1, 15:] = True
    xyh[2, :, 1] = 20.0  # a car the model drives, far away
    xyh[2, :, 0] = np.arange(steps) * 0.5
    valid[2] = True
    sc = Scenario.from_arrays(
        xyh, valid, np.tile([4.5, 2.0], (3, 1)), np.full(3, AgentKind.VEHICLE), sdc=2, current_index=cur,
        scenario_id="entering",
    )  # fmt: skip
    engine = BatchEngine(tiny(), 1, SamplingConfig(seed=0))
    engine.start_rows([0], RowSpec(sc, steps - cur - 1, np.array([False, False, True]), entering=True), [0])
    engine.run()
    v = engine.valid[0, 1]
    if leaves is None:  # never clear: it never enters
        assert not v.any()
    else:  # it enters where the log brought it in, once the parked car has gone, then the model drives it
        assert np.flatnonzero(v)[0] == leaves and v[leaves:].all()
        np.testing.assert_allclose(engine.xyh[0, 1, leaves], sc.xyh[1, 15])
        assert engine.row_controlled[0, 1]


@pytest.mark.parametrize("npc", ["replay", "idm"])
def test_log_bound_npcs_refuse_episodes_longer_than_the_log(npc: str) -> None:
    env = raw_env(npc=npc, max_cycles=81)
    with pytest.raises(ValueError, match=f"max_cycles=81 but '{npc}' NPCs can play only the 80 steps"):
        env.reset(seed=0, options={"scene": CROSSING})
    env = raw_env(npc=npc, max_cycles=80)  # the whole log is fine
    env.reset(seed=0, options={"scene": CROSSING})
    assert play(env) >= 1 and env.sim.steps <= 80


def test_batched_ego_env_past_the_log_equals_separate_envs() -> None:
    float32 = SamplingConfig(compute_dtype="float32")  # as "auto" for one scene, whatever the batch
    kw = {"npc": TrajeglishNPC(tiny(), float32), "max_cycles": 90, "reward": KEEP_GOING}
    venv = BatchedEgoEnv(2, **kw)
    obs, _ = venv.reset(seed=4, options={"scene": CROSSING})
    refs = [EgoEnv(**kw) for _ in range(2)]
    for i, ref in enumerate(refs):
        assert np.array_equal(ref.reset(seed=4 + i, options={"scene": CROSSING})[0], obs[i])
    for _ in range(90):
        got = venv.step(np.zeros((2, 2), np.float32))
        for i, ref in enumerate(refs):
            want = ref.step(np.zeros(2, np.float32))
            assert got[1][i] == want[1] and got[3][i] == want[3]
            assert np.array_equal(got[4]["final_obs"][i] if want[3] else got[0][i], want[0])
    assert got[3].all()  # truncated at max_cycles, 9 s after the current step (the log has 8 s)


def test_routes_past_the_log_follow_the_lanes_and_an_idm_ego_drives_them() -> None:
    from trajeglish_env.env.controllers import RuleBasedController
    from trajeglish_env.env.lane_routes import LanePoints, extended_routes
    from trajeglish_env.env.scenes import load_bundle

    bundle = load_bundle()
    track = bundle.get(bundle.index_of("highway-racetrack-999000"))
    lanes = LanePoints.of(track)
    routes = extended_routes(track, np.array([track.sdc]), 1000.0)
    assert 69 + 1000 <= routes.length[0] <= 69 + 1000 + 70  # the loop is followed round and round
    points, _ = routes.at(np.zeros(200, np.int64), np.linspace(70, routes.length[0], 200))
    gap = np.linalg.norm(points[:, None] - lanes.xy[None], axis=-1).min(axis=1)
    assert gap.max() < 0.6  # the continuation lies on lane centres
    road = bundle.get(bundle.index_of("highway-highway-999000"))  # its lanes run on 343 m past the log
    lanes = LanePoints.of(road)
    env = raw_env(npc="constant_velocity", max_cycles=200, reward=KEEP_GOING)
    env.reset(seed=0, options={"scene": "highway-highway-999000"})
    ego, controller = env.agent_selection, RuleBasedController("idm")
    for agent in env.agent_iter():
        _, _, term, trunc, _ = env.last()
        env.step(None if term or trunc else controller.action(env, agent))
    sim = env.sim
    path = sim.driver.xyh[env.agent_index(ego), road.num_steps :, :2]
    assert np.linalg.norm(path[:, None] - lanes.xy[None], axis=-1).min(axis=1).max() < 1.0  # on its lane
    logged = np.hypot(*np.diff(road.xyh[road.sdc, road.current_index :, :2], axis=0).T).sum()
    assert sim.progress[0] > logged + 150  # it kept driving along its route past the log
