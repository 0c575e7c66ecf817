"""Score parity with the official WOSAC implementation on the shared WOMD scenario and 32-rollout submission.

Reference values: ``shared/docs/wosac_metrics.md`` §9 (tables A, B and C), computed with Waymo's own
TensorFlow code. Every score must match to 1e-4.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import womd_submission, womd_tfrecord

from trajeglish_env.metrics import (
    CONFIGS,
    compute_features,
    displacement_errors,
    prepare_scene,
    read_submission,
    read_womd_details,
    rollout_trajectories,
    score_rollouts,
)
from trajeglish_env.sources.womd import read_womd

TOLERANCE = 1e-4

# §9 table A: the test submission, current (2025) code, with the 2025 and 2024 configs.
TABLE_A_COMMON = {
    "linear_speed": 0.647147,
    "linear_acceleration": 0.129309,
    "angular_speed": 0.061596,
    "angular_acceleration": 0.309280,
    "distance_to_nearest_object": 0.237239,
    "collision_indication": 0.052868,
    "time_to_collision": 0.754345,
    "distance_to_road_edge": 0.402153,
    "offroad_indication": 0.073568,
    "traffic_light_violation": 0.999969,
    "ade": 2.505281,
    "min_ade": 2.084689,
    "collision_rate": 0.6875,
    "offroad_rate": 0.265625,
    "traffic_light_violation_rate": 0.0,
    "kinematic": 0.286833,
    "interactive": 0.249723,
}
TABLE_A = {
    "2025": {**TABLE_A_COMMON, "metametric": 0.258240, "map_based": 0.252852},
    "2024": {**TABLE_A_COMMON, "metametric": 0.228349, "map_based": 0.167449},
}
# §9 table B: the log replayed as all 32 rollouts.
TABLE_B_COMMON = {
    "linear_speed": 0.826529,
    "linear_acceleration": 0.530525,
    "angular_speed": 0.487326,
    "angular_acceleration": 0.656286,
    "distance_to_nearest_object": 0.400351,
    "collision_indication": 0.999969,
    "time_to_collision": 0.836213,
    "distance_to_road_edge": 0.559178,
    "offroad_indication": 0.999969,
    "traffic_light_violation": 0.999969,
    "ade": 0.0,
    "min_ade": 0.0,
    "collision_rate": 0.25,
}
TABLE_B = {
    "2025": {**TABLE_B_COMMON, "metametric": 0.826631},
    "2024": {**TABLE_B_COMMON, "metametric": 0.804592},
}


@pytest.fixture(scope="module")
def womd():
    """(scenario, raw log details, submitted rollouts) of the shared sample."""
    scenario = next(read_womd(womd_tfrecord()))
    details = next(read_womd_details(womd_tfrecord()))
    (rollouts,) = read_submission(womd_submission())
    return scenario, details, rollouts


def _assert_matches(scores, expected: dict[str, float]) -> None:
    got = scores.to_dict()
    wrong = {k: (got[k], v) for k, v in expected.items() if abs(got[k] - v) > TOLERANCE}
    assert not wrong, f"fields differing from the reference by more than {TOLERANCE}: {wrong}"


def test_submission_file_holds_the_expected_rollouts(womd):
    scenario, _, rollouts = womd
    assert rollouts.scenario_id == scenario.scenario_id == "637f20cafde22ff8"
    assert rollouts.xyz.shape == (32, 50, 80, 3) and rollouts.heading.shape == (32, 50, 80)
    simulated = scenario.track_id[scenario.valid[:, scenario.current_index]]
    assert sorted(rollouts.object_id.tolist()) == sorted(simulated.tolist())


@pytest.mark.parametrize("config", ["2025", "2024"])
def test_submission_scores_match_the_official_ones(womd, config):
    scenario, details, rollouts = womd
    scores = score_rollouts(
        scenario, rollouts.xyh, rollouts.object_id, config, rollouts_z=rollouts.z, details=details
    )
    assert scores.num_rollouts == 32 and scores.num_evaluated == 4
    _assert_matches(scores, TABLE_A[config])


def test_2024_era_time_to_collision_over_all_objects(womd):
    scenario, details, rollouts = womd
    legacy = dataclasses.replace(CONFIGS["2024"], ttc_vehicles_only=False)
    scores = score_rollouts(
        scenario, rollouts.xyh, rollouts.object_id, legacy, rollouts_z=rollouts.z, details=details
    )
    _assert_matches(scores, {"time_to_collision": 0.783677, "metametric": 0.231282, "interactive": 0.256241})


@pytest.mark.parametrize("config", ["2025", "2024"])
def test_log_replayed_as_rollouts_matches_the_official_scores(womd, config):
    scenario, details, _ = womd
    simulated = np.flatnonzero(scenario.valid[:, scenario.current_index])
    future = slice(scenario.current_index + 1, None)
    xyh = np.concatenate([details.xyz[simulated, future, :2], details.heading[simulated, future, None]], -1)
    z = details.xyz[simulated, future, 2]
    scores = score_rollouts(
        scenario,
        np.repeat(xyh[None], 32, axis=0),
        scenario.track_id[simulated],
        config,
        rollouts_z=np.repeat(z[None], 32, axis=0),
        details=details,
    )
    _assert_matches(scores, TABLE_B[config])


def test_spot_feature_values_of_object_1675(womd):
    """§9 table C: features of object 1675 at t = 1, 10, 40 (log and rollout 0), ADE of rollout 0."""
    scenario, details, rollouts = womd
    scene = prepare_scene(scenario, details)
    assert scene.track_id[:4].tolist() == [1675, 1676, 2320, 2406]
    assert scene.is_vehicle[:4].tolist() == [True, True, False, True]
    order = np.argsort(rollouts.object_id)[np.searchsorted(np.sort(rollouts.object_id), scene.track_id)]
    xyz, heading, valid = rollout_trajectories(scene, rollouts.xyz[:, order], rollouts.heading[:, order])
    features = compute_features(scene, xyz[:2], heading[:2], valid[:2])
    steps = [1, 10, 40]
    # (feature, batch: 0 = log, 1 = rollout 0) -> (values, tolerance: the reference's float32 noise)
    expected = {
        ("linear_speed", 0): ([5.10512, 5.28580, 4.13581], 1e-4),
        ("linear_speed", 1): ([3.84169, 4.62101, 5.73981], 1e-4),
        ("linear_acceleration", 0): ([-0.79961, -2.58129, -3.86029], 1e-4),
        ("angular_speed", 0): ([-0.37335, -0.32094, 0.31279], 1e-4),
        ("distance_to_nearest_object", 0): ([35.73776, 31.16290, 18.63910], 1e-3),
        ("distance_to_road_edge", 0): ([-1.31789, -2.25593, -1.72219], 1e-3),
        ("distance_to_road_edge", 1): ([-1.01164, -2.02403, 5.23069], 1e-3),
    }
    for (name, batch), (values, tol) in expected.items():
        got = getattr(features, name)[batch, 0, steps]
        np.testing.assert_allclose(got, values, atol=tol, err_msg=f"{name} batch {batch}")
    ade = displacement_errors(scene, xyz[1:])
    np.testing.assert_allclose(ade[0], [5.46256, 2.62914, 0.70294, 0.62576], atol=1e-4)
    np.testing.assert_allclose([ade.mean(1).min(), ade.mean(1).max()], [2.08469, 3.05072], atol=1e-4)


def test_the_2024_era_config_is_named_and_scored_as_that_years_code(womd) -> None:
    """`--metrics 2024` is the 2024 weights under today's official code (time to collision of vehicles
    only); the 2024 leaderboard's own scores need that year's code: `--metrics 2024-era`."""
    from trajeglish_env.cli import build_parser

    scenario, details, rollouts = womd
    scores = score_rollouts(
        scenario, rollouts.xyh, rollouts.object_id, "2024-era", rollouts_z=rollouts.z, details=details
    )
    assert scores.config == "2024-era"
    _assert_matches(scores, {"time_to_collision": 0.783677, "metametric": 0.231282, "interactive": 0.256241})
    args = build_parser().parse_args(["score-submission", "x", "--data", "d", "--metrics", "2024-era"])
    assert args.metrics == "2024-era"
