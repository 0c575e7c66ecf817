"""The parts of a logged scene that the realism metrics need and a :class:`Scenario` does not keep.

A Scenario is planar and cleaned: positions are zeroed at invalid steps, there is no z, no box height
and one (length, width) per agent, the WOMD object types TYPE_OTHER/TYPE_UNSET become vehicles, and a
signal has one stop point. The official metrics use the raw values: 3-D speeds, z-aware road-edge
association, box bottoms at ``z - height / 2``, raw (placeholder) states at invalid steps, and per-step
stop points. :class:`LogDetails` carries them; :meth:`LogDetails.planar` derives them from a Scenario
alone (z = 0, height = 0), which is exact for generated scenes and an approximation for WOMD ones
(read WOMD details with :func:`trajeglish_env.metrics.womd_details.read_womd_details`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.scenario import AgentKind, Scenario

__all__ = ["KIND_TO_OBJECT_TYPE", "TYPE_VEHICLE", "LogDetails"]

TYPE_VEHICLE = 1  # WOMD Track.ObjectType of vehicles
# AgentKind -> WOMD Track.ObjectType (TYPE_VEHICLE, TYPE_PEDESTRIAN, TYPE_CYCLIST)
KIND_TO_OBJECT_TYPE = {AgentKind.VEHICLE: 1, AgentKind.PEDESTRIAN: 2, AgentKind.CYCLIST: 3}


@dataclass(frozen=True, eq=False)
class LogDetails:
    """Raw per-track and per-map-point values aligned with one Scenario (same agents, points, signals).

    ``track_id [N]`` (to check the alignment); ``xyz [N, T, 3]`` and ``heading [N, T]`` box centres and
    headings including the raw values at invalid steps; ``box [N, 3]`` (length, width, height) at the
    current step; ``object_type [N]`` WOMD Track.ObjectType; ``map_z [P]`` z of each map point;
    ``signal_stop [T, L, 2]`` stop point of each signal at each step ((0, 0) where not reported).
    """

    track_id: np.ndarray
    xyz: np.ndarray
    heading: np.ndarray
    box: np.ndarray
    object_type: np.ndarray
    map_z: np.ndarray
    signal_stop: np.ndarray

    @classmethod
    def planar(cls, scenario: Scenario) -> LogDetails:
        """Details implied by a Scenario alone: z = 0, height = 0, the Scenario's boxes, kinds and stops."""
        n, t = scenario.valid.shape
        xyz = np.zeros((n, t, 3), np.float64)
        xyz[..., :2] = scenario.xyh[..., :2]
        box = np.zeros((n, 3), np.float64)
        box[:, :2] = scenario.size
        types = np.array([KIND_TO_OBJECT_TYPE[AgentKind(k)] for k in scenario.kind], dtype=np.int64)
        stop = np.broadcast_to(scenario.signal_xy[None], (t, *scenario.signal_xy.shape)).copy()
        return cls(
            track_id=scenario.track_id.copy(),
            xyz=xyz,
            heading=scenario.xyh[..., 2].copy(),
            box=box,
            object_type=types.reshape(n),
            map_z=np.zeros(len(scenario.map_points), np.float64),
            signal_stop=stop,
        )

    def check_matches(self, scenario: Scenario) -> None:
        """Raise ValueError (naming the field) unless these details belong to ``scenario``."""
        n, t = scenario.valid.shape
        where = f"log details of scenario {scenario.scenario_id!r}"
        expected = {
            "track_id": (n,),
            "xyz": (n, t, 3),
            "heading": (n, t),
            "box": (n, 3),
            "object_type": (n,),
            "map_z": (len(scenario.map_points),),
            "signal_stop": (t, len(scenario.signal_lane_id), 2),
        }
        for name, shape in expected.items():
            got = np.shape(getattr(self, name))
            if got != shape:
                raise ValueError(f"{where}: field '{name}' has shape {got}, expected {shape}")
        if not np.array_equal(self.track_id, scenario.track_id):
            raise ValueError(f"{where}: track ids differ from the scenario's (not the same scene or order)")
        valid = scenario.valid
        if not (np.isfinite(self.xyz[valid]).all() and np.isfinite(self.heading[valid]).all()):
            raise ValueError(f"{where}: non-finite position or heading at a valid step")
