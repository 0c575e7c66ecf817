"""Urban scenes (vehicles, cyclists, pedestrians, signalized intersections) generated with Eclipse SUMO.

A scene source for :mod:`trajeglish_env.sources.generation`: shard ``i`` is one SUMO simulation of a
random grid, spider or random network (network and demand drawn from ``scene_seed(seed, i, 0)``),
warmed up and then cut into ``count`` WOMD-like scenes of 91 steps at 10 Hz (``current_index`` 10),
up to ``scenes_per_window`` per window. Each scene is centred on its self-driving car, a vehicle valid
over the whole window chosen near the centre of activity; like WOMD's perception, an agent is valid
while it exists within ``agent_radius_m`` of the sdc, and the map keeps the polylines within
``map_radius_m`` of the sdc's path (so it covers every valid agent, like a WOMD map). The
traffic-light state of every signalized movement is kept at every step.
SUMO itself is required: ``pip install 'trajeglish_env[sumo]'`` (binaries ship in the eclipse-sumo
wheel; nothing is downloaded).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.sources.generation import scene_seed
from trajeglish_env.sources.sumo_map import NetworkMap, signal_states
from trajeglish_env.sources.sumo_net import NETWORK_KINDS
from trajeglish_env.sources.sumo_sim import DT, SimulationConfig, SumoRun, simulate
from trajeglish_env.sources.sumo_tools import SumoNotAvailableError, SumoToolError, check_available

__all__ = [
    "KINDS",
    "SumoNotAvailableError",
    "check_available",
    "SumoSceneConfig",
    "SumoToolError",
    "cut_scenes",
    "generate_shard",
    "simulate_shard",
]

KINDS: tuple[str, ...] = NETWORK_KINDS
NUM_STEPS = 91
CURRENT_INDEX = 10
# 2: curbs that meet end to start are one polyline and curb stubs are left out (sumo_map.chain_road_edges):
# no wedge of a junction is signed off the road; scenes of version 1 are not resumed into
# 3: curbs within 0.25 m chained and their hooks dropped (sumo_map.despike: a spider network's acute block
# corners put logged vehicles 15 m "off the road"); a partial last shard simulates the full shard's time
GENERATOR_VERSION = 3


@dataclass(frozen=True)
class SumoSceneConfig:
    """How one shard's simulation is run and cut into scenes."""

    warmup_s: float = 20.0  # simulated before the first scene starts (the network starts populated)
    window_stride_s: float = 4.0  # start-time spacing of consecutive windows (each is 9.1 s long)
    scenes_per_window: int = 2  # scenes cut from one window, around different self-driving cars
    sdc_separation_m: float = 100.0  # preferred distance between the sdcs of one window
    spare_windows: int = 2  # extra windows simulated in case some have too few suitable sdcs
    agent_radius_m: float = 80.0  # agents are valid (perceived) while this close to the sdc
    map_radius_m: float = 100.0  # keep polylines with a point this close to the sdc's path in the window
    max_agents: int = 128  # WOMD's scenes hold up to ~128 agents: keep the nearest
    max_tracks_to_predict: int = 8
    sdc_min_travel_m: float = 10.0  # prefer an sdc that drives at least this far during the scene
    simulation: SimulationConfig = field(default_factory=SimulationConfig)

    def duration_s(self, count: int) -> float:
        """Simulated seconds needed for ``count`` scenes (plus spares)."""
        windows = -(-count // self.scenes_per_window) + self.spare_windows
        return self.warmup_s + (windows - 1) * self.window_stride_s + (NUM_STEPS - 1) * DT


DEFAULT_CONFIG = SumoSceneConfig()


def shard_network_kind(kinds: tuple[str, ...], seed: int, shard_index: int) -> tuple[str, int]:
    """The network kind of a shard and the seed of its simulation (both from ``scene_seed(seed, i, 0)``)."""
    unknown = sorted(set(kinds) - set(KINDS))
    if not kinds or unknown:
        raise ValueError(f"SUMO scene kinds: expected a non-empty subset of {KINDS}, got {list(kinds)}")
    sim_seed = scene_seed(seed, shard_index, 0)
    kind = kinds[np.random.default_rng(sim_seed).integers(len(kinds))]
    return kind, sim_seed


def shard_kind(kinds: tuple[str, ...], seed: int, shard_index: int) -> str:
    """The network kind of shard ``shard_index`` (one simulation, one kind: ``generate`` reports them)."""
    return shard_network_kind(tuple(kinds), seed, shard_index)[0]


def simulate_shard(
    kinds: tuple[str, ...], seed: int, shard_index: int, count: int, config: SumoSceneConfig = DEFAULT_CONFIG
) -> SumoRun:
    """Run the one SUMO simulation behind shard ``shard_index`` (long enough for ``count`` scenes)."""
    kind, sim_seed = shard_network_kind(tuple(kinds), seed, shard_index)
    return simulate(kind, sim_seed, config.warmup_s, config.duration_s(count), config.simulation)


# ---------------------------------------------------------------------------------------------- scene cutting
def _choose_sdc(
    run: SumoRun, window: slice, rng: np.random.Generator, config: SumoSceneConfig, taken: list[int]
) -> int | None:
    """A vehicle valid over the whole window near the centre of activity (None if there is none).

    Vehicles in ``taken`` (the sdcs of earlier scenes of this window) are excluded, and candidates at
    least ``sdc_separation_m`` away from them are preferred, so one window yields scenes in different places.
    """
    valid = run.valid[:, window]
    full = (run.kind == AgentKind.VEHICLE) & valid.all(axis=1)
    full[taken] = False
    if not full.any():
        return None
    xy = run.xyh[:, window, :2]
    travel = np.linalg.norm(np.diff(xy, axis=1), axis=-1).sum(axis=1)
    candidates = np.flatnonzero(full & (travel >= config.sdc_min_travel_m))
    if len(candidates) == 0:
        candidates = np.flatnonzero(full)
    if taken:
        gap = np.linalg.norm(xy[candidates, None, CURRENT_INDEX] - xy[None, taken, CURRENT_INDEX], axis=-1)
        far = candidates[gap.min(axis=1) >= config.sdc_separation_m]
        candidates = far if len(far) else candidates
    centre = np.median(xy[valid[:, CURRENT_INDEX], CURRENT_INDEX], axis=0)
    distance = np.linalg.norm(xy[candidates, CURRENT_INDEX] - centre, axis=1)
    nearest = candidates[np.argsort(distance, kind="stable")[: max(1, (len(candidates) + 1) // 2)]]
    return int(rng.choice(nearest))


def _crop_map(net_map: NetworkMap, centres: np.ndarray, radius: float) -> dict[str, np.ndarray]:
    """Scenario map fields for the polylines with a point within ``radius`` of any of ``centres [k,2]``."""
    nearest = np.min([net_map.polyline_min_distance(c) for c in centres], axis=0)
    keep = np.flatnonzero(nearest <= radius)
    lengths = np.diff(net_map.offsets)[keep]
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    point_index = np.repeat(net_map.offsets[keep] - offsets[:-1], lengths) + np.arange(offsets[-1])
    return {
        "map_points": net_map.points[point_index],
        "map_offsets": offsets,
        "map_kind": net_map.kind[keep],
        "map_id": net_map.map_id[keep],
    }


def _signals(run: SumoRun, window: slice, kept_ids: np.ndarray) -> dict[str, np.ndarray]:
    """Signal lanes, stop points and states over the window for the signalized movements in the map."""
    net_map = run.net_map
    keep = np.flatnonzero(np.isin(net_map.signal_lane_id, kept_ids))
    tls = np.asarray(net_map.signal_tls, dtype=object)[keep]
    states = np.zeros((NUM_STEPS, len(keep)), dtype=np.int8)
    for tls_id in np.unique(tls) if len(tls) else []:
        if tls_id not in run.tls_states:
            raise ValueError(f"SUMO traffic light {tls_id!r} controls mapped lanes but reported no states")
        columns = np.flatnonzero(tls == tls_id)
        states[:, columns] = signal_states(run.tls_states[tls_id][window], net_map.signal_link[keep][columns])
    return {
        "signal_lane_id": net_map.signal_lane_id[keep],
        "signal_xy": net_map.signal_xy[keep],
        "signal_state": states,
    }


def _scene(run: SumoRun, start: int, sdc: int, scenario_id: str, config: SumoSceneConfig) -> Scenario:
    """Crop one window of ``run`` around agent ``sdc`` into a Scenario."""
    window = slice(start, start + NUM_STEPS)
    gap = np.linalg.norm(run.xyh[:, window, :2] - run.xyh[sdc, None, window, :2], axis=-1)
    # Like WOMD's perception: an agent is valid while it exists within ``agent_radius_m`` of the sdc.
    valid = run.valid[:, window] & (gap <= config.agent_radius_m)
    xyh = np.where(valid[..., None], run.xyh[:, window], 0.0)
    closest = np.where(valid, gap, np.inf).min(axis=1)
    near = np.flatnonzero(closest <= config.agent_radius_m)
    agents = np.sort(near[np.argsort(closest[near], kind="stable")[: config.max_agents]])
    sdc_index = int(np.flatnonzero(agents == sdc)[0])
    full = np.flatnonzero(valid[agents].all(axis=1) & (agents != sdc))
    by_gap = full[np.argsort(gap[agents[full], CURRENT_INDEX], kind="stable")][: config.max_tracks_to_predict]
    # Agents are valid within agent_radius_m of the sdc at each step, so a map around the sdc's path (every
    # 10th step; a car moves at most ~25 m in between) covers all of them, not just the first seconds.
    path = xyh[sdc, np.r_[CURRENT_INDEX, 0:NUM_STEPS:10, NUM_STEPS - 1], :2]
    map_fields = _crop_map(run.net_map, path, config.map_radius_m)
    scene = Scenario(
        xyh=xyh[agents],
        valid=valid[agents],
        size=run.size[agents],
        kind=run.kind[agents].astype(np.int8),
        track_id=agents.astype(np.int64),
        sdc=sdc_index,
        scenario_id=scenario_id,
        source="sumo",
        dt=DT,
        current_index=CURRENT_INDEX,
        tracks_to_predict=np.sort(by_gap).astype(np.int64),
        **map_fields,
        **_signals(run, window, map_fields["map_id"]),
    )
    return scene.validate()


def cut_scenes(
    run: SumoRun, seed: int, shard_index: int, count: int, config: SumoSceneConfig = DEFAULT_CONFIG
) -> list[Scenario]:
    """Cut ``count`` scenes from consecutive windows of ``run``, up to ``scenes_per_window`` per window."""
    stride = int(round(config.window_stride_s / DT))
    scenes: list[Scenario] = []
    for start in range(0, run.num_steps - NUM_STEPS + 1, stride):
        taken: list[int] = []
        while len(scenes) < count and len(taken) < config.scenes_per_window:
            slot = len(scenes)
            rng = np.random.default_rng(scene_seed(seed, shard_index, slot + 1))
            sdc = _choose_sdc(run, slice(start, start + NUM_STEPS), rng, config, taken)
            if sdc is None:
                break
            taken.append(sdc)
            scenes.append(
                _scene(run, start, sdc, f"sumo-{run.network_kind}-{seed}-{shard_index}-{slot}", config)
            )
    if len(scenes) < count:
        raise RuntimeError(
            f"SUMO shard {shard_index} (seed {seed}, {run.network_kind} network): only {len(scenes)} of "
            f"{count} scenes found a vehicle present for all {NUM_STEPS} steps; the traffic is too sparse"
        )
    return scenes


def generate_shard(
    kinds: tuple[str, ...],
    seed: int,
    shard_index: int,
    count: int,
    config: SumoSceneConfig = DEFAULT_CONFIG,
    capacity: int | None = None,
) -> list[Scenario]:
    """``count`` scenes of shard ``shard_index``: one SUMO simulation cut into windows (deterministic).
    ``capacity``: the scenes a full shard holds; the simulation is the full shard's, so a run's last,
    partial shard holds the first scenes of the full one (the same id, the same scene)."""
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    run = simulate_shard(kinds, seed, shard_index, max(count, capacity or count), config)
    return cut_scenes(run, seed, shard_index, count, config)
