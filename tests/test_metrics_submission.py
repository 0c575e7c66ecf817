"""Sim Agents submission files: round trip, and clear errors for corrupt or inconsistent ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from trajeglish_env.metrics import LogDetails, SubmissionFormatError, SubmittedRollouts, read_submission
from trajeglish_env.metrics.submission import SubmissionProto, encode_submission, parse_submission
from trajeglish_env.scenario import AgentKind, MapKind, Scenario


def _rollouts(
    scenario_id: str = "abc", rollouts: int = 3, agents: int = 4, steps: int = 80
) -> SubmittedRollouts:
    rng = np.random.default_rng(0)
    return SubmittedRollouts(
        scenario_id=scenario_id,
        object_id=np.array([7, 3, 11, 5][:agents]),
        xyz=rng.normal(0, 10, (rollouts, agents, steps, 3)).astype(np.float32),
        heading=rng.uniform(-3, 3, (rollouts, agents, steps)).astype(np.float32),
    )


def test_round_trip_keeps_every_value(tmp_path: Path):
    original = [_rollouts("first"), _rollouts("second", rollouts=2)]
    path = tmp_path / "sub.binproto"
    path.write_bytes(encode_submission(original))
    back = read_submission(path)
    assert [b.scenario_id for b in back] == ["first", "second"]
    for a, b in zip(original, back, strict=True):
        np.testing.assert_array_equal(a.object_id, b.object_id)
        np.testing.assert_array_equal(a.xyz, b.xyz)
        np.testing.assert_array_equal(a.heading, b.heading)
    assert back[0].xyh.shape == (3, 4, 80, 3) and back[0].z.shape == (3, 4, 80)


def test_joint_scenes_listing_objects_in_another_order_are_aligned():
    item = _rollouts()
    message = SubmissionProto.FromString(encode_submission([item]))
    scene = message.scenario_rollouts[0].joint_scenes[1]
    trajectories = list(scene.simulated_trajectories)
    copies = [type(t)() for t in trajectories]
    for copy, original in zip(copies, trajectories, strict=True):
        copy.CopyFrom(original)
    del scene.simulated_trajectories[:]
    scene.simulated_trajectories.extend(copies[::-1])  # reversed order in joint scene 1
    (back,) = parse_submission(message.SerializeToString())
    np.testing.assert_array_equal(back.xyz, item.xyz)


def test_corrupt_and_inconsistent_submissions_are_rejected(tmp_path: Path):
    with pytest.raises(SubmissionFormatError, match="not a SimAgentsChallengeSubmission"):
        parse_submission(b"\xff\xff\xff\xff garbage", origin="bad.binproto")
    with pytest.raises(SubmissionFormatError, match="cannot read"):
        read_submission(tmp_path / "missing.binproto")
    good = encode_submission([_rollouts()])
    with pytest.raises(SubmissionFormatError, match="sub.binproto: "):
        parse_submission(good[: len(good) // 2], origin="sub.binproto")

    message = SubmissionProto.FromString(good)
    del message.scenario_rollouts[0].joint_scenes[2].simulated_trajectories[1]
    with pytest.raises(SubmissionFormatError, match="joint scene 2 does not hold the same objects"):
        parse_submission(message.SerializeToString())

    message = SubmissionProto.FromString(good)
    del message.scenario_rollouts[0].joint_scenes[1].simulated_trajectories[3].heading[-1]
    with pytest.raises(SubmissionFormatError, match="joint scene 1, object 5: .* must all have 80 values"):
        parse_submission(message.SerializeToString())

    message = SubmissionProto.FromString(good)
    message.scenario_rollouts[0].joint_scenes[0].simulated_trajectories[0].center_x[4] = float("nan")
    with pytest.raises(SubmissionFormatError, match="object 7: non-finite"):
        parse_submission(message.SerializeToString())

    with pytest.raises(SubmissionFormatError, match="appears twice"):
        parse_submission(encode_submission([_rollouts("x"), _rollouts("x")]))


def test_log_details_must_belong_to_the_scenario():
    scene = Scenario.from_arrays(
        np.zeros((2, 5, 3)),
        np.ones((2, 5), bool),
        np.ones((2, 2)),
        np.full(2, AgentKind.VEHICLE),
        polylines=[np.array([[0.0, 0.0], [1.0, 0.0]])],
        polyline_kinds=[MapKind.ROAD_EDGE_BOUNDARY],
        current_index=2,
    )
    details = LogDetails.planar(scene)
    details.check_matches(scene)
    renamed = Scenario.from_arrays(
        np.zeros((2, 5, 3)),
        np.ones((2, 5), bool),
        np.ones((2, 2)),
        np.zeros(2),
        track_id=np.array([4, 9]),
        polylines=[np.array([[0.0, 0.0], [1.0, 0.0]])],
        polyline_kinds=[MapKind.ROAD_EDGE_BOUNDARY],
        current_index=2,
    )
    with pytest.raises(ValueError, match="track ids differ"):
        details.check_matches(renamed)
    mapless = Scenario.from_arrays(
        np.zeros((2, 5, 3)), np.ones((2, 5), bool), np.ones((2, 2)), np.zeros(2), current_index=2
    )
    with pytest.raises(ValueError, match="field 'map_z' has shape"):
        details.check_matches(mapless)
