"""The guard's wrong-way rule: lane directions per map cell, and guarded vehicles never turn or drive onto a
lane against every lane there (the masks of the other rules had left them swerving into the oncoming lane,
and leaving junctions into it)."""

from __future__ import annotations

import numpy as np
from helpers import tiny

from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.engine import RolloutEngine
from trajeglish_env.sampler.lane_directions import LaneDirections
from trajeglish_env.scenario import AgentKind, MapKind, Scenario


def _two_way_road(xyh0: list[tuple[float, float, float]]) -> Scenario:
    """A straight road along x: the eastbound lane centre at y = -2, the westbound one at y = +2 (points
    0.5 m apart, as the generators'), edges at y = -8 and +8 (room to turn); one parked vehicle per
    ``xyh0`` state."""
    x = np.arange(-60.0, 60.01, 0.5)
    east = np.stack([x, np.full_like(x, -2.0)], 1)
    west = np.stack([x[::-1], np.full_like(x, 2.0)], 1)
    lower = np.stack([x, np.full_like(x, -8.0)], 1)  # edges keep the road on their left
    upper = np.stack([x[::-1], np.full_like(x, 8.0)], 1)
    n, t = len(xyh0), 91
    xyh = np.repeat(np.array(xyh0, dtype=np.float64)[:, None], t, axis=1)
    return Scenario.from_arrays(
        xyh,
        np.ones((n, t), bool),
        np.tile([4.5, 2.0], (n, 1)),
        np.full(n, int(AgentKind.VEHICLE)),
        polylines=[east, west, lower, upper],
        polyline_kinds=[MapKind.LANE_SURFACE_STREET, MapKind.LANE_SURFACE_STREET]
        + [MapKind.ROAD_EDGE_BOUNDARY] * 2,
    )


def test_a_box_is_against_the_lanes_only_where_every_lane_near_runs_the_other_way() -> None:
    lanes = LaneDirections.of(_two_way_road([(0.0, -2.0, 0.0)]))
    q = np.array(
        [
            [0.0, -2.0, 0.0],  # eastbound lane, heading east
            [0.0, -2.0, np.pi],  # eastbound lane, heading west: against
            [0.0, 2.0, np.pi],  # westbound lane, heading west
            [0.0, 2.6, 0.1],  # westbound lane, heading east: against
            [0.0, -2.0, np.pi / 2],  # across the lane: not against it
            [0.0, 10.0, np.pi],  # off every lane: never against
            [500.0, 0.0, 0.0],  # off the map's grid
        ]
    )
    assert lanes.against(q).tolist() == [False, True, False, True, False, False, False]
    assert lanes.lane_bits(q[5:, :2]).tolist() == [0, 0]
    no_lanes = Scenario.from_arrays(
        np.zeros((1, 91, 3)), np.ones((1, 91), bool), np.ones((1, 2)), np.zeros(1)
    )
    assert LaneDirections.of(no_lanes) is None  # no lanes, no rule


def test_guarded_vehicles_never_turn_against_their_lane() -> None:
    """A vehicle on the eastbound lane turned 121 degrees from it (turning round): its candidates that end
    more than 124 degrees from the lane (the lane's and the heading's 11.25-degree bins 11 apart) are masked
    as a map rule, those under 120 are not; one already against
    the lanes (a car parked facing the traffic) keeps all its candidates; without the rule nothing is."""
    sc = _two_way_road([(0.0, -2.0, 2.12), (0.0, 2.0, 0.0)])  # the second faces the westbound traffic
    engine = RolloutEngine(tiny(), sc, 1, 5, sc.valid[:, sc.current_index].copy(), config=SamplingConfig())
    geometry, v = engine.guard.geometry, engine.vocab.size
    pairs = geometry.pairs(engine, np.zeros(2, np.int64), np.array([0, 1]), np.full(2, engine.t))
    assert pairs.keep_way.tolist() == [True, False]
    every = np.broadcast_to(np.arange(v), (2, v))
    _, _, off, _ = geometry.blocked_parts(pairs, np.arange(2), every)
    step = geometry.templates[AgentKind.VEHICLE]
    heading = 2.12 + step[:, 2]
    on_lane = np.hypot(step[:, 0], step[:, 1]) < 0.5  # ends on the lane (farther: off it, not checked)
    against = on_lane & (heading > np.deg2rad(124))
    assert against.any() and off[0, against].all()
    assert not off[0, heading < np.deg2rad(120)].any()
    assert not off[1].any()
    ruled_off = SamplingConfig(guard_wrong_way=False)
    engine = RolloutEngine(tiny(), sc, 1, 5, sc.valid[:, sc.current_index].copy(), config=ruled_off)
    one = (np.zeros(1, np.int64), np.zeros(1, np.int64), np.full(1, engine.t))
    assert not engine.guard.geometry.pairs(engine, *one).keep_way[0]


def test_a_vehicle_off_the_lanes_may_not_drive_onto_one_the_wrong_way() -> None:
    """Junctions of SUMO maps hold no lanes: a guarded vehicle in one was not checked and left it into the
    oncoming lane (development SUMO scenes: 6.6 % of guarded vehicle steps against the lanes with the rule
    for vehicles on a lane only, 11.2 % without it, the log none)."""
    from trajeglish_env.geometry import to_global

    sc = _two_way_road([(0.0, -4.4, 2.6), (0.0, 2.0, 0.0)])  # 2.4 m off the eastbound lane, heading 149 deg
    engine = RolloutEngine(tiny(), sc, 1, 5, sc.valid[:, sc.current_index].copy(), config=SamplingConfig())
    geometry, v = engine.guard.geometry, engine.vocab.size
    pairs = geometry.pairs(engine, np.zeros(1, np.int64), np.zeros(1, np.int64), np.full(1, engine.t))
    lanes = pairs.lanes[0]
    assert lanes.lane_bits(pairs.origin[0, :2]) == 0 and pairs.keep_way[0]  # off the lanes, still ruled
    cand = to_global(pairs.origin[0][None], geometry.templates[AgentKind.VEHICLE])
    onto = lanes.against(cand)
    assert onto.any()
    _, _, off, _ = geometry.blocked_parts(pairs, np.zeros(1, np.int64), np.arange(v)[None])
    assert off[0, onto].all()
