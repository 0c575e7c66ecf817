"""Big batches decoded as engine shards in threads (``env/engine_shards.py``): where they are used, and
that they play exactly what one engine of all the rows plays."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch
from helpers import tiny

from trajeglish_env.env import TrajeglishNPC
from trajeglish_env.env import engine_shards as shards_module
from trajeglish_env.env.engine_shards import THREADED_MIN_SCENES, ShardedEngineRows, engine_shards
from trajeglish_env.env.vector import BatchedEgoEnv
from trajeglish_env.model.layers import Linear, linear_compute
from trajeglish_env.sampler.config import SamplingConfig


def test_shards_only_where_auto_would_run_two_threads_on_a_big_cpu_batch() -> None:
    assert engine_shards(128, "auto", "cpu", cores=2) == 2
    assert engine_shards(THREADED_MIN_SCENES, "auto", "cpu", cores=2) == 2
    assert engine_shards(THREADED_MIN_SCENES - 1, "auto", "cpu", cores=2) == 1  # the GIL: slower below
    assert engine_shards(128, 1, "cpu", cores=2) == 1  # threads asked for: as asked
    assert engine_shards(128, None, "cpu", cores=2) == 1
    assert engine_shards(128, "auto", "cuda:0", cores=2) == 1  # the GPU decodes
    assert engine_shards(128, "auto", "cpu", cores=16) == 1  # 16 torch threads there (not measured)
    assert engine_shards(128, "auto", "cpu", cores=1) == 1
    with pytest.raises(ValueError, match=r"shards must be in 1\.\.3 \(the rows\), got 4"):
        ShardedEngineRows(lambda rows: None, 3, 4, externals_first=False)


def ego_actions(steps: int, n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    return [rng.uniform(-1, 1, (n, 2)).astype(np.float32) for _ in range(steps)]


@pytest.mark.parametrize(
    ("guard", "order"), [(False, "first"), (True, "first"), (True, "last"), (False, "random")]
)
def test_a_sharded_batch_plays_what_one_engine_plays(
    monkeypatch: pytest.MonkeyPatch, guard: bool, order: str
) -> None:
    """5 scenes as two shards in threads (rows 0-1 and 2-4; forced, as ``"auto"`` does from 96 scenes on
    2 cores) against one engine of the 5 rows on one thread: the same observations, rewards, episode ends
    and final observations, bit for bit, over 24 steps in which every scene ends and restarts, wherever the
    ego acts in its step."""
    monkeypatch.setattr(
        shards_module,
        "engine_shards",
        lambda n, threads, device, cores=None: 2 if threads == "auto" else 1,
    )
    spec = TrajeglishNPC(tiny(), SamplingConfig(guard=guard))
    runs = []
    for threads in ("auto", 1):
        venv = BatchedEgoEnv(5, npc=spec, max_cycles=9, torch_threads=threads, order=order)
        rows = venv.core.batch.rows
        assert isinstance(rows, ShardedEngineRows) == (threads == "auto")
        if threads == "auto":
            assert rows.bounds.tolist() == [0, 2, 5] and [e.B for e in rows.engines] == [2, 3]
            assert torch.get_num_threads() == 1  # one torch thread per shard thread
        obs, _ = venv.reset(seed=3)
        runs.append([obs] + [venv.step(a) for a in ego_actions(24, 5)])
        venv.close()
    sharded, single = runs
    assert np.array_equal(sharded[0], single[0])
    ends = 0
    for (o, r, term, trunc, info), (o1, r1, term1, trunc1, info1) in zip(
        sharded[1:], single[1:], strict=True
    ):
        assert np.array_equal(o, o1) and np.array_equal(r, r1)
        assert np.array_equal(term, term1) and np.array_equal(trunc, trunc1)
        for i in np.flatnonzero(term | trunc):
            assert np.array_equal(info["final_obs"][i], info1["final_obs"][i])
        ends += int((term | trunc).sum())
    assert ends >= 10  # every scene ended and restarted (rows of both shards restarted mid-run)


def test_the_compute_dtype_of_one_thread_does_not_reach_another() -> None:
    """``linear_compute`` is per thread: a shard multiplying in bfloat16 leaves another's layers alone."""
    torch.manual_seed(0)
    layer = Linear(64, 64).eval()
    x = torch.randn(40, 64)
    with torch.no_grad():
        want = layer(x)
    inside, release, got = threading.Event(), threading.Event(), {}

    def hold() -> None:
        with torch.no_grad(), linear_compute(torch.bfloat16):
            got["bfloat16"] = layer(x)
            inside.set()
            release.wait(10)

    worker = threading.Thread(target=hold)
    worker.start()
    assert inside.wait(10)
    with torch.no_grad():
        got["here"] = layer(x)
    release.set()
    worker.join()
    assert torch.equal(got["here"], want) and not torch.equal(got["bfloat16"], want)
