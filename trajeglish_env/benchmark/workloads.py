"""Workloads of the benchmarks: scenes and model inputs built deterministically (no data files needed)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from trajeglish_env.env.scenes import load_bundle
from trajeglish_env.geometry import wrap_angle
from trajeglish_env.model import ModelConfig, SceneInputs
from trajeglish_env.scenario import AgentKind, MapKind, Scenario, SignalState

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


def random_inputs(cfg: ModelConfig, batch: int, seed: int = 0) -> tuple[SceneInputs, torch.Tensor]:
    """Random encoder inputs and tokens of ``batch`` full windows (for model speed measurements)."""
    g = torch.Generator().manual_seed(seed)
    a, m, p = cfg.max_agents, cfg.max_polylines, cfg.points_per_polyline
    scene = SceneInputs(
        agent_xyh=torch.randn(batch, a, 3, generator=g) * 20,
        agent_size=torch.rand(batch, a, 2, generator=g) * 3 + 1,
        agent_kind=torch.randint(0, 3, (batch, a), generator=g),
        agent_mask=torch.ones(batch, a, dtype=torch.bool),
        map_points=torch.randn(batch, m, p, 2, generator=g) * 40,
        map_point_mask=torch.ones(batch, m, p, dtype=torch.bool),
        map_kind=torch.randint(0, 20, (batch, m), generator=g),
        map_mask=torch.ones(batch, m, dtype=torch.bool),
        map_signal=torch.randint(0, 4, (batch, m), generator=g),
    )
    return scene, torch.randint(0, cfg.vocab_size, (batch, a, cfg.steps), generator=g)


def nearest_agents(sc: Scenario, agents: int) -> Scenario:
    """The scene cut to its sdc and the ``agents - 1`` agents nearest to it at the current step."""
    cur = sc.current_index
    present = np.flatnonzero(sc.valid[:, cur])
    dist = np.linalg.norm(sc.xyh[present, cur, :2] - sc.xyh[sc.sdc, cur, :2], axis=-1)
    keep = np.sort(present[np.argsort(dist, kind="stable")[:agents]])
    return sc.with_agents(keep)


def benchmark_scenes(agents: int = 24) -> list[Scenario]:
    """Every bundled scene with at least ``agents`` agents present, cut to exactly ``agents`` (the sdc
    and its nearest neighbours): the four SUMO urban scenes for 24 agents."""
    bundle = load_bundle()
    scenes = [bundle.get(i) for i in range(len(bundle))]
    big = [s for s in scenes if int(s.valid[:, s.current_index].sum()) >= agents]
    if not big:
        raise ValueError(f"no bundled scene has {agents} agents present at its current step")
    return [nearest_agents(s, agents) for s in big]


def model_checkpoint() -> tuple[Any, str]:
    """The shipped model, or the ``small`` preset with random weights when it is not installed."""
    import torch

    from trajeglish_env.checkpoint import Checkpoint, CheckpointError, load_pretrained
    from trajeglish_env.model import TrajeglishModel, preset
    from trajeglish_env.tokenizer import load_default_tokenizer

    try:
        return load_pretrained(), "shipped"
    except CheckpointError:
        vocab = load_default_tokenizer()
        torch.manual_seed(0)
        model = TrajeglishModel(preset("small", vocab_size=vocab.size)).eval()
        return Checkpoint(model=model, vocabulary=vocab, training={}), "small preset, random weights"


def grid_scene(n: int = 200, steps: int = 91) -> Scenario:
    """``n`` vehicles on parallel lanes 8 m apart, driving +x at 5-10 m/s."""
    rng = np.random.default_rng(0)
    cols = 20
    start = np.stack([np.arange(n) % cols * 12.0, np.arange(n) // cols * 4.0], -1)
    speed = rng.uniform(5, 10, n)
    xyh = np.zeros((n, steps, 3))
    xyh[..., 0] = start[:, :1] + speed[:, None] * np.arange(steps) * 0.1
    xyh[..., 1] = start[:, 1:]
    lanes = [np.stack([np.arange(-50, 400.0), np.full(450, y)], -1) for y in np.unique(start[:, 1])]
    return Scenario.from_arrays(
        xyh,
        np.ones((n, steps), bool),
        np.tile([4.5, 1.9], (n, 1)),
        np.full(n, AgentKind.VEHICLE),
        sdc=0,
        polylines=lanes,
        polyline_kinds=[2] * len(lanes),
        scenario_id=f"grid-{n}",
        source="bench",
    )
