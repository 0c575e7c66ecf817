"""The compiled road-edge queries (trajeglish_env/guard_kernels.py): number for number the NumPy path's,
corner by corner and box by box on real maps (flat and raised), rows of several maps in one call, points
in cells not computed yet and outside the grid; the guard samples the same tokens and counts the same with
them and without them; ``TRAJEGLISH_NO_NUMBA=1`` switches them off."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import bundle_scene, womd_tfrecord
from test_edge_cells import tilted

import trajeglish_env.edge_cells as edge_cells
import trajeglish_env.guard_kernels as guard_kernels
from trajeglish_env.batch_geometry import edge_rows, road_edges
from trajeglish_env.edge_cells import EdgeCells
from trajeglish_env.sources.womd import read_womd


@pytest.fixture
def kernels_switch(monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    """Switches the compiled queries on or off for the test (numba must be installed: a dependency)."""
    assert guard_kernels.AVAILABLE, "numba is a dependency of trajeglish_env: install it (pip install numba)"

    def switch(on: bool) -> None:
        monkeypatch.setattr(guard_kernels, "AVAILABLE", on)

    return switch


def _maps() -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """The road edges of a SUMO scene, of the shared WOMD scene and of a roundabout raised on a slope (the
    reference then chooses in 3-D), and a centre on each."""
    scenes = [bundle_scene("sumo-random-999000-0-0"), next(read_womd(womd_tfrecord()))]
    scenes.append(bundle_scene("highway-roundabout-999001"))
    edges = [edge_rows(road_edges(sc)) for sc in scenes[:2]] + [tilted(road_edges(scenes[2]))]  # type: ignore[arg-type]
    return edges, [sc.xyh[sc.sdc, sc.current_index, :2] for sc in scenes]


def _padded(edges: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of road edges padded to one width, as the guard's engines hold them."""
    width = max(c.shape[1] for c, _ in edges)
    columns = np.zeros((len(edges), 7, width), np.float32)
    links = np.full((len(edges), 3, width), -1, np.int64)
    for r, (c, lk) in enumerate(edges):
        columns[r, :, : c.shape[1]], links[r, :, : c.shape[1]] = c, lk
    return columns, links, np.array([c.shape[1] for c, _ in edges])


def test_compiled_corners_and_boxes_equal_numpy_on_real_maps(kernels_switch) -> None:  # type: ignore[no-untyped-def]
    edges, centres = _maps()
    padded = _padded(edges)
    rng = np.random.default_rng(7)
    n = 3000
    rows = rng.integers(0, len(edges), n)
    points = np.stack(centres)[rows] + rng.uniform(-25, 25, (n, 2))
    points[:40] += rng.uniform(-1e4, 1e4, (40, 2))  # outside the grid: the NumPy path's full scan
    xyh = np.column_stack([points, rng.uniform(-np.pi, np.pi, n)])
    size = np.column_stack([rng.uniform(0.5, 12.0, n), rng.uniform(0.5, 3.0, n)])

    def answers(cells: EdgeCells) -> tuple[np.ndarray, np.ndarray]:
        maps = cells.map_ids(edges)[rows]
        return cells.signed(maps, rows, points, padded), cells.box_excess(maps, rows, xyh, size, padded)

    kernels_switch(True)
    fresh = EdgeCells()  # every block computed on the way, by the NumPy path the kernels leave them to
    first = answers(fresh)
    assert fresh.slots > 20
    again = answers(fresh)  # from the computed cells: the kernels answer almost all of them themselves
    status, out = np.zeros(n, np.int8), np.empty(n, np.float32)
    maps = fresh.map_ids(edges)[rows]
    guard_kernels.signed_points(points, maps, rows, fresh._grid(), *padded[:2], out, status)
    assert (status == guard_kernels.LEFT).sum() <= 40
    kernels_switch(False)
    numpy_fresh = answers(EdgeCells())
    for got in (first, again):
        for a, b in zip(got, numpy_fresh, strict=True):
            assert np.array_equal(a, b), np.flatnonzero(a != b)[:5]
    signed, excess = numpy_fresh
    assert 0.05 < np.isneginf(signed).mean() < 0.9 and (signed > 0).sum() > 100
    assert (excess > 0).sum() > 100 and np.isneginf(excess).sum() > 100


def _guarded_tokens(kernels_switch, on: bool) -> tuple[np.ndarray, dict[str, int]]:  # type: ignore[no-untyped-def]
    """The shipped model's guarded NPCs of a bundled SUMO scene (24 agents), 25 parallel steps."""
    from trajeglish_env.benchmark.workloads import benchmark_scenes
    from trajeglish_env.checkpoint import load_pretrained
    from trajeglish_env.sampler import RolloutEngine, SamplingConfig

    kernels_switch(on)
    calls = [0]
    box_excess = guard_kernels.box_excess

    def counted(*args):  # type: ignore[no-untyped-def]
        calls[0] += 1
        return box_excess(*args)

    sc = benchmark_scenes(24)[1]
    live = sc.valid[:, sc.current_index]
    eng = RolloutEngine(load_pretrained(), sc, 1, 25, live, config=SamplingConfig(temperature=0.75))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(guard_kernels, "box_excess", counted)
        eng.run()
    assert eng.guard is not None
    assert (calls[0] > 50) == on  # the road-edge rule's boxes went through the kernels (or not)
    return eng.tokens.copy(), dataclasses.asdict(eng.guard.stats)


def test_the_guard_samples_the_same_with_and_without_the_kernels(kernels_switch) -> None:  # type: ignore[no-untyped-def]
    on, off = _guarded_tokens(kernels_switch, True), _guarded_tokens(kernels_switch, False)
    np.testing.assert_array_equal(on[0], off[0])
    assert on[1] == off[1]
    assert on[1]["guarded"] > 100  # the road-edge rule applies to most of its vehicles


def test_an_environment_variable_switches_the_kernels_off() -> None:
    code = "import trajeglish_env.guard_kernels as r, sys; print(r.AVAILABLE, 'numba' in sys.modules)"
    env = {**os.environ, "TRAJEGLISH_NO_NUMBA": "1"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_compiled_block_lists_equal_numpy_on_real_maps(kernels_switch) -> None:  # type: ignore[no-untyped-def]
    """Every cell of the blocks a walk over each map touches: the same segments, counts and safe flags."""
    edges, centres = _maps()
    rng = np.random.default_rng(3)
    cells = EdgeCells()
    ids = cells.map_ids(edges)
    kernels_switch(True)
    compared = 0
    for m, centre in zip(ids.tolist(), centres, strict=True):
        grid = cells.maps[m]
        for point in centre + rng.uniform(-60, 60, (12, 2)):
            bx, by = (np.floor((point - [grid.x0, grid.y0]) / (grid.cell * edge_cells.BLOCK))).astype(int)
            if not (0 <= bx < grid.nbx and 0 <= by < grid.nby):
                continue
            place = (grid.cell, grid.x0, grid.y0, int(bx), int(by))
            got = guard_kernels.block_lists(grid.wide, grid.slope, grid.links, *place)
            want = edge_cells._block_lists(grid, int(bx), int(by))
            for a, b in zip(got, want, strict=True):
                np.testing.assert_array_equal(a, b)
            compared += 1
            assert want[0].sum() > 0
    assert compared >= 30


def test_compiled_box_overlaps_equal_box_collisions(kernels_switch) -> None:  # type: ignore[no-untyped-def]
    """Random boxes near one another, some sharing a centre, touching along an edge or turned by right
    angles: the compiled verdicts are the metric's, box by box."""
    from trajeglish_env.compiled import overlaps
    from trajeglish_env.metrics.boxes import box_collisions

    rng = np.random.default_rng(5)
    n = 20000
    a = np.column_stack([rng.uniform(-5, 5, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    b = np.column_stack([rng.uniform(-5, 5, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    size_a, size_b = rng.uniform(0.3, 6.0, (n, 2)), rng.uniform(0.3, 6.0, (n, 2))
    b[:500] = a[:500]  # the same centre
    b[500:1000] = a[500:1000] + [[0.0, 0.0, np.pi / 2]]
    a[1000:1500, 2] = b[1000:1500, 2] = 0.0  # axis-aligned, touching end to end
    b[1000:1500, :2] = a[1000:1500, :2] + np.column_stack(
        [(size_a[1000:1500, 0] + size_b[1000:1500, 0]) / 2, 0 * a[1000:1500, 0]]
    )
    kernels_switch(True)
    got = overlaps(a, size_a, b, size_b)
    want = box_collisions(a, size_a, b, size_b)
    np.testing.assert_array_equal(got, want)
    assert 0.2 < want.mean() < 0.8 and not want[1000:1500].all()


def test_compiled_all_safe_equals_numpy_on_real_maps(kernels_switch) -> None:  # type: ignore[no-untyped-def]
    """Squares of every size around points of three maps, over blocks computed or not, safe or not, and
    beyond the grid: the same verdicts."""
    edges, centres = _maps()
    padded = _padded(edges)
    rng = np.random.default_rng(9)
    cells = EdgeCells()
    ids = cells.map_ids(edges)
    n = 4000
    rows = rng.integers(0, len(edges), n)
    points = np.stack(centres)[rows] + rng.uniform(-40, 40, (n, 2))
    kernels_switch(True)
    near = np.repeat(points[:3000], 8, axis=0) + rng.uniform(-4, 4, (24000, 2))  # blocks computed there
    cells.signed(ids[np.repeat(rows[:3000], 8)], np.repeat(rows[:3000], 8), near, padded)
    reach = rng.uniform(0.0, 4.0, n)
    points[:200] += 1e4  # beyond the grid
    got = cells.all_safe(ids[rows], points, reach)
    kernels_switch(False)
    want = cells.all_safe(ids[rows], points, reach)
    np.testing.assert_array_equal(got, want)
    assert want.sum() > 50 and (~want[200:]).sum() > 1000 and not want[:200].any()
