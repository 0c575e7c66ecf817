"""The per-step geometry of many scenes at once equals the scene-by-scene rules it replaces: road-edge
distances number for number, canonical nearest-first selection, and observations of several different
scenes computed together equal to each scene's own."""

from __future__ import annotations

import numpy as np
import pytest

from trajeglish_env.batch_geometry import (
    NearbyItems,
    PaddedRows,
    edge_rows,
    nearest_first,
    nearest_segments,
    nearest_segments_near,
    pad_stack,
    point_segment_distances,
    road_edge_distances,
    road_edges,
    selection_d2,
)
from trajeglish_env.env import EgoEnv, RewardConfig
from trajeglish_env.env.batch_outcomes import BatchGeometry
from trajeglish_env.env.routes import logged_paths, stack_paths
from trajeglish_env.env.scenes import load_bundle
from trajeglish_env.geometry import box_corners
from trajeglish_env.metrics.road_edges import Z_STRETCH, RoadEdges, signed_distance_to_road_edges
from trajeglish_env.scenario import ROAD_EDGE_KINDS, MapKind, Scenario


def test_road_edge_distances_of_many_scenes_equal_the_reference_rule() -> None:
    bundle = load_bundle()
    scenes = [bundle.get(i) for i in range(len(bundle))]
    edges = [road_edges(s) for s in scenes]
    keep = [i for i, e in enumerate(edges) if e is not None]
    assert len(keep) >= 15
    rows = [edge_rows(edges[i]) for i in keep]
    columns, links = (
        pad_stack([r[0] for r in rows], 0.0, last=True),
        pad_stack([r[1] for r in rows], -1, last=True),
    )
    count = np.array([r[0].shape[1] for r in rows])
    rng = np.random.default_rng(0)
    scene = rng.integers(len(keep), size=400)  # several queries per scene, in any order
    points = []
    for q in scene:
        sc = scenes[keep[q]]
        a, t = rng.integers(sc.num_agents), rng.integers(sc.num_steps)
        xyh = sc.xyh[a, t] + np.r_[rng.normal(0, 4, 2), 0.0]  # on and off the road
        points.append(box_corners(xyh, sc.size[a]))
    points = np.stack(points)
    got = road_edge_distances(columns, links, count, scene, points)
    want = np.stack(
        [signed_distance_to_road_edges(p, edges[keep[q]]) for p, q in zip(points, scene, strict=True)]
    )
    assert got.dtype == np.float32 and np.array_equal(got, want)
    assert (want > 0).mean() > 0.05 and (want < 0).mean() > 0.3  # both sides were queried
    # the same nearest segments when only those near an anchor (up to the drift away) are scanned
    near = NearbyItems(reach=15.0, drift=5.0)
    centres = points.mean(axis=1) + rng.uniform(-3.5, 3.5, (len(points), 2))
    keys = [(scenes[keep[q]], 0) for q in scene]
    candidates = near.update(
        keys, centres, lambda sc, p: point_segment_distances(edge_rows(road_edges(sc))[0], p)
    )
    assert 0 < candidates.shape[1] < columns.shape[2]
    full = nearest_segments(columns, count, scene, points)
    restricted = nearest_segments_near(columns, count, scene, points, candidates, near.anchor, near.reach)
    assert np.array_equal(restricted, full)
    far = points + 300.0  # far from every anchor's candidates: answered by the full scan
    restricted = nearest_segments_near(columns, count, scene, far, candidates, near.anchor, near.reach)
    assert np.array_equal(restricted, nearest_segments(columns, count, scene, far))


def test_nearest_first_is_ordered_by_key_then_index() -> None:
    key = np.array([[3.0, 1.0, 1.0, np.inf, 0.5, 1.0], [np.inf, 2.0, np.inf, np.inf, np.inf, np.inf]])
    idx, found = nearest_first(key, 3)
    assert idx[0].tolist() == [4, 1, 2] and found[0].all()  # the tie at 1.0 keeps the lowest indices
    assert idx[1, 0] == 1 and found[1].tolist() == [True, False, False]
    idx, found = nearest_first(key[:, :2], 4)  # fewer candidates than asked for
    assert idx[0, :2].tolist() == [1, 0] and found[0].tolist() == [True, True, False, False]


def test_padded_rows_refresh_only_changed_rows_and_grow() -> None:
    a, b, c = object(), object(), object()
    values = {a: np.array([1, 2]), b: np.array([3]), c: np.array([4, 5, 6])}
    calls = []

    def get(source: object) -> np.ndarray:
        calls.append(source)
        return values[source]

    rows = PaddedRows(fill=-1)
    assert rows.sync([a, b], get).tolist() == [[1, 2], [3, -1]]
    assert rows.sync([a, b], get).tolist() == [[1, 2], [3, -1]] and calls == [a, b]
    assert rows.sync([a, c], get).tolist() == [[1, 2, -1], [4, 5, 6]] and calls == [a, b, c]
    assert rows.sync([b, c], get).tolist() == [[3, -1, -1], [4, 5, 6]]


def test_stacked_paths_project_like_each_set() -> None:
    rng = np.random.default_rng(1)
    sets = []
    for n in (2, 1, 3):
        xy = np.cumsum(rng.normal(1.0, 0.3, (n, 30, 2)), axis=1) * rng.uniform(1, 3)
        heading = np.arctan2(np.gradient(xy[..., 1], axis=1), np.gradient(xy[..., 0], axis=1))
        sets.append(logged_paths(np.concatenate([xy, heading[..., None]], -1), np.ones((n, 30), bool)))
    paths, first = stack_paths(sets)
    assert first.tolist() == [0, 2, 3] and len(paths) == 6
    for k, p in enumerate(sets):
        rows = np.arange(len(p))
        xy = p.points[rows, p.count // 2] + 0.3
        s_prev = p.count // 2 * p.spacing - 2.0
        for mine, theirs in zip(
            paths.project(first[k] + rows, xy, s_prev), p.project(rows, xy, s_prev), strict=True
        ):
            assert np.array_equal(mine, theirs)


def test_observations_of_different_scenes_together_equal_each_alone() -> None:
    names = ["highway-merge-999000", "sumo-random-999000-0-0", "highway-roundabout-999001"]
    envs = [EgoEnv(npc="replay", max_cycles=6) for _ in names]
    for env, name in zip(envs, names, strict=True):
        env.reset(seed=0, options={"scene": name})
        for _ in range(3):
            env.step(np.array([0.5, 0.1], dtype=np.float32))
    sims = [env.aec.sim.state for env in envs]
    agents = [env.aec.agent_index(env.agent) for env in envs]
    together = BatchGeometry().observations(sims + sims[:1], agents + agents[:1])  # a scene twice
    for i, env in enumerate(envs):
        assert np.array_equal(together[i], env.aec.observe(env.agent))
    assert np.array_equal(together[3], together[0])
    assert len({len(s.size) for s in sims}) > 1 and len({len(s.map_points) for s in sims}) == 3


def _without_map(scene_name: str, keep_lanes: bool) -> Scenario:
    """A bundled scene with its road edges removed (``keep_lanes``) or with no map at all."""
    sc = load_bundle().get(load_bundle().index_of(scene_name))
    keep = [
        k
        for k in range(sc.num_polylines)
        if keep_lanes and MapKind(int(sc.map_kind[k])) not in ROAD_EDGE_KINDS
    ]
    return Scenario.from_arrays(
        sc.xyh,
        sc.valid,
        sc.size,
        sc.kind,
        track_id=sc.track_id,
        sdc=sc.sdc,
        polylines=[sc.polyline(k) for k in keep],
        polyline_kinds=sc.map_kind[keep],
        scenario_id=f"{sc.scenario_id}-bare",
        dt=sc.dt,
        current_index=sc.current_index,
    )


def test_scenes_without_road_edges_or_map_mix_with_others() -> None:
    scenes = [
        _without_map("highway-merge-999000", keep_lanes=True),
        load_bundle().get(load_bundle().index_of("highway-exit-999000")),
        _without_map("highway-two-way-999000", keep_lanes=False),
    ]
    far_off = np.array([0.0, 1.0], dtype=np.float32)  # full steer: leaves the road within a few steps
    keep_going = RewardConfig(
        terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False
    )
    envs = [EgoEnv(scenes=[sc], npc="replay", max_cycles=30, reward=keep_going) for sc in scenes]
    for env in envs:
        env.reset(seed=0)
    offroad = np.zeros(3, bool)
    for _ in range(25):
        for i, env in enumerate(envs):
            _, _, _, _, info = env.step(far_off)
            offroad[i] |= info["offroad"]
        sims = [env.aec.sim.state for env in envs]
        together = BatchGeometry().observations(sims, [env.aec.agent_index(env.agent) for env in envs])
        for i, env in enumerate(envs):
            assert np.array_equal(together[i], env.aec.observe(env.agent))
    assert offroad.tolist() == [False, True, False]  # without road edges nothing is off-road
    assert not together[2][88:280].any()  # no map points without a map


def test_scanning_only_nearby_items_gives_the_full_scan(monkeypatch: pytest.MonkeyPatch) -> None:
    """Many scenes scan only the road edges and map points near each agent (anchored, re-chosen as the
    agents move): outcomes and observations equal those of a full scan, step after step."""
    from trajeglish_env.env import batch_outcomes

    names = ["highway-merge-999000", "sumo-random-999000-0-1", "highway-roundabout-999001"]
    envs = [EgoEnv(npc="replay", max_cycles=40) for _ in names]
    for env, name in zip(envs, names, strict=True):
        env.reset(seed=0, options={"scene": name})
    near, full = BatchGeometry(), BatchGeometry()
    rng = np.random.default_rng(2)
    for _ in range(30):  # long enough for the agents to leave their first anchors
        for env in envs:
            if not (env.aec.terminations[env.agent] or env.aec.truncations[env.agent]):
                env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        sims = [env.aec.sim.state for env in envs]
        agents = [env.aec.agent_index(env.agent) for env in envs]
        monkeypatch.setattr(batch_outcomes, "NEARBY_MIN_PAIRS", 0)
        got = near.outcomes(sims), near.observations(sims, agents)
        monkeypatch.setattr(batch_outcomes, "NEARBY_MIN_PAIRS", 10**12)
        want = full.outcomes(sims), full.observations(sims, agents)
        for a, b in zip(got[0], want[0], strict=True):
            assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
        assert np.array_equal(got[1], want[1])
    assert near._near_edges.version > 1 and near._near_points is not None and near._near_points.version > 1


@pytest.mark.parametrize("hilly", [False, True])
def test_selection_distances_are_the_reference_formula_on_flat_and_hilly_maps(hilly: bool) -> None:
    """The in-place (and, on a flat map, z-free) form gives exactly the reference's float32 numbers."""
    rng = np.random.default_rng(3)
    lines = [np.cumsum(rng.normal(0, 4, (12, 3)), axis=0) for _ in range(3)]
    if not hilly:
        lines = [line[:, :2] for line in lines]
    cols = RoadEdges.from_polylines(lines).columns  # [7,S] float32
    x, y = (rng.uniform(-20, 20, (5, 8)).astype(np.float32) for _ in range(2))
    got = selection_d2(np.broadcast_to(cols, (5, *cols.shape)), x, y)
    f32 = np.float32
    ax, ay, az, dx, dy, dz, inverse = (c[None, None] for c in cols)
    ux, uy = x[..., None] - ax, y[..., None] - ay
    t = np.clip((ux * dx + uy * dy) * inverse, 0, 1)
    rz = Z_STRETCH * (f32(0) - az - t * dz)
    want = (ux - t * dx) ** 2 + (uy - t * dy) ** 2 + rz * rz
    assert got.dtype == np.float32 and got.shape == (5, 8, cols.shape[1])
    assert np.array_equal(got, want)
    assert (rz != 0).any() == hilly
