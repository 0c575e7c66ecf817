"""Digests that key saved results: a file's sha256 and one of a source tree's Python files (a result
computed by other code or from another checkpoint is computed again)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


def source_digest(root: Path) -> str:
    """The sha256 (16 hex digits) of the Python sources under ``root``, their paths and contents."""
    digest = hashlib.sha256()
    for source in sorted(root.rglob("*.py")):
        digest.update(source.relative_to(root).as_posix().encode() + b"\0")
        digest.update(source.read_bytes())
    return digest.hexdigest()[:16]


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The sha256 (hex) of a file's bytes, read in blocks (checkpoints are megabytes)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
