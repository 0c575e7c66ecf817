"""Locating and running the Eclipse SUMO command-line tools (shipped in the ``eclipse-sumo`` wheel).

Every SUMO call of the SUMO scene source goes through :func:`run_tool`, so a missing installation gives
one clear :class:`SumoNotAvailableError` and a failing tool a :class:`SumoToolError` quoting its stderr.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Sequence
from pathlib import Path

INSTALL_HINT = (
    "install it with: pip install 'trajeglish_env[sumo]' (the eclipse-sumo wheel ships the binaries), or "
    "point SUMO_HOME at a SUMO installation (its bin/ holds sumo and netgenerate)"
)
_STDERR_TAIL_CHARS = 2000


class SumoNotAvailableError(FileNotFoundError):
    """Eclipse SUMO (its Python package or its binaries) cannot be found (bad input for the CLI: one line,
    exit code 2)."""


class SumoToolError(RuntimeError):
    """A SUMO tool (netgenerate, sumo) exited with an error; the message quotes its stderr tail."""


def sumo_home() -> Path:
    """The SUMO installation: the ``sumo`` package of the eclipse-sumo wheel, else ``$SUMO_HOME``."""
    try:
        import sumo  # the eclipse-sumo wheel; sets SUMO_HOME for the tools it ships

        return Path(sumo.SUMO_HOME)
    except ImportError as error:
        env_home = os.environ.get("SUMO_HOME")
        if env_home:
            return Path(env_home)
        raise SumoNotAvailableError(
            f"Eclipse SUMO is not installed (import sumo failed: {error}); {INSTALL_HINT}"
        ) from error


def sumo_binary(name: str) -> Path:
    """Path of the SUMO executable ``name`` (e.g. ``"sumo"``, ``"netgenerate"``); a clear error if absent."""
    home = sumo_home()
    path = home / "bin" / name
    if not (path.is_file() and os.access(path, os.X_OK)):
        raise SumoNotAvailableError(
            f"SUMO binary {name!r} not found at {path} (SUMO_HOME={home}); {INSTALL_HINT}"
        )
    return path


def check_available() -> None:
    """Fail now, with the install hint, when a SUMO tool the generator runs is missing."""
    for name in ("netgenerate", "sumo"):
        sumo_binary(name)


def run_tool(name: str, args: Sequence[str], cwd: Path, timeout_s: float = 600.0) -> str:
    """Run SUMO tool ``name`` with ``args`` in ``cwd``; return its stdout, raise SumoToolError on failure."""
    binary = sumo_binary(name)
    env = dict(os.environ, SUMO_HOME=str(sumo_home()))
    try:
        done = subprocess.run(
            [str(binary), *args],
            cwd=cwd,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout_s,
            check=False,
        )
    except subprocess.TimeoutExpired as error:
        raise SumoToolError(
            f"{name} did not finish within {timeout_s:.0f} s (args: {' '.join(args)})"
        ) from error
    except OSError as error:
        raise SumoNotAvailableError(
            f"cannot execute SUMO binary {binary}: {error}; {INSTALL_HINT}"
        ) from error
    if done.returncode != 0:
        tail = (done.stderr or done.stdout or "").strip()[-_STDERR_TAIL_CHARS:]
        raise SumoToolError(f"{name} failed with exit code {done.returncode}: {tail or '(no output)'}")
    return done.stdout
