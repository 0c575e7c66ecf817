"""Read and write Waymo Sim Agents submissions (``SimAgentsChallengeSubmission`` / ``ScenarioRollouts``)
without protoc or the waymo package (message classes: :mod:`submission_schema`).

A submission is one or more ``.binproto`` shards, each a ``SimAgentsChallengeSubmission`` with the
metadata (:class:`SubmissionMetadata`) and some scenarios' rollouts, packed for upload as a ``.tar.gz``.
:func:`read_submission` reads a shard, a single ``ScenarioRollouts`` or a whole archive. Serialized
messages concatenate: the bytes of the metadata followed by those of :func:`encode_scenario` for each
scenario are one valid shard (how :mod:`trajeglish_env.submission_export` assembles shards).
"""

from __future__ import annotations

import os
import tarfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from google.protobuf.message import DecodeError, Message

from trajeglish_env.metrics.submission_metadata import SubmissionMetadata
from trajeglish_env.metrics.submission_schema import ScenarioRolloutsProto, SubmissionProto

__all__ = [
    "SubmissionFormatError",
    "SubmissionMetadata",
    "SubmissionProto",
    "SubmittedRollouts",
    "encode_scenario",
    "encode_submission",
    "is_archive",
    "iter_submission",
    "parse_submission",
    "read_submission",
    "read_submission_metadata",
    "submission_files",
]

_POSE_FIELDS = ("center_x", "center_y", "center_z", "heading")


class SubmissionFormatError(ValueError):
    """A submission file is malformed; the message names the file, scenario, joint scene and object."""


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


def _parse(data: bytes, where: str) -> tuple[list[Message], SubmissionMetadata | None]:
    """The ScenarioRollouts messages and the metadata of a shard (or of a lone ScenarioRollouts)."""
    try:
        message = SubmissionProto.FromString(data)
        messages, metadata = list(message.scenario_rollouts), SubmissionMetadata.from_message(message)
    except DecodeError:
        messages, metadata = [], None
    if metadata is None and not any(len(m.joint_scenes) for m in messages):
        try:
            single = ScenarioRolloutsProto.FromString(data)
        except DecodeError as exc:
            raise SubmissionFormatError(
                f"{where}not a SimAgentsChallengeSubmission or ScenarioRollouts protobuf: {exc}"
            ) from exc
        if len(single.joint_scenes) == 0:
            raise SubmissionFormatError(f"{where}no scenario rollouts with joint scenes found")
        messages = [single]
    return messages, metadata


def parse_submission(data: bytes, *, origin: str = "") -> list[SubmittedRollouts]:
    """Rollouts of every scenario in a serialized SimAgentsChallengeSubmission (or one ScenarioRollouts)."""
    where = f"{origin}: " if origin else ""
    rollouts = [_scenario_arrays(m, where) for m in _parse(data, where)[0]]
    _check_unique([r.scenario_id for r in rollouts], where)
    return rollouts


def _check_unique(ids: list[str], where: str) -> None:
    seen: set[str] = set()
    for sid in ids:
        if sid in seen:
            raise SubmissionFormatError(f"{where}scenario {sid!r} appears twice")
        seen.add(sid)


def is_archive(path: str | os.PathLike[str]) -> bool:
    """Whether a path is a packed submission: named ``.tar.gz`` / ``.tgz``, or a tar archive by its
    contents (compressed or not, whatever its name)."""
    if str(path).endswith((".tar.gz", ".tgz")):
        return True
    try:
        return Path(path).is_file() and tarfile.is_tarfile(path)
    except OSError:
        return False


def _shards(path: Path) -> Iterator[tuple[str, bytes]]:
    """(origin, bytes) of every shard of a submission file or archive, in archive order."""
    try:
        if not is_archive(path):
            yield str(path), path.read_bytes()
            return
        with tarfile.open(path, "r:*") as tar:
            for member in tar:
                if member.isfile():
                    handle = tar.extractfile(member)
                    assert handle is not None  # a regular member always has contents
                    yield f"{path}:{member.name}", handle.read()
    except (OSError, tarfile.TarError, EOFError) as exc:
        raise SubmissionFormatError(f"{path}: cannot read submission: {exc}") from exc


def submission_files(path: str | os.PathLike[str]) -> list[Path]:
    """The files of a submission: a shard, an archive, or a directory's ``*.binproto*`` shards (sorted)."""
    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if ".binproto" in p.name and not p.name.startswith("."))
        if not files:
            raise SubmissionFormatError(f"{path}: no submission shards (*.binproto*) in this directory")
        return files
    if not path.is_file():
        raise SubmissionFormatError(f"{path}: cannot read submission: no such file or directory")
    return [path]


def iter_submission(
    path: str | os.PathLike[str], keep: Callable[[int], bool] | None = None
) -> Iterator[tuple[int, SubmittedRollouts]]:
    """``(position, rollouts)`` of every scenario of a submission (shard, ``.tar.gz`` or directory of
    shards), one shard in memory at a time; ``keep(position)`` False skips a scenario's decoding (how
    ranks share the scoring)."""
    seen: set[str] = set()
    position = 0
    for file in submission_files(path):
        for origin, data in _shards(file):
            for message in _parse(data, f"{origin}: ")[0]:
                sid = str(message.scenario_id)
                if sid in seen:
                    raise SubmissionFormatError(f"{origin}: scenario {sid!r} appears twice")
                seen.add(sid)
                if keep is None or keep(position):
                    yield position, _scenario_arrays(message, f"{origin}: ")
                position += 1


def read_submission(path: str | os.PathLike[str]) -> list[SubmittedRollouts]:
    """Read a ``.binproto`` shard or a ``.tar.gz`` of shards: each scenario's rollouts, in file order."""
    return [item for _, item in iter_submission(path)]


def read_submission_metadata(path: str | os.PathLike[str]) -> list[SubmissionMetadata | None]:
    """The metadata of every shard of a submission file or archive (None for a shard without any)."""
    return [_parse(data, f"{o}: ")[1] for file in submission_files(path) for o, data in _shards(file)]


def encode_scenario(item: SubmittedRollouts) -> bytes:
    """One scenario's rollouts as a SimAgentsChallengeSubmission fragment; fragments and the metadata's
    bytes concatenate into a shard."""
    message = SubmissionProto()
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


def encode_submission(rollouts: list[SubmittedRollouts], metadata: SubmissionMetadata | None = None) -> bytes:
    """Serialize rollouts (and the metadata, if given) as one SimAgentsChallengeSubmission shard."""
    head = metadata.encode() if metadata is not None else b""
    return head + b"".join(encode_scenario(item) for item in rollouts)
