"""Bend weights (training/bend_weights.py): which tokens the lane ahead makes hard to guess from an agent's
own trend, on a hand-made road, and how training uses them;
the turn-onset probe (scripts/turn_onset_probe.py)."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from helpers import REPO, bundle_scene, extended_tiny_checkpoint, small_scenes

from trajeglish_env.model.config import preset
from trajeglish_env.model.lanes import scene_road_points, window_road_view
from trajeglish_env.scenario import MapKind, Scenario
from trajeglish_env.scenario_io import save_scenarios
from trajeglish_env.training.bend_weights import bend_flags, bend_weights
from trajeglish_env.training.dataset import collate_windows
from trajeglish_env.training.interaction_weights import interaction_weights
from trajeglish_env.training.loss import TrainingLoss
from trajeglish_env.training.train import TrainConfig, train, window_config
from trajeglish_env.training.training_data import TokenizedWindows

STEPS = 24  # tokens of a window; states: STEPS + 1
RADIUS = 20.0


def _bend_road() -> np.ndarray:
    """A lane running east along y = 0 up to x = 0, then a left half circle of radius 20 m."""
    straight = np.stack([np.linspace(-80.0, 0.0, 81), np.zeros(81)], -1)
    phi = np.linspace(0.0, math.pi, 200)[1:]
    arc = np.stack([RADIUS * np.sin(phi), RADIUS * (1 - np.cos(phi))], -1)
    return np.concatenate([straight, arc])


def _agents() -> tuple[np.ndarray, np.ndarray]:
    """States ``[4,S,3]`` and validity of: 0 approaching the bend straight at 10 m/s; 1 following the arc at
    10 m/s; 2 approaching it at 1 m/s; 3 as 0, seen only from step 6 on."""
    t = np.arange(STEPS + 1) * 0.1
    approach = np.stack([-30.0 + 10 * t, np.zeros_like(t), np.zeros_like(t)], -1)
    phi = 0.5 + 0.5 * t  # 10 m/s on a 20 m radius
    on_arc = np.stack([RADIUS * np.sin(phi), RADIUS * (1 - np.cos(phi)), phi], -1)
    slow = np.stack([-8.0 + 1 * t, np.zeros_like(t), np.zeros_like(t)], -1)
    xyh = np.stack([approach, on_arc, slow, approach])
    valid = np.ones(xyh.shape[:2], dtype=bool)
    valid[3, :6] = False
    return xyh, valid


def _flags() -> np.ndarray:
    scene = Scenario.from_arrays(
        np.zeros((1, 20, 3)),
        np.ones((1, 20), dtype=bool),
        np.array([[4.5, 2.0]]),
        np.array([0]),
        polylines=[_bend_road()],
        polyline_kinds=[MapKind.LANE_SURFACE_STREET],
        scenario_id="bend",
        source="test",
    )
    xyh, valid = _agents()
    road, mask = window_road_view(scene_road_points(scene), xyh, valid, STEPS)
    as_t = lambda a: torch.from_numpy(np.ascontiguousarray(a))[None]  # noqa: E731
    return bend_flags(as_t(xyh), as_t(valid), as_t(road), as_t(mask))[0].numpy()


def test_the_bend_ahead_is_flagged_where_the_trend_misses_it() -> None:
    flags = _flags()
    # agent 0 at x = -30 + t m looks 15 m ahead, to x = t - 15: the lane nearest there runs more than 0.2 rad
    # left of straight on from x = 20 sin 0.2 = 3.97 m (step 19) on; resampled every 2 m, whose points take
    # the direction of their segment, the flag may come up to two steps later
    first = int(flags[0].argmax())
    assert 19 <= first <= 21 and flags[0, first:].all() and not flags[0, :first].any()
    assert not flags[1].any()  # on the arc at its turn rate: its trend already says where the lane goes
    assert not flags[2].any()  # too slow for its heading to say anything
    assert not flags[:, :3].any()  # no turn rate before three earlier states
    assert not flags[3, :9].any() and np.array_equal(flags[3, 9:], flags[0, 9:])  # seen from step 6


def test_bend_weights_weigh_the_flagged_targets_only() -> None:
    ckpt = extended_tiny_checkpoint("lane_input")
    scenes = [
        bundle_scene(f"highway-{name}")
        for name in ("racetrack-999000", "roundabout-999001", "highway-999001")
    ]
    windows = window_config(dataclasses.replace(ckpt.model.cfg, steps=STEPS, max_agents=24))  # 2.4 s windows
    ds = TokenizedWindows(scenes, windows, ckpt.vocabulary, None, seed=3)
    batch = collate_windows([ds[g] for g in range(3)])
    assert bend_weights(batch, 1.0) is None
    w = bend_weights(batch, 4.0)
    assert w is not None and w.shape == batch["tokens"].shape
    assert set(torch.unique(w).tolist()) <= {1.0, 4.0}
    valid = batch["agent_valid"] & batch["agent_mask"][..., None]
    steps = batch["tokens"].shape[-1]
    flags = bend_flags(
        batch["agent_xyh"], valid, batch["road_points"][:, :steps], batch["road_mask"][:, :steps]
    )
    assert torch.equal(w == 4.0, flags)
    assert (flags[:2].sum((1, 2)) > 20).all()  # the racetrack's and the roundabout's windows hold bends
    both = TrainingLoss(ckpt.model, TrainConfig(interaction_weight=2.0, bend_weight=4.0))._weights(batch)
    closing = interaction_weights(batch, 2.0)
    assert closing is not None and (closing == 2.0).any()
    assert torch.equal(both, w * closing)  # the two weights multiply
    assert TrainingLoss(ckpt.model, TrainConfig())._weights(batch) is None
    blind = extended_tiny_checkpoint("neighbour_input")
    plain = TokenizedWindows(small_scenes(), window_config(blind.model.cfg), blind.vocabulary, None, seed=3)
    with pytest.raises(ValueError, match="train with --lane-input"):
        bend_weights(collate_windows([plain[0]]), 4.0)


def test_settings(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match="bend_weight must be >= 1, got 0.5"):
        TrainConfig(bend_weight=0.5)
    with pytest.raises(ValueError, match="bend_weight finds the bends in the lane points"):
        train(tmp_path / "none", tmp_path / "run", preset("tiny"), TrainConfig(bend_weight=3.0))


def test_turn_phases_in_closed_form() -> None:
    sys.path.insert(0, str(REPO / "scripts"))
    from turn_onset_probe import turn_phases

    # states 0-9 head straight, then 0.03 rad a step to the right (the first turning token is 9: state 9 to
    # 10); a second agent seen from state 4 on
    heading = np.concatenate([np.zeros(10), -0.03 * np.arange(1, 16)])[None].repeat(2, 0)
    valid = np.ones_like(heading, dtype=bool)
    valid[1, :4] = False
    onset, turning, sign = turn_phases(heading, valid, 24)
    # token t: before = (h[t] - h[t-3]) / 3, after = (h[t+3] - h[t]) / 3; onset when before is 0 and after
    # beyond 0.015: t = 8 (after 0.02) and 9 (0.03); t = 10 (before 0.01) is neither; turning from t = 11 to
    # the last token whose after is known (t + 3 <= 24)
    assert np.flatnonzero(onset[0]).tolist() == [8, 9]
    assert np.flatnonzero(turning[0]).tolist() == list(range(11, 22))
    assert (sign[0, 7:22] == -1).all() and (sign[0, :7] == 0).all()  # t = 7 sees the turn's start
    assert np.array_equal(onset[1], onset[0]) and np.array_equal(turning[1], turning[0])
    valid[1, :7] = False  # before token 9 is unknown now: only token 10 could be an onset, and is not
    onset, turning, _ = turn_phases(heading, valid, 24)
    assert np.flatnonzero(onset[1]).tolist() == [] and np.flatnonzero(turning[1]).tolist() == list(
        range(11, 22)
    )


def test_turn_onset_probe_script(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The shipped model on bundled curved scenes: it expects nearly all of a turn that continues."""
    names = ("racetrack-999000", "racetrack-999001", "roundabout-999000", "roundabout-999001")
    save_scenarios(tmp_path / "s.scn.npz", [bundle_scene(f"highway-{n}") for n in names])
    script = [sys.executable, str(REPO / "scripts" / "turn_onset_probe.py"), "--windows", "4", "--json"]
    done = subprocess.run([*script, "--data", str(tmp_path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert (result["scenes"], result["windows"]) == (4, 4)
    assert sorted(result["by_kind"]) == ["all", "racetrack", "roundabout"]
    every = result["by_kind"]["all"]
    assert (every["onsets"], every["turnings"]) == (16, 899)
    assert 0.95 < every["turning_share"] < 1.0 and 0.0 < every["onset_share"] < every["turning_share"]
    assert every["turning_log"] == pytest.approx(every["turning_model"] / every["turning_share"])
    bad = subprocess.run(
        [*script, "--data", str(tmp_path), "--temperature", "0"], capture_output=True, text=True
    )
    assert bad.returncode == 2 and "--temperature > 0" in bad.stderr
