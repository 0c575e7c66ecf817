"""The road ahead of guarded sampling (``SamplingConfig.guard_road_ahead``): kept-up motions are the token
repeated, reaches are the env's off-road rule along each arc, lazily decided draws are the full mask's,
and with the shipped model it keeps racetrack traffic moving without taking it off the road."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import bundle_scene, tiny
from test_guard import excess

from trajeglish_env.batch_geometry import road_edges
from trajeglish_env.benchmark.workloads import model_checkpoint
from trajeglish_env.geometry import to_global
from trajeglish_env.sampler import SamplingConfig, rollout, sampling
from trajeglish_env.sampler import guard as guard_module
from trajeglish_env.sampler.config import GUARD_ROAD_MARGIN
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.sampler.guard_ahead import (
    AHEAD_CHECKS,
    AHEAD_MIN_MOVE,
    AHEAD_MOST_STEPS,
    ahead_masks,
    ahead_of_all,
    kept_up,
)
from trajeglish_env.sampler.guard_geometry import GuardGeometry
from trajeglish_env.scenario import AgentKind


def test_the_option_is_metres_ahead() -> None:
    assert SamplingConfig(guard_road_ahead=5).guard_road_ahead == 5
    with pytest.raises(ValueError, match="guard_road_ahead must be >= 0"):
        SamplingConfig(guard_road_ahead=-1.0)


def test_a_kept_up_motion_is_the_step_repeated_and_its_arc_between_steps() -> None:
    rng = np.random.default_rng(0)
    n = 200
    origin = np.column_stack([rng.normal(0, 50, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    step = np.column_stack([rng.uniform(0.2, 3.0, n), rng.normal(0, 0.2, n), rng.normal(0, 0.15, n)])
    step[:20, 1:] = 0.0  # straight on
    move = np.hypot(step[:, 0], step[:, 1])
    pose = origin
    for k in range(1, 7):
        pose = to_global(pose, step)
        np.testing.assert_allclose(kept_up(origin, step, k * move), pose, atol=1e-9)
    half = kept_up(origin, step, 2.5 * move)  # an arc: two and a half steps, then a half
    np.testing.assert_allclose(kept_up(half, step, 0.5 * move), kept_up(origin, step, 3 * move), atol=1e-9)
    slow = np.array([[0.01, 0.0, 0.0]])  # a creeping motion is followed for at most AHEAD_MOST_STEPS
    np.testing.assert_allclose(kept_up(np.zeros((1, 3)), slow, 100.0)[0, 0], 0.01 * AHEAD_MOST_STEPS)


def _racetrack_engine(ahead: float) -> tuple[RolloutEngine, np.ndarray]:
    sc = bundle_scene("highway-racetrack-999000")
    active = sc.valid[:, sc.current_index].copy()
    # the road rules alone (the speed-change rule would mask the untrained model's jumps too)
    config = SamplingConfig(guard=True, seed=2, guard_road_ahead=ahead, guard_step_change=0.0)
    engine = RolloutEngine(tiny(), sc, 1, 4, active, config=config)
    for _ in range(2):
        engine.step()
    return engine, np.flatnonzero(active & (sc.kind == AgentKind.VEHICLE))


def _racetrack_reach(ahead: float) -> tuple[RolloutEngine, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The racetrack engine's vehicles, their pairs' one-step masks and their reach and looked-at
    candidates over every candidate."""
    engine, vehicles = _racetrack_engine(ahead)
    geometry, v = engine.guard.geometry, engine.vocab.size
    pairs = geometry.pairs(
        engine, np.zeros(len(vehicles), np.int64), vehicles, np.full(len(vehicles), engine.t)
    )
    every = np.broadcast_to(np.arange(v), (len(vehicles), v))
    collide, off = geometry.blocked(pairs, np.arange(len(vehicles)), every)
    reach, look = geometry.reach(pairs, np.arange(len(vehicles)), every, ~(collide | off))
    return engine, vehicles, pairs.edges.road, reach, look


def test_the_rule_looks_at_allowed_moving_vehicles_near_an_edge_and_masks_the_short_arcs() -> None:
    engine, vehicles, road, reach, look = _racetrack_reach(6.0)
    v = engine.vocab.size
    templates = engine.vocab.templates[AgentKind.VEHICLE][:v]
    moving = np.hypot(templates[:, 0], templates[:, 1]) >= AHEAD_MIN_MOVE
    assert not (look & ~moving[None]).any() and not look[~road].any() and look[road].any()
    assert (reach[~look] == AHEAD_CHECKS).all()
    masked = ahead_of_all(reach, look)
    best = np.where(look, reach, 0).max(axis=1)
    assert np.array_equal(masked, look & (reach < best[:, None])) and masked.sum() > 50
    _, _, _, reach_off, look_off = _racetrack_reach(0.0)  # the rule off: nothing looked at
    assert not look_off.any() and (reach_off == AHEAD_CHECKS).all()


def test_reach_is_the_envs_off_road_rule_point_by_point() -> None:
    """Each looked-at candidate's box is on the road (by the metric's own signed distance, against the
    margin or how far off it is already) at every point of its arc up to its reach, and off at the next."""
    ahead = 6.0
    engine, vehicles, _, reach, look = _racetrack_reach(ahead)
    sc, t, v = engine.sc, engine.t, engine.vocab.size
    edges = road_edges(sc)
    templates = engine.vocab.templates[AgentKind.VEHICLE][:v]
    i, j = np.nonzero(look)
    agents = vehicles[i]
    origin = engine.mxyh[0, agents, t]
    limit = np.maximum(GUARD_ROAD_MARGIN, excess(origin, sc.size[agents], edges))
    want = np.full(len(i), AHEAD_CHECKS)
    for k in range(AHEAD_CHECKS, 0, -1):
        pose = kept_up(origin, templates[j], ahead * k / AHEAD_CHECKS)
        want[excess(pose, sc.size[agents], edges) > limit] = k - 1
    assert np.array_equal(reach[i, j], want)
    assert (want < AHEAD_CHECKS).sum() > 100 and (want == AHEAD_CHECKS).sum() > 100


def test_partial_knowledge_never_contradicts_the_full_rule() -> None:
    rng = np.random.default_rng(3)
    m, c = 400, 40
    reach = rng.integers(0, AHEAD_CHECKS + 1, (m, c))
    look = rng.random((m, c)) < 0.7
    full = ahead_of_all(reach, look)
    for share in (0.1, 0.5, 1.0):
        known = rng.random((m, c)) < share
        masked, unsure = ahead_masks(reach * known, look & known)
        masked, unsure = masked & known, unsure & known
        assert not (masked & ~full).any()  # masked for sure: masked by the full rule
        settled = known & look & ~masked & ~unsure
        assert not (settled & full).any()  # kept for sure: kept by the full rule
    masked, unsure = ahead_masks(reach, look)  # everything known: the full rule, the unsure ones kept
    assert np.array_equal(masked, full) and not (unsure & full).any()


class _ReachMask:
    """A stand-in geometry: blocked where ``blocked [m,V]``; the road-ahead rule looks at ``look [m,V]``
    (of the allowed ones) with reach ``reach [m,V]``."""

    road_ahead = 5.0

    def __init__(self, blocked: np.ndarray, reach: np.ndarray, look: np.ndarray):
        self.mask, self.reach_, self.look = blocked, reach, look

    def blocked(self, pairs: object, sel: np.ndarray, tokens: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        hit = self.mask[sel[:, None], tokens]
        return hit, np.zeros_like(hit)

    def blocked_parts(
        self, pairs: object, sel: np.ndarray, tokens: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        hit = self.mask[sel[:, None], tokens]
        return hit, np.zeros_like(hit), np.zeros_like(hit), np.zeros_like(hit)

    def reach(
        self, pairs: object, sel: np.ndarray, tokens: np.ndarray, allowed: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        return self.reach_[sel[:, None], tokens], self.look[sel[:, None], tokens] & allowed


def test_a_decided_lazy_draw_is_the_full_draw_of_the_road_ahead_rule() -> None:
    """Peaked distributions, random masks and reaches, numbers near token boundaries: wherever a lazy pass
    says it decided a draw, its token is the draw of the logits masked by the one-step rules and the
    road-ahead rule over every candidate."""
    rng = np.random.default_rng(11)
    m, vocab = 600, 384
    logits = torch.from_numpy(rng.normal(size=(m, vocab)) * rng.choice([4.0, 8.0, 16.0], size=(m, 1)))
    blocked = rng.random((m, vocab)) < rng.choice([0.02, 0.3], size=(m, 1))
    reach = np.where(
        rng.random((m, vocab)) < rng.choice([0.0, 0.5, 0.95], size=(m, 1)),
        AHEAD_CHECKS,
        rng.integers(0, AHEAD_CHECKS, (m, vocab)),
    )
    look = rng.random((m, vocab)) < 0.9
    geometry = _ReachMask(blocked, reach, look)
    full_mask = blocked | ahead_of_all(reach, look & ~blocked)
    probs = sampling.token_probs(logits, 0.75)
    masked = probs.numpy() * ~full_mask
    cum = np.cumsum(masked, axis=1) / masked.sum(axis=1, keepdims=True)
    edge = cum[np.arange(m), rng.integers(0, vocab, m)]
    uniform = np.clip(edge + rng.choice([-1e-9, 0.0, 1e-9, 0.01], size=m), 0.0, 1.0 - 1e-16)
    guard = guard_module.SamplingGuard(geometry)  # type: ignore[arg-type]
    want = sampling.sample_with_uniform(
        logits.masked_fill(torch.from_numpy(full_mask), -np.inf), 0.75, 1.0, uniform
    )
    probs_np, cdf_np = probs.numpy(), probs.cumsum(-1).numpy()
    decided = np.zeros(m, bool)
    for k in (6, 24, 96):
        rest = np.flatnonzero(~decided)
        chosen, done = guard._lazy_draw(None, rest, probs_np[rest], cdf_np[rest], k, uniform[rest])  # type: ignore[arg-type]
        assert np.array_equal(chosen[done], want[rest[done]])
        decided[rest[done]] = True
    full = guard._full_draw(
        None, np.flatnonzero(~decided), logits[torch.from_numpy(~decided)], 0.75, 1.0, uniform[~decided]
    )  # type: ignore[arg-type]
    assert np.array_equal(full, want[~decided])
    assert 0.2 < decided.mean() < 0.95  # lazy passes decide many draws, unsure candidates hold back others
    argmax = logits.masked_fill(torch.from_numpy(full_mask), -np.inf).argmax(-1).numpy()
    for k in (6, 24):
        chosen, done = guard._lazy_argmax(None, np.arange(m), logits, k)  # type: ignore[arg-type]
        assert np.array_equal(chosen[done], argmax[done]) and done.mean() > 0.3


@pytest.mark.parametrize("temperature", [0.05, 0.0])
def test_lazy_checks_draw_what_the_full_mask_draws_with_the_road_ahead(
    temperature: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    sc = bundle_scene("highway-roundabout-999001")
    active = sc.valid[:, sc.current_index].copy()
    runs = {}
    for ahead, lazy in ((0.0, True), (6.0, True), (6.0, False)):
        if not lazy:
            monkeypatch.setattr(guard_module, "LAZY_CANDIDATES", ())  # every candidate of every agent checked
        config = SamplingConfig(temperature=temperature, guard=True, seed=5, guard_road_ahead=ahead)
        engine = RolloutEngine(tiny(), sc, 2, 12, active, config=config)
        engine.run()
        runs[ahead, lazy] = engine
    assert np.array_equal(runs[6.0, True].tokens, runs[6.0, False].tokens)
    assert not np.array_equal(runs[6.0, True].tokens, runs[0.0, True].tokens)  # the rule changed draws
    stats = runs[6.0, True].guard.stats
    assert stats.full < stats.guarded  # some draws were decided lazily


def _standing_and_off_road(ahead: float) -> tuple[float, int]:
    """Share of the bundled racetrack's vehicle steps under 0.5 m/s in 4 guarded rollouts of 40 steps by
    the shipped model, and the steps a vehicle's box went farther off the road than it was."""
    sc = bundle_scene("highway-racetrack-999000")
    c = sc.current_index
    ro = rollout(model_checkpoint()[0], sc, 4, 40, config=SamplingConfig(seed=0, guard_road_ahead=ahead))
    speed = np.linalg.norm(np.diff(ro.xyh[..., c:, :2], axis=-2), axis=-1) / sc.dt
    vehicle = (sc.kind == AgentKind.VEHICLE)[None, :, None]
    ok = ro.valid[..., c:-1] & ro.valid[..., c + 1 :] & vehicle
    edges = road_edges(sc)
    worse = 0
    for r in range(ro.xyh.shape[0]):
        for t in range(c, c + 40):
            agents = np.flatnonzero(ok[r, :, t - c])
            before, after = (excess(ro.xyh[r, agents, t + k], sc.size[agents], edges) for k in (0, 1))
            worse += int((after > np.maximum(before, GUARD_ROAD_MARGIN) + 1e-6).sum())
    return float(((speed < 0.5) & ok).sum() / ok.sum()), worse


def test_with_the_road_ahead_racetrack_vehicles_keep_moving_and_on_the_road() -> None:
    before, off_before = _standing_and_off_road(0.0)
    after, off_after = _standing_and_off_road(5.0)
    assert off_before == off_after == 0
    assert before > 0.005 and after < before / 2  # 0.0089 -> 0.0 with the shipped model


def test_road_answers_do_not_depend_on_what_was_measured_before() -> None:
    """The road rule's masks over every candidate are the same from a fresh guard, from one whose road-edge
    cells earlier queries computed (a vehicle whose whole reach, its kept-up motion included, is in safe cells
    is left unchecked: no candidate of it is masked either way), and from one answering again from its
    per-agent memory (parallel decoding asks several times a step)."""
    engine, vehicles = _racetrack_engine(6.0)
    used = engine.guard.geometry
    rows, t = np.zeros(len(vehicles), np.int64), np.full(len(vehicles), engine.t)
    every = np.broadcast_to(np.arange(engine.vocab.size), (len(vehicles), engine.vocab.size))

    def masks(geometry: GuardGeometry) -> tuple[np.ndarray, ...]:
        pairs = geometry.pairs(engine, rows, vehicles, t)
        sel = np.arange(len(vehicles))
        collide, off = geometry.blocked(pairs, sel, every)
        reach, look = geometry.reach(pairs, sel, every, ~(collide | off))
        return collide, off, ahead_of_all(reach, look), pairs.edges.limit[pairs.edges.road]

    def fresh() -> GuardGeometry:
        return GuardGeometry.of(engine.vocab.templates, engine.config)

    want = masks(fresh())
    assert want[1].sum() > 0 and want[2].sum() > 50, (want[1].sum(), want[2].sum())
    warm_cells = fresh()
    warm_cells._cells = used._cells  # blocks computed over the steps played
    for got in (masks(warm_cells), masks(used), masks(used)):
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
