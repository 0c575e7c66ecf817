"""The metadata of a Waymo Sim Agents submission (who submits which method, and how it was made).

Every field of ``SimAgentsChallengeSubmission`` besides the rollouts, with the leaderboard's rules: the
submission type, the account (the e-mail registered at waymo.com/open), a unique method name, authors,
affiliation and description are required; the lidar, camera and public-model-pretraining flags and the
closed-loop acknowledgement are always written (False is an answer too); ``num_model_parameters`` is an
integer with a multiplier suffix (``"200K"``, ``"3M"``).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from typing import Any

from google.protobuf.message import Message

from trajeglish_env.metrics.submission_schema import METADATA_FIELDS, SIM_AGENTS_SUBMISSION, SubmissionProto

__all__ = ["SubmissionMetadata", "format_parameter_count"]

_PARAMETERS = re.compile(r"^[0-9]+[KMBT]$")
_REQUIRED_TEXT = ("account_name", "unique_method_name", "affiliation", "description", "num_model_parameters")
_FLAG = {  # metadata field -> the CLI flag that sets it (for error messages)
    "account_name": "--account-name",
    "unique_method_name": "--method-name",
    "authors": "--authors",
    "affiliation": "--affiliation",
    "description": "--description",
    "num_model_parameters": "--num-model-parameters",
}


@dataclass(frozen=True)
class SubmissionMetadata:
    """The non-rollout fields of a ``SimAgentsChallengeSubmission`` (see the module docstring)."""

    account_name: str = ""
    unique_method_name: str = ""
    authors: tuple[str, ...] = ()
    affiliation: str = ""
    description: str = ""
    method_link: str = ""
    uses_lidar_data: bool = False
    uses_camera_data: bool = False
    uses_public_model_pretraining: bool = False
    public_model_names: tuple[str, ...] = ()
    num_model_parameters: str = ""
    acknowledge_complies_with_closed_loop_requirement: bool = False
    submission_type: int = SIM_AGENTS_SUBMISSION

    def validate(self) -> SubmissionMetadata:
        """Raise ValueError naming every missing or malformed field (and its CLI flag); return self."""
        missing = [n for n in _REQUIRED_TEXT if not getattr(self, n).strip()]
        if not [a for a in self.authors if a.strip()]:
            missing.insert(2, "authors")
        problems = [f"{n} ({_FLAG[n]})" for n in missing]
        if self.account_name.strip() and "@" not in self.account_name:
            problems.append("account_name must be the e-mail registered at waymo.com/open (--account-name)")
        if self.num_model_parameters.strip() and not _PARAMETERS.match(self.num_model_parameters):
            problems.append(
                f"num_model_parameters {self.num_model_parameters!r} must be an integer with a suffix "
                "K, M, B or T, e.g. '200K' (--num-model-parameters)"
            )
        if self.uses_public_model_pretraining and not self.public_model_names:
            problems.append("public_model_names: name the pretrained public models (--public-model-names)")
        if not self.acknowledge_complies_with_closed_loop_requirement:
            problems.append("acknowledge_complies_with_closed_loop_requirement must be true")
        if self.submission_type != SIM_AGENTS_SUBMISSION:
            problems.append(f"submission_type must be SIM_AGENTS_SUBMISSION ({SIM_AGENTS_SUBMISSION})")
        if problems:
            raise ValueError("submission metadata: missing or invalid: " + "; ".join(problems))
        return self

    def to_dict(self) -> dict[str, Any]:
        """JSON-able fields (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def message(self) -> Message:
        """A ``SimAgentsChallengeSubmission`` holding only this metadata, every field set explicitly."""
        message = SubmissionProto()
        for name, (_, _, repeated) in METADATA_FIELDS.items():
            value = getattr(self, name)
            if repeated:
                getattr(message, name).extend(value)
            else:
                setattr(message, name, value)
        return message

    def encode(self) -> bytes:
        """The serialized metadata (the head of every submission shard)."""
        return self.message().SerializeToString()

    @classmethod
    def from_message(cls, message: Message) -> SubmissionMetadata | None:
        """The metadata of a parsed submission; None if it carries none (e.g. the official test file)."""
        if not any(message.HasField(n) for n, (_, _, rep) in METADATA_FIELDS.items() if not rep):
            return None
        values = {
            name: tuple(getattr(message, name)) if repeated else getattr(message, name)
            for name, (_, _, repeated) in METADATA_FIELDS.items()
        }
        return cls(**values)


def format_parameter_count(count: int) -> str:
    """A parameter count the way the leaderboard wants it: an integer and a suffix (1,534,208 -> "1534K")."""
    for suffix, unit in (("T", 10**12), ("B", 10**9), ("M", 10**6)):
        if round(count / unit) >= 10:
            return f"{round(count / unit)}{suffix}"
    return f"{max(1, round(count / 10**3))}K"
