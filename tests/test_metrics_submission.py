"""Sim Agents submission files: round trip, and clear errors for corrupt or inconsistent ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from trajeglish_env.metrics import LogDetails, SubmissionFormatError, SubmittedRollouts, read_submission
from trajeglish_env.metrics.submission import (
    SubmissionMetadata,
    SubmissionProto,
    encode_submission,
    iter_submission,
    parse_submission,
    read_submission_metadata,
)
from trajeglish_env.metrics.submission_metadata import format_parameter_count
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


OFFICIAL_NUMBERS = {  # sim_agents_submission.proto, SimAgentsChallengeSubmission
    "scenario_rollouts": 1,
    "submission_type": 2,
    "account_name": 3,
    "unique_method_name": 4,
    "authors": 5,
    "affiliation": 6,
    "description": 7,
    "method_link": 8,
    "uses_lidar_data": 9,
    "uses_camera_data": 10,
    "uses_public_model_pretraining": 11,
    "num_model_parameters": 12,
    "public_model_names": 13,
    "acknowledge_complies_with_closed_loop_requirement": 14,
}
META = SubmissionMetadata(
    account_name="someone@example.com",
    unique_method_name="m",
    authors=("A", "B"),
    affiliation="X",
    description="d",
    method_link="https://example.com",
    uses_public_model_pretraining=True,
    public_model_names=("some-llm",),
    num_model_parameters="3M",
    acknowledge_complies_with_closed_loop_requirement=True,
)


def test_metadata_has_every_official_field_and_round_trips(tmp_path: Path):
    fields = SubmissionProto.DESCRIPTOR.fields_by_name
    assert {name: f.number for name, f in fields.items()} == OFFICIAL_NUMBERS
    assert fields["submission_type"].enum_type.values_by_name["SIM_AGENTS_SUBMISSION"].number == 1
    data = encode_submission([_rollouts("a"), _rollouts("b")], META)
    (path := tmp_path / "s.binproto").write_bytes(data)
    assert read_submission_metadata(path) == [META]
    assert [r.scenario_id for r in read_submission(path)] == ["a", "b"]
    # every field is present on the wire, False flags included
    message = SubmissionProto.FromString(data)
    assert message.HasField("uses_lidar_data") and message.HasField("uses_camera_data")
    (empty := tmp_path / "e.binproto").write_bytes(META.encode())  # a shard with no scenario
    assert read_submission(empty) == [] and read_submission_metadata(empty) == [META]


def test_metadata_validation_names_every_problem():
    with pytest.raises(ValueError) as info:
        SubmissionMetadata(account_name="me", num_model_parameters="1.5M").validate()
    message = str(info.value)
    for problem in (
        "unique_method_name (--method-name)",
        "authors (--authors)",
        "affiliation",
        "e-mail",
        "'1.5M' must be an integer",
        "closed_loop_requirement must be true",
    ):
        assert problem in message, problem
    assert META.validate() is META
    assert [format_parameter_count(n) for n in (950, 95_000, 1_534_208, 45_000_000, 7_000_000_000)] == [
        "1K",
        "95K",
        "1534K",
        "45M",
        "7000M",
    ]


def test_archives_and_directories_of_shards_read_back(tmp_path: Path):
    from trajeglish_env.submission_export import pack_archive

    shards = []
    for k, names in enumerate((["a", "b"], ["c"])):
        shard = tmp_path / f"submission.binproto-{k:05d}-of-00002"
        shard.write_bytes(encode_submission([_rollouts(n) for n in names], META))
        shards.append(shard)
    first, second = pack_archive(shards, tmp_path / "x.tar.gz"), pack_archive(shards, tmp_path / "y.tar.gz")
    assert first.read_bytes() == second.read_bytes()  # reproducible: no time stamps, fixed order
    assert [r.scenario_id for r in read_submission(first)] == ["a", "b", "c"]
    assert [r.scenario_id for r in read_submission(tmp_path)] == ["a", "b", "c"]  # the directory
    assert [i for i, _ in iter_submission(first, keep=lambda i: i % 2 == 1)] == [1]
    assert read_submission_metadata(first) == [META, META]
    (tmp_path / "dup.binproto-00002-of-00002").write_bytes(encode_submission([_rollouts("a")]))
    with pytest.raises(SubmissionFormatError, match="scenario 'a' appears twice"):
        read_submission(tmp_path)


def test_an_archive_is_read_by_its_contents_whatever_its_name(tmp_path: Path):
    """A .tar.gz saved without its extension, or a plain .tar, reads as the archive it is (it was parsed as
    one protobuf shard: "Wire format was corrupt")."""
    import shutil
    import tarfile

    from helpers import womd_submission

    want = [r.scenario_id for r in read_submission(womd_submission())]
    for name, mode in (("sub.tar", "w"), ("packed", "w:gz")):
        with tarfile.open(tmp_path / name, mode) as tar:
            tar.add(womd_submission(), arcname="submission.binproto-00000-of-00001")
        assert [r.scenario_id for r in read_submission(tmp_path / name)] == want
    shutil.copy(womd_submission(), tmp_path / "plain")
    assert [r.scenario_id for r in read_submission(tmp_path / "plain")] == want  # a shard stays a shard
