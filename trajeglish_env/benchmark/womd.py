"""The ``womd`` section of ``trajeglish bench``: a real WOMD scene with all its agents, the size users run
(issue 16). It times (a) full-control rollouts of every agent valid at the current step, as a Sim Agents
submission needs them (32 rollouts x 80 steps), in one process and split over the usable cores'
processes (``rollout(..., processes=...)``, the same rollouts), and (b) the AEC env (the README's lead
API) on that scene: the sdc is the one external agent and replays its log, every other agent is a
default Trajeglish NPC. highway-env's ``intersection-v0`` is timed right after, so the env's ratio to it
comes from one run.

The scenario file is never downloaded: ``--womd FILE``, else the shared data folder (see
:func:`candidate_paths`); when none is found the section is skipped with the places it looked."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from trajeglish_env.benchmark.aec import aec_env_speed, present_agents
from trajeglish_env.cores import usable_cores
from trajeglish_env.scenario import Scenario

SHARED_FILE = "data/womd/motion_data_one_scenario.tfrecord"  # the shared real scenario, in `shared/`
ROLLOUTS, HORIZON = 32, 80  # one scene of a Sim Agents submission
QUICK_ROLLOUTS, QUICK_HORIZON = 2, 5
ENV_WARMUP, QUICK_ENV_STEPS = 2, 3


def candidate_paths(cwd: Path | None = None) -> list[Path]:
    """Where the shared scenario may be, in search order: ``$TRAJEGLISH_SHARED``, then a ``shared/``
    folder in the checkout's folder or any folder above it (a git worktree sits below the main
    checkout), then the same from the current directory. No duplicates."""
    roots: list[Path] = []
    if os.environ.get("TRAJEGLISH_SHARED"):
        roots.append(Path(os.environ["TRAJEGLISH_SHARED"]))
    repo = Path(__file__).resolve().parents[2]
    here = (cwd or Path.cwd()).resolve()
    for base in (repo, here):
        roots += [folder / "shared" for folder in (base, *base.parents)]
    found: list[Path] = []
    for root in roots:
        if (path := root / SHARED_FILE) not in found:
            found.append(path)
    return found


def locate_womd(explicit: str | os.PathLike[str] | None = None) -> Path | str:
    """The scenario file to time: ``explicit`` if given, else the first of :func:`candidate_paths` that
    exists. Returns the path, or the reason to skip the section (naming where it looked)."""
    if explicit is not None:
        path = Path(explicit)
        return path if path.is_file() else f"no WOMD scenario file at {path} (--womd)"
    places = candidate_paths()
    for path in places:
        if path.is_file():
            return path
    unset = "" if os.environ.get("TRAJEGLISH_SHARED") else " (TRAJEGLISH_SHARED is unset)"
    return (
        f"no WOMD scenario: looked for {SHARED_FILE} under $TRAJEGLISH_SHARED{unset}, then shared/ beside "
        f"the checkout and the current directory: {', '.join(str(p) for p in places)}; pass --womd FILE"
    )


def load_womd(path: Path) -> Scenario:
    """The first scene of a WOMD TFRecord file (a corrupt or empty file is a ValueError naming it)."""
    from trajeglish_env.sources.womd import read_womd

    scene = next(read_womd(path), None)
    if scene is None:
        raise ValueError(f"bench --womd: {path} holds no scenario")
    return scene


def womd_section(path: Path, scene: Scenario | None = None, quick: bool = False) -> dict[str, Any]:
    """The section's figures for the scene in ``path`` (``scene``: that scene, already read):
    ``rollouts`` (one torch thread, as the ``rollout`` section), ``rollouts_split`` (the same over the usable
    cores' processes, one thread each), ``env`` (the AEC env at its default
    settings) and ``highway_env`` (``intersection-v0`` timed right after the env)."""
    import torch

    from trajeglish_env.benchmark.measure import highway_env_speed, rollout_speed
    from trajeglish_env.benchmark.workloads import model_checkpoint

    scene = load_womd(path) if scene is None else scene
    ckpt, model = model_checkpoint()
    rollouts, horizon = (QUICK_ROLLOUTS, QUICK_HORIZON) if quick else (ROLLOUTS, HORIZON)
    steps = QUICK_ENV_STEPS if quick else scene.num_steps - scene.current_index - 1 - ENV_WARMUP
    threads = torch.get_num_threads()  # the env sets its own: restore the suite's afterwards
    cores = usable_cores()
    try:
        torch.set_num_threads(1)
        timed = rollout_speed(ckpt, scene, rollouts, horizon)
        split = rollout_speed(ckpt, scene, rollouts, horizon, processes=cores) if cores > 1 else None
        env = aec_env_speed(scene, steps, 1 if quick else ENV_WARMUP)
    finally:
        torch.set_num_threads(threads)
    each = {"rollouts": rollouts, "horizon": horizon, "torch_threads": 1}
    return {
        "file": str(path),
        "scenario_id": scene.scenario_id,
        "agents": present_agents(scene),
        "model": model,
        "rollouts": {**each, **timed},
        "rollouts_split": {**each, "processes": cores, **split} if split else {"skipped": "one core"},
        "env": env,
        "highway_env": highway_env_speed(40, 60 if quick else 300),
    }


def womd_ratio(section: dict[str, Any]) -> float | None:
    """The AEC env's steps/s over ``intersection-v0``'s steps/s of the same run (None when skipped)."""
    env, base = section.get("env"), section.get("highway_env", {}).get("steps_per_s")
    return round(env["env_steps_per_s"] / base, 3) if env and base else None
