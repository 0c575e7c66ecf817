"""Step outcomes and observations of many simulations at once (the arrays of :mod:`batch_geometry`).

A :class:`BatchGeometry` serves one scene (an unbatched env) or every scene of a batched env; it keeps the
padded static arrays of the scenes it saw last (sizes, road edges, observation map points, routes) and
refreshes only the rows whose scene state changed (a reset)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from trajeglish_env.batch_geometry import (
    OTHER,
    NearbyItems,
    PaddedRows,
    collision_flags,
    latest_states,
    offroad_flags,
    pad_stack,
    point_segment_distances,
    vector_observations,
)
from trajeglish_env.env.routes import Paths, stack_paths
from trajeglish_env.env.scene_state import SceneState
from trajeglish_env.env.signal_features import signal_features
from trajeglish_env.geometry import wrap_angle

EDGE_REACH, EDGE_DRIFT = 40.0, 10.0  # m: road edges kept around an agent, and how far it may move off
MAP_DRIFT = 15.0  # m an agent may move before the map points kept around it are chosen again
NEARBY_MIN_PAIRS = 20_000  # query x item pairs from which scanning only the nearby items pays off


@dataclass(frozen=True)
class Pictures:
    """Per scene (padded ``[B,N]``): every agent's latest decided state, presence, velocity, moved flag."""

    state: np.ndarray
    present: np.ndarray
    velocity: np.ndarray
    moved: np.ndarray


@dataclass(frozen=True)
class EgoFeatures:
    """Per query: what an observation needs about the observing agent (arrays over the queries)."""

    speed: np.ndarray
    accel: np.ndarray
    yaw_rate: np.ndarray
    route_fraction: np.ndarray
    lateral: np.ndarray
    heading_error: np.ndarray
    route_ahead: np.ndarray  # [Q,R,2] global points of the route ahead


class BatchGeometry:
    """Outcomes (:meth:`outcomes`) and observations (:meth:`observations`) of a list of scene states."""

    def __init__(self) -> None:
        self._size = PaddedRows(1.0)
        self._kind = PaddedRows(0)
        self._edge_columns = PaddedRows(0.0, last=True)
        self._edge_links = PaddedRows(-1, last=True)
        self._paths: tuple[list[object], Paths, np.ndarray] | None = None
        self._near_edges = NearbyItems(EDGE_REACH, EDGE_DRIFT)
        self._near_points: NearbyItems | None = None  # made with the observation radius
        self._map_gathered: tuple[int, np.ndarray, np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ static arrays
    def _edges(self, sims: Sequence[SceneState]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Road-edge columns ``[B,7,S]``, links ``[B,3,S]`` and segment counts ``[B]``."""
        columns = self._edge_columns.sync(sims, lambda s: s.edge_columns)
        links = self._edge_links.sync(sims, lambda s: s.edge_links)
        return columns, links, np.array([s.edge_columns.shape[1] for s in sims])

    def _routes(self, sims: Sequence[SceneState]) -> tuple[Paths, np.ndarray]:
        """Every simulation's routes stacked, and the first route row of each."""
        if (
            self._paths is None
            or len(self._paths[0]) != len(sims)
            or any(a is not b for a, b in zip(self._paths[0], sims, strict=True))
        ):
            paths, first = stack_paths([s.routes for s in sims])
            self._paths = (list(sims), paths, first)
        return self._paths[1], self._paths[2]

    # ------------------------------------------------------------------ outcomes
    def outcomes(
        self, sims: Sequence[SceneState]
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Per simulation, at its current step: its live external agents, whether each collides, is off
        the road, and its new arc length along its route (see ``Simulation.finish_step``)."""
        lives = [s.live_external() for s in sims]
        counts = [len(live) for live in lives]
        scene = np.repeat(np.arange(len(sims)), counts)
        agent = np.concatenate(lives).astype(np.int64)
        if not len(agent):
            empty = np.zeros(0, dtype=bool)
            return [(live, empty, empty, np.zeros(0)) for live in lives]
        xyh = pad_stack([s.row.xyh[:, s.t] for s in sims])
        valid = pad_stack([s.row.valid[:, s.t] for s in sims], False)
        size = self._size.sync(sims, lambda s: s.size)[:, : xyh.shape[1]]
        kind = self._kind.sync(sims, lambda s: s.kind)
        hit = collision_flags(xyh, valid, size, scene, agent)
        cols, links, count = self._edges(sims)
        margin = np.array([s.offroad_margin for s in sims])[scene]
        nearby = None
        if len(scene) * cols.shape[2] >= NEARBY_MIN_PAIRS:  # a few scenes: a full scan is cheaper
            keys = [(sims[b], a) for b, a in zip(scene.tolist(), agent.tolist(), strict=True)]
            candidates = self._near_edges.update(
                keys, xyh[scene, agent, :2], lambda s, p: point_segment_distances(s.edge_columns, p)
            )
            nearby = (candidates, self._near_edges.anchor, self._near_edges.reach)
        off = offroad_flags(
            xyh[scene, agent],
            size[scene, agent],
            kind[scene, agent],
            cols,
            links,
            count,
            scene,
            margin,
            nearby,
        )
        paths, first = self._routes(sims)
        rows = first[scene] + np.concatenate([s.route_row[live] for s, live in zip(sims, lives, strict=True)])
        progress = np.concatenate(
            [s.progress[s.route_row[live]] for s, live in zip(sims, lives, strict=True)]
        )
        s_new, _, _ = paths.project(rows, xyh[scene, agent, :2], progress)
        bounds = np.cumsum([0, *counts])
        return [
            (live, hit[a:b], off[a:b], s_new[a:b])
            for live, a, b in zip(lives, bounds[:-1], bounds[1:], strict=True)
        ]

    # ------------------------------------------------------------------ observations
    def pictures(self, sims: Sequence[SceneState]) -> Pictures:
        """Every scene as it stands now (mid-step: who has moved so far), padded to ``[B,N]``."""
        now, after, before, valid_now, valid_after, valid_before, moved = [], [], [], [], [], [], []
        for s in sims:
            xyh, valid, t, m = s.row.xyh, s.row.valid, s.t, s.row.moved()
            last = valid.shape[1] - 1
            now.append(xyh[:, t])
            after.append(xyh[:, min(t + 1, last)])
            before.append(xyh[:, max(t - 1, 0)])
            valid_now.append(valid[:, t])
            valid_after.append(valid[:, t + 1] if t < last else np.zeros_like(m))
            valid_before.append(valid[:, max(t - 1, 0)] & (t > 0))
            moved.append(m)
        dt = np.array([s.dt for s in sims])[:, None]
        flags = [pad_stack(v, False) for v in (valid_now, valid_after, valid_before, moved)]
        state, present, velocity = latest_states(
            pad_stack(now), pad_stack(after), pad_stack(before), *flags, dt
        )
        return Pictures(state, present, velocity, flags[3])

    def ego_features(
        self, sims: Sequence[SceneState], scene: np.ndarray, agent: np.ndarray, pictures: Pictures
    ) -> EgoFeatures:
        """The observing agents' own features: kinematics, and their place on their routes."""
        obs = sims[0].obs
        paths, first = self._routes(sims)
        rows = first[scene] + np.array([sims[b].route_row[a] for b, a in zip(scene, agent, strict=True)])
        own = pictures.state[scene, agent]
        s_prev = np.array([sims[b].progress[sims[b].route_row[a]] for b, a in zip(scene, agent, strict=True)])
        s_now, lateral, route_heading = paths.project(rows, own[:, :2], s_prev)
        ahead = s_now[:, None] + obs.route_spacing * np.arange(1, obs.route_points + 1)
        points, _ = paths.at(np.broadcast_to(rows[:, None], ahead.shape), ahead)
        length = np.maximum(paths.length[rows], 1e-6)
        goal = np.array([sims[b].has_goal[sims[b].route_row[a]] for b, a in zip(scene, agent, strict=True)])
        kin = [(sims[b].kin, a) for b, a in zip(scene, agent, strict=True)]
        return EgoFeatures(
            speed=np.array([k.speed[a] for k, a in kin]),
            accel=np.array([k.accel[a] for k, a in kin]),
            yaw_rate=np.array([k.yaw_rate[a] for k, a in kin]),
            route_fraction=np.where(goal, np.minimum(s_now / length, 1.0), 1.0),
            lateral=lateral,
            heading_error=wrap_angle(own[:, 2] - route_heading),
            route_ahead=points,
        )

    def _nearby_map(
        self,
        sims: Sequence[SceneState],
        scene: np.ndarray,
        agent: np.ndarray,
        centres: np.ndarray,
        radius: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per query, its scene's observation map points near it ``[Q,K,2]`` (ascending), their categories
        and which are real: every point within ``radius`` of the agent is among them, since the agent is
        within the drift of the anchor they were chosen around (1 m spare for rounding); for a few queries,
        simply all of them."""
        if len(scene) * max(len(s.map_points) for s in sims) < NEARBY_MIN_PAIRS:  # scan them all
            points = pad_stack([sims[b].map_points for b in scene])
            category = pad_stack([sims[b].map_category for b in scene], OTHER)
            real = (
                np.arange(points.shape[1])[None] < np.array([len(sims[b].map_points) for b in scene])[:, None]
            )
            return points, category, real
        near = self._near_points
        if near is None or near.reach != radius + MAP_DRIFT + 1.0:
            near = self._near_points = NearbyItems(radius + MAP_DRIFT + 1.0, MAP_DRIFT)
            self._map_gathered = None
        keys = [(sims[b], a) for b, a in zip(scene.tolist(), agent.tolist(), strict=True)]
        index = near.update(
            keys,
            centres,
            lambda s, p: np.hypot(s.map_points[:, 0] - p[0], s.map_points[:, 1] - p[1]),
        )
        if self._map_gathered is None or self._map_gathered[0] != near.version:
            safe = np.maximum(index, 0)
            points = np.zeros((*index.shape, 2))
            category = np.full(index.shape, OTHER, dtype=np.int8)
            for q, (sim, _) in enumerate(near.keys):
                points[q] = sim.map_points[safe[q]] if len(sim.map_points) else 0.0
                category[q] = sim.map_category[safe[q]] if len(sim.map_points) else OTHER
            self._map_gathered = (near.version, points, category, index >= 0)
        return self._map_gathered[1:]

    def observations(self, sims: Sequence[SceneState], agents: Sequence[int]) -> np.ndarray:
        """``vector`` observations ``[Q, F]`` of external agent ``agents[i]`` of ``sims[i]`` (a simulation
        may appear several times), as they stand now."""
        unique: list[SceneState] = []
        position: dict[int, int] = {}
        for s in sims:
            if id(s) not in position:
                position[id(s)] = len(unique)
                unique.append(s)
        configs = {s.obs for s in unique}
        if len(configs) != 1:
            raise ValueError(
                f"observations: the scenes of one call must share the observation settings, got {configs}"
            )
        obs = next(iter(configs))
        scene = np.array([position[id(s)] for s in sims], dtype=np.int64)
        agent = np.asarray(agents, dtype=np.int64)
        pictures = self.pictures(unique)
        ego = self.ego_features(unique, scene, agent, pictures)
        size = self._size.sync(unique, lambda s: s.size)
        points, category, real = self._nearby_map(
            unique, scene, agent, pictures.state[scene, agent, :2], obs.radius
        )
        own_size = size[scene, agent]
        head = np.stack(
            [
                ego.speed / 30.0,
                ego.accel / 10.0,
                ego.yaw_rate,
                own_size[:, 0] / 10.0,
                own_size[:, 1] / 5.0,
                ego.route_fraction,
                ego.lateral / 5.0,
                ego.heading_error / np.pi,
            ],
            axis=-1,
        )
        size_n = size[:, : pictures.state.shape[1]]
        vector = vector_observations(
            head,
            pictures.state[scene, agent],
            pictures.state[scene],
            pictures.present[scene],
            pictures.velocity[scene],
            pictures.moved[scene],
            size_n[scene],
            agent,
            points,
            category,
            real,
            ego.route_ahead,
            obs.neighbours,
            obs.map_points,
            obs.radius,
        )
        if not obs.signals:
            return vector
        signals = signal_features(
            [s.signal_xy for s in unique],
            [s.signal_state for s in unique],
            [s.t for s in unique],
            scene,
            pictures.state[scene, agent],
            obs.signals,
            obs.radius,
        )
        return np.concatenate([vector, signals], axis=1)
