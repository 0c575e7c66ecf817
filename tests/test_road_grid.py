"""The sampler's grid lookup of road points (sampler/road_grid.py): on the shared WOMD scene every point
within reach of an agent is among its candidates, and the road features read through the grid are the
features read against all of the scene's points."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import womd_tfrecord

from trajeglish_env.model.lanes import BEHIND, REACH, near_states, road_points_of, road_view
from trajeglish_env.sampler.road_grid import CELL, SPAN, RoadGrid, grid_road_view, road_grid_of
from trajeglish_env.scenario import Scenario
from trajeglish_env.sources.womd import read_womd


@pytest.fixture(scope="module")
def womd() -> Scenario:
    return next(read_womd(womd_tfrecord()))


def _positions(scene: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """``[3,N,3]`` states of every agent at three steps (float64) and their validity."""
    steps = [0, scene.current_index, scene.num_steps - 1]
    return scene.xyh[:, steps].transpose(1, 0, 2).astype(np.float64), scene.valid[:, steps].T


def test_every_point_road_view_can_read_is_a_candidate_and_nothing_beyond_the_cells(womd: Scenario) -> None:
    points = road_points_of(womd)
    grid = RoadGrid(points)
    assert len(points) == 4124 and sorted(map(tuple, grid.points)) == sorted(map(tuple, points))
    xyh, valid = _positions(womd)
    far, on_road = [-1e4, -1e4, 0.0], [*(points[0, :2] + 0.5), 1.0]
    states = np.concatenate([xyh[valid], [far, on_road]])
    index, mask = grid.near(states)
    assert index.shape == mask.shape and index.shape[0] == len(states)
    bound = (SPAN + 1) * CELL * np.sqrt(2)  # the farthest corner of the cells around a position
    for p, (i, m) in enumerate(zip(index, mask, strict=True)):
        rel = grid.points[:, :2] - states[p, :2]
        dist = np.linalg.norm(rel, axis=-1)
        ahead = rel @ np.array([np.cos(states[p, 2]), np.sin(states[p, 2])])
        readable = set(np.flatnonzero((dist < REACH) & (ahead > -BEHIND)).tolist())
        got = i[m].tolist()
        assert len(got) == len(set(got))  # each point once
        assert readable <= set(got), p
        assert (dist[got] < bound).all()
        assert (ahead[got] > -BEHIND - CELL * np.sqrt(2) - 0.01).all()  # cells wholly behind are skipped
    assert not mask[-2].any()  # nothing near a position 10 km away
    # on the city map an agent's cells hold far fewer points than the box of all agents does, and not
    # twice those it can read
    near_all = len(near_states(points, xyh[1][valid[1]][:, :2]))
    assert mask[: valid.sum()].sum(1).mean() < 0.2 * near_all
    cur = xyh[1][valid[1]]
    rel = grid.points[None, :, :2] - cur[:, None, :2]
    ahead = rel[..., 0] * np.cos(cur[:, 2:3]) + rel[..., 1] * np.sin(cur[:, 2:3])
    readable = ((np.linalg.norm(rel, axis=-1) < REACH) & (ahead > -BEHIND)).sum(1)
    got = grid.near(cur)[1].sum(1)
    assert got.sum() < 1.6 * readable.sum(), (got.sum(), readable.sum())


def test_features_read_through_the_grid_are_those_read_against_every_point(womd: Scenario) -> None:
    points = road_points_of(womd)
    xyh, valid = _positions(womd)
    grid = road_grid_of(womd)
    assert road_grid_of(womd) is grid  # built once per scene
    # rows of the same scene at three steps, and a row without a road
    grids = [grid, grid, grid, None]
    xs, vs = np.concatenate([xyh, xyh[:1]]), np.concatenate([valid, valid[:1]])
    feats, mask = grid_road_view(grids, xs, vs)
    assert not mask[3].any() and not feats[3].any()  # no road: nothing read
    assert not mask[:3][~torch.from_numpy(valid)].any()  # an invalid agent reads nothing
    every = torch.ones(1, len(points), dtype=torch.bool)
    same = total = 0
    for r in range(3):
        ref, ref_mask = road_view(
            torch.from_numpy(points)[None],
            every,
            torch.from_numpy(xyh[r])[None],
            torch.from_numpy(valid[r])[None],
        )
        ref, ref_mask = ref[0], ref_mask[0]
        assert (mask[r].sum(-1) == ref_mask.sum(-1)).all()  # as many points read by every agent
        assert ref_mask.sum() > 1000
        for a in np.flatnonzero(valid[r]):
            total += 1
            # the points read, in any order (the encoder pools over them): equal, or swapped at a tie
            got = torch.sort(feats[r, a][mask[r, a]].flatten()).values
            want = torch.sort(ref[a][ref_mask[a]].flatten()).values
            same += bool(torch.allclose(got, want, atol=1e-5))
    assert total == valid.sum() and same >= total - 2, (same, total)  # 147 of 148


def test_kept_road_codes_are_those_computed_afresh(womd: Scenario, monkeypatch: pytest.MonkeyPatch) -> None:
    """A road-reading model's rollout of the WOMD scene, looking ahead: at every step the lane encoder's codes
    the row reads (kept ones reused where an agent is at the state they were computed at: drafts that held)
    are exactly those computed afresh from the states, all agents in one batch, and fewer agent-states are
    computed than read; those of the steps a new window primes are kept too (nothing computed again)."""
    from helpers import extended_tiny_checkpoint

    from trajeglish_env.model.layers import linear_compute
    from trajeglish_env.sampler import SamplingConfig, row_roads
    from trajeglish_env.sampler.engine import BatchEngine
    from trajeglish_env.sampler.rows import RowSpec

    computed = []
    fresh_features = row_roads.road_features

    def counting(st, rows, xyh, valid):  # type: ignore[no-untyped-def]
        computed.append(int(valid.sum()))
        return fresh_features(st, rows, xyh, valid)

    ckpt = extended_tiny_checkpoint("lane_input")
    eng = BatchEngine(ckpt, 1, SamplingConfig(temperature=0.0))
    live = womd.valid[:, womd.current_index] & (np.arange(womd.num_agents) < 6)  # one context, looks ahead
    eng.start_rows([0], RowSpec(womd, 10, live), [3])
    monkeypatch.setattr(row_roads, "road_features", counting)
    rows, agents = np.array([0]), np.arange(eng.N)[None]
    assert eng.roads is not None

    def fresh(step: int) -> torch.Tensor:
        valid = eng.valid[:, :, step]
        feats, mask = fresh_features(eng, rows, eng.mxyh[:, :, step], valid)
        with torch.no_grad(), linear_compute(eng._compute_dtype):
            code = ckpt.model.lanes(feats, mask).float()
        return torch.where(torch.from_numpy(valid)[..., None], code, eng.roads.empty())

    read = checked = 0
    while eng.stepping.any():
        eng.step()
        now = int(eng.now[0])
        steps = np.full((1, eng.N), now)
        before = sum(computed)
        with torch.inference_mode(), linear_compute(eng._compute_dtype):  # as the engine's steps run
            got = eng.roads.codes(eng, rows, agents, steps)
        assert torch.equal(got, fresh(now))
        read += int(eng.valid[0, :, now].sum())
        assert sum(computed) - before <= int(eng.valid[0, :, now].sum())
        for back in range(1, eng.prime + 1):  # the steps a new window primes: kept, not computed again
            if now - back <= womd.current_index:
                break
            before = sum(computed)
            with torch.inference_mode(), linear_compute(eng._compute_dtype):
                got = eng.roads.codes(eng, rows, agents, steps - back)
            assert torch.equal(got, fresh(now - back))
            assert sum(computed) == before
            checked += 1
    assert eng.look_ahead_calls > 0 and checked > 0
    assert sum(computed) < 2 * read  # look-ahead codes were reused at the next steps


def test_an_agents_features_do_not_depend_on_the_others_read_with_it(womd: Scenario) -> None:
    """Each agent of the WOMD scene read alone (fewer candidate points in its call) gets, bit for bit, the
    features it gets among all 50: coincident points of overlapping lanes tie on distance, and ties go by
    candidate order (21 of the 50 differed when the top-k broke them by the call's width)."""
    grid = road_grid_of(womd)
    t = womd.current_index
    xyh = womd.xyh[womd.valid[:, t], t][None]
    assert xyh.shape[1] == 50
    together, together_mask = grid_road_view([grid], xyh, np.ones(xyh.shape[:2], bool))
    for a in range(xyh.shape[1]):
        alone, alone_mask = grid_road_view([grid], xyh[:, a : a + 1], np.ones((1, 1), bool))
        assert torch.equal(alone[0, 0], together[0, a]), a
        assert torch.equal(alone_mask[0, 0], together_mask[0, a]), a
