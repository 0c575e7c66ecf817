"""The guard's stall rule: a vehicle that drove, then stood for ``guard_stall_steps`` steps with the way
clear must set off at pace; parked cars, short stops and riders with a box ahead are left alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.guard_signals import DEPART_GAIN, DEPART_PACE, DEPART_STEP
from trajeglish_env.sampler.guard_stall import RELEASE_STEPS, stalled


def _history(steps: list[float], start: float = 0.0) -> np.ndarray:
    """Model states ``[1, T, 3]`` of an agent driving east with forward ``steps`` (m) a step."""
    x = start + np.concatenate([[0.0], np.cumsum(steps)])
    return np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=-1)[None]


def _stalled(steps: list[float], min_steps: int = 20, t: int | None = None) -> bool:
    xyh = _history(steps)
    valid = np.ones(xyh.shape[:2], bool)
    return bool(stalled(xyh, valid, np.array([xyh.shape[1] - 1 if t is None else t]), min_steps)[0])


def test_a_car_that_drove_and_stood_long_enough_is_stalled() -> None:
    drove = [0.8] * 30
    assert _stalled(drove + [0.0] * 20)  # 2 s standing after driving
    assert not _stalled(drove + [0.0] * 19)  # a short stop (a stop sign, a gap to wait for) stays the model's
    assert not _stalled([0.0] * 60)  # a parked car never drove: never pushed
    assert not _stalled([0.03] * 10 + [0.0] * 40)  # nor one that only crept (under 0.5 m/s)
    # the departure phase: still under the rule while it speeds up, for RELEASE_STEPS steps at most
    assert _stalled(drove + [0.0] * 25 + [0.02 + 0.01 * k for k in range(RELEASE_STEPS)])
    assert not _stalled(drove + [0.0] * 25 + [0.1] * (RELEASE_STEPS + 1))
    # steps after ``t`` (not decided yet) are not read; a gap in the history breaks the run
    assert not _stalled(drove + [0.0] * 25, t=40)
    xyh = _history(drove + [0.0] * 25)
    valid = np.ones(xyh.shape[:2], bool)
    valid[0, 45] = False
    assert not stalled(xyh, valid, np.array([55]), 20)[0]


def test_stall_steps_is_validated() -> None:
    assert SamplingConfig().guard_stall_steps == 10
    for bad in (-1, 2.0, True, "20"):
        with pytest.raises(ValueError, match="guard_stall_steps must be an int >= 0"):
            SamplingConfig(guard_stall_steps=bad)  # type: ignore[arg-type]


def test_the_stall_mask_is_the_green_rules_and_widens_first() -> None:
    """A stalled rider's candidates slower than the departure pace are masked as the speed-change rule's
    (the fallback widens them first), its faster ones are left to the other rules; a box right ahead ends
    the rule."""
    from helpers import bundle_scene, tiny

    from trajeglish_env.sampler.engine import RolloutEngine
    from trajeglish_env.scenario import AgentKind

    sc = bundle_scene("highway-intersection-999000")
    t = sc.current_index
    riders = np.flatnonzero(sc.valid[:, t] & (sc.kind != AgentKind.PEDESTRIAN))
    engine = RolloutEngine(tiny(), sc, 1, 5, sc.valid[:, t].copy(), config=SamplingConfig())
    geometry, v = engine.guard.geometry, engine.vocab.size
    rows, steps = np.zeros(len(riders), np.int64), np.full(len(riders), engine.t)
    pairs = geometry.pairs(engine, rows, riders, steps)
    assert not pairs.stall.any()  # the log's vehicles drive at the current step
    sel = np.arange(len(riders))
    every = np.broadcast_to(np.arange(v), (len(riders), v))
    for creep in (0.0, 0.05):
        forced = dataclasses.replace(
            pairs, stall=np.ones(len(riders), bool), pace=np.full(len(riders), creep)
        )
        collide, _, off, jump = geometry.blocked_parts(forced, sel, every)
        step = geometry.templates[forced.kind[:, None], every, 0]
        need = min(max(creep + DEPART_GAIN, DEPART_STEP), DEPART_PACE)
        assert (jump | (step >= need - 1e-12)).all()  # every slower candidate is masked
        assert (~jump & (step >= need)).any(axis=1).all()
        assert forced.guarded.all()
    # the engine's own state: the first rider stood 25 steps after driving, the way clear
    agent = riders[0]
    x, y, h = engine.mxyh[0, agent, t]
    back = np.arange(t + 1)[::-1][:, None] * 0.8 * np.array([np.cos(h), np.sin(h)])
    engine.mxyh[0, agent, : t + 1, :2] = np.array([x, y]) - back
    engine.mxyh[0, agent, t - 2 : t + 1, :2] = engine.mxyh[0, agent, t - 2, :2]
    engine.valid[0, agent, : t + 1] = True
    one = (np.zeros(1, np.int64), np.array([agent]), np.array([t]))
    assert not geometry.pairs(engine, *one).stall[0]  # 2 steps standing: under guard_stall_steps
    geometry.stall_steps = 2
    assert geometry.pairs(engine, *one).stall[0]
    other = next(j for j in np.flatnonzero(engine.valid[0, :, t]) if j != agent)
    ahead = (sc.size[agent, 0] + sc.size[other, 0]) / 2 + 1.0  # a box 1 m in front: not pushed
    x, y, h = engine.mxyh[0, agent, t]
    engine.xyh[0, other, t] = (x + ahead * np.cos(h), y + ahead * np.sin(h), h)
    assert not geometry.pairs(engine, *one).stall[0]


def _demo_speeds(stall_steps: int) -> tuple[np.ndarray, float]:
    """Speeds ``[N, 80]`` (m/s) of every agent in ``make demo``'s episode (the shipped model, the IDM ego)
    under ``guard_stall_steps``, and the NPCs' collision rate."""
    from trajeglish_env.env import RewardConfig, raw_env
    from trajeglish_env.env.config import TrajeglishNPC
    from trajeglish_env.env.controllers import RuleBasedController
    from trajeglish_env.env.demo import npc_outcomes

    never_end = RewardConfig(
        terminate_on_collision=False, terminate_on_offroad=False, terminate_on_goal=False
    )
    npc = TrajeglishNPC(None, SamplingConfig(guard_stall_steps=stall_steps))
    env = raw_env(npc=npc, order="first", reward=never_end)
    env.reset(seed=0, options={"scene": "highway-intersection-999000"})
    controller = RuleBasedController("idm")
    for name in env.agent_iter():
        _, _, terminated, truncated, _ = env.last()
        env.step(None if terminated or truncated else controller.action(env, name))
    cur = env.scenario.current_index
    xy = env.sim.state.row.xyh[:, cur : cur + 81, :2]
    return np.linalg.norm(np.diff(xy, axis=1), axis=-1) / env.scenario.dt, npc_outcomes(env)[
        "npc_collision_rate"
    ]


def test_the_demo_npc_that_stood_at_the_crossing_sets_off() -> None:
    """In ``make demo``'s episode an NPC slowed for a crossing car stood at the intersection from 3.5 s to
    the end with the crossing empty (the model's mass on moving tokens 0.000): with the rule it sets off 1 s
    after stopping, and no NPC collides either way."""
    stuck, collided = _demo_speeds(0)
    pushed, collided_pushed = _demo_speeds(SamplingConfig().guard_stall_steps)
    assert collided == collided_pushed == 0.0
    dt = 0.1
    assert stuck[2, 40:].sum() * dt < 1.0  # stood (or crept under a metre) for the last 4 s
    assert pushed[2, 35:40].max() < 0.5 and pushed[2, 40:].sum() * dt > 5.0  # stood, then drove on


def test_only_a_frozen_rider_is_pushed() -> None:
    """The rule pushes a stalled rider only where the model gives moving less than FROZEN_MASS (the demo's
    NPC: 0.000); one the model means to set off keeps its own timing."""
    from trajeglish_env.sampler.guard_stall import FROZEN_MASS, frozen

    moving = np.array([[False, True, True], [False, True, True]])
    probs = np.array([[1.0 - FROZEN_MASS / 2, FROZEN_MASS / 4, FROZEN_MASS / 4], [0.5, 0.25, 0.25]])
    assert frozen(probs, moving).tolist() == [True, False]
