"""Geometry of guarded sampling (:mod:`~trajeglish_env.sampler.guard`): for the (row, agent) pairs sampled
in one model call, the obstacles near each agent, the road edges near each vehicle
(:mod:`~trajeglish_env.sampler.guard_edges`) and the red or green lights ahead of it
(:mod:`~trajeglish_env.sampler.guard_signals`), and which candidate tokens would overlap an obstacle, or
put the vehicle off the road or across a red stop line, or leave it standing at a green light.

Vectorized over pairs, candidates and neighbours, with the env's own functions
(:mod:`~trajeglish_env.batch_geometry`): boxes overlap by the separating-axis test the env's collision
flag uses, and off-road is the env's rule. Every number of a pair depends on its own row only, never on
the rows sampled with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import TypeVar

import numpy as np

from trajeglish_env.batch_geometry import PaddedRows
from trajeglish_env.compiled import overlaps, pair_compiled
from trajeglish_env.edge_cells import EdgeCells
from trajeglish_env.geometry import to_global
from trajeglish_env.sampler.candidate_memo import CandidateMemo, memo_keys
from trajeglish_env.sampler.config import SamplingConfig
from trajeglish_env.sampler.guard_ahead import AHEAD_CHECKS, AHEAD_MIN_MOVE, road_reach
from trajeglish_env.sampler.guard_edges import RoadView, road_rule, road_view
from trajeglish_env.sampler.guard_follow import FOLLOW_SLACK, STEP_SECONDS, follow_caps
from trajeglish_env.sampler.guard_neighbours import half_diagonal, neighbours
from trajeglish_env.sampler.guard_signals import SceneSignals
from trajeglish_env.sampler.guard_stall import departure_need, stall_candidates, stalled, way_clear
from trajeglish_env.sampler.lane_directions import MAX_SCENES, LaneDirections
from trajeglish_env.sampler.pair_memo import StepPairs, seen_states, view_key
from trajeglish_env.sampler.rows import RowStates
from trajeglish_env.sampler.scene_cache import SceneCache
from trajeglish_env.scenario import AgentKind


@dataclass(frozen=True)
class Pairs:
    """The ``n`` pairs of a model call as the guard sees them: ``rows``/``agents [n]``; ``origin [n,3]``
    the model's state the candidates start from at steps ``t [n]``, ``size [n,2]``, ``kind [n]``,
    ``extent [n]`` the reach of its candidates' corners; the obstacles near each agent ``near_xyh [n,K,3]``,
    ``near_size [n,K,2]``, ``near_real [n,K]`` and ``near_escape [n,K]`` (those that moved into its
    current box, kept only to be escaped: ``SamplingConfig.guard_escape``); its road ``edges``; ``red [n]``
    vehicles and cyclists with a red light within reach, ``depart [n]`` those the green rule applies to (a
    green light ahead, the way clear), the ``signals`` of their rows, ``pace [n]`` the forward distance of
    each agent's last move (its model states at ``t - 1`` and ``t``), NaN for pedestrians and where there is
    no state at ``t - 1``, ``stall [n]`` those the stall rule pushes on
    (:mod:`~trajeglish_env.sampler.guard_stall`), ``keep_way [n]`` the vehicles the wrong-way rule keeps
    from turning against the lanes (in rows with ``lanes``, not against them already), and
    ``follow_cap [n]`` the longest forward step the following rule allows each (inf: none;
    :mod:`~trajeglish_env.sampler.guard_follow`); ``memo_keys [n,8]`` what its road-edge answers depend on
    (:mod:`~trajeglish_env.sampler.candidate_memo`)."""

    rows: np.ndarray
    agents: np.ndarray
    t: np.ndarray
    origin: np.ndarray
    size: np.ndarray
    kind: np.ndarray
    extent: np.ndarray
    near_xyh: np.ndarray
    near_size: np.ndarray
    near_real: np.ndarray
    near_escape: np.ndarray
    edges: RoadView
    red: np.ndarray
    depart: np.ndarray
    signals: dict[int, SceneSignals]
    pace: np.ndarray
    stall: np.ndarray
    keep_way: np.ndarray
    lanes: dict[int, LaneDirections]
    follow_cap: np.ndarray
    memo_keys: np.ndarray

    @property
    def guarded(self) -> np.ndarray:
        """``[n]`` pairs some candidate of which could be masked (an obstacle near, a road edge, a red
        light, a green one, a stall to end, lanes to keep the way of)."""
        guarded = self.near_real.any(axis=1) | self.edges.road | self.red | self.depart | self.stall
        return guarded | self.keep_way | np.isfinite(self.follow_cap)


T = TypeVar("T")

# Share of ``guard_step_change`` a class's forward step may change by from one step to the next: vehicles
# all of it, cyclists half (their tokenized logs change by at most 0.3 m, vehicles' 0.8 m on WOMD), not
# pedestrians (they turn on the spot and step back).
STEP_CHANGE_SHARE = {AgentKind.VEHICLE: 1.0, AgentKind.PEDESTRIAN: np.inf, AgentKind.CYCLIST: 0.5}


class GuardGeometry:
    """Obstacles and road edges of the sampled pairs of an engine's rows (``templates [classes,V,3]``:
    the motion tokens; ``road_margin``: how far a candidate corner may lie beyond a road edge;
    ``green_rule``: whether riders at a green light with the way clear must move; ``road_ahead``: metres
    of each candidate's kept-up motion checked against the road edges, 0 for none; ``step_change``: metres
    by which a vehicle's forward step may change from its last one, :data:`STEP_CHANGE_SHARE` of it for
    the other classes, 0 for no such rule; ``stall_steps``: steps a rider that drove may stand with the way
    clear before it must set off, 0 for no such rule; ``wrong_way``: whether a vehicle may not turn or
    drive onto a lane against every lane there, :mod:`~trajeglish_env.sampler.lane_directions`;
    ``follow_decel``: the deceleration (m/s^2) at which a vehicle or cyclist must still be able to stop
    behind the box ahead, 0 for no such rule), with each row-agent's road-edge list kept between steps."""

    def __init__(
        self,
        templates: np.ndarray,
        road_margin: float = 0.0,
        green_rule: bool = True,
        escape: bool = False,
        road_ahead: float = 0.0,
        step_change: float = 0.0,
        stall_steps: int = 0,
        wrong_way: bool = False,
        follow_decel: float = 0.0,
    ):
        self.templates = np.asarray(templates, dtype=np.float64)
        self.road_margin = float(road_margin)
        self.green_rule = bool(green_rule)
        self.escape = bool(escape)
        self.road_ahead = float(road_ahead)
        self.move = np.hypot(self.templates[..., 0], self.templates[..., 1]).max(axis=1)  # per class
        share = np.array([STEP_CHANGE_SHARE[AgentKind(k)] for k in range(len(self.templates))])
        self.step_change = share * float(step_change) if step_change > 0 else np.full(len(share), np.inf)
        self.stall_steps = int(stall_steps)
        self.wrong_way = bool(wrong_way)
        self.follow_decel = float(follow_decel)
        self._lanes = SceneCache(LaneDirections.of, MAX_SCENES)
        self._columns = PaddedRows(0.0, last=True)
        self._links = PaddedRows(-1, last=True)
        self._cells = EdgeCells()
        self._signals = SceneCache(SceneSignals.of, 256)
        # road-edge answers per row-agent: the rule's (applies, limit), candidates' excess, their reach
        self._road_memo, self._excess_memo, self._reach_memo = (CandidateMemo() for _ in range(3))
        self._step_pairs = StepPairs()  # this step's pairs, for a later call with the same views

    def forget_step(self, remember: bool) -> None:
        """A step begins: the pairs kept from the last one are not read again; ``remember``: whether this
        step's calls keep theirs for the calls after them (:mod:`~trajeglish_env.sampler.pair_memo`: they
        pay where the step's drafts are guarded first, whose views the model's call mostly shares)."""
        self._step_pairs.clear()
        self._step_pairs.active = remember

    @classmethod
    def of(cls, templates: np.ndarray, config: SamplingConfig) -> GuardGeometry:
        """The geometry of the guard rules ``config`` sets, for the motion tokens ``templates``."""
        return cls(
            *(templates, config.guard_road_margin, config.guard_green, config.guard_escape),
            *(config.guard_road_ahead, config.guard_step_change, config.guard_stall_steps),
            *(config.guard_wrong_way, config.guard_follow_decel),
        )

    def pairs(
        self,
        rs: RowStates,
        rr: np.ndarray,
        who: np.ndarray,
        tt: np.ndarray,
        view: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Pairs:
        """The guard's view of agents ``who`` of rows ``rr`` about to be sampled at steps ``tt``; ``view``:
        which agents moved before each pair and their next states (default: as the rows say)."""
        return self.recall(rs, rr, who, tt, view)[0]

    def recall(
        self,
        rs: RowStates,
        rr: np.ndarray,
        who: np.ndarray,
        tt: np.ndarray,
        view: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[Pairs, np.ndarray]:
        """:meth:`pairs`, and ``[n]`` which of them an earlier call of this step computed from the same
        view (taken from it: :mod:`~trajeglish_env.sampler.pair_memo`, the same numbers). Without a view
        (or while the memory is off, :meth:`forget_step`) nothing is kept or taken."""
        if view is None or not self._step_pairs.active:
            return self._fresh_pairs(rs, rr, who, tt, view), np.zeros(len(rr), bool)
        key = view_key(view[0], view[1], rs.valid[rr, :, tt + 1])
        shape, epoch = (rs.B, rs.N), self._cells.epoch
        return self._step_pairs.recall(rr, who, tt, view, key, shape, epoch, partial(self._fresh_pairs, rs))

    def _fresh_pairs(
        self,
        rs: RowStates,
        rr: np.ndarray,
        who: np.ndarray,
        tt: np.ndarray,
        view: tuple[np.ndarray, np.ndarray] | None,
    ) -> Pairs:
        """:meth:`pairs` computed anew."""
        origin, size, kind = rs.mxyh[rr, who, tt], rs.size[rr, who], rs.kind[rr, who]
        extent = self.move[kind] + half_diagonal(size)  # candidate corners lie within this of the origin
        latest = seen_states(rs, rr, who, tt, view)
        *near, escape, tangled = neighbours(rs, rr, who, tt, origin, size, extent, latest, self.escape)
        padded = (
            self._columns.sync(rs.edges, lambda e: e[0]),  # type: ignore[index]
            self._links.sync(rs.edges, lambda e: e[1]),  # type: ignore[index]
            np.array([e[0].shape[1] for e in rs.edges]),
        )
        wheeled = kind != AgentKind.PEDESTRIAN  # cyclists keep to the road as vehicles do
        edges = road_view(self._cells, rs, rr, padded, self.road_margin)
        keys = memo_keys(origin, size, kind, edges.maps, self._cells.epoch)
        self._road_rule(edges, rr, who, origin, size, kind, keys, wheeled & (edges.maps >= 0))
        red, depart, signals = self._lights(rs, rr, tt, origin, size, extent, wheeled)
        clear = way_clear(origin, size, *near) & ~tangled  # one overlapping another box already is not pushed
        if self.green_rule:
            depart &= clear
        else:
            depart[:] = False
        # the forward distance of each vehicle's and cyclist's last move, model states t - 1 to t (in the
        # frame of the first); NaN for pedestrians and where there is no state at t - 1
        before = np.maximum(tt - 1, 0)
        prev = rs.mxyh[rr, who, before]
        d = origin[:, :2] - prev[:, :2]
        forward = d[:, 0] * np.cos(prev[:, 2]) + d[:, 1] * np.sin(prev[:, 2])
        known = (tt >= 1) & rs.valid[rr, who, before] & (kind != AgentKind.PEDESTRIAN)
        pace = np.where(known, forward, np.nan)
        cap = np.full(len(rr), np.inf)
        if self.follow_decel > 0 and wheeled.any():
            q = np.flatnonzero(wheeled)
            turn = np.where(known, np.angle(np.exp(1j * (origin[:, 2] - prev[:, 2]))), 0.0)
            state, present, velocity, moved = latest
            present = present[q].copy()
            present[np.arange(len(q)), who[q]] = False
            ahead = (state[q], rs.size[rr[q]], present, velocity[q] / STEP_SECONDS)
            riders = rs.kind[rr[q]] != AgentKind.PEDESTRIAN
            cap[q] = follow_caps(origin[q], size[q], pace[q], turn[q], *ahead, riders, self.follow_decel)
        stall = np.zeros(len(rr), bool)
        if self.stall_steps > 0:  # the history is read only where the rule may apply
            q = np.flatnonzero(stall_candidates(pace, clear) & ~red & ~depart)
            if len(q):
                hist = rs.mxyh[rr[q], who[q]], rs.valid[rr[q], who[q]]
                stall[q] = stalled(*hist, tt[q], self.stall_steps)
        keep_way, lanes = self._lane_rule(rs, rr, origin, kind)
        return Pairs(
            *(rr, who, tt, origin, size, kind, extent, *near, escape, edges, red, depart, signals, pace),
            *(stall, keep_way, lanes, cap, keys),
        )

    def _road_rule(
        self,
        edges: RoadView,
        rr: np.ndarray,
        who: np.ndarray,
        origin: np.ndarray,
        size: np.ndarray,
        kind: np.ndarray,
        keys: np.ndarray,
        on_map: np.ndarray,
    ) -> None:
        """Fill ``edges``' rule flags and limits of the vehicles and cyclists ``on_map [n]``
        (:func:`~trajeglish_env.sampler.guard_edges.road_rule`, remembered per row-agent): within reach of
        their candidates' corners, and of their kept-up motion's, the road must be safe to leave them
        unchecked."""
        v = np.flatnonzero(on_map)
        if not len(v):
            return
        reach = np.maximum(self.move[kind[v]], self.road_ahead) + half_diagonal(size[v])

        def measure(i: np.ndarray, j: np.ndarray) -> np.ndarray:
            q = np.unique(i)
            road, limit = road_rule(edges, v[q], origin[v[q]], size[v[q]], reach[q])
            answers = np.zeros((len(v), 2))
            answers[q, 0], answers[q, 1] = road, limit
            return answers[i, j]

        entries = np.broadcast_to(np.arange(2), (len(v), 2))
        got = self._road_memo.lookup(rr[v], who[v], keys[v], entries, np.ones((len(v), 2), bool), measure, 2)
        edges.road[v], edges.limit[v] = got[:, 0] > 0, got[:, 1]

    def _lane_rule(
        self, rs: RowStates, rr: np.ndarray, origin: np.ndarray, kind: np.ndarray
    ) -> tuple[np.ndarray, dict[int, LaneDirections]]:
        """``[n]`` the vehicles the wrong-way rule applies to (in a row whose map has lanes, and not against
        them already: a car parked against the traffic, or one overtaking in the oncoming lane, is left
        alone; one in a junction, where no lane may be near, is not: it may not leave it into a lane the
        wrong way), and the lane directions of their rows."""
        keep, lanes = np.zeros(len(rr), bool), {}
        if not self.wrong_way:
            return keep, lanes
        vehicles = kind == AgentKind.VEHICLE
        for row in np.unique(rr[vehicles]).tolist():
            sc = rs.scenes[row]
            ld = None if sc is None else self._lanes.get(sc)
            if ld is not None:
                lanes[row] = ld
        for ld, rows in _by_scene(lanes, list(lanes)):
            q = np.flatnonzero(vehicles & _among(rr, rows))
            keep[q] = ~ld.against(origin[q])  # off the lanes too: a junction is no way into the oncoming lane
        return keep, lanes

    def step_changes(self, p: Pairs, sel: np.ndarray, tokens: np.ndarray) -> np.ndarray:
        """``[m,c]`` how far (m) the forward step of candidates ``tokens [m,c]`` of pairs ``sel [m]`` differs
        from the agent's last one, in units of its class's limit (0 where the rule does not apply)."""
        kind = p.kind[sel]
        step = self.templates[kind[:, None], tokens, 0]
        change = np.abs(step - p.pace[sel][:, None]) / self.step_change[kind][:, None]
        return np.nan_to_num(change, nan=0.0)

    def jumps(self, p: Pairs, sel: np.ndarray, tokens: np.ndarray) -> np.ndarray:
        """``[m,c]`` candidates ``tokens [m,c]`` of pairs ``sel [m]`` whose forward step differs from the
        agent's last one by more than its class's speed-change limit (a car stopping dead from 20 m/s in
        one step, or jumping from 10 to 29 m/s and back)."""
        return self.step_changes(p, sel, tokens) > 1.0

    def _lights(
        self,
        rs: RowStates,
        rr: np.ndarray,
        tt: np.ndarray,
        origin: np.ndarray,
        size: np.ndarray,
        extent: np.ndarray,
        riders: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, dict[int, SceneSignals]]:
        """``[n]`` the vehicles and cyclists (``riders [n]``) with a red stop point within reach of a
        candidate, ``[n]`` those with a green one ahead on their lane, and their rows' signals."""
        red, green, signals = np.zeros(len(rr), bool), np.zeros(len(rr), bool), {}
        for row in np.unique(rr[riders]).tolist():
            sc = rs.scenes[row]
            ss = None if sc is None else self._signals.get(sc)
            if ss is not None:
                signals[row] = ss
        for ss, rows in _by_scene(signals, list(signals)):  # rows of one scene share its signals: one pass
            q = np.flatnonzero(riders & _among(rr, rows))
            red[q] = ss.near_red(origin[q, :2], tt[q], extent[q]).any(axis=1)
            green[q] = ss.green_ahead(origin[q], size[q, 0], tt[q])
        return red, green, signals

    def blocked(self, p: Pairs, sel: np.ndarray, tokens: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For pairs ``sel [m]`` and their candidate ``tokens [m,c]``: which would overlap an obstacle, and
        which would break a map rule ``[m,c]`` (take the vehicle off the road where the road-edge rule
        applies, across the stop line of a red light on its lane, leave it standing at a green one, or change
        its speed more than a step allows: :meth:`jumps`)."""
        collide, escape, off, jump = self.blocked_parts(p, sel, tokens)
        return collide | escape, off | jump

    def reach(
        self, p: Pairs, sel: np.ndarray, tokens: np.ndarray, allowed: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """For pairs ``sel [m]`` and their candidate ``tokens [m,c]`` that the one-step rules ``allowed``:
        the candidates the road-ahead rule looks at ``[m,c]`` (moving vehicles and cyclists under the
        road-edge rule) and their reach (:func:`~trajeglish_env.sampler.guard_ahead.road_reach`)."""
        step = self.templates[p.kind[sel][:, None], tokens]
        look = allowed & p.edges.road[sel][:, None] & (np.hypot(step[..., 0], step[..., 1]) >= AHEAD_MIN_MOVE)
        if self.road_ahead <= 0:
            look[:] = False
        reach = np.full(look.shape, AHEAD_CHECKS, np.int64)
        if not look.any():
            return reach, look

        def measure(i: np.ndarray, j: np.ndarray) -> np.ndarray:
            pick = sel[i]
            every = np.ones((len(i), 1), bool)
            return road_reach(
                p.edges, pick, p.origin[pick], p.size[pick], step[i, j][:, None], self.road_ahead, every
            )[:, 0]

        width = self.templates.shape[1]
        got = self._reach_memo.lookup(
            p.rows[sel], p.agents[sel], p.memo_keys[sel], tokens, look, measure, width
        )
        reach[look] = got[look].astype(np.int64)
        return reach, look

    def _excess(self, p: Pairs, sel: np.ndarray, tokens: np.ndarray, cand: np.ndarray) -> np.ndarray:
        """``[m,c]`` how far the most off-road corner of each candidate box (tokens ``[m,c]`` of pairs ``sel
        [m]``, poses ``cand [m,c,3]``) lies beyond a road edge (:meth:`RoadView.box_excess`, remembered)."""

        def measure(i: np.ndarray, j: np.ndarray) -> np.ndarray:
            return p.edges.box_excess(sel[i], cand[i, j][:, None], p.size[sel[i]])[:, 0]

        want = np.ones(tokens.shape, bool)
        width = self.templates.shape[1]
        return self._excess_memo.lookup(
            p.rows[sel], p.agents[sel], p.memo_keys[sel], tokens, want, measure, width
        )

    def _collisions(self, p: Pairs, sel: np.ndarray, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``[m,c]`` candidate poses ``cand [m,c,3]`` of pairs ``sel [m]`` overlapping an obstacle to avoid,
        and one only to escape (``Pairs.near_escape``)."""
        size = p.size[sel]
        collide, escape = np.zeros(cand.shape[:2], bool), np.zeros(cand.shape[:2], bool)
        if p.near_xyh.shape[1]:
            nx, ns, real = p.near_xyh[sel], p.near_size[sel], p.near_real[sel]
            dx = cand[:, :, None, 0] - nx[:, None, :, 0]
            dy = cand[:, :, None, 1] - nx[:, None, :, 1]
            limit = half_diagonal(size)[:, None] + half_diagonal(ns)  # [m,K]: circles apart, boxes apart
            i, v, k = np.nonzero(real[:, None] & (dx * dx + dy * dy < (limit * limit)[:, None]))
            if len(i):
                hit = overlaps(cand[i, v], size[i], nx[i, k], ns[i, k])
                soft = p.near_escape[sel][i, k]
                collide[i[hit & ~soft], v[hit & ~soft]] = True
                escape[i[hit & soft], v[hit & soft]] = True
        return collide, escape

    def blocked_parts(
        self, p: Pairs, sel: np.ndarray, tokens: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`blocked` split ``[m,c]``: overlaps with an obstacle to avoid, with one only to escape
        (``Pairs.near_escape``); the map rules; the speed-change rule (:meth:`jumps`) with the stall rule."""
        kind, size = p.kind[sel], p.size[sel]
        cand = to_global(p.origin[sel][:, None], self.templates[kind[:, None], tokens])  # [m,c,3]
        step = self.templates[kind[:, None], tokens, 0]
        # standing or creeping riders under the green or the stall rule: the step must grow by DEPART_GAIN
        # a step up to DEPART_PACE (NaN: no such need)
        need_go, need_stall = (
            np.where(flag, departure_need(p.pace[sel]), np.nan) for flag in (p.depart[sel], p.stall[sel])
        )
        kernels = pair_compiled()
        if kernels is not None:  # the same verdicts, compiled (pair_kernels.blocked_core)
            collide, escape, off, jump = (np.empty(tokens.shape, bool) for _ in range(4))
            near = (p.near_xyh[sel], p.near_size[sel], p.near_real[sel], p.near_escape[sel])
            rules = (p.follow_cap[sel], need_go, need_stall, p.pace[sel], self.step_change[kind])
            kernels.blocked_core(
                cand, np.ascontiguousarray(size), *near, step, *rules, collide, escape, off, jump
            )
        else:
            collide, escape = self._collisions(p, sel, cand)
            # no faster than lets it stop behind the box ahead (inf: no box), no slower than a departure
            off = (step > p.follow_cap[sel][:, None] + FOLLOW_SLACK) | (step < need_go[:, None])
            jump = self.jumps(p, sel, tokens) | (step < need_stall[:, None])
        q = np.flatnonzero(p.edges.road[sel])
        if len(q):
            off[q] |= self._excess(p, sel[q], tokens[q], cand[q]) > p.edges.limit[sel[q]][:, None]
        red = p.red[sel]
        for ss, rows in _by_scene(p.signals, np.unique(p.rows[sel][red]).tolist()):  # one pass per scene
            q = np.flatnonzero(red & _among(p.rows[sel], rows))
            pick = sel[q]
            near_red = ss.near_red(p.origin[pick, :2], p.t[pick], p.extent[pick])
            off[q] |= ss.violations(p.origin[pick, :2], cand[q, :, :2], p.t[pick], near_red)
        way = p.keep_way[sel]
        for ld, rows in _by_scene(p.lanes, np.unique(p.rows[sel][way]).tolist()):  # one pass per scene
            q = np.flatnonzero(way & _among(p.rows[sel], rows))
            off[q] |= ld.against(cand[q])
        return collide, escape, off, jump


def _by_scene(per_row: dict[int, T], rows: list[int]) -> list[tuple[T, list[int]]]:
    """``rows`` grouped by what they hold (``per_row``: a scene's signals or lanes per row; rows of one scene
    share them)."""
    groups: dict[int, tuple[T, list[int]]] = {}
    for row in rows:
        ss = per_row[row]
        groups.setdefault(id(ss), (ss, []))[1].append(row)
    return list(groups.values())


def _among(values: np.ndarray, rows: list[int]) -> np.ndarray:
    """``np.isin(values, rows)``, a comparison where ``rows`` is one row (a single env: every call)."""
    return values == rows[0] if len(rows) == 1 else np.isin(values, rows)
