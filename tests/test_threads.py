"""The ``"auto"`` torch-thread policy: several threads on free cores, one beside busy processes; the thread
count never changes a sampled token."""

from __future__ import annotations

import numpy as np
import torch
from helpers import bundle_scene, tiny, tiny_kwargs

import trajeglish_env
from trajeglish_env.env.drivers import EngineRows
from trajeglish_env.env.split import batched_ego_env
from trajeglish_env.env.threads import AdaptiveThreads, auto_threads, cpu_seconds, threads_for, usable_cores
from trajeglish_env.sampler import rollout


def test_threads_fit_beside_the_cores_other_processes_keep_busy() -> None:
    assert [auto_threads(b, cores=2) for b in (1, 3, 4, 7, 8, 128)] == [2, 2, 2, 2, 2, 2]
    assert [auto_threads(b, cores=16) for b in (1, 3, 4, 8, 12, 32, 128)] == [2, 2, 2, 2, 3, 8, 16]
    assert auto_threads(1, cores=1) == auto_threads(4, cores=1) == 1
    assert threads_for(0.0, wanted=2, cores=2) == 2  # an idle machine
    assert threads_for(0.95, wanted=2, cores=2) == 1  # one busy process beside us
    assert threads_for(1.9, wanted=2, cores=2) == 1  # never fewer than one
    assert threads_for(1.0, wanted=8, cores=16) == 8
    busy, own = cpu_seconds() or (1.0, 0.0)
    assert busy >= own > 0 or busy > 0


def test_the_policy_drops_to_one_thread_while_the_cores_are_busy(monkeypatch) -> None:
    from trajeglish_env.env import threads as module

    before = torch.get_num_threads()
    clock = iter([0.0, 3.0, 6.0])
    samples = iter([(100.0, 10.0), (105.5, 13.0), (108.5, 16.0)])  # others: 2.5/3 = 0.83, then 0 cores
    monkeypatch.setattr(module.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(module, "cpu_seconds", lambda: next(samples))
    monkeypatch.setattr(module, "usable_cores", lambda: 2)
    try:
        policy = AdaptiveThreads(num_scenes=32)
        assert policy.threads == 1 and torch.get_num_threads() == before  # it decides, the env applies
        policy.tick()
        assert policy.threads == 1
        policy.tick()
        assert policy.threads == 2
    finally:
        torch.set_num_threads(before)


def test_the_first_look_at_the_load_comes_after_a_quarter_second(monkeypatch) -> None:
    """A batch never runs more than one thread beside a busy process: it starts on one, the first check is
    due FIRST_CHECK_S after the start, the later ones every every_s."""
    from trajeglish_env.env import threads as module

    before = torch.get_num_threads()
    clock = iter([0.0, 0.1, 0.3, 1.0, 2.4])
    samples = iter([(100.0, 10.0), (100.55, 10.3), (102.65, 12.4)])  # others: 0.83 cores, then none
    monkeypatch.setattr(module.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(module, "cpu_seconds", lambda: next(samples))
    monkeypatch.setattr(module, "usable_cores", lambda: 2)
    try:
        policy = AdaptiveThreads(num_scenes=32)
        assert module.FIRST_CHECK_S == 0.25 and policy.threads == 1
        policy.tick()  # 0.1 s: not due yet
        assert policy.threads == 1
        policy.tick()  # 0.3 s: the first look finds a busy core
        assert policy.threads == 1
        policy.tick()  # 1.0 s: the next look is 2 s after the first
        assert policy.threads == 1
        policy.tick()  # 2.4 s: the cores are free again
        assert policy.threads == 2
    finally:
        torch.set_num_threads(before)


def test_a_single_env_takes_a_second_core_once_a_look_finds_it_free(monkeypatch) -> None:
    """One scene decodes about 48 positions a call (its step's and the look-ahead's): two threads on an idle
    2-core machine, from the first look on; never on a single core."""
    from trajeglish_env.env import threads as module

    clock = iter([0.0, 0.1, 0.3])
    samples = iter([(100.0, 10.0), (100.32, 10.3)])  # others: 0.02 / 0.3 s, an idle machine
    monkeypatch.setattr(module.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(module, "cpu_seconds", lambda: next(samples))
    monkeypatch.setattr(module, "usable_cores", lambda: 2)
    policy = AdaptiveThreads(num_scenes=1)
    assert (policy.wanted, policy.threads) == (2, 1)
    policy.tick()  # 0.1 s: not due yet
    assert policy.threads == 1
    policy.tick()  # 0.3 s: the cores are free
    assert policy.threads == 2
    monkeypatch.setattr(module.time, "perf_counter", lambda: 0.0)
    monkeypatch.setattr(module, "cpu_seconds", lambda: (100.0, 10.0))
    monkeypatch.setattr(module, "usable_cores", lambda: 1)
    alone = AdaptiveThreads(num_scenes=1)
    assert (alone.wanted, alone.threads) == (1, 1)


def test_the_thread_count_never_changes_a_token() -> None:
    scene = bundle_scene("highway-exit-999001")  # 16 agents: several model contexts per step
    before = torch.get_num_threads()
    try:
        outs = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            outs.append(rollout(tiny(), scene, rollouts=2, horizon=4).tokens)
    finally:
        torch.set_num_threads(before)
    assert np.array_equal(outs[0], outs[1])


def test_the_env_sets_its_threads_only_while_it_runs_the_model(monkeypatch) -> None:
    """A learner in the same process keeps its own torch thread count: the env's count (one thread, or the
    auto policy's) holds only inside its model calls."""
    seen: list[int] = []
    advance = EngineRows.advance

    def recording(self, *args, **kwargs):
        seen.append(torch.get_num_threads())
        return advance(self, *args, **kwargs)

    monkeypatch.setattr(EngineRows, "advance", recording)
    before = torch.get_num_threads()
    torch.set_num_threads(3)  # the caller's count, unlike any the envs pick here
    try:
        env = trajeglish_env.env(scenes=[bundle_scene("highway-exit-999001")], **tiny_kwargs(max_cycles=3))
        env.reset(seed=0)
        assert torch.get_num_threads() == 3
        for agent in env.agent_iter():
            env.step(
                None
                if env.terminations[agent] or env.truncations[agent]
                else env.action_space(agent).sample()
            )
            assert torch.get_num_threads() == 3
        env.close()
        # EnvConfig.torch_threads = "auto" inside the model calls: one until a look finds a free core
        assert seen and set(seen) <= {1, min(2, usable_cores())}
        seen.clear()
        batch = batched_ego_env(4, scenes=[bundle_scene("highway-exit-999001")], processes=1, **tiny_kwargs())
        batch.reset(seed=0)
        batch.step(np.zeros((4, 2), np.float32))
        # the auto policy's counts: it starts on one and may take the second core once a look (0.25 s in)
        # finds it free, which a loaded machine can reach within these few steps
        assert torch.get_num_threads() == 3 and seen and set(seen) <= {1, min(2, usable_cores())}
        batch.close()
    finally:
        torch.set_num_threads(before)


def test_a_containers_cpu_quota_caps_the_usable_cores(tmp_path, monkeypatch) -> None:
    """`docker --cpus=2` on a 64-core host left the env's "auto" policies at 64 threads / processes."""
    from trajeglish_env import cores

    v2 = tmp_path / "v2"
    v2.mkdir()
    (v2 / "cpu.max").write_text("150000 100000\n")
    assert cores.cgroup_cpu_quota(str(v2)) == 1.5
    (v2 / "cpu.max").write_text("max 100000\n")
    assert cores.cgroup_cpu_quota(str(v2)) is None
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("300000")
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000")
    assert cores.cgroup_cpu_quota(str(v1)) == 3.0
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1")
    assert cores.cgroup_cpu_quota(str(v1)) is None and cores.cgroup_cpu_quota(str(tmp_path / "none")) is None
    monkeypatch.setattr(cores, "cgroup_cpu_quota", lambda: 0.5)
    assert cores.usable_cores() == 1


def test_closed_envs_give_the_heaps_free_pages_back() -> None:
    from trajeglish_env.heap import release_freed_memory

    assert release_freed_memory() is True  # glibc: malloc_trim ran
