"""The sampler's grid lookup of road points (sampler/road_grid.py): on the shared WOMD scene every point
within reach of an agent is among its candidates, and the road features read through the grid are the
features read against all of the scene's points."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import womd_tfrecord

from trajeglish_env.model.lanes import REACH, near_states, road_points_of, road_view
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


def test_every_point_within_reach_is_a_candidate_and_nothing_beyond_the_cells(womd: Scenario) -> None:
    points = road_points_of(womd)
    grid = RoadGrid(points)
    assert len(points) == 4124 and sorted(map(tuple, grid.points)) == sorted(map(tuple, points))
    xyh, valid = _positions(womd)
    xy = np.concatenate([xyh[valid][:, :2], [[-1e4, -1e4], points[0, :2] + 0.5]])  # far away, on the road
    index, mask = grid.near(xy)
    assert index.shape == mask.shape and index.shape[0] == len(xy)
    bound = (SPAN + 1) * CELL * np.sqrt(2)  # the farthest corner of the cells around a position
    for p, (i, m) in enumerate(zip(index, mask, strict=True)):
        dist = np.linalg.norm(grid.points[:, :2] - xy[p], axis=-1)
        within = set(np.flatnonzero(dist < REACH).tolist())
        got = i[m].tolist()
        assert len(got) == len(set(got))  # each point once
        assert within <= set(got), p
        assert (dist[got] < bound).all()
    assert not mask[-2].any()  # nothing near a position 10 km away
    # on the city map an agent's cells hold far fewer points than the box of all agents does
    near_all = len(near_states(points, xyh[1][valid[1]][:, :2]))
    assert mask[: valid.sum()].sum(1).mean() < 0.5 * near_all


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
