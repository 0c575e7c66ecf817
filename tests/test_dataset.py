"""Training windows: frame, neighbour selection, map chunks, padding, determinism."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers import straight_road_scene
from torch.utils.data import DataLoader

from trajeglish_env.geometry import to_global
from trajeglish_env.model.map_chunks import chunk_map, nearest_chunks
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training.dataset import WindowConfig, WindowDataset, collate_windows, make_window


def test_window_is_in_a_random_agents_frame_and_maps_back_exactly() -> None:
    scene = straight_road_scene(num_agents=6)
    w = make_window(scene, WindowConfig(steps=33, max_agents=4), np.random.default_rng(3))
    a = int(w["agent_mask"].sum())
    assert a == 4 and w["agent_mask"][-a:].all()  # padding first
    start = int(w["start"])
    # exactly one agent sits at the origin with heading 0 at the window's first step: the frame agent
    at_origin = np.flatnonzero(np.abs(w["agent_xyh"][:a, 0]).sum(-1) < 1e-9)
    assert len(at_origin) == 1
    for slot in range(a):
        i = scene.agent_index(int(w["agent_track_id"][slot]))
        ok = w["agent_valid"][slot]
        back = to_global(w["frame"], w["agent_xyh"][slot].astype(np.float64))
        np.testing.assert_allclose(back[ok], scene.xyh[i, start : start + 33][ok], atol=1e-4)
        assert w["agent_kind"][slot] == scene.kind[i]
        np.testing.assert_allclose(w["agent_size"][slot], scene.size[i])
    # the 4 kept agents are the 4 nearest to the frame agent at the start step
    frame_track = int(w["agent_track_id"][at_origin[0]])
    f = scene.agent_index(frame_track)
    live = np.flatnonzero(scene.valid[:, start])
    d = np.linalg.norm(scene.xyh[live, start, :2] - scene.xyh[f, start, :2], axis=-1)
    nearest = set(scene.track_id[live[np.argsort(d, kind="stable")[:4]]].tolist())
    assert set(w["agent_track_id"][:a].tolist()) == nearest


def test_radius_limits_agents_and_map() -> None:
    scene = straight_road_scene(num_agents=6)
    cfg = WindowConfig(agent_radius=13.0, map_radius=8.0, max_polylines=50, points_per_polyline=5)
    w = make_window(scene, cfg, np.random.default_rng(0))
    start = int(w["start"])
    a = int(w["agent_mask"].sum())
    assert a < scene.num_agents  # somebody is out of range
    assert w["agent_mask"][-a:].all() and not w["agent_mask"][:-a].any()  # padding first
    real = w["agent_xyh"][-a:, 0]
    frame_slot = np.flatnonzero(np.abs(real).sum(-1) < 1e-9)[0]
    dist = np.linalg.norm(real[:, :2] - real[frame_slot, :2], axis=-1)
    assert (dist <= 13.0 + 1e-4).all()
    live = np.flatnonzero(scene.valid[:, start])
    frame_i = scene.agent_index(int(w["agent_track_id"][-a:][frame_slot]))
    all_d = np.linalg.norm(scene.xyh[live, start, :2] - scene.xyh[frame_i, start, :2], axis=-1)
    assert a == int((all_d <= 13.0).sum())
    pts = w["map_points"][w["map_mask"]]
    pm = w["map_point_mask"][w["map_mask"]]
    assert w["map_mask"].sum() > 0
    nearest = np.where(pm, np.linalg.norm(pts, axis=-1), np.inf).min(-1)
    assert (nearest <= 8.0 + 1e-4).all()
    assert np.isin(w["map_kind"][w["map_mask"]], scene.map_kind).all()
    assert start >= 0


def test_chunking_covers_every_point_once_per_chunk_boundary() -> None:
    scene = straight_road_scene()
    chunks = chunk_map(scene, 20)
    lengths = np.diff(scene.map_offsets)  # 450 points each
    assert chunks.num_chunks == int(np.ceil((lengths - 1) / 19).sum())
    first = chunks.points[chunks.polyline == 0]
    np.testing.assert_array_equal(first[0, :, 0], np.arange(-50.0, -30.0))
    np.testing.assert_array_equal(first[1, 0], first[0, -1])  # consecutive chunks share an end point
    last_mask = chunks.mask[chunks.polyline == 0][-1]
    assert last_mask.sum() == 449 - 23 * 19 + 1
    pts, pmask, kind, mask, _ = nearest_chunks(chunks, np.array([0.0, 0.0, np.pi / 2]), 3, 100.0)
    assert mask.all() and kind.shape == (3,)
    # in a frame rotated by +90 degrees, global +x points along local -y
    nearest = pts[0][pmask[0]]
    assert np.allclose(nearest[:, 0], nearest[0, 0], atol=1e-4)


def test_windows_are_deterministic_and_worker_independent(tmp_path) -> None:
    scenes = [straight_road_scene(num_agents=5, seed=s) for s in range(6)]
    save_scenarios(tmp_path / "shard.scn.npz", scenes)
    cfg = WindowConfig(steps=17, max_agents=6, max_polylines=8, points_per_polyline=10)
    ds = WindowDataset(tmp_path, cfg, seed=11)
    assert len(ds) == 6
    a = collate_windows([ds[i] for i in range(6)])
    loader = DataLoader(
        WindowDataset(tmp_path, cfg, seed=11), batch_size=3, num_workers=2, collate_fn=collate_windows
    )
    b = list(loader)
    for key in a:
        torch.testing.assert_close(a[key], torch.cat([x[key] for x in b]))
    assert a["agent_xyh"].shape == (6, 6, 17, 3) and a["agent_xyh"].dtype == torch.float32
    assert a["map_points"].shape == (6, 8, 10, 2)
    ds.set_epoch(1)
    c = collate_windows([ds[i] for i in range(6)])
    assert not torch.equal(a["agent_track_id"], c["agent_track_id"])  # new draws in a new epoch


def test_short_scene_and_bad_config_are_refused() -> None:
    scene = dataclasses.replace(straight_road_scene(steps=12), current_index=5)
    scene = scene.validate()
    with pytest.raises(ValueError, match="12 steps, fewer than the window's 33"):
        make_window(scene, WindowConfig(), np.random.default_rng(0))
    with pytest.raises(ValueError, match="WindowConfig.max_agents"):
        WindowConfig(max_agents=0)
    with pytest.raises(FileNotFoundError, match="no such scenario file"):
        WindowDataset("/nonexistent/dir")


def test_agents_invalid_at_start_are_not_chosen() -> None:
    scene = straight_road_scene(num_agents=6)
    valid = scene.valid.copy()
    valid[2, :50] = False
    scene = dataclasses.replace(scene, valid=valid)
    for seed in range(5):
        w = make_window(scene, WindowConfig(steps=33), np.random.default_rng(seed))
        start = int(w["start"])
        ids = w["agent_track_id"][w["agent_mask"]]
        assert (102 in ids.tolist()) == bool(valid[2, start])
