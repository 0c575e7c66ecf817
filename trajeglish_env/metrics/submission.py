"""Read and write Waymo Sim Agents submissions (``SimAgentsChallengeSubmission`` / ``ScenarioRollouts``)
without protoc or the waymo package: the message classes are built here from a descriptor.

Field numbers follow the public ``sim_agents_submission.proto`` (proto2): SimAgentsChallengeSubmission
{1 scenario_rollouts}; ScenarioRollouts {1 scenario_id, 2 joint_scenes}; JointScene {1
simulated_trajectories}; SimulatedTrajectory {2 center_x, 3 center_y, 4 center_z, 5 heading (packed
floats), 6 object_id}. Other fields (submission metadata, Scenario Gen boxes) are skipped as unknown.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError, Message

__all__ = [
    "SubmissionFormatError",
    "SubmittedRollouts",
    "encode_submission",
    "parse_submission",
    "read_submission",
]

_PACKAGE = "trajeglish_env.sim_agents"
_F = descriptor_pb2.FieldDescriptorProto
_POSE_FIELDS = ("center_x", "center_y", "center_z", "heading")


class SubmissionFormatError(ValueError):
    """A submission file is malformed; the message names the file, scenario, joint scene and object."""


def _build_classes() -> dict[str, type[Message]]:
    """Message classes of the submission schema, in a private descriptor pool."""
    schema: dict[str, list[tuple[str, int, int, bool, str]]] = {
        "SimulatedTrajectory": [
            *[
                (name, number, _F.TYPE_FLOAT, True, "")
                for name, number in zip(_POSE_FIELDS, (2, 3, 4, 5), strict=True)
            ],
            ("object_id", 6, _F.TYPE_INT32, False, ""),
        ],
        "JointScene": [("simulated_trajectories", 1, _F.TYPE_MESSAGE, True, "SimulatedTrajectory")],
        "ScenarioRollouts": [
            ("scenario_id", 1, _F.TYPE_STRING, False, ""),
            ("joint_scenes", 2, _F.TYPE_MESSAGE, True, "JointScene"),
        ],
        "SimAgentsChallengeSubmission": [
            ("scenario_rollouts", 1, _F.TYPE_MESSAGE, True, "ScenarioRollouts"),
        ],
    }
    file_proto = descriptor_pb2.FileDescriptorProto(name="trajeglish_env/sim_agents_subset.proto")
    file_proto.package = _PACKAGE
    file_proto.syntax = "proto2"
    for message_name, fields in schema.items():
        message = file_proto.message_type.add(name=message_name)
        for name, number, kind, repeated, type_name in fields:
            field = message.field.add(name=name, number=number, type=kind)
            field.label = _F.LABEL_REPEATED if repeated else _F.LABEL_OPTIONAL
            if type_name:
                field.type_name = f".{_PACKAGE}.{type_name}"
            elif repeated:
                field.options.packed = True
    pool = descriptor_pool.DescriptorPool()
    pool.AddSerializedFile(file_proto.SerializeToString())
    return {
        name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{_PACKAGE}.{name}"))
        for name in schema
    }


_CLASSES = _build_classes()
SubmissionProto: type[Message] = _CLASSES["SimAgentsChallengeSubmission"]
ScenarioRolloutsProto: type[Message] = _CLASSES["ScenarioRollouts"]


@dataclass(frozen=True, eq=False)
class SubmittedRollouts:
    """The rollouts of one scenario: ``object_id [N]``, ``xyz [R, N, T, 3]`` and ``heading [R, N, T]``
    (float32, agents in the order of the first joint scene)."""

    scenario_id: str
    object_id: np.ndarray
    xyz: np.ndarray
    heading: np.ndarray

    @property
    def xyh(self) -> np.ndarray:
        """``[R, N, T, 3]`` (x, y, heading), the planar rollouts :func:`score_rollouts` takes."""
        return np.concatenate([self.xyz[..., :2], self.heading[..., None]], axis=-1)

    @property
    def z(self) -> np.ndarray:
        """``[R, N, T]`` box-centre heights."""
        return self.xyz[..., 2]


def _scenario_arrays(proto: Message, where: str) -> SubmittedRollouts:
    """Arrays of one ScenarioRollouts message, with every structural check."""
    sid = str(proto.scenario_id)
    where = f"{where}scenario {sid!r}: "
    if not sid:
        raise SubmissionFormatError(f"{where}missing scenario_id")
    if len(proto.joint_scenes) == 0:
        raise SubmissionFormatError(f"{where}no joint scenes")
    ids = np.array([tr.object_id for tr in proto.joint_scenes[0].simulated_trajectories], dtype=np.int64)
    if len(ids) == 0:
        raise SubmissionFormatError(f"{where}joint scene 0 has no trajectories")
    if len(np.unique(ids)) != len(ids):
        raise SubmissionFormatError(f"{where}joint scene 0 lists an object id twice")
    order = np.argsort(ids)
    steps = len(proto.joint_scenes[0].simulated_trajectories[0].center_x)
    poses = np.empty((len(proto.joint_scenes), len(ids), steps, 4), dtype=np.float32)
    for r, scene in enumerate(proto.joint_scenes):
        scene_ids = np.array([tr.object_id for tr in scene.simulated_trajectories], dtype=np.int64)
        if len(scene_ids) != len(ids) or not np.array_equal(np.sort(scene_ids), ids[order]):
            extra = sorted(set(scene_ids.tolist()) ^ set(ids.tolist()))
            raise SubmissionFormatError(
                f"{where}joint scene {r} does not hold the same objects as joint scene 0 "
                f"(differing ids: {extra[:10]}; {len(scene_ids)} vs {len(ids)} trajectories)"
            )
        # Row of each of this scene's trajectories in the order of joint scene 0.
        rows = order[np.searchsorted(ids[order], scene_ids)]
        for row, trajectory in zip(rows, scene.simulated_trajectories, strict=True):
            lengths = [len(getattr(trajectory, name)) for name in _POSE_FIELDS]
            if lengths != [steps] * 4:
                raise SubmissionFormatError(
                    f"{where}joint scene {r}, object {trajectory.object_id}: center_x/y/z and heading must "
                    f"all have {steps} values, got {lengths}"
                )
            for k, name in enumerate(_POSE_FIELDS):
                poses[r, row, :, k] = getattr(trajectory, name)
    if not np.isfinite(poses).all():
        r, row = np.argwhere(~np.isfinite(poses).all(axis=(2, 3)))[0]
        raise SubmissionFormatError(f"{where}joint scene {r}, object {ids[row]}: non-finite pose values")
    return SubmittedRollouts(
        scenario_id=sid, object_id=ids, xyz=poses[..., :3].copy(), heading=poses[..., 3].copy()
    )


def parse_submission(data: bytes, *, origin: str = "") -> list[SubmittedRollouts]:
    """Rollouts of every scenario in a serialized SimAgentsChallengeSubmission (or one ScenarioRollouts)."""
    where = f"{origin}: " if origin else ""
    messages: list[Message] = []
    try:
        messages = list(SubmissionProto.FromString(data).scenario_rollouts)
    except DecodeError:
        messages = []
    if not any(len(m.joint_scenes) for m in messages):
        try:
            single = ScenarioRolloutsProto.FromString(data)
        except DecodeError as exc:
            raise SubmissionFormatError(
                f"{where}not a SimAgentsChallengeSubmission or ScenarioRollouts protobuf: {exc}"
            ) from exc
        if len(single.joint_scenes) == 0:
            raise SubmissionFormatError(f"{where}no scenario rollouts with joint scenes found")
        messages = [single]
    rollouts = [_scenario_arrays(m, where) for m in messages]
    seen: set[str] = set()
    for item in rollouts:
        if item.scenario_id in seen:
            raise SubmissionFormatError(f"{where}scenario {item.scenario_id!r} appears twice")
        seen.add(item.scenario_id)
    return rollouts


def read_submission(path: str | os.PathLike[str]) -> list[SubmittedRollouts]:
    """Read a ``.binproto`` submission file: the rollouts of each of its scenarios, in file order."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SubmissionFormatError(f"{path}: cannot read submission: {exc}") from exc
    return parse_submission(data, origin=str(path))


def encode_submission(rollouts: list[SubmittedRollouts]) -> bytes:
    """Serialize rollouts as a SimAgentsChallengeSubmission (the scenario_rollouts part only)."""
    message = SubmissionProto()
    for item in rollouts:
        scenario = message.scenario_rollouts.add(scenario_id=item.scenario_id)
        for r in range(item.xyz.shape[0]):
            scene = scenario.joint_scenes.add()
            for i, object_id in enumerate(item.object_id):
                scene.simulated_trajectories.add(
                    center_x=item.xyz[r, i, :, 0].tolist(),
                    center_y=item.xyz[r, i, :, 1].tolist(),
                    center_z=item.xyz[r, i, :, 2].tolist(),
                    heading=item.heading[r, i].tolist(),
                    object_id=int(object_id),
                )
    return message.SerializeToString()
