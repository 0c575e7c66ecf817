"""Protobuf classes for the parts of WOMD's ``Scenario`` message that we read, built without protoc.

The schema is a subset of the public ``waymo_open_dataset/protos/scenario.proto`` and ``map.proto``
(proto2), written here as a ``FileDescriptorProto`` with the same field numbers and wire types, so the
official serialized records parse with it; fields not listed (lidar, camera tokens, velocities, lane
neighbours, ...) are skipped by protobuf as unknown fields. Enum fields are declared as ``int32`` (the
same varint wire encoding) so an unexpected enum value reaches our code and gets a clear error instead
of vanishing into unknown fields. The classes live in a private descriptor pool under the package
``trajeglish_env.womd`` so they can never clash with the official ``waymo.open_dataset`` classes.
"""

from __future__ import annotations

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import Message

PACKAGE = "trajeglish_env.womd"

_F = descriptor_pb2.FieldDescriptorProto
_SCALARS = {
    "double": _F.TYPE_DOUBLE,
    "float": _F.TYPE_FLOAT,
    "int32": _F.TYPE_INT32,
    "int64": _F.TYPE_INT64,
    "bool": _F.TYPE_BOOL,
    "string": _F.TYPE_STRING,
}

# message name -> [(field name, number, type, repeated, oneof name or "")]; a type that is not a scalar
# names another message of this schema. Numbers and types follow the official protos.
_SCHEMA: dict[str, list[tuple[str, int, str, bool, str]]] = {
    "MapPoint": [("x", 1, "double", False, ""), ("y", 2, "double", False, ""), ("z", 3, "double", False, "")],
    "ObjectState": [
        ("center_x", 2, "double", False, ""),
        ("center_y", 3, "double", False, ""),
        ("center_z", 4, "double", False, ""),
        ("length", 5, "float", False, ""),
        ("width", 6, "float", False, ""),
        ("height", 7, "float", False, ""),
        ("heading", 8, "float", False, ""),
        ("valid", 11, "bool", False, ""),
    ],
    "Track": [
        ("id", 1, "int32", False, ""),
        ("object_type", 2, "int32", False, ""),  # enum Track.ObjectType
        ("states", 3, "ObjectState", True, ""),
    ],
    "TrafficSignalLaneState": [
        ("lane", 1, "int64", False, ""),
        ("state", 2, "int32", False, ""),  # enum TrafficSignalLaneState.State
        ("stop_point", 3, "MapPoint", False, ""),
    ],
    "DynamicMapState": [("lane_states", 1, "TrafficSignalLaneState", True, "")],
    "RequiredPrediction": [("track_index", 1, "int32", False, "")],
    "LaneCenter": [("type", 2, "int32", False, ""), ("polyline", 8, "MapPoint", True, "")],
    "RoadLine": [("type", 1, "int32", False, ""), ("polyline", 2, "MapPoint", True, "")],
    "RoadEdge": [("type", 1, "int32", False, ""), ("polyline", 2, "MapPoint", True, "")],
    "StopSign": [("lane", 1, "int64", True, ""), ("position", 2, "MapPoint", False, "")],
    "Crosswalk": [("polygon", 1, "MapPoint", True, "")],
    "SpeedBump": [("polygon", 1, "MapPoint", True, "")],
    "Driveway": [("polygon", 1, "MapPoint", True, "")],
    "MapFeature": [
        ("id", 1, "int64", False, ""),
        ("lane", 3, "LaneCenter", False, "feature_data"),
        ("road_line", 4, "RoadLine", False, "feature_data"),
        ("road_edge", 5, "RoadEdge", False, "feature_data"),
        ("stop_sign", 7, "StopSign", False, "feature_data"),
        ("crosswalk", 8, "Crosswalk", False, "feature_data"),
        ("speed_bump", 9, "SpeedBump", False, "feature_data"),
        ("driveway", 10, "Driveway", False, "feature_data"),
    ],
    "Scenario": [
        ("timestamps_seconds", 1, "double", True, ""),
        ("tracks", 2, "Track", True, ""),
        ("objects_of_interest", 4, "int32", True, ""),
        ("scenario_id", 5, "string", False, ""),
        ("sdc_track_index", 6, "int32", False, ""),
        ("dynamic_map_states", 7, "DynamicMapState", True, ""),
        ("map_features", 8, "MapFeature", True, ""),
        ("current_time_index", 10, "int32", False, ""),
        ("tracks_to_predict", 11, "RequiredPrediction", True, ""),
    ],
}


def _file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    """The schema above as a proto2 file descriptor."""
    file_proto = descriptor_pb2.FileDescriptorProto(name="trajeglish_env/womd_subset.proto", package=PACKAGE)
    file_proto.syntax = "proto2"
    for message_name, fields in _SCHEMA.items():
        message = file_proto.message_type.add(name=message_name)
        oneofs: list[str] = []
        for name, number, type_name, repeated, oneof in fields:
            field = message.field.add(name=name, number=number)
            field.label = _F.LABEL_REPEATED if repeated else _F.LABEL_OPTIONAL
            if type_name in _SCALARS:
                field.type = _SCALARS[type_name]
            else:
                field.type = _F.TYPE_MESSAGE
                field.type_name = f".{PACKAGE}.{type_name}"
            if oneof:
                if oneof not in oneofs:
                    oneofs.append(oneof)
                    message.oneof_decl.add(name=oneof)
                field.oneof_index = oneofs.index(oneof)
    return file_proto


def _build_classes() -> dict[str, type[Message]]:
    """Message classes of the schema, registered in a private pool (never the default one)."""
    pool = descriptor_pool.DescriptorPool()
    pool.AddSerializedFile(_file_descriptor().SerializeToString())
    return {
        name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{PACKAGE}.{name}"))
        for name in _SCHEMA
    }


_CLASSES = _build_classes()
ScenarioProto: type[Message] = _CLASSES["Scenario"]
MapFeatureProto: type[Message] = _CLASSES["MapFeature"]
