"""Red lights under guarded sampling: the candidates masked are exactly the WOSAC violations (metric code
on every candidate), and guarded rollouts of a signalized SUMO grid run no red light but where the guard
had to drop its map rules."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import tiny

from trajeglish_env.metrics.features import prepare_scene
from trajeglish_env.metrics.traffic_lights import red_light_violations
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.sampler.guard_signals import SceneSignals
from trajeglish_env.scenario import AgentKind, Scenario

sumo = pytest.importorskip("trajeglish_env.sources.sumo")


@pytest.fixture(scope="module")
def grid_scenes() -> list[Scenario]:
    try:
        run = sumo.simulate_shard(("grid",), 3, 0, 4)
    except sumo.SumoNotAvailableError as error:
        pytest.skip(str(error))
    return sumo.cut_scenes(run, 3, 0, 4)


def test_scenes_without_signals_have_no_red_lights() -> None:
    from helpers import bundle_scene

    assert SceneSignals.of(bundle_scene("highway-intersection-999000")) is None
    assert SceneSignals.of(bundle_scene("sumo-random-999000-0-0")) is None  # a state table, no signal


def test_masked_candidates_are_the_metrics_violations(grid_scenes: list[Scenario]) -> None:
    sc = grid_scenes[0]
    ss = SceneSignals.of(sc)
    assert ss is not None
    metric = prepare_scene(sc).signals
    rng = np.random.default_rng(0)
    # every logged vehicle state at every step, moved by 64 random displacements of up to 6 m
    agents, steps = np.nonzero(sc.valid[:, :-1] & (sc.kind == AgentKind.VEHICLE)[:, None])
    origin = sc.xyh[agents, steps, :2]
    cand = origin[:, None] + rng.uniform(-6, 6, (len(agents), 64, 2))
    near = ss.near_red(origin, steps, np.full(len(agents), np.inf))
    got = ss.violations(origin, cand, steps, near)
    want = np.zeros_like(got)
    for t in np.unique(steps):  # the metric on each two-step trajectory (origin -> candidate)
        q = np.flatnonzero(steps == t)
        xy = np.stack([np.broadcast_to(origin[q, None], cand[q].shape), cand[q]], axis=2)  # [m, c, 2, 2]
        want[q] = red_light_violations(metric, xy, np.ones(xy.shape[:3], bool), int(t))[..., 0]
    assert np.array_equal(got, want)
    assert want.sum() > 100  # the scene really has red lights to run


def test_guarded_vehicles_and_cyclists_stop_at_red(grid_scenes: list[Scenario]) -> None:
    runs, fallbacks = {False: 0, True: 0}, 0
    for sc in grid_scenes:
        metric = prepare_scene(sc).signals
        active = sc.valid[:, sc.current_index].copy()
        riders = sc.kind != AgentKind.PEDESTRIAN
        cur = sc.current_index
        for guard in (False, True):
            config = SamplingConfig(temperature=1.0, guard=guard, seed=1)
            engine = RolloutEngine(tiny(), sc, 2, 30, active, config=config)
            engine.run()
            xy, valid = engine.xyh[:, :, cur : cur + 31, :2], engine.valid[:, :, cur : cur + 31]
            runs[guard] += int(red_light_violations(metric, xy, valid, cur)[:, riders].sum())
            if guard:
                fallbacks += engine.guard.stats.edge_fallback + engine.guard.stats.plain_fallback
    assert runs[False] >= 40  # the untrained model runs red lights
    assert runs[True] <= fallbacks < 10  # only where every candidate broke a rule
