"""Guarded sampling: the masks are exactly the env's collision and off-road rules over every candidate,
guarded rollouts never overlap an agent that moved before (or has not moved yet) nor leave the road, the
lazy checks draw what the full mask draws, and a row's guarded rollout does not depend on its batch."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers import bundle_scene, queue_scene, straight_road_scene, tiny

from trajeglish_env.batch_geometry import collision_flags, road_edges
from trajeglish_env.geometry import box_corners, to_global
from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.metrics.collision_fault import collisions_by_fault
from trajeglish_env.metrics.road_edges import signed_distance_to_road_edges
from trajeglish_env.sampler import guard as guard_module
from trajeglish_env.sampler import sampling
from trajeglish_env.sampler.config import GUARD_ROAD_MARGIN, SamplingConfig
from trajeglish_env.sampler.engine import BatchEngine, RolloutEngine, RowSpec
from trajeglish_env.scenario import AgentKind


def test_the_guard_option_is_a_bool() -> None:
    assert SamplingConfig(guard=True).guard is True
    with pytest.raises(TypeError, match="SamplingConfig.guard"):
        SamplingConfig(guard=1)  # type: ignore[arg-type]
    assert SamplingConfig().guard_road_margin == GUARD_ROAD_MARGIN == 0.0  # WOSAC's off-road threshold
    with pytest.raises(ValueError, match="guard_road_margin must be >= 0"):
        SamplingConfig(guard_road_margin=-0.1)


def brute_force_masks(engine: RolloutEngine, agent: int) -> tuple[np.ndarray, np.ndarray]:
    """Every candidate of ``agent`` in rollout 0 at the current step against every other agent (its next
    box if it moved, else its current one) and the scene's road edges, with the env's functions."""
    sc, t = engine.sc, engine.t
    cand = to_global(engine.mxyh[0, agent, t], engine.vocab.templates[sc.kind[agent]])  # [V,3]
    moved = engine.known[0, :, t] & engine.valid[0, :, t + 1]
    still = engine.valid[0, :, t] & ~engine.known[0, :, t]
    others = np.flatnonzero((moved | still) & (np.arange(sc.num_agents) != agent))
    boxes = np.where(moved[others, None], engine.xyh[0, others, t + 1], engine.xyh[0, others, t])
    collide = box_collisions(cand[:, None], sc.size[agent], boxes[None], sc.size[others][None]).any(axis=1)
    if sc.kind[agent] == AgentKind.PEDESTRIAN:  # vehicles and cyclists keep to the road
        return collide, np.zeros(len(cand), bool)
    edges = road_edges(sc)
    now = excess(engine.mxyh[0, agent, t][None], sc.size[agent], edges)[0]
    return collide, excess(cand, sc.size[agent], edges) > max(GUARD_ROAD_MARGIN, now)


def excess(xyh: np.ndarray, size: np.ndarray, edges: object) -> np.ndarray:
    """``[k]`` how far (m) the most off-road corner of each box ``xyh [k,3]`` lies beyond a road edge."""
    return signed_distance_to_road_edges(box_corners(xyh, size), edges).max(axis=-1)


@pytest.mark.parametrize("name", ["straight", "queue", "highway-roundabout-999001"])
def test_masks_are_the_envs_rules_over_every_candidate(name: str) -> None:
    scenes = {"straight": lambda: straight_road_scene(8, 40), "queue": queue_scene}
    scene = scenes.get(name, lambda: bundle_scene(name))()
    n = scene.num_agents
    external = np.zeros(n, bool)
    external[scene.sdc] = True
    active = scene.valid[:, scene.current_index]
    # one-step masks (the road ahead: its own file; the speed-change rule: the next test; the stall,
    # following and wrong-way rules: tests/test_guard_stall.py, test_brake_test.py, test_lane_directions.py)
    config = SamplingConfig(
        guard=True,
        seed=3,
        guard_road_ahead=0.0,
        guard_step_change=0.0,
        guard_stall_steps=0,
        guard_follow_decel=0.0,
        guard_wrong_way=False,
    )
    engine = RolloutEngine(tiny(), scene, 1, 5, active & ~external, external, config=config)
    for _ in range(2):  # play two steps, then stop mid-step: the sdc has moved, the NPCs have not
        while (agent := engine.advance()) is not None:
            engine.supply(agent, scene.xyh[agent, engine.t + 1])
    assert engine.advance() == scene.sdc
    engine.supply(scene.sdc, scene.xyh[scene.sdc, engine.t + 1])
    npcs = np.flatnonzero(active & ~external)
    rows, t = np.zeros(len(npcs), np.int64), np.full(len(npcs), engine.t)
    geometry = engine.guard.geometry
    pairs = geometry.pairs(engine, rows, npcs, t)
    v = engine.vocab.size
    collide, off = geometry.blocked(
        pairs, np.arange(len(npcs)), np.broadcast_to(np.arange(v), (len(npcs), v))
    )
    masked = np.zeros(2, np.int64)
    for i, agent in enumerate(npcs):
        want_collide, want_off = brute_force_masks(engine, agent)
        assert np.array_equal(collide[i], want_collide), f"agent {agent}: collisions differ"
        assert np.array_equal(off[i], want_off), f"agent {agent}: off-road differs"
        masked += [want_collide.sum(), want_off.sum()]
    assert masked.sum() > 50  # the scene really has candidates to mask


def forward_steps(mxyh: np.ndarray) -> np.ndarray:
    """``[..., T-1]`` the forward distance of each move of model states ``mxyh [..., T, 3]``, in the frame
    of the state it starts from."""
    d = np.diff(mxyh[..., :2], axis=-2)
    return d[..., 0] * np.cos(mxyh[..., :-1, 2]) + d[..., 1] * np.sin(mxyh[..., :-1, 2])


def test_the_speed_change_rule_masks_steps_that_differ_from_the_last_by_more_than_the_limit() -> None:
    """Brute force over every candidate: a vehicle's candidate whose forward step differs from its last
    move by more than ``guard_step_change`` m is masked (cyclists: half of it; pedestrians never), and
    nothing else is (no obstacle or road is near: the rule alone)."""
    scene = straight_road_scene(8, 40)
    active = scene.valid[:, scene.current_index]
    config = SamplingConfig(guard=True, seed=3, guard_step_change=0.7)
    engine = RolloutEngine(tiny(), scene, 1, 5, active, config=config)
    engine.run()
    geometry = engine.guard.geometry
    agents = np.flatnonzero(active)
    t = engine.current + 2
    pairs = geometry.pairs(engine, np.zeros(len(agents), np.int64), agents, np.full(len(agents), t))
    v = engine.vocab.size
    every = np.broadcast_to(np.arange(v), (len(agents), v))
    got = geometry.jumps(pairs, np.arange(len(agents)), every)
    last = forward_steps(engine.mxyh[0, agents, t - 1 : t + 1])[:, 0]
    for i, agent in enumerate(agents):
        limit = {AgentKind.VEHICLE: 0.7, AgentKind.CYCLIST: 0.35}.get(AgentKind(scene.kind[agent]), np.inf)
        want = np.abs(engine.vocab.templates[scene.kind[agent], :, 0] - last[i]) > limit
        assert np.array_equal(got[i], want), agent
    assert got.sum() > 100  # most templates of a moving car are out of reach in one step
    with pytest.raises(ValueError, match="guard_step_change must be >= 0"):
        SamplingConfig(guard_step_change=-1.0)


def test_guarded_vehicles_never_change_speed_beyond_the_limit() -> None:
    """An untrained model's vehicles jump between any speeds from step to step; guarded, no vehicle's
    forward step changes by more than ``guard_step_change`` (0.5 m) in a step while no rule gives way."""
    sc = bundle_scene("highway-highway-999000")
    active = sc.valid[:, sc.current_index].copy()
    change = {}
    for guard in (False, True):
        config = SamplingConfig(temperature=1.0, guard=guard, seed=1)
        engine = RolloutEngine(tiny(), sc, 2, 12, active, config=config)
        engine.run()
        vehicles = np.flatnonzero(active & (sc.kind == AgentKind.VEHICLE))
        steps = forward_steps(engine.mxyh[:, vehicles, engine.current - 1 :])
        change[guard] = np.abs(np.diff(steps, axis=-1)).max()
    stats = engine.guard.stats
    assert change[False] > 2.0
    assert stats.step_fallback == stats.edge_fallback == stats.plain_fallback == 0
    assert change[True] <= 0.5 + 1e-9


def new_events(engine: RolloutEngine) -> tuple[int, int]:
    """Collisions that were not there a step before (among the agents sampled), and vehicles that go
    beyond a road edge or farther beyond it (the guard's rule) a step later, summed over rollouts and
    steps."""
    sc = engine.sc
    agents = np.flatnonzero(engine.controlled)
    edges = road_edges(sc)
    scene = np.zeros(len(agents), np.int64)
    hits = off = 0
    for r in range(engine.R):
        for t in range(engine.current, engine.xyh.shape[2] - 1):
            xyh, valid = engine.xyh[r, :, t : t + 2], engine.valid[r, :, t : t + 2]
            was, now = (
                collision_flags(xyh[None, :, k], valid[None, :, k], sc.size[None], scene, agents)
                for k in (0, 1)
            )
            hits += int((now & ~was).sum())
            vehicles = agents[(sc.kind[agents] == AgentKind.VEHICLE) & valid[agents].all(axis=1)]
            before, after = (excess(xyh[vehicles, k], sc.size[vehicles], edges) for k in (0, 1))
            off += int((after > np.maximum(before, GUARD_ROAD_MARGIN) + 1e-6).sum())
    return hits, off


def test_guarded_rollouts_neither_collide_nor_leave_the_road() -> None:
    sc = bundle_scene("highway-roundabout-999000")
    active = sc.valid[:, sc.current_index].copy()
    runs = {}
    for guard in (False, True):
        engine = RolloutEngine(tiny(), sc, 2, 20, active, config=SamplingConfig(temperature=1.0, guard=guard))
        engine.run()
        runs[guard] = engine
    hits, off = new_events(runs[False])
    assert hits >= 2 and off >= 10  # the untrained model crashes and leaves the road
    stats = runs[True].guard.stats
    assert stats.edge_fallback == stats.plain_fallback == 0 and stats.masked > 50
    assert new_events(runs[True]) == (0, 0)


@pytest.mark.parametrize("temperature", [0.05, 0.0])
def test_lazy_checks_draw_what_the_full_mask_draws(
    temperature: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    sc = bundle_scene("highway-roundabout-999001")
    active = sc.valid[:, sc.current_index].copy()
    config = SamplingConfig(temperature=temperature, guard=True, seed=5)
    lazy = RolloutEngine(tiny(), sc, 2, 12, active, config=config)
    lazy.run()
    monkeypatch.setattr(guard_module, "LAZY_CANDIDATES", ())  # every candidate of every agent checked
    full = RolloutEngine(tiny(), sc, 2, 12, active, config=config)
    full.run()
    assert np.array_equal(lazy.tokens, full.tokens)
    stats = lazy.guard.stats
    assert stats.masked > 10 and stats.full < stats.guarded / 2  # lazily decided, and the guard mattered
    assert full.guard.stats.full == full.guard.stats.guarded


class _FixedMask:
    """A guard geometry whose ``blocked`` reads a fixed mask ``[m,V]`` (pairs by index)."""

    road_ahead = 0.0

    def __init__(self, blocked: np.ndarray):
        self.mask = blocked

    def blocked(self, pairs: object, sel: np.ndarray, tokens: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        hit = self.mask[sel[:, None], tokens]
        return hit, np.zeros_like(hit)


@pytest.mark.parametrize("vocab", [384, 2048])
def test_a_decided_lazy_draw_is_the_full_masked_draw_even_at_token_boundaries(vocab: int) -> None:
    """Peaked distributions (as a trained model's), random masks, numbers placed within 1e-9 of a token
    boundary of the masked CDF: wherever a lazy pass says it decided the draw, its token is the full mask's
    draw."""
    rng = np.random.default_rng(7)
    m = 600
    logits = torch.from_numpy(rng.normal(size=(m, vocab)) * rng.choice([4.0, 8.0, 16.0], size=(m, 1)))
    blocked = rng.random((m, vocab)) < rng.choice([0.02, 0.3, 0.7], size=(m, 1))
    probs = sampling.token_probs(logits, 0.75)
    masked = probs.numpy() * ~blocked
    cum = np.cumsum(masked, axis=1) / masked.sum(axis=1, keepdims=True)
    edge = cum[np.arange(m), rng.integers(0, vocab, m)]
    uniform = np.clip(edge + rng.choice([-1e-9, 0.0, 1e-9, 0.01], size=m), 0.0, 1.0 - 1e-16)
    guard = guard_module.SamplingGuard(_FixedMask(blocked))  # type: ignore[arg-type]
    masked_logits = logits.masked_fill(torch.from_numpy(blocked), -np.inf)
    want = sampling.sample_with_uniform(masked_logits, 0.75, 1.0, uniform)
    probs_np, cdf_np = probs.numpy(), probs.cumsum(-1).numpy()
    decided = np.zeros(m, bool)
    for k in (6, 24, 96, 384):
        rest = np.flatnonzero(~decided)
        chosen, done = guard._lazy_draw(None, rest, probs_np[rest], cdf_np[rest], k, uniform[rest])  # type: ignore[arg-type]
        assert np.array_equal(chosen[done], want[rest[done]])
        decided[rest[done]] = True
    assert decided.mean() > 0.3  # the passes decide many pairs (near a boundary they cannot)


def test_guarded_rows_equal_their_solo_runs() -> None:
    names = ["highway-merge-999000", "sumo-random-999000-0-0", "highway-roundabout-999001"]
    scenes = [bundle_scene(name) for name in names]
    specs = [RowSpec(sc, 8, sc.valid[:, sc.current_index].copy()) for sc in scenes]
    config = SamplingConfig(temperature=1.0, guard=True)

    def run(rows: list[int]) -> BatchEngine:
        engine = BatchEngine(tiny(), len(rows), config, cache_dtype=torch.float32)
        for row, i in enumerate(rows):
            engine.start_rows([row], specs[i], [20 + i])
        engine.run()
        return engine

    batch = run([2, 0, 1])
    masked = 0
    for row, i in enumerate([2, 0, 1]):
        solo = run([i])
        n, steps = scenes[i].num_agents, scenes[i].current_index + 9
        assert np.array_equal(batch.tokens[row, :n, : steps - 1], solo.tokens[0, :n, : steps - 1]), names[i]
        masked += solo.guard.stats.masked
    assert masked > 20


class FixedMasks:
    """A stand-in geometry: pair i's candidates collide where ``collide[i]`` and leave the road where
    ``off[i]`` (whatever the tokens asked about, which are all V here)."""

    road_ahead = 0.0

    def __init__(
        self,
        collide: np.ndarray,
        off: np.ndarray,
        escape: np.ndarray | None = None,
        jump: np.ndarray | None = None,
    ):
        self.collide, self.off = collide, off
        self.escape = np.zeros_like(collide) if escape is None else escape
        self.jump = np.zeros_like(collide) if jump is None else jump

    def blocked(self, pairs: object, sel: np.ndarray, tokens: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.collide[sel] | self.escape[sel], self.off[sel] | self.jump[sel]

    def blocked_parts(
        self, pairs: object, sel: np.ndarray, tokens: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return self.collide[sel], self.escape[sel], self.off[sel], self.jump[sel]

    def step_changes(self, pairs: object, sel: np.ndarray, tokens: np.ndarray) -> np.ndarray:
        return np.where(self.jump[sel], 2.0 + np.arange(tokens.shape[1]) / 100, 0.0)


def test_fallbacks_widen_the_speed_rule_then_drop_the_road_rule_then_the_guard() -> None:
    v, n = 12, 400
    logits = torch.randn(n, v, generator=torch.Generator().manual_seed(0)) * 2
    uniform = np.random.default_rng(0).random(n)
    first_half = np.arange(v) < v // 2
    collide = np.zeros((n, v), bool)
    off = np.zeros((n, v), bool)
    collide[0::4], off[0::4] = True, True  # everything masked: drawn unguarded
    collide[1::4], off[1::4] = first_half, ~first_half  # only the road rule left: dropped, collisions stay
    collide[2::4], off[2::4] = first_half, np.arange(v) == v - 1  # allowed: the second half but the last
    collide[3::4], off[3::4] = collide[2::4], off[2::4]
    jump = np.zeros((n, v), bool)
    jump[1::4] = True  # the speed rule widened leaves nothing either: the road rule goes next
    jump[3::4] = np.arange(v) >= v // 2  # every candidate left jumps: the gentlest of them is kept
    guard = guard_module.SamplingGuard(FixedMasks(collide, off, jump=jump))  # type: ignore[arg-type]
    tokens = guard._full_draw(None, np.arange(n), logits, 1.0, 1.0, uniform)  # type: ignore[arg-type]
    plain = guard_module.sample_with_uniform(logits, 1.0, 1.0, uniform)
    assert np.array_equal(tokens[0::4], plain[0::4])
    assert (tokens[1::4] >= v // 2).all() and (tokens[2::4] >= v // 2).all() and (tokens[2::4] < v - 1).all()
    assert (tokens[3::4] == v // 2).all()  # the smallest speed change (FixedMasks: 2 + token / 100)
    assert guard.stats.plain_fallback == len(tokens[0::4]) and guard.stats.edge_fallback == len(tokens[1::4])
    assert guard.stats.step_fallback == len(tokens[3::4])
    allowed = (plain[2::4] >= v // 2) & (plain[2::4] < v - 1)
    same = (tokens[2::4] == plain[2::4])[allowed].mean()  # 0.72: one number per draw keeps most tokens
    assert 0.5 < same < 1.0 and 0.3 < allowed.mean() < 0.7


def test_allowed_draws_stand_and_the_guarded_draw_is_exactly_the_masked_distribution() -> None:
    """The guard keeps the model's draw where the rules allow it and redraws from the masked logits with a
    second number elsewhere (``_full_draw(..., keep)``, what ``sample`` does at top_p = 1): every allowed draw
    stands, no blocked token comes out, and over 200,000 numbers each token's frequency is its probability
    under the mask (p / Z), not the model's p."""
    v, n = 10, 200_000
    logits = torch.from_numpy(np.random.default_rng(3).normal(size=v) * 1.5)[None].repeat(n, 1)
    blocked = np.zeros((n, v), bool)
    blocked[:, [1, 4, int(logits[0].argmax())]] = True  # the most likely token among them
    uniform = (np.arange(n) + 0.5) / n
    guard = guard_module.SamplingGuard(FixedMasks(blocked, np.zeros_like(blocked)))  # type: ignore[arg-type]
    plain = guard_module.sample_with_uniform(logits, 1.0, 1.0, uniform)
    redraw = sampling.second_uniform(uniform)
    tokens = guard._full_draw(None, np.arange(n), logits, 1.0, 1.0, redraw, plain)  # type: ignore[arg-type]
    allowed = ~blocked[0, plain]
    assert np.array_equal(tokens[allowed], plain[allowed]) and not blocked[0, tokens].any()
    p = torch.softmax(logits[0], -1).numpy()
    q = np.where(blocked[0], 0.0, p) / p[~blocked[0]].sum()
    freq = np.bincount(tokens, minlength=v) / n
    assert np.abs(freq - q).max() < 0.005 and np.abs(freq - p).max() > 0.05
    assert 0.2 < (~allowed).mean() < 0.95  # the mask takes a real share of the mass


def test_with_nothing_to_escape_to_the_agents_to_escape_are_dropped_first() -> None:
    v, n = 12, 300
    logits = torch.randn(n, v, generator=torch.Generator().manual_seed(1)) * 2
    uniform = np.random.default_rng(1).random(n)
    first_half = np.arange(v) < v // 2
    collide, off, escape = np.zeros((n, v), bool), np.zeros((n, v), bool), np.zeros((n, v), bool)
    escape[0::2] = True  # no candidate escapes: those agents are left out, the rest of the guard stays
    collide[0::2] = first_half
    escape[1::2] = first_half  # the second half escapes: drawn from it
    guard = guard_module.SamplingGuard(FixedMasks(collide, off, escape))  # type: ignore[arg-type]
    tokens = guard._full_draw(None, np.arange(n), logits, 1.0, 1.0, uniform)  # type: ignore[arg-type]
    assert (tokens >= v // 2).all()
    assert guard.stats.escape_fallback == n // 2 and guard.stats.plain_fallback == 0


def closing_in_scene() -> object:
    """A car (the sdc) logged at 5 m/s with a logged car 0.1 m behind it at the current step doing 10 m/s:
    its next box overlaps the sdc's current one by 0.9 m, the guard's "no move undoes it" case."""
    sc = straight_road_scene(2, 40)
    t = np.arange(sc.num_steps) * 0.1
    xyh = np.zeros_like(sc.xyh)
    xyh[0, :, 0] = 9.6 + 5.0 * t
    xyh[1, :, 0] = 10.0 * t
    kind = np.full(2, AgentKind.VEHICLE)
    return dataclasses.replace(sc, xyh=xyh, valid=np.ones_like(sc.valid), kind=kind)


def test_an_agent_driven_into_moves_out_of_the_way_with_guard_escape_when_it_acts_after_it() -> None:
    sc = closing_in_scene()
    controlled = np.array([True, False])  # the other replays its log: it does not react
    struck = {}
    for place, priority in (("first", [-1.0, 0.0]), ("last", [1.0, 0.0])):
        for escape in (False, True):
            # the one-step road rule: the road ahead keeps the untrained sdc out of the logged car's way;
            # the escape rule alone (the speed rule would change the untrained model's draws)
            config = SamplingConfig(
                temperature=1.0,
                guard=True,
                guard_escape=escape,
                seed=2,
                guard_road_ahead=0.0,
                guard_step_change=0.0,
            )
            engine = RolloutEngine(tiny(), sc, 16, 15, controlled, config=config, priority=np.array(priority))
            engine.run()
            hit, at_fault = collisions_by_fault(engine.xyh, engine.valid, sc.size, 0, sc.current_index)
            struck[place, escape] = int(hit.sum())
            assert not at_fault.any(), (place, escape)
    # acting last, the guard sees the logged car's move and escapes it; acting first, the order hides it
    assert struck["last", False] >= 10 and struck["last", True] <= 2, struck
    assert struck["first", False] >= 10 and struck["first", True] >= 10, struck


def test_only_an_agent_that_moved_into_the_box_this_step_is_kept_to_escape() -> None:
    """The closing-in logged car is kept as an obstacle to escape; one parked half on the sdc's box from
    the step before (a log's overlapping boxes) did not move into it and stays left out, as without
    escape (on the WOMD scene this kept 521 of 529 fallbacks away, its rollouts bit for bit those without
    escape)."""
    closing = closing_in_scene()
    xyh = closing.xyh.copy()
    xyh[1, :, 0] = xyh[0, :, 0] - 2.0  # 2 m behind the sdc's centre (4.5 m long boxes), moving with it
    parked = dataclasses.replace(closing, xyh=xyh)
    for sc, kept in ((closing, True), (parked, False)):
        config = SamplingConfig(guard=True, seed=2)
        engine = RolloutEngine(tiny(), sc, 1, 15, np.array([True, False]), config=config)
        assert engine.guard is not None
        one = np.array([0])
        p = engine.guard.geometry.pairs(engine, one, one, np.array([sc.current_index]), None)
        assert p.near_escape.any() == kept and p.near_real.any() == kept


def test_an_external_agent_driving_into_an_npc_keeps_its_collision() -> None:
    """An ego (external) that drives into the NPC ahead is not escaped: the NPC does not jump away from a
    collision the env must report to the ego's policy."""
    sc = closing_in_scene()
    controlled, external = np.array([True, False]), np.array([False, True])
    config = SamplingConfig(  # as above
        temperature=1.0, guard=True, seed=2, guard_road_ahead=0.0, guard_step_change=0.0
    )
    priority = np.array([1.0, 0.0])  # the ego moves first: the NPC's guard sees it drive into its box
    engine = RolloutEngine(
        tiny(), sc, 16, 15, controlled, external=external, config=config, priority=priority
    )
    while engine.stepping.any():
        agent = engine.advance()
        if agent is not None:
            engine.supply(agent, np.broadcast_to(sc.xyh[agent, engine.t + 1], (16, 3)))
    hit, at_fault = collisions_by_fault(engine.xyh, engine.valid, sc.size, 0, sc.current_index)
    assert hit.sum() >= 10 and not at_fault.any(), hit.sum()  # the ego's collision stands


def test_the_guard_sees_a_logged_agents_move_only_when_it_acted_before() -> None:
    sc = closing_in_scene()
    controlled = np.array([True, False])
    for priority, seen in (([-1.0, 0.0], False), ([1.0, 0.0], True)):
        config = SamplingConfig(temperature=1.0, guard=True, seed=2)
        engine = RolloutEngine(tiny(), sc, 1, 15, controlled, config=config, priority=np.array(priority))
        engine.step()  # plans the model context: the acting order
        t = engine.now[:1]
        assert engine.acting_rank[0].tolist() == ([0, 1] if not seen else [1, 0])
        moved = engine.guard_moved(np.array([0]), np.array([0]), t)
        assert moved[0].tolist() == [False, seen]  # the sdc's own token of the step is not decided yet
        assert engine.guard_moved(np.array([0]), np.array([1]), t)[0, 1]  # a logged agent sees its own

    with pytest.raises(TypeError, match="SamplingConfig.guard_escape must be a bool"):
        SamplingConfig(guard_escape=1)  # type: ignore[arg-type]
