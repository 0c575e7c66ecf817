"""Stop events for highway-env scenes: one vehicle brakes hard to a stop, and the traffic behind reacts.

highway-env's IDM traffic rarely holds a hard stop in front of a follower, so a model trained on its
scenes never sees what a follower does then (the brake test's failure: unguarded NPCs rear-end a
braking ego). A ``KIND+stop`` scene kind (``highway+stop``, ``roundabout+stop``, ...) is the base kind
with one such event: at a random step around the current one, a moving vehicle with a follower close
behind it in its lane (the sdc when it has one, else a random such vehicle near the sdc) brakes at a
constant rate to a stop and holds, without changing lanes, to the end of the scene. Everyone else
drives by IDM/MOBIL as before; scenes with a crash are retried like any other. These kinds are not in
the source's default kinds: ask for them with ``generate --kinds highway+stop ...``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from highway_env.road.road import Road
from highway_env.vehicle.kinematics import Vehicle

STOP_SUFFIX = "+stop"


@dataclass(frozen=True)
class StopEvent:
    """When (recorded ``step``) and how hard (``decel`` m/s^2) the chosen vehicle stops; who stops is
    decided at that step from the traffic then (see :func:`choose_stopper`), by ``pick`` in [0, 1)."""

    step: int
    decel: float
    pick: float
    max_gap: float = 30.0
    headway: float = 3.0
    min_speed: float = 5.0
    near_sdc: float = 80.0


def split_kind(kind: str) -> tuple[str, bool]:
    """``"merge+stop"`` -> ``("merge", True)``; ``"merge"`` -> ``("merge", False)``."""
    if kind.endswith(STOP_SUFFIX):
        return kind[: -len(STOP_SUFFIX)], True
    return kind, False


def draw_stop_event(seed: int, attempt: int, current_index: int, steps: int) -> StopEvent:
    """The event of one try of a ``+stop`` scene, from its own stream (the base kind's draws are not
    touched): a step from 0.5 s before the current one to 3 s after it, a rate of 3-6 m/s^2 (the env's
    own ego brakes at up to 6)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, attempt, 0x5709]))
    low = max(current_index - 5, 0)
    high = max(min(current_index + 30, steps - 2), low)
    return StopEvent(int(rng.integers(low, high + 1)), float(rng.uniform(3.0, 6.0)), float(rng.random()))


def _has_close_follower(road: Road, vehicle: Vehicle, event: StopEvent) -> bool:
    """Whether a vehicle follows ``vehicle`` in its lane within ``max_gap`` m bumper to bumper, or within
    ``headway`` seconds at the vehicle's speed (highway traffic keeps 1.5 s and more)."""
    _, rear = road.neighbour_vehicles(vehicle, vehicle.lane_index)
    if rear is None:
        return False
    gap = float(np.linalg.norm(vehicle.position - rear.position)) - (vehicle.LENGTH + rear.LENGTH) / 2
    return gap <= max(event.max_gap, event.headway * vehicle.speed)


def choose_stopper(road: Road, sdc: Vehicle, event: StopEvent) -> Vehicle | None:
    """The vehicle that stops: the sdc if it moves at ``min_speed`` or more with a follower close behind
    (:func:`_has_close_follower`), else one such vehicle within ``near_sdc`` m of the sdc (by
    ``event.pick``); None when there is none."""
    moving = [v for v in road.vehicles if not v.crashed and v.speed >= event.min_speed]
    if sdc in moving and _has_close_follower(road, sdc, event):
        return sdc
    near = [
        v
        for v in moving
        if np.linalg.norm(v.position - sdc.position) <= event.near_sdc and _has_close_follower(road, v, event)
    ]
    if not near:
        return None
    return near[min(int(event.pick * len(near)), len(near) - 1)]


def start_stop(vehicle: Vehicle, event: StopEvent) -> None:
    """Make ``vehicle`` (a ``SceneIDMVehicle``) brake at ``event.decel`` to a stop and hold, in its lane."""
    vehicle.stop_decel = event.decel
    vehicle.enable_lane_change = False
    vehicle.target_lane_index = vehicle.lane_index


def stop_id_suffix(event: StopEvent | None, track: int | None) -> str:
    """What a ``+stop`` scene's id gets after its seed: ``-stop-a{track}-t{step}`` naming the vehicle that
    stopped (its track id) and the recorded step it began, or nothing when no vehicle qualified."""
    return "" if event is None or track is None else f"-stop-a{track}-t{event.step}"


def stop_event_in(scene: Any) -> tuple[int, int] | None:
    """``(agent index, step)`` of the stop event a generated ``+stop`` scene records in its id, else None."""
    match = re.search(r"\+stop-\d+-stop-a(\d+)-t(\d+)$", scene.scenario_id)
    if match is None:
        return None
    return scene.agent_index(int(match.group(1))), int(match.group(2))
