"""Road-edge cells (trajeglish_env/edge_cells.py): the signed distance a point's cell gives is the
reference's (batch_geometry.road_edge_distances) number for number, on flat maps and on maps with
elevation; a point in a safe cell, or anywhere in a square that all_safe clears, is on the road."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import bundle_scene, womd_tfrecord

import trajeglish_env.edge_cells as edge_cells
from trajeglish_env.batch_geometry import edge_rows, road_edge_distances, road_edges
from trajeglish_env.edge_cells import EdgeCells
from trajeglish_env.metrics.road_edges import RoadEdges
from trajeglish_env.sources.womd import read_womd


def reference(columns: np.ndarray, links: np.ndarray, points: np.ndarray) -> np.ndarray:
    padded = (columns[None], links[None], np.array([columns.shape[1]]))
    return road_edge_distances(*padded, np.zeros(1, np.int64), points[None].astype(np.float32))[0]


def query(cells: EdgeCells, columns: np.ndarray, links: np.ndarray, points: np.ndarray) -> np.ndarray:
    maps = np.repeat(cells.map_ids([(columns, links)]), len(points))
    padded = (columns[None], links[None], np.array([columns.shape[1]]))
    return cells.signed(maps, np.zeros(len(points), np.int64), points, padded)


def tilted(edges: RoadEdges) -> tuple[np.ndarray, np.ndarray]:
    """The edges raised on a slope (z = 0.08 x + 0.05 y + 3): the reference then chooses in 3-D."""
    lift = np.array([0.0, 0.0, 1.0], np.float32)
    z = lambda p: (0.08 * p[:, 0] + 0.05 * p[:, 1] + 3.0).astype(np.float32)[:, None]  # noqa: E731
    start = edges.start * (1 - lift) + z(edges.start) * lift
    end = edges.end * (1 - lift) + z(edges.end) * lift
    return edge_rows(RoadEdges(start, end, edges.previous, edges.following))


@pytest.mark.parametrize("name", ["womd", "highway-roundabout-999001", "sumo-random-999000-0-0", "tilted"])
def test_cells_give_the_reference_distance(name: str) -> None:
    if name == "womd":
        scene = next(read_womd(womd_tfrecord()))
    else:
        scene = bundle_scene("highway-roundabout-999001" if name == "tilted" else name)
    edges = road_edges(scene)
    assert edges is not None
    columns, links = tilted(edges) if name == "tilted" else edge_rows(edges)
    rng = np.random.default_rng(1)
    centre = scene.xyh[scene.sdc, scene.current_index, :2]
    points = centre + rng.uniform(-70, 70, (6000, 2))
    points[:200] = centre + rng.uniform(-1e4, 1e4, (200, 2))  # many outside the grid: a full scan
    cells = EdgeCells()
    got, want = query(cells, columns, links, points), reference(columns, links, points)
    safe = np.isneginf(got)
    assert np.array_equal(got[~safe], want[~safe])
    assert (want[safe] < 0).all()
    assert 0.02 < safe.mean() < 0.9 and (want[~safe] > 0).sum() > 100
    assert (cells.length[: cells.slots * edge_cells.BLOCK**2] > 0).all()  # every cell lists a segment
    again = query(cells, columns, links, points)  # from the cells computed the first time
    assert np.array_equal(again, got, equal_nan=True)


def test_a_cleared_square_is_on_the_road() -> None:
    """A 60 m x 40 m road (its edge counter-clockwise, road on the left): squares far enough inside are
    cleared, and every point of a cleared square is on the road; squares across the edge are not."""
    corners = np.array([[0, 0], [60, 0], [60, 40], [0, 40], [0, 0]], np.float64)
    line = np.concatenate(
        [np.linspace(corners[i], corners[i + 1], 31)[:-1] for i in range(4)] + [corners[:1]]
    )
    columns, links = edge_rows(RoadEdges.from_polylines([line]))
    cells = EdgeCells()
    maps = cells.map_ids([(columns, links)])
    rng = np.random.default_rng(2)
    centres = rng.uniform([-10, -10], [70, 50], (400, 2))
    reach = np.full(len(centres), 6.0)
    on = np.repeat(maps, len(centres))
    assert not cells.all_safe(on, centres, reach).any() and cells.slots == 0  # computes no block
    grid = np.stack(np.meshgrid(np.arange(-20, 80, 2.0), np.arange(-20, 60, 2.0)), -1).reshape(-1, 2)
    cells.locate(np.repeat(maps, len(grid)), grid)  # the blocks of the whole area, as queries compute them
    clear = cells.all_safe(on, centres, reach)
    assert clear.sum() >= 10
    inside = (centres > reach[:, None]).all(axis=1) & (centres < np.array([60, 40]) - reach[:, None]).all(
        axis=1
    )
    assert not (clear & ~inside).any()  # a square across the edge is never cleared
    for c in centres[clear][:20]:
        points = c + rng.uniform(-6, 6, (200, 2))
        assert (reference(columns, links, points) < 0).all()


def test_too_many_maps_start_the_store_afresh(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(edge_cells, "MAX_MAPS", 3)
    scene = bundle_scene("highway-roundabout-999001")
    base = edge_rows(road_edges(scene))
    maps = [(base[0].copy(), base[1]) for _ in range(4)]
    cells = EdgeCells()
    assert cells.map_ids(maps[:3]).tolist() == [0, 1, 2]
    assert cells.map_ids(maps[3:]).tolist() == [0]  # the store was full: started afresh
    assert len(cells.maps) == 1
    points = scene.xyh[scene.sdc, scene.current_index, :2] + np.array(
        [[0.0, 0.0], [30.0, 5.0], [-20.0, 40.0]]
    )
    got, want = query(cells, *maps[3], points), reference(*maps[3], points)
    assert np.array_equal(got[~np.isneginf(got)], want[~np.isneginf(got)])
    assert cells.map_ids([(np.zeros((7, 0), np.float32), np.zeros((3, 0), np.int64))]).tolist() == [-1]
