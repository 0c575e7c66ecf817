"""The batched ego env split over worker processes: exactly the rollouts of one process (autoresets, seeds,
per-scene tools, SB3), errors that name the scenes' worker, and the automatic process count."""

from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch
from helpers import tiny
from stable_baselines3 import PPO

from trajeglish_env.cores import can_fork
from trajeglish_env.env import RandomAgents, RewardConfig, TrajeglishNPC
from trajeglish_env.env import shards as shards_module
from trajeglish_env.env.sb3 import SB3VecEnv
from trajeglish_env.env.split import (
    SplitEgoEnv,
    SplitParallelEnv,
    auto_env_processes,
    batched_ego_env,
    batched_parallel_env,
)
from trajeglish_env.env.vector import BatchedEgoEnv, BatchedParallelEnv

pytestmark = pytest.mark.skipif(not can_fork(), reason="the split env forks its workers (Linux)")

SCENES = ["highway-merge-999000", "sumo-random-999000-0-0", "highway-exit-999001"]


def kwargs(**overrides: object) -> dict:
    """Tiny-model NPCs, 6-step episodes (several autoresets in a test), a few bundled scenes."""
    from helpers import bundle_scene

    return {
        "scenes": [bundle_scene(name) for name in SCENES],
        "npc": TrajeglishNPC(tiny()),
        "max_cycles": 6,
        "torch_threads": 1,
        **overrides,
    }


def ego_states(venv: BatchedEgoEnv) -> list[np.ndarray]:
    """Each scene's current ego state (a function run where the scenes live)."""
    return [env.sim.driver.xyh[env.sim.index_of(env.agent)].copy() for env in venv.envs]


def same_step(got: tuple, want: tuple) -> None:
    obs, rew, term, trunc, info = got
    obs2, rew2, term2, trunc2, info2 = want
    assert np.array_equal(obs, obs2) and np.array_equal(rew, rew2)
    assert np.array_equal(term, term2) and np.array_equal(trunc, trunc2)
    assert sorted(info) == sorted(info2)
    if "final_obs" in info:
        assert np.array_equal(info["_final_obs"], info2["_final_obs"])
        for a, b in zip(info["final_obs"], info2["final_obs"], strict=True):
            assert (a is None and b is None) or np.array_equal(a, b)
    if "agent" in info:  # scenes restarted this step: their new egos
        assert list(info["agent"]) == list(info2["agent"])


def test_split_env_plays_exactly_what_one_process_plays() -> None:
    one = BatchedEgoEnv(5, **kwargs())
    split = SplitEgoEnv(5, processes=2, **kwargs())
    try:
        assert [len(s) for s in split.shards] == [2, 3]
        assert split.single_action_space == one.single_action_space
        assert split.observation_space == one.observation_space
        obs, info = split.reset(seed=7)
        obs2, info2 = one.reset(seed=7)
        assert np.array_equal(obs, obs2) and list(info["agent"]) == list(info2["agent"])
        rng = np.random.default_rng(0)
        ended = 0
        for _ in range(14):  # two autoresets of every scene
            actions = rng.uniform(-1, 1, (5, 2)).astype(np.float32)
            got, want = split.step(actions), one.step(actions)
            same_step(got, want)
            ended += int((got[2] | got[3]).sum())
        assert ended >= 10
        # per-scene tools reach into the workers: names, methods, the scene's simulation (a copy)
        assert [env.agent for env in split.envs] == [env.agent for env in one.envs]
        target = np.array([1.0, 2.0, 0.1])
        towards = [env.action_towards(env.agent, target) for env in (split.envs[4], one.envs[4])]
        assert np.array_equal(*towards)
        assert split.envs[3].scenario.scenario_id == one.envs[3].scenario.scenario_id
        states = [s for shard in split.apply(ego_states) for s in shard]
        assert all(np.array_equal(a, b) for a, b in zip(states, ego_states(one), strict=True))
        # resetting one scene in its worker, with a chosen scene: the others go on where they are
        obs3, info3 = split.envs[1].reset(seed=3, options={"scene": SCENES[2]})
        obs4, info4 = one.envs[1].reset(seed=3, options={"scene": SCENES[2]})
        assert np.array_equal(obs3, obs4) and info3 == info4
        assert split.agents[1] == info3["agent"] == one.agents[1]  # the caller knows the new ego
        actions = np.zeros((5, 2), np.float32)
        same_step(split.step(actions), one.step(actions))
        # explicit seeds per scene
        obs, _ = split.reset(seed=[1, 2, 3, 4, 5])
        assert np.array_equal(obs, one.reset(seed=[1, 2, 3, 4, 5])[0])
    finally:
        split.close()
    assert split.closed and all(not w.is_alive() for w in split.workers.workers)
    with pytest.raises(RuntimeError, match="SplitEgoEnv is closed"):
        split.step(np.zeros((5, 2), np.float32))


def test_split_env_refuses_bad_inputs_and_names_the_worker_of_an_error() -> None:
    with pytest.raises(ValueError, match="processes must be a positive int or 'auto'"):
        SplitEgoEnv(4, processes=0, npc="idm")
    with pytest.raises(ValueError, match=r"num_envs must be an int >= processes \(3\)"):
        SplitEgoEnv(2, processes=3, npc="idm")
    with pytest.raises(FileNotFoundError, match="/no/such/dir"):  # in this process, before any fork
        SplitEgoEnv(2, processes=2, npc="idm", scenes="/no/such/dir")
    venv = SplitEgoEnv(4, processes=2, **kwargs())
    reference = BatchedEgoEnv(4, **kwargs())
    try:
        venv.reset(seed=0)
        reference.reset(seed=0)
        with pytest.raises(ValueError, match="expected 4 actions"):
            venv.step(np.zeros((3, 2), np.float32))
        bad = np.zeros((4, 2), np.float32)
        bad[3] = [3.0, 0.0]
        # checked before any worker moves: the next step is still the reference's
        agent = venv.envs[3].agent
        with pytest.raises(ValueError, match=f"agent {agent}: action .* outside the action space"):
            venv.step(bad)
        same_step(venv.step(np.zeros((4, 2), np.float32)), reference.step(np.zeros((4, 2), np.float32)))
        # an error raised in a worker comes back with its type, naming the worker's scenes
        with pytest.raises(ValueError, match="scene") as caught:
            venv.envs[2].reset(options={"scene": "no-such-scene"})
        assert any("worker of scenes 2..3" in note for note in caught.value.__notes__)
        same_step(venv.step(np.zeros((4, 2), np.float32)), reference.step(np.zeros((4, 2), np.float32)))
        # a dead worker: a clear error, not a hang
        os.kill(venv.workers.workers[1].pid, signal.SIGKILL)
        venv.workers.workers[1].join()
        with pytest.raises(RuntimeError, match=r"the worker of scenes 2..3 died \(exit code -9\)"):
            venv.step(np.zeros((4, 2), np.float32))
    finally:
        venv.close()


def test_sb3_on_the_split_env_equals_one_process_and_trains() -> None:
    kw = kwargs()
    split, one = SB3VecEnv(4, processes=2, **kw), SB3VecEnv(4, processes=1, **kw)
    try:
        assert isinstance(split.venv, SplitEgoEnv) and isinstance(one.venv, BatchedEgoEnv)
        split.seed(5)
        one.seed(5)
        assert np.array_equal(split.reset(), one.reset())
        rng = np.random.default_rng(1)
        for _ in range(8):
            a = rng.uniform(-1, 1, (4, 2)).astype(np.float32)
            got, want = split.step(a), one.step(a)
            assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
            assert np.array_equal(got[2], want[2])
            for i in np.flatnonzero(got[2]):
                assert np.array_equal(got[3][i]["terminal_observation"], want[3][i]["terminal_observation"])
        assert split.get_attr("agent") == one.get_attr("agent")
        assert (
            split.get_attr("observation_space")
            == one.get_attr("observation_space")
            == [one.observation_space] * 4
        )
        assert split.env_method("agent_index", split.get_attr("agent", 0)[0], indices=0) == one.env_method(
            "agent_index", one.get_attr("agent", 0)[0], indices=0
        )
        model = PPO("MlpPolicy", split, n_steps=8, batch_size=16, n_epochs=1, seed=0, device="cpu")
        model.learn(32)
        assert model.num_timesteps >= 32
    finally:
        split.close()
        one.close()


def test_auto_process_count_uses_the_free_cores_and_enough_scenes(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(shards_module, "usable_cores", lambda: 4)
    monkeypatch.setattr(shards_module, "others_busy_cores", lambda: 0.0)
    assert [auto_env_processes(b) for b in (1, 7, 8, 12, 16, 128)] == [1, 1, 2, 3, 4, 4]
    monkeypatch.setattr(shards_module, "others_busy_cores", lambda: 1.0)  # one core kept busy by another
    assert auto_env_processes(128) == 3
    monkeypatch.setattr(shards_module, "others_busy_cores", lambda: 3.0)
    assert auto_env_processes(128) == 1
    monkeypatch.setattr(shards_module, "can_fork", lambda: False)
    monkeypatch.setattr(shards_module, "others_busy_cores", lambda: 0.0)
    assert auto_env_processes(128) == 1
    assert isinstance(batched_ego_env(2, processes="auto", npc="idm", max_cycles=3), BatchedEgoEnv)
    with pytest.raises(ValueError, match="processes must be a positive int or 'auto'"):
        batched_ego_env(2, processes="many", npc="idm")


def test_auto_gives_a_gpu_model_one_spawned_worker_per_64_scenes(monkeypatch: pytest.MonkeyPatch) -> None:
    """Measured on an H200 at B = 1,024: 16 GPU workers of 64 scenes ran 3.6x one process; so ``"auto"``
    takes one per 64 scenes, at most one per core, and keeps fewer than two workers' worth in one process."""
    from trajeglish_env.env.split import _count

    monkeypatch.setattr(shards_module, "usable_cores", lambda: 16)
    gpu = {"npc": TrajeglishNPC(tiny(), device="cuda")}
    assert [_count("auto", b, None, gpu, "auto") for b in (8, 127, 128, 1024, 4096)] == [1, 1, 2, 16, 16]
    assert _count("auto", 1024, None, gpu, 4) == 16  # a worker runs one thread whatever the caller asked
    assert _count(3, 1024, None, gpu, "auto") == 3  # a count is kept
    monkeypatch.setattr(shards_module, "usable_cores", lambda: 2)
    assert _count("auto", 1024, None, gpu, "auto") == 2
    cpu = {"npc": TrajeglishNPC(tiny())}
    assert _count("auto", 1024, None, cpu, 2) == 1  # several torch threads on the CPU: one process


def test_split_env_with_rule_based_npcs_and_one_scene_per_worker() -> None:
    kw = {"npc": "idm", "max_cycles": 5, "reward": RewardConfig(terminate_on_collision=False)}
    split, one = SplitEgoEnv(3, processes=3, **kw), BatchedEgoEnv(3, **kw)
    try:
        assert np.array_equal(split.reset(seed=11)[0], one.reset(seed=11)[0])
        for _ in range(7):
            a = np.full((3, 2), 0.3, np.float32)
            same_step(split.step(a), one.step(a))
    finally:
        split.close()


def test_split_parallel_env_plays_exactly_what_one_process_plays() -> None:
    kw = kwargs(external=RandomAgents(2), max_cycles=5)
    split, one = SplitParallelEnv(5, processes=2, **kw), BatchedParallelEnv(5, **kw)
    try:
        assert split.observation_space("x") == one.observation_space("x")
        got, want = split.reset(seed=9), one.reset(seed=9)
        assert split.agents == one.agents and all(len(a) == 2 for a in split.agents)
        for g, w in zip(got[0], want[0], strict=True):
            assert g.keys() == w.keys() and all(np.array_equal(g[a], w[a]) for a in g)
        for step in range(7):
            actions = [{a: one.action_space(a).sample() for a in agents} for agents in one.agents]
            assert all(split.action_space(a) == one.action_space(a) for agents in one.agents for a in agents)
            out, ref = split.step(actions), one.step(actions)
            for k in range(5):
                assert [d.keys() for d in out[k]] == [d.keys() for d in ref[k]]
            for g, w in zip(out[0], ref[0], strict=True):
                assert all(np.array_equal(g[a], w[a]) for a in g)
            assert out[1] == ref[1] and out[2] == ref[2] and out[3] == ref[3]
            assert split.agents == one.agents
            if step == 5:  # every scene has ended: restart three, across both workers, in a chosen order
                assert split.agents == [[]] * 5
                got, want = split.reset_scenes([4, 0, 2], seed=30), one.reset_scenes([4, 0, 2], seed=30)
                assert [o.keys() for o in got[0]] == [o.keys() for o in want[0]]
                assert split.agents == one.agents and split.agents[1] == [] and split.agents[4]
        # checked before any worker moves, naming the scene
        bad = [{a: one.action_space(a).sample() for a in agents} for agents in split.agents]
        bad[4] = {}
        with pytest.raises(KeyError, match="scene 4 has no action for agent"):
            split.step(bad)
        with pytest.raises(ValueError, match=r"scene indices \[5\] out of range for 5 scenes"):
            split.reset_scenes([5])
        assert [len(p) for p in split.apply(_scene_count)] == [2, 3]
        assert split.apply(lambda env, k: k * len(env.agents), 10) == [20, 30]  # a lambda goes by value
        with pytest.raises(TypeError, match="must pickle to reach the worker processes"):
            split.apply(_scene_count, threading.Lock())  # said before anything is sent, the workers go on
        assert [len(p) for p in split.apply(_scene_count)] == [2, 3]
    finally:
        split.close()
    assert all(not w.is_alive() for w in split.workers.workers)
    assert isinstance(batched_parallel_env(2, processes="auto", npc="idm"), BatchedParallelEnv)


def _scene_count(env: BatchedParallelEnv) -> list[list[str]]:
    return env.agents


def _tagged(env: BatchedEgoEnv, tag: str, pause: float = 0.0) -> tuple[str, int]:
    """A shard's answer naming the call (the first shard may take its time)."""
    if pause and env.envs[0].agent:
        time.sleep(pause)
    return tag, len(env.envs)


def test_split_env_stays_in_step_after_interruptions_and_a_dead_worker() -> None:
    venv = SplitEgoEnv(6, processes=3, npc="idm", max_cycles=5)
    try:
        venv.reset(seed=0)

        # a command whose answer was never read (Ctrl-C while waiting): read and dropped before the next one
        def interrupt(*_: object) -> None:
            raise KeyboardInterrupt

        previous = signal.signal(signal.SIGALRM, interrupt)
        signal.setitimer(signal.ITIMER_REAL, 0.2)
        try:
            with pytest.raises(KeyboardInterrupt):
                venv.apply(_tagged, "first", 1.0)
        finally:
            signal.signal(signal.SIGALRM, previous)
        assert venv.apply(_tagged, "second") == [("second", 2)] * 3
        assert isinstance(venv.envs[0].agent, str)
        # the middle worker dies: an error naming its scenes, and the others still answer their own calls
        os.kill(venv.workers.workers[1].pid, signal.SIGKILL)
        venv.workers.workers[1].join()
        with pytest.raises(RuntimeError, match=r"the worker of scenes 2..3 died"):
            venv.step(np.zeros((6, 2), np.float32))
        assert isinstance(venv.envs[0].agent, str) and isinstance(venv.envs[5].agent, str)
        with pytest.raises(RuntimeError, match=r"the worker of scenes 2..3 died"):
            _ = venv.envs[2].agent
    finally:
        venv.close()


def test_scenes_reset_one_by_one_then_step_and_workers_stop_with_the_env() -> None:
    kw = {"npc": "idm", "max_cycles": 5}
    split, one = SplitEgoEnv(4, processes=2, **kw), BatchedEgoEnv(4, **kw)
    for venv in (split, one):  # the pattern of examples/train_ppo_ego.py's evaluation
        for k, env in enumerate(venv.envs):
            env.reset(seed=10 + k)
    assert split.agents == one.agents
    got, want = split.step_each(np.zeros((4, 2), np.float32)), one.step_each(np.zeros((4, 2), np.float32))
    assert all(np.array_equal(g[0], w[0]) and g[1:4] == w[1:4] for g, w in zip(got, want, strict=True))
    workers = split.workers.workers
    del split  # no close(): dropping the env stops its workers (the scene proxies hold it weakly)
    gc.collect()
    assert all(not w.is_alive() for w in workers)
    with pytest.raises(ValueError, match="torch_threads must be 'auto', None or 1"):
        SplitEgoEnv(4, processes=2, torch_threads=2, **kw)
    # asking for several torch threads keeps "auto" in one process (SB3VecEnv's default)
    threads = torch.get_num_threads()
    try:
        assert isinstance(SB3VecEnv(16, torch_threads=2, **kw).venv, BatchedEgoEnv)
    finally:
        torch.set_num_threads(threads)


ORPHAN = """
import sys, time
from trajeglish_env.env.split import SplitEgoEnv
def busy(env):
    time.sleep(60)
venv = SplitEgoEnv(4, processes=2, npc="idm", max_cycles=5)
venv.reset(seed=0)
print(" ".join(str(w.pid) for w in venv.workers.workers), flush=True)
venv.apply(busy)  # the workers are busy (not reading their pipes) when the caller is killed
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_workers_end_when_the_caller_is_killed() -> None:
    caller = subprocess.Popen([sys.executable, "-c", ORPHAN], stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(p) for p in caller.stdout.readline().split()]  # type: ignore[union-attr]
        assert len(pids) == 2 and all(_alive(p) for p in pids)
    finally:
        caller.kill()
        caller.wait()
    deadline = time.monotonic() + 10
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(p) for p in pids)


def test_split_envs_render_the_frames_of_one_process() -> None:
    kw = {"npc": "idm", "max_cycles": 5, "render_mode": "rgb_array"}
    split, one = SplitEgoEnv(2, processes=2, **kw), BatchedEgoEnv(2, **kw)
    psplit, pone = SplitParallelEnv(2, processes=2, **kw), BatchedParallelEnv(2, **kw)
    try:
        split.reset(seed=1)
        one.reset(seed=1)
        split.step(np.zeros((2, 2), np.float32))
        one.step(np.zeros((2, 2), np.float32))
        frames, want = split.render(), one.render()
        assert len(frames) == 2 and all(f.dtype == np.uint8 and f.ndim == 3 for f in frames)
        assert all(np.array_equal(f, w) for f, w in zip(frames, want, strict=True))
        psplit.reset(seed=2)
        pone.reset(seed=2)
        assert all(np.array_equal(f, w) for f, w in zip(psplit.render(), pone.render(), strict=True))
    finally:
        split.close()
        psplit.close()


def _explode() -> None:
    raise ValueError("this answer cannot be loaded here")


class _Unloadable:
    """Pickles in the worker, fails to unpickle in the caller."""

    def __reduce__(self) -> tuple[object, tuple[()]]:
        return _explode, ()


def _unloadable(env: BatchedEgoEnv) -> _Unloadable:
    return _Unloadable()


def test_an_answer_that_cannot_be_loaded_is_an_error_and_the_env_goes_on() -> None:
    venv = SplitEgoEnv(4, processes=2, npc="idm", max_cycles=5)
    try:
        venv.reset(seed=0)
        with pytest.raises(ValueError, match="cannot be loaded here"):
            venv.apply(_unloadable)
        assert venv.workers.pending == [0, 0]
        venv.step(np.zeros((4, 2), np.float32))
    finally:
        venv.close()
    assert all(not w.is_alive() for w in venv.workers.workers)


def test_a_split_env_made_in_another_thread_keeps_its_workers() -> None:
    made: list[SplitEgoEnv] = []

    def make() -> None:
        made.append(SplitEgoEnv(4, processes=2, npc="idm", max_cycles=5))

    thread = threading.Thread(target=make)
    thread.start()
    thread.join()  # the thread that forked the workers is gone; they live on
    venv = made[0]
    try:
        venv.reset(seed=0)
        venv.step(np.zeros((4, 2), np.float32))
        assert all(w.is_alive() for w in venv.workers.workers)
    finally:
        venv.close()


def test_spawned_workers_play_exactly_what_one_process_plays(monkeypatch: pytest.MonkeyPatch) -> None:
    """The start method of a model meant for a GPU (fresh interpreters, the model sent as a CPU copy)
    gives the one-process rollouts too; here on the CPU, spawning forced."""
    import trajeglish_env.env.split as split_module

    monkeypatch.setattr(split_module, "start_method", lambda config, options: "spawn")
    one = BatchedEgoEnv(4, **kwargs())
    split = SplitEgoEnv(4, processes=2, **kwargs())
    try:
        assert split.workers.method == "spawn"
        obs, info = split.reset(seed=5)
        obs2, info2 = one.reset(seed=5)
        assert np.array_equal(obs, obs2) and list(info["agent"]) == list(info2["agent"])
        rng = np.random.default_rng(1)
        for _ in range(8):  # an autoreset of every scene
            actions = rng.uniform(-1, 1, (4, 2)).astype(np.float32)
            same_step(split.step(actions), one.step(actions))
        states = [s for shard in split.apply(ego_states) for s in shard]
        assert all(np.array_equal(a, b) for a, b in zip(states, ego_states(one), strict=True))
    finally:
        split.close()
    assert all(not w.is_alive() for w in split.workers.workers)


def test_a_gpu_model_spawns_its_workers_and_goes_to_them_on_the_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    """``TrajeglishNPC(device="cuda")``: the workers are spawned (a CUDA context cannot fork) and get a CPU
    copy of the model with the device named, so each puts it on its GPU; without CUDA, one clear error
    before any worker starts."""
    npc = TrajeglishNPC(tiny(), device="cuda")
    assert shards_module.start_method(None, {"npc": npc}) == "spawn"
    assert shards_module.start_method(None, {"npc": TrajeglishNPC(tiny())}) == "fork"
    assert shards_module.start_method(None, {"npc": "idm"}) == "fork"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # as on a GPU machine
    prepared = shards_module.prepared_config(None, {"npc": npc}, "SplitEgoEnv", 4).npc
    assert prepared.device == "cuda"
    assert next(prepared.checkpoint.model.parameters()).device.type == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(RuntimeError, match="SplitEgoEnv: the NPC model's device 'cuda' needs CUDA"):
        SplitEgoEnv(4, processes=2, **kwargs(npc=npc))


def test_batched_envs_render_as_single_envs_do_before_reset_and_without_a_mode() -> None:
    """Before reset a batched env rendered ``(None, None)`` silently (single envs raise), and the parallel
    ones rendered without a render_mode."""
    import warnings

    for kind in (BatchedEgoEnv, BatchedParallelEnv):
        env = kind(2, npc="idm", max_cycles=3, render_mode="rgb_array")
        with pytest.raises(RuntimeError, match=r"call reset\(\) before render\(\)"):
            env.render()
        env.close()
        quiet = kind(2, npc="idm", max_cycles=3)
        quiet.reset(seed=0)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert quiet.render() is None
        assert any("without a render_mode" in str(w.message) for w in caught)
        quiet.close()


def _missing_file(env):
    raise FileNotFoundError("no such file: x.npz")


def _ones(env):
    return 1


def test_a_commands_oserror_reaches_the_caller_and_the_worker_lives_on() -> None:
    """A first version of the quiet exit on a broken pipe took any OSError of a command (a user's
    FileNotFoundError in `apply`) for the caller being gone: the worker died, the error was lost."""
    split = SplitEgoEnv(2, processes=2, npc="replay", max_cycles=3)
    try:
        split.reset(seed=0)
        with pytest.raises(FileNotFoundError, match="no such file: x.npz"):
            split.apply(_missing_file)
        assert split.apply(_ones) == [1, 1]
    finally:
        split.close()


def _defined_late(name: str, source: str, monkeypatch: pytest.MonkeyPatch) -> object:
    """A function of ``__main__`` defined now, after the workers forked (their ``__main__`` lacks it)."""
    namespace = {"__name__": "__main__"}
    exec(source, namespace)
    monkeypatch.setattr(sys.modules["__main__"], name, namespace[name], raising=False)
    return namespace[name]


def test_apply_takes_a_function_defined_after_the_workers_forked(monkeypatch: pytest.MonkeyPatch) -> None:
    """Such a function pickled by reference, and every worker died unpickling it (``AttributeError: Can't
    get attribute 'late' on <module '__main__'>``): the env was lost. Now it goes by value."""
    venv = SplitEgoEnv(4, processes=2, npc="idm", max_cycles=5)
    try:
        venv.reset(seed=0)
        late = _defined_late("late", "def late(env, k):\n    return k * len(env.envs)\n", monkeypatch)
        assert venv.apply(late, 3) == [6, 6]
        k = 5
        assert venv.apply(lambda env: k * len(env.envs)) == [10, 10]  # a closure too
        venv.step(np.zeros((4, 2), np.float32))
    finally:
        venv.close()


def _refuse_to_load() -> None:
    raise ImportError("no module named 'gone' here")


class _LoadsNowhere:
    """A function that pickles here and cannot be unpickled in a worker."""

    def __init__(self) -> None:
        self.__qualname__ = "gone.fn"

    def __call__(self, env: BatchedEgoEnv) -> int:
        return 0

    def __reduce__(self) -> tuple[object, tuple[()]]:
        return _refuse_to_load, ()


def test_a_function_a_worker_cannot_load_is_a_clear_error_and_the_env_goes_on(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The worker died unpickling the command; now the caller gets an error naming the function, the
    worker's scenes, the cause and the remedy, and the env goes on."""
    venv = SplitEgoEnv(4, processes=2, npc="idm", max_cycles=5)
    try:
        venv.reset(seed=0)
        with pytest.raises(
            shards_module.CommandLoadError,
            match=r"apply: 'gone.fn' did not reach the workers: SplitEgoEnv: the worker of scenes 0..1 could "
            r"not load it: ImportError: no module named 'gone' here; define it at module level before",
        ):
            venv.apply(_LoadsNowhere())
        assert venv.workers.pending == [0, 0]
        venv.step(np.zeros((4, 2), np.float32))
        assert venv.apply(_ones) == [1, 1]
        # without cloudpickle, a late function of __main__ goes by reference: the workers say they lack it
        monkeypatch.setitem(sys.modules, "cloudpickle", None)
        later = _defined_late("later", "def later(env):\n    return 0\n", monkeypatch)
        with pytest.raises(shards_module.CommandLoadError, match=r"'later' .*Can't get attribute 'later'"):
            venv.apply(later)
        venv.step(np.zeros((4, 2), np.float32))
        assert venv.apply(_ones) == [1, 1]
    finally:
        venv.close()
    assert all(not w.is_alive() for w in venv.workers.workers)
