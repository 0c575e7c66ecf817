"""NPC policies: the documented interface and the rule-based ones (log replay, constant velocity, and the
Intelligent Driver Model along each agent's logged path). The Trajeglish model is the default NPC policy;
it is run by the rollout engine (:mod:`trajeglish_env.env.drivers`), not through this interface.

The NPC interface (any object with these two methods can drive the NPCs)::

    class MyNPCs:
        def reset(self, scenario: Scenario, npc: np.ndarray, current_index: int, seed: int) -> None:
            ...  # npc [N] bool: the agents this policy drives from current_index on

        def act(self, view: WorldView, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            ...  # next states [k,3] and validity [k] of ``agents`` (indices, k >= 1) at step view.t + 1

``act`` is called once per group of consecutive NPCs in the intra-timestep order (the NPCs between two
external agents), so a group sees every move made before it; all of it is vectorized over the group.

Episodes may run past the end of the log (``max_cycles``): agents the log brings in later are handed to
the policy where their log ends (``act`` is then called for them too). A policy that can only play the log
says so with an optional ``max_steps(scenario, current_index) -> int`` (steps it can drive after
``current_index``); the env refuses longer episodes with it instead of cutting them short.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from trajeglish_env.env.routes import Paths, logged_paths
from trajeglish_env.env.world import WorldView
from trajeglish_env.metrics.boxes import box_collisions
from trajeglish_env.sampler.guard_signals import SceneSignals
from trajeglish_env.scenario import AgentKind, Scenario


@runtime_checkable
class NPCPolicy(Protocol):
    """Drives the NPCs of an episode (see the module docstring)."""

    def reset(self, scenario: Scenario, npc: np.ndarray, current_index: int, seed: int) -> None:
        """Start an episode: ``npc`` marks the agents this policy drives from ``current_index``."""

    def act(self, view: WorldView, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Next states ``[k,3]`` of ``agents`` given the world now, and whether each could act."""


def log_steps(scenario: Scenario, current_index: int) -> int:
    """Steps of the log after ``current_index``: what log-bound policies can play."""
    return scenario.num_steps - 1 - current_index


class ReplayNPC:
    """NPCs follow the log exactly (episodes end with the log)."""

    max_steps = staticmethod(log_steps)

    def reset(self, scenario: Scenario, npc: np.ndarray, current_index: int, seed: int) -> None:
        """Prepare for a new episode (see the NPC interface)."""
        self.scenario = scenario

    def act(self, view: WorldView, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Next states and validity of ``agents`` (see the NPC interface)."""
        t1 = view.t + 1
        if t1 >= self.scenario.num_steps:
            return np.zeros((len(agents), 3)), np.zeros(len(agents), dtype=bool)
        return self.scenario.xyh[agents, t1].copy(), self.scenario.valid[agents, t1].copy()


class ConstantVelocityNPC:
    """NPCs keep the velocity (and heading) of their last step."""

    def reset(self, scenario: Scenario, npc: np.ndarray, current_index: int, seed: int) -> None:
        """Prepare for a new episode (see the NPC interface)."""
        self.dt = float(scenario.dt)

    def act(self, view: WorldView, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Next states and validity of ``agents`` (see the NPC interface)."""
        t = view.t
        now = view.xyh[agents, t]
        before = view.xyh[agents, max(t - 1, 0)]
        ok = view.valid[agents, max(t - 1, 0)] & (t > 0)
        step = np.where(ok[:, None], now[:, :2] - before[:, :2], 0.0)
        nxt = now.copy()
        nxt[:, :2] += step
        return nxt, np.ones(len(agents), dtype=bool)


@dataclass(frozen=True)
class IDMParams:
    """Intelligent Driver Model parameters (Treiber et al. 2000) and the leader search along the path.

    The desired speed is the agent's highest logged speed (at least ``min_desired_speed``); a path whose
    log ends slower than ``stop_speed`` ends with a stopped obstacle (the agent stops where the log
    stopped), otherwise it is extended straight by ``path_extension`` m. Another agent is a leader when its
    box would touch this agent's box (widened by ``lateral_margin`` on each side) somewhere ahead on its path
    within ``lookahead`` m; the gap is the path length free before that place. An agent yields to crossing
    traffic: another agent whose constant-velocity motion over the next ``yield_horizon`` s
    enters the path ahead (at an angle of more than 30 degrees to it) before this agent can be there plus
    ``yield_margin`` s is a stopped obstacle where it enters (0 s: no yielding). A vehicle or cyclist
    stops at the stop line of a signal red on its lane ahead (a stopped obstacle there) when it can stop
    before it braking at ``max_brake``; closer, it drives on (it ran every red light before stop 81).
    """

    accel: float = 1.5
    comfort_brake: float = 2.0
    max_brake: float = 8.0
    time_headway: float = 1.5
    min_gap: float = 2.0
    delta: float = 4.0
    lookahead: float = 50.0
    lateral_margin: float = 0.5
    yield_horizon: float = 3.0
    yield_margin: float = 1.0
    min_desired_speed: float = 1.0
    stop_speed: float = 1.0
    path_extension: float = 100.0
    spacing: float = 1.0


class IDMNPC:
    """IDM along each NPC's logged path, the leader found on that path (vectorized over agents; episodes
    end with the log, where the paths end)."""

    max_steps = staticmethod(log_steps)

    def __init__(self, params: IDMParams = IDMParams()):
        self.params = params

    def reset(self, scenario: Scenario, npc: np.ndarray, current_index: int, seed: int) -> None:
        """Prepare for a new episode (see the NPC interface)."""
        p = self.params
        self.scenario = scenario
        future = scenario.valid[:, current_index:]
        speed = scenario.speed()[:, current_index:]
        last = future.shape[1] - 1 - np.argmax(future[:, ::-1], axis=1)
        end_speed = speed[np.arange(scenario.num_agents), last]
        self.stops_at_end = end_speed < p.stop_speed
        extension = np.where(self.stops_at_end, 0.0, p.path_extension)
        self.paths: Paths = logged_paths(scenario.xyh[:, current_index:], future, p.spacing, extension)
        self.s = np.zeros(scenario.num_agents)
        self.v = np.where(scenario.valid[:, current_index], speed[:, 0], 0.0)
        self.v0 = np.maximum(np.where(future, speed, 0.0).max(axis=1), p.min_desired_speed)
        self.signals = SceneSignals.of(scenario)

    def _leaders(
        self, agents: np.ndarray, state: np.ndarray, present: np.ndarray, velocity: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Gap ``[G,N]`` (m, bumper to bumper; inf where agent j does not lead agent i on i's path) and
        leader speed along the path ``[G,N]``; only pairs within ``lookahead`` m are examined."""
        p, paths, sc = self.params, self.paths, self.scenario
        g, n = len(agents), sc.num_agents
        s = self.s[agents]
        here, _ = paths.at(agents, s)
        reach_far = p.lookahead + sc.size[agents, 0][:, None] + sc.size[None, :, 0]
        close = np.linalg.norm(here[:, None] - state[None, :, :2], axis=-1) <= reach_far
        close &= present[None, :] & (np.arange(n)[None, :] != agents[:, None])
        gi, j = np.nonzero(close)
        gap = np.full((g, n), np.inf)
        v_lead = np.zeros((g, n))
        if len(gi) == 0:
            return gap, v_lead
        i = agents[gi]
        width = int(np.ceil(p.lookahead / p.spacing)) + 1
        idx = np.minimum(
            np.floor(s[gi] / p.spacing).astype(np.int64)[:, None] + np.arange(width),
            (paths.count[i] - 1)[:, None],
        )
        # the first place along i's path where its box (widened by the lateral margin) would touch j's box
        points = paths.points[i[:, None], idx]  # [pairs, W, 2]
        radius = np.hypot(sc.size[:, 0], sc.size[:, 1]) / 2
        d = np.hypot(points[..., 0] - state[j, None, 0], points[..., 1] - state[j, None, 1])
        maybe = d < (radius[i] + radius[j] + p.lateral_margin)[:, None]
        pk, wk = np.nonzero(maybe)
        touch = np.zeros(maybe.shape, bool)
        if len(pk):
            box = np.column_stack([points[pk, wk], paths.heading[i[pk], idx[pk, wk]]])
            wide = sc.size[i[pk]] + np.array([0.0, 2 * p.lateral_margin])
            touch[pk, wk] = box_collisions(box, wide, state[j[pk]], sc.size[j[pk]])
        first = np.argmax(touch, axis=1)
        pair = np.arange(len(gi))
        # only agents ahead lead (a follower within the margin of the rear bumper never stops the agent):
        # first == 0 is one within the margin ahead already, no room to go on
        h0 = paths.heading[i, idx[:, 0]]
        ahead = (state[j, 0] - here[gi, 0]) * np.cos(h0) + (state[j, 1] - here[gi, 1]) * np.sin(h0) > 0
        lead = touch.any(axis=1) & ahead
        before = idx[pair, np.maximum(first - 1, 0)]
        gap[gi, j] = np.where(lead, np.maximum(before * p.spacing - s[gi], 0.0), np.inf)
        heading = paths.heading[i, idx[pair, first]]
        v_along = np.maximum(velocity[j, 0] * np.cos(heading) + velocity[j, 1] * np.sin(heading), 0.0)
        cross = self._crossing_gaps(i, j, s[gi], idx, points, state, velocity)
        yields = cross < gap[gi, j]
        gap[gi, j] = np.where(yields, cross, gap[gi, j])
        v_lead[gi, j] = np.where(yields, 0.0, v_along)
        return gap, v_lead

    def _crossing_gaps(
        self,
        i: np.ndarray,
        j: np.ndarray,
        s: np.ndarray,
        idx: np.ndarray,
        points: np.ndarray,
        state: np.ndarray,
        velocity: np.ndarray,
    ) -> np.ndarray:
        """Per pair (agent ``i`` at ``s`` on its path, whose next path points are ``points [P,W,2]`` at
        indices ``idx [P,W]``; agent ``j``): the gap (m) to where ``j`` will cross ``i``'s path, where ``i``
        must yield to it (see :class:`IDMParams`), else inf."""
        p, sc = self.params, self.scenario
        out = np.full(len(i), np.inf)
        moving = np.hypot(velocity[j, 0], velocity[j, 1]) > 0.5
        if p.yield_horizon <= 0 or not moving.any():
            return out
        q = np.flatnonzero(moving)
        tau = np.arange(1, int(round(p.yield_horizon / 0.25)) + 1) * 0.25  # [K] s
        pred = state[j[q], None, :2] + velocity[j[q], None, :] * tau[None, :, None]  # [Q,K,2]
        d2 = ((points[q][:, None] - pred[:, :, None]) ** 2).sum(-1)  # [Q,K,W]
        best = np.argmin(d2, axis=2)
        rows = np.arange(len(q))[:, None]
        near = d2[rows, np.arange(len(tau))[None, :], best]
        at = idx[q][rows, best]  # [Q,K]
        s_at = at * p.spacing
        reach = sc.size[i[q], 1] / 2 + sc.size[j[q], 0] / 2 + p.lateral_margin
        motion = np.arctan2(velocity[j[q], 1], velocity[j[q], 0])
        across = np.abs(np.cos(motion[:, None] - self.paths.heading[i[q, None], at])) < np.cos(np.pi / 6)
        enters = (near <= reach[:, None] ** 2) & across & (s_at > s[q, None])
        hit = enters.any(axis=1)
        k = np.argmax(enters, axis=1)
        conflict = s_at[np.arange(len(q)), k]
        gap = conflict - s[q] - (sc.size[i[q], 0] + sc.size[j[q], 1]) / 2
        arrive = np.maximum(gap, 0.0) / np.maximum(self.v[i[q]], 1.0)  # s until i's front is there
        must = hit & (tau[k] < arrive + p.yield_margin)
        out[q[must]] = gap[must]
        return out

    def act(self, view: WorldView, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Next states and validity of ``agents`` (see the NPC interface)."""
        p, paths, sc = self.params, self.paths, self.scenario
        agents = np.asarray(agents, dtype=np.int64)
        state, present, velocity = view.latest()
        s, v = self.s[agents], self.v[agents]
        gap, v_lead = self._leaders(agents, state, present, velocity)
        # the end of a path that stops in the log is a stopped obstacle
        end_gap = np.where(
            self.stops_at_end[agents], paths.length[agents] - s - sc.size[agents, 0] / 2, np.inf
        )
        gap = np.concatenate(
            [gap, end_gap[:, None], self._red_gap(agents, state, v, view.t)[:, None]], axis=1
        )
        v_lead = np.concatenate([v_lead, np.zeros((len(agents), 2))], axis=1)
        nearest = np.argmin(gap, axis=1)
        g = gap[np.arange(len(agents)), nearest]
        dv = v - v_lead[np.arange(len(agents)), nearest]
        free = 1.0 - (v / self.v0[agents]) ** p.delta
        s_star = p.min_gap + np.maximum(
            0.0, v * p.time_headway + v * dv / (2 * np.sqrt(p.accel * p.comfort_brake))
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            interaction = np.where(np.isfinite(g), (s_star / np.maximum(g, 0.1)) ** 2, 0.0)
        acc = np.clip(p.accel * (free - interaction), -p.max_brake, p.accel)
        dt = view.dt
        v_next = np.maximum(v + acc * dt, 0.0)
        s_next = np.minimum(s + (v + v_next) / 2 * dt, paths.length[agents])
        v_next = np.where(s_next >= paths.length[agents], np.minimum(v_next, (s_next - s) / dt), v_next)
        xy, h = paths.at(agents, s_next)
        nxt = np.concatenate([xy, h[:, None]], axis=1)
        # never drive into a box: a move that would overlap an agent it is clear of now is not made
        hold = self._blocked(agents, state[agents], nxt, state, present)
        nxt[hold] = state[agents[hold]]
        s_next, v_next = np.where(hold, s, s_next), np.where(hold, 0.0, v_next)
        self.s[agents], self.v[agents] = s_next, v_next
        return nxt, np.ones(len(agents), dtype=bool)

    def _red_gap(self, agents: np.ndarray, state: np.ndarray, v: np.ndarray, t: int) -> np.ndarray:
        """``[k]`` metres to the stop line of a red signal ahead on each agent's lane where it can still stop
        before it (inf elsewhere, and for pedestrians)."""
        out = np.full(len(agents), np.inf)
        riders = self.scenario.kind[agents] != AgentKind.PEDESTRIAN
        if self.signals is None or not riders.any():
            return out
        q = agents[riders]
        gap = self.signals.red_gap(state[q], self.scenario.size[q, 0], np.full(len(q), t))
        stoppable = gap >= v[riders] ** 2 / (2 * self.params.max_brake)  # closer: through on amber
        out[riders] = np.where(stoppable, gap, np.inf)
        return out

    def _blocked(
        self, agents: np.ndarray, now: np.ndarray, nxt: np.ndarray, state: np.ndarray, present: np.ndarray
    ) -> np.ndarray:
        """``[G]`` agents whose box at ``nxt [G,3]`` would overlap another present agent's latest box
        ``state [N,3]`` that their box at ``now [G,3]`` does not overlap."""
        size = self.scenario.size
        radius = np.hypot(size[:, 0], size[:, 1]) / 2
        reach = radius[agents][:, None] + radius[None, :] + np.hypot(*(nxt[:, :2] - now[:, :2]).T)[:, None]
        close = present[None, :] & (np.arange(len(size))[None, :] != agents[:, None])
        close &= np.hypot(*(now[:, None, :2] - state[None, :, :2]).transpose(2, 0, 1)) < reach
        g, j = np.nonzero(close)
        out = np.zeros(len(agents), bool)
        if len(g):
            a = agents[g]
            hit = box_collisions(nxt[g], size[a], state[j], size[j]) & ~box_collisions(
                now[g], size[a], state[j], size[j]
            )
            out[g[hit]] = True
        return out


RULE_BASED = {"replay": ReplayNPC, "constant_velocity": ConstantVelocityNPC, "idm": IDMNPC}


def make_npc_policy(name: str) -> NPCPolicy:
    """A fresh rule-based NPC policy by name (``replay``, ``constant_velocity`` or ``idm``)."""
    if name not in RULE_BASED:
        raise ValueError(f"unknown rule-based NPC policy {name!r}; expected one of {sorted(RULE_BASED)}")
    return RULE_BASED[name]()
