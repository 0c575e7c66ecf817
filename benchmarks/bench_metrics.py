"""Time of scoring rollouts with the realism metrics (WOSAC 2025 config) on a synthetic scene.

Usage: python benchmarks/bench_metrics.py [--agents 128] [--rollouts 32] [--evaluated 8 0] [--repeats 3]
       [--json]

The scene is built with NumPy: a 4-lane ring road (radius 250 m, surface-street lanes, road edges and
lane centres sampled every 0.5 m like the generated highway maps, about 6,400 road-edge segments), a
signal-controlled lane with a red light, and ``--agents`` vehicles driving 91 steps at 10 Hz, all of
them simulated. ``--evaluated`` lists the numbers of scored agents to time: 8 is the WOSAC / WOMD
setting (the sdc and the agents to predict; our generated scenes name up to 8 too), 0 means every
agent (a scene that names no agents of interest). The rollouts are the logged future plus random-walk
noise (so some leave the road and some collide). The best wall time of ``--repeats`` runs is reported
with its CPU time; the machine may be shared.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import report  # noqa: E402

from trajeglish_env.geometry import wrap_angle  # noqa: E402
from trajeglish_env.metrics import score_rollouts  # noqa: E402
from trajeglish_env.scenario import AgentKind, MapKind, Scenario, SignalState  # noqa: E402

RADIUS = 250.0
LANE_WIDTH = 3.5
LANES = 4
SPACING = 0.5


def _circle(radius: float, clockwise: bool = False) -> np.ndarray:
    """Closed circle polyline sampled every ``SPACING`` metres (counter-clockwise unless ``clockwise``)."""
    n = int(np.ceil(2 * np.pi * radius / SPACING))
    angle = np.linspace(0.0, 2 * np.pi, n + 1)
    if clockwise:
        angle = angle[::-1]
    return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=-1)


def ring_scene(num_agents: int, seed: int = 0, steps: int = 91) -> Scenario:
    """A ring road with ``num_agents`` vehicles driving counter-clockwise in 4 lanes."""
    rng = np.random.default_rng(seed)
    lane = np.arange(num_agents) % LANES
    radius = RADIUS + (lane + 0.5) * LANE_WIDTH
    per_lane = -(-num_agents // LANES)
    start = (np.arange(num_agents) // LANES) * 2 * np.pi / per_lane + rng.uniform(0, 0.02, num_agents)
    speed = rng.uniform(8.0, 16.0, num_agents)
    t = np.arange(steps) * 0.1
    angle = start[:, None] + speed[:, None] * t[None] / radius[:, None]
    xyh = np.stack(
        [radius[:, None] * np.cos(angle), radius[:, None] * np.sin(angle), wrap_angle(angle + np.pi / 2)],
        axis=-1,
    )
    edges = [_circle(RADIUS + LANES * LANE_WIDTH), _circle(RADIUS, clockwise=True)]  # road on the left
    centres = [_circle(RADIUS + (k + 0.5) * LANE_WIDTH) for k in range(LANES)]
    state = np.full((steps, 1), SignalState.STOP, dtype=np.int8)  # lane 0 is red throughout
    return Scenario.from_arrays(
        xyh,
        np.ones((num_agents, steps), dtype=bool),
        np.tile([4.8, 2.0], (num_agents, 1)),
        np.full(num_agents, AgentKind.VEHICLE),
        track_id=np.arange(num_agents) + 1000,
        polylines=edges + centres,
        polyline_kinds=[MapKind.ROAD_EDGE_BOUNDARY] * 2 + [MapKind.LANE_SURFACE_STREET] * LANES,
        polyline_ids=np.arange(len(edges) + LANES),
        scenario_id=f"ring-{num_agents}",
        source="benchmark",
        signal_lane_id=np.array([2]),
        signal_xy=np.array([[RADIUS + 0.5 * LANE_WIDTH, 5.0]]),
        signal_state=state,
    )


def noisy_rollouts(scenario: Scenario, rollouts: int, seed: int = 1) -> np.ndarray:
    """``[R, N, T_f, 3]`` rollouts: the logged future plus a random walk in position and heading."""
    rng = np.random.default_rng(seed)
    future = scenario.xyh[:, scenario.current_index + 1 :]
    walk = np.cumsum(rng.normal(0.0, [0.08, 0.08, 0.01], (rollouts, *future.shape)), axis=2)
    return future[None] + walk


def _time(scenario: Scenario, rollouts: np.ndarray, config: str, repeats: int) -> dict:
    """Best-of-``repeats`` wall and CPU time of one :func:`score_rollouts` call, with a few scores."""
    walls, cpus = [], []
    for _ in range(repeats):
        wall0, cpu0 = time.perf_counter(), time.process_time()
        scores = score_rollouts(scenario, rollouts, scenario.track_id, config)
        walls.append(time.perf_counter() - wall0)
        cpus.append(time.process_time() - cpu0)
    best = int(np.argmin(walls))
    return {
        "evaluated_agents": scores.num_evaluated,
        "seconds": round(walls[best], 3),
        "cpu_seconds": round(cpus[best], 3),
        "all_seconds": [round(w, 3) for w in walls],
        "metametric": round(scores.metametric, 6),
        "collision_rate": round(scores.collision_rate, 4),
        "offroad_rate": round(scores.offroad_rate, 4),
        "traffic_light_violation_rate": round(scores.traffic_light_violation_rate, 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=128)
    parser.add_argument("--rollouts", type=int, default=32)
    parser.add_argument("--evaluated", type=int, nargs="+", default=[8, 0], help="scored agents (0: all)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--config", default="2025")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    scenario = ring_scene(args.agents)
    rollouts = noisy_rollouts(scenario, args.rollouts)
    result: dict = {
        "agents": args.agents,
        "rollouts": args.rollouts,
        "future_steps": int(rollouts.shape[2]),
        "road_edge_segments": int(
            sum(len(p) - 1 for p in scenario.polylines(frozenset({MapKind.ROAD_EDGE_BOUNDARY})))
        ),
        "config": args.config,
        "cpu_count": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "runs": {},
    }
    for evaluated in args.evaluated:
        # The sdc (agent 0) plus agents 1 .. evaluated - 1 of interest; none named means all are scored.
        chosen = replace(scenario, tracks_to_predict=np.arange(1, evaluated, dtype=np.int64))
        label = f"{evaluated}_evaluated" if evaluated else "all_evaluated"
        result["runs"][label] = _time(chosen, rollouts, args.config, args.repeats)
    report(result, args.json)


if __name__ == "__main__":
    main()
