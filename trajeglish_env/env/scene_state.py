"""The explicit per-scene state that the per-step geometry pass reads (``env/batch_outcomes.py``): a
running scene's arrays, built at reset and updated in place by its simulation, so the geometry code
depends on these fields alone and not on the simulation that owns them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajeglish_env.env.config import ObservationConfig
from trajeglish_env.env.drivers import RowView
from trajeglish_env.env.routes import Paths


@dataclass
class Kinematics:
    """Per-agent speed, last accelerations and yaw rate of the external agents (arrays over all agents)."""

    speed: np.ndarray
    accel: np.ndarray
    lateral: np.ndarray
    yaw_rate: np.ndarray


@dataclass(eq=False)
class SceneState:
    """One running scene as the geometry pass sees it (identity marks an episode: padded arrays are
    refreshed when a row's state object changes).

    ``row``: the exact states so far; ``size [N,2]``, ``kind [N]``, ``dt``; road edges as segment columns
    ``edge_columns [7,S]`` / ``edge_links [3,S]`` and ``offroad_margin``; the observation's map points
    ``map_points [K,2]`` / ``map_category [K]`` and settings ``obs``; the external agents
    ``external_index [E]``, which have left (``retired [N]``), their routes (``routes`` rows, ``route_row
    [N]``, ``progress [E]`` m, ``has_goal [E]``) and kinematics ``kin``. Mutable arrays change in place.
    """

    row: RowView
    size: np.ndarray
    kind: np.ndarray
    dt: float
    edge_columns: np.ndarray
    edge_links: np.ndarray
    offroad_margin: float
    map_points: np.ndarray
    map_category: np.ndarray
    obs: ObservationConfig
    external_index: np.ndarray
    retired: np.ndarray
    routes: Paths
    route_row: np.ndarray
    progress: np.ndarray
    has_goal: np.ndarray
    kin: Kinematics
    signal_xy: np.ndarray  # [L,2] stop points of the signal-controlled lanes
    signal_state: np.ndarray | None  # [T,L] SignalState per logged step (None: no signals)

    @property
    def t(self) -> int:
        """The step being played."""
        return self.row.t

    def live_external(self) -> np.ndarray:
        """External agents still in the scene (index order)."""
        return self.external_index[~self.retired[self.external_index]]
