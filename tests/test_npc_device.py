"""Where the NPC model decodes (``TrajeglishNPC.device``): the CPU gives the rollout of the checkpoint's own
device, a copy is made rather than the caller's model moved, and a GPU that is not there is one clear line
(the GPU figures themselves come from ``trajeglish bench --device cuda`` on a GPU machine)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch
from helpers import tiny

from trajeglish_env.benchmark.suite import BenchConfig
from trajeglish_env.checkpoint import on_device
from trajeglish_env.env import EgoEnv, TrajeglishNPC
from trajeglish_env.env.split import batched_ego_env


def test_device_cpu_plays_the_checkpoints_rollout() -> None:
    ckpt = tiny()
    assert on_device(ckpt, "cpu") is ckpt  # already there: no copy
    rollouts = []
    for npc in (TrajeglishNPC(ckpt), TrajeglishNPC(ckpt, device="cpu")):
        env = EgoEnv(npc=npc, max_cycles=6)
        obs, _ = env.reset(seed=4)
        frames = [obs]
        for _ in range(5):
            obs, *_ = env.step(np.zeros(2, np.float32))
            frames.append(obs)
        rollouts.append(np.stack(frames))
    assert np.array_equal(*rollouts)


def test_a_device_that_is_not_there_is_one_clear_line() -> None:
    with pytest.raises(ValueError, match="TrajeglishNPC.device must name a torch device"):
        TrajeglishNPC(device="gpu please")
    with pytest.raises(ValueError, match="bench: --device must name a torch device"):
        BenchConfig(device="gpu please")
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(RuntimeError, match="'cuda': CUDA is not available on this machine"):
        EgoEnv(npc=TrajeglishNPC(tiny(), device="cuda"), max_cycles=4)
    with pytest.raises(ValueError, match="bench: --device cuda: CUDA is not available"):
        BenchConfig(device="cuda")
    # a model meant for another device never splits the scenes over forked processes
    with pytest.raises(RuntimeError, match="CUDA is not available"):
        batched_ego_env(16, processes="auto", npc=TrajeglishNPC(tiny(), device="cuda"), max_cycles=4)


def test_a_model_meant_for_a_gpu_splits_only_when_asked_to() -> None:
    from trajeglish_env.env.shards import on_gpu
    from trajeglish_env.env.split import _count

    assert on_gpu(None, {"npc": TrajeglishNPC(device="cuda:1")})
    assert not on_gpu(None, {"npc": TrajeglishNPC(device="cpu")}) and not on_gpu(None, {"npc": "idm"})
    assert _count("auto", 64, None, {"npc": TrajeglishNPC(device="cuda")}, "auto") == 1
    # a loaded checkpoint already on another device counts too (a meta-device stand-in for a GPU)
    ckpt = tiny()
    elsewhere = dataclasses.replace(ckpt, model=copy.deepcopy(ckpt.model).to("meta"))
    assert on_gpu(None, {"npc": TrajeglishNPC(elsewhere)}) and not on_gpu(None, {"npc": TrajeglishNPC(ckpt)})
    from trajeglish_env.env.split import SplitEgoEnv

    with pytest.raises(RuntimeError, match="on a CUDA device or keep it on the CPU, got 'meta'"):
        SplitEgoEnv(4, processes=2, npc=TrajeglishNPC(elsewhere))  # a count spawns GPU workers


def test_a_copy_is_moved_not_the_callers_model(monkeypatch: pytest.MonkeyPatch) -> None:
    ckpt = tiny()
    moved: list[str] = []

    def fake_to(self: torch.nn.Module, *args: object, **kwargs: object) -> torch.nn.Module:
        moved.append(str(args[0]))
        return self

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.nn.Module, "to", fake_to)
    other = on_device(ckpt, "cuda")
    assert moved == ["cuda"] and other is not ckpt and other.model is not ckpt.model
    assert other.vocabulary is ckpt.vocabulary
