"""Message classes of the Waymo Sim Agents submission schema, built from a descriptor (no protoc, no
waymo package).

Field numbers follow the public ``sim_agents_submission.proto`` (proto2, package waymo.open_dataset):

- ``SimulatedTrajectory``: 2 center_x, 3 center_y, 4 center_z, 5 heading (packed floats), 6 object_id;
- ``JointScene``: 1 simulated_trajectories; ``ScenarioRollouts``: 1 scenario_id, 2 joint_scenes;
- ``SimAgentsChallengeSubmission``: 1 scenario_rollouts, 2 submission_type (enum SubmissionType: UNKNOWN
  0, SIM_AGENTS_SUBMISSION 1), 3 account_name, 4 unique_method_name, 5 authors (repeated), 6 affiliation,
  7 description, 8 method_link, 9 uses_lidar_data, 10 uses_camera_data, 11
  uses_public_model_pretraining, 12 num_model_parameters (string such as "200K"), 13 public_model_names
  (repeated), 14 acknowledge_complies_with_closed_loop_requirement.

The message names are the official ones in a private package, so the bytes are the official format.
"""

from __future__ import annotations

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import Message

__all__ = ["METADATA_FIELDS", "SIM_AGENTS_SUBMISSION", "ScenarioRolloutsProto", "SubmissionProto"]

_PACKAGE = "trajeglish_env.sim_agents"
_F = descriptor_pb2.FieldDescriptorProto
_S, _B, _FLOAT, _I32, _MSG, _ENUM = (
    _F.TYPE_STRING,
    _F.TYPE_BOOL,
    _F.TYPE_FLOAT,
    _F.TYPE_INT32,
    _F.TYPE_MESSAGE,
    _F.TYPE_ENUM,
)
SIM_AGENTS_SUBMISSION = 1  # SimAgentsChallengeSubmission.SubmissionType value of a Sim Agents entry

# name -> (number, type, repeated) of the submission's metadata fields, in field-number order
METADATA_FIELDS: dict[str, tuple[int, int, bool]] = {
    "submission_type": (2, _ENUM, False),
    "account_name": (3, _S, False),
    "unique_method_name": (4, _S, False),
    "authors": (5, _S, True),
    "affiliation": (6, _S, False),
    "description": (7, _S, False),
    "method_link": (8, _S, False),
    "uses_lidar_data": (9, _B, False),
    "uses_camera_data": (10, _B, False),
    "uses_public_model_pretraining": (11, _B, False),
    "num_model_parameters": (12, _S, False),
    "public_model_names": (13, _S, True),
    "acknowledge_complies_with_closed_loop_requirement": (14, _B, False),
}

_SUBMISSION_TYPE = "SimAgentsChallengeSubmission.SubmissionType"
# message -> [(field, number, type, repeated, message or enum type)]
_SCHEMA: dict[str, list[tuple[str, int, int, bool, str]]] = {
    "SimulatedTrajectory": [
        ("center_x", 2, _FLOAT, True, ""),
        ("center_y", 3, _FLOAT, True, ""),
        ("center_z", 4, _FLOAT, True, ""),
        ("heading", 5, _FLOAT, True, ""),
        ("object_id", 6, _I32, False, ""),
    ],
    "JointScene": [("simulated_trajectories", 1, _MSG, True, "SimulatedTrajectory")],
    "ScenarioRollouts": [
        ("scenario_id", 1, _S, False, ""),
        ("joint_scenes", 2, _MSG, True, "JointScene"),
    ],
    "SimAgentsChallengeSubmission": [
        ("scenario_rollouts", 1, _MSG, True, "ScenarioRollouts"),
        *[
            (name, number, kind, repeated, _SUBMISSION_TYPE if kind == _ENUM else "")
            for name, (number, kind, repeated) in METADATA_FIELDS.items()
        ],
    ],
}


def _build_classes() -> dict[str, type[Message]]:
    """The schema's message classes, in a private descriptor pool."""
    file_proto = descriptor_pb2.FileDescriptorProto(name="trajeglish_env/sim_agents_submission.proto")
    file_proto.package = _PACKAGE
    file_proto.syntax = "proto2"
    for message_name, fields in _SCHEMA.items():
        message = file_proto.message_type.add(name=message_name)
        if message_name == "SimAgentsChallengeSubmission":
            enum = message.enum_type.add(name="SubmissionType")
            enum.value.add(name="UNKNOWN", number=0)
            enum.value.add(name="SIM_AGENTS_SUBMISSION", number=SIM_AGENTS_SUBMISSION)
        for name, number, kind, repeated, type_name in fields:
            field = message.field.add(name=name, number=number, type=kind)
            field.label = _F.LABEL_REPEATED if repeated else _F.LABEL_OPTIONAL
            if type_name:
                field.type_name = f".{_PACKAGE}.{type_name}"
            elif repeated and kind == _FLOAT:
                field.options.packed = True
    pool = descriptor_pool.DescriptorPool()
    pool.AddSerializedFile(file_proto.SerializeToString())
    return {
        name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{_PACKAGE}.{name}"))
        for name in _SCHEMA
    }


_CLASSES = _build_classes()
SubmissionProto: type[Message] = _CLASSES["SimAgentsChallengeSubmission"]
ScenarioRolloutsProto: type[Message] = _CLASSES["ScenarioRollouts"]
