"""One episode of one scene, apart from any RL API: roles, intra-timestep order, the external agents'
kinematics, routes and per-step outcomes. A :class:`~trajeglish_env.env.scene_batch.SceneBatch` runs
simulations (one per scene row) together with the NPC driver; the AEC env is a batch of one."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from trajeglish_env.batch_geometry import edge_rows, road_edges
from trajeglish_env.env.actions import action_towards, bicycle_step, class_limits, delta_step, token_step
from trajeglish_env.env.config import EnvConfig, RandomAgents, TrajeglishNPC
from trajeglish_env.env.drivers import RowView
from trajeglish_env.env.lane_routes import extended_routes
from trajeglish_env.env.observations import make_observer
from trajeglish_env.env.rewards import StepOutcome, collisions, offroad, step_reward
from trajeglish_env.env.routes import logged_paths
from trajeglish_env.env.scene_state import Kinematics, SceneState
from trajeglish_env.env.world import WorldView
from trajeglish_env.geometry import wrap_angle
from trajeglish_env.scenario import Scenario, agent_name
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary
from trajeglish_env.user_warnings import warn_at_caller


def agent_names(scenario: Scenario) -> list[str]:
    """Names of every agent of a scene, in index order."""
    return [agent_name(k, i) for k, i in zip(scenario.kind, scenario.track_id, strict=True)]


def episode_names(scenario: Scenario, external: np.ndarray, style: str) -> list[str]:
    """Names of every agent of an episode: by class and track id, the external agents ``agent_j`` instead
    (j: their place in ``external``) with ``style`` ``"slot"`` (EnvConfig.agent_names)."""
    names = agent_names(scenario)
    if style == "slot":
        for j, i in enumerate(external):
            names[int(i)] = f"agent_{j}"
    return names


def select_external(scenario: Scenario, spec: object, rng: np.random.Generator) -> np.ndarray:
    """Indices of the external agents, in their configured order; clear errors for unknown ids or agents
    absent at the current step (e.g. a scene whose sdc is not present)."""
    cur, sid = scenario.current_index, scenario.scenario_id
    present = scenario.valid[:, cur]
    if spec == "sdc":
        if not present[scenario.sdc]:
            raise ValueError(
                f"scenario {sid!r}: its sdc (agent {scenario.sdc}, track id "
                f"{scenario.track_id[scenario.sdc]}) is not present at the current step {cur}; "
                "choose external agents by track id"
            )
        return np.array([scenario.sdc], dtype=np.int64)
    if spec == "all":
        return np.flatnonzero(present)
    if isinstance(spec, RandomAgents):
        pool = np.flatnonzero(present)
        if spec.k > len(pool) and not spec.at_most:
            raise ValueError(
                f"scenario {sid!r}: RandomAgents(k={spec.k}) but only {len(pool)} agents are present "
                "(RandomAgents(k, at_most=True) takes them all in such scenes)"
            )
        if not spec.with_sdc:
            return rng.choice(pool, size=min(spec.k, len(pool)), replace=False).astype(np.int64)
        sdc = select_external(scenario, "sdc", rng)  # present, or the error saying it is not
        others = pool[pool != scenario.sdc]
        drawn = rng.choice(others, size=min(spec.k - 1, len(others)), replace=False)
        return np.concatenate([sdc, drawn]).astype(np.int64)
    ids = list(spec)  # type: ignore[call-overload]
    known = {int(t): i for i, t in enumerate(scenario.track_id)}
    unknown = [t for t in ids if t not in known]
    if unknown:
        raise ValueError(
            f"scenario {sid!r}: unknown agent id(s) {unknown} in the external (controlled) agents; "
            f"track ids present at step {cur}: {scenario.track_id[present].tolist()}"
        )
    if len(set(ids)) != len(ids):
        raise ValueError(f"scenario {sid!r}: external track ids must be unique, got {ids}")
    idx = np.array([known[t] for t in ids], dtype=np.int64)
    absent = [int(scenario.track_id[i]) for i in idx if not present[i]]
    if absent:
        raise ValueError(
            f"scenario {sid!r}: external agents {absent} are not present at the current step {cur}"
        )
    return idx


def acting_priority(
    order: object, external: np.ndarray, names: list[str], rng: np.random.Generator
) -> np.ndarray:
    """Priorities ``[N]`` (lower acts earlier) realising an order setting (see EnvConfig.order)."""
    n, k = len(names), len(external)
    prio = np.zeros(n)
    if order == "first":
        prio[external] = np.arange(k) - k
    elif order == "last":
        prio[external] = np.arange(k) + 1.0
    elif order == "random":
        prio = rng.permutation(n).astype(np.float64)
    else:
        index = {name: i for i, name in enumerate(names)}
        listed = list(order)  # type: ignore[call-overload]
        unknown = [a for a in listed if a not in index]
        if unknown:
            raise ValueError(f"order: unknown agent name(s) {unknown}; this scene's agents are {names[:30]}")
        prio[[index[a] for a in listed]] = np.arange(len(listed)) - len(listed)
    return prio


@dataclass(frozen=True)
class Roles:
    """Who is external (``external_index``, in configured order), the acting ``priority [N]`` (lower acts
    earlier) and the NPC driver's ``seed``, drawn from an episode's random stream."""

    external_index: np.ndarray
    priority: np.ndarray
    seed: int

    @classmethod
    def draw(cls, scenario: Scenario, config: EnvConfig, rng: np.random.Generator) -> Roles:
        """The roles of an episode (external agents, then order, then the seed: the stream's order)."""
        external = select_external(scenario, config.external, rng)
        names = episode_names(scenario, external, config.agent_names)
        priority = acting_priority(config.order, external, names, rng)
        return cls(external, priority, int(rng.integers(2**31 - 1)))

    def mask(self, n: int) -> np.ndarray:
        """``[n]`` True for the external agents."""
        out = np.zeros(n, dtype=bool)
        out[self.external_index] = True
        return out


def episode_horizon(scenario: Scenario, config: EnvConfig) -> int:
    """Steps of an episode: ``max_cycles``, else the rest of the log."""
    cur = scenario.current_index
    horizon = config.max_cycles if config.max_cycles is not None else scenario.num_steps - 1 - cur
    if horizon < 1:
        raise ValueError(f"scenario {scenario.scenario_id!r}: no steps after the current index {cur}")
    return horizon


@dataclass(frozen=True)
class AgentReport:
    """One external agent's result of a timestep, in the RL APIs' terms."""

    reward: float
    terminated: bool
    truncated: bool
    info: dict[str, Any]


class Simulation:
    """A running episode of one scene whose states live in ``row`` (its NPC driver's row)."""

    def __init__(
        self,
        scenario: Scenario,
        config: EnvConfig,
        vocabulary: MotionVocabulary | None,
        roles: Roles,
        row: RowView,
        horizon: int,
    ):
        self.sc, self.config, self.vocabulary = scenario, config, vocabulary
        cur = scenario.current_index
        self.dt = float(scenario.dt)
        self.horizon = horizon
        self.names = episode_names(scenario, roles.external_index, config.agent_names)
        self.external_index = roles.external_index
        self.external = roles.mask(scenario.num_agents)
        self.npc = scenario.valid[:, cur] & ~self.external
        self.policy_driven = self._policy_driven()
        self.priority = roles.priority
        self.seed = roles.seed  # the episode's draw seed (from the env's seed): policies may derive theirs
        self.driver = row
        self.retired = np.zeros(scenario.num_agents, dtype=bool)
        ext = self.external_index
        speed = scenario.speed()[:, cur]
        prev = max(cur - 1, 0)
        turn = wrap_angle(scenario.xyh[:, cur, 2] - scenario.xyh[:, prev, 2]) / self.dt
        turn = np.where(scenario.valid[:, prev] & (cur > 0), turn, 0.0)
        zeros = np.zeros(scenario.num_agents)
        self.kin = Kinematics(speed.copy(), zeros.copy(), zeros.copy(), turn)
        # routes: each external agent's logged path from the current step on, continued along the lanes
        # when the episode runs past the log (as far as the agent could drive in the extra time)
        beyond = cur + horizon - (scenario.num_steps - 1)
        if beyond > 0:
            self.routes = extended_routes(scenario, ext, beyond * self.dt * config.limits.max_speed)
        else:
            self.routes = logged_paths(scenario.xyh[ext, cur:], scenario.valid[ext, cur:], spacing=1.0)
        self.route_row = np.full(scenario.num_agents, -1, dtype=np.int64)  # agent -> its route's row
        self.route_row[ext] = np.arange(len(ext))
        self.progress = np.zeros(len(ext))
        self.collision_steps = np.zeros(len(ext), dtype=np.int64)  # steps spent in collision / off-road
        self.offroad_steps = np.zeros(len(ext), dtype=np.int64)
        self.last_collision = np.zeros(len(ext), dtype=bool)
        self.last_offroad = np.zeros(len(ext), dtype=bool)
        self.goal_paid = np.zeros(len(ext), dtype=bool)  # the goal reward is paid once per episode
        self.has_goal = self.routes.length >= config.reward.min_route_length
        if not self.has_goal.all():  # nothing to drive for: their reward is the penalties alone
            shown = shown_names(self.names, scenario, ext[~self.has_goal])
            warn_at_caller(
                f"scene {scenario.scenario_id!r}: external agent(s) {shown} "
                f"move less than RewardConfig.min_route_length ({config.reward.min_route_length:g} m) in the "
                "log: no goal and no progress reward, only penalties (infos 'has_goal' False)"
            )
        self.observer = make_observer(config.observation, scenario, config.obs)
        self.edges = road_edges(scenario)
        _warn_bad_starts(scenario, ext, self.names, self.edges, config.reward.offroad_margin)
        edge_columns, edge_links = edge_rows(self.edges)
        self.state = SceneState(
            row=row,
            size=scenario.size,
            kind=scenario.kind,
            dt=self.dt,
            edge_columns=edge_columns,
            edge_links=edge_links,
            offroad_margin=config.reward.offroad_margin,
            map_points=self.observer.points,
            map_category=self.observer.category,
            obs=config.obs,
            external_index=ext,
            retired=self.retired,
            routes=self.routes,
            route_row=self.route_row,
            progress=self.progress,
            has_goal=self.has_goal,
            kin=self.kin,
            signal_xy=scenario.signal_xy,
            signal_state=scenario.signal_state,
        )
        self.steps = 0

    @property
    def t(self) -> int:
        return self.driver.t

    def external_order(self) -> list[int]:
        """Live external agents still to act this step, in order."""
        return [int(a) for a in self.driver.external_order() if not self.retired[a]]

    def finish_step(
        self, computed: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    ) -> tuple[np.ndarray, StepOutcome]:
        """Outcome of the step just completed for the live external agents (returned with it), from this
        scene's entry of :meth:`~trajeglish_env.env.batch_outcomes.BatchGeometry.outcomes`."""
        live, hit, off, s_new = computed
        rows = self.route_row[live]
        gained = s_new - self.progress[rows]
        self.progress[rows] = s_new
        goal = self.has_goal[rows] & (s_new >= self.routes.length[rows] - self.config.reward.goal_tolerance)
        # collisions and off-road excursions are penalised once, when they start
        new_hit, new_off = hit & (self.last_collision[rows] == 0), off & (self.last_offroad[rows] == 0)
        self.collision_steps[rows] += hit
        self.offroad_steps[rows] += off
        self.last_collision[rows], self.last_offroad[rows] = hit, off
        # the goal too is paid once, when first reached (an agent that drives on may park there)
        new_goal = goal & ~self.goal_paid[rows]
        self.goal_paid[rows] |= goal
        outcome = step_reward(
            self.config.reward,
            np.where(self.has_goal[rows], gained, 0.0),  # no goal, no progress reward (progress_m counts on)
            self.routes.length[rows],
            new_hit,
            new_off,
            new_goal,
            self.kin.accel[live],
            self.kin.lateral[live],
        )
        self.steps += 1
        return live, replace(outcome, collision=hit, offroad=off, goal=goal)

    def _policy_driven(self) -> np.ndarray:
        """``[N]`` agents whose motion a policy makes (drawn by class; the others replay the log, drawn
        grey): no NPC with ``npc="replay"``; with Trajeglish NPCs that drive entering agents, also the agents
        the log brings in after the current step."""
        npc = self.config.npc
        if npc == "replay":
            return np.zeros_like(self.npc)
        driven = self.npc.copy()
        if isinstance(npc, TrajeglishNPC) and npc.drive_entering:
            cur = self.sc.current_index
            driven |= self.sc.valid[:, cur + 1 :].any(1) & ~self.sc.valid[:, cur] & ~self.external
        return driven

    def agent_info(
        self, a: int, collision: bool = False, offroad: bool = False, goal: bool = False
    ) -> dict[str, Any]:
        """External agent ``a``'s info: this step's flags, whether its route has a goal, its progress so
        far and whether it has reached its goal at some step (at reset: no flags, no progress, the same
        keys as after a step)."""
        row = self.route_row[a]
        has_goal = bool(self.has_goal[row])
        done = min(float(self.progress[row] / max(self.routes.length[row], 1e-6)), 1.0) if has_goal else 1.0
        return {
            "collision": collision,
            "offroad": offroad,
            "goal": goal,
            "has_goal": has_goal,  # a route of min_route_length m or more (one parked in the log has none)
            "progress_m": float(self.progress[row]),
            "route_fraction": done,  # as the observation reads it: 1 on a route with no goal
            "collision_steps": int(self.collision_steps[row]),
            "offroad_steps": int(self.offroad_steps[row]),
            "goal_reached": bool(self.goal_paid[row]),
        }

    def report(self, live: np.ndarray, out: StepOutcome) -> dict[str, AgentReport]:
        """Rewards, flags and infos of the live external agents after :meth:`finish_step`; a finished agent
        is retired (it leaves the scene at the next step)."""
        truncated = self.horizon_reached
        r = self.config.reward
        done = (
            (r.terminate_on_collision & out.collision)
            | (r.terminate_on_offroad & out.offroad)
            | (r.terminate_on_goal & out.goal)
        )
        reports = {}
        for k, a in enumerate(live.tolist()):
            reports[self.names[a]] = AgentReport(
                reward=float(out.reward[k]),
                terminated=bool(done[k]),
                truncated=bool(truncated and not done[k]),
                info=self.agent_info(a, bool(out.collision[k]), bool(out.offroad[k]), bool(out.goal[k])),
            )
        self.retired[live[done | truncated]] = True
        return reports

    @property
    def horizon_reached(self) -> bool:
        return self.steps >= self.horizon

    @property
    def has_live_agents(self) -> bool:
        """Some external agent is still in the episode."""
        return bool((~self.retired[self.external_index]).any())

    def index_of(self, agent: str) -> int:
        """Index in the scene of an external agent's name."""
        for i in self.external_index:
            if self.names[i] == agent:
                return int(i)
        known = sorted(self.names[i] for i in self.external_index)
        raise KeyError(f"no external agent named {agent!r}; external agents: {known}")

    def action_towards(self, agent: int, target: np.ndarray) -> np.ndarray | int:
        """The action that brings external ``agent`` closest to state ``target [3]`` at the next step."""
        templates = self.vocabulary.templates[self.sc.kind[agent]] if self.vocabulary is not None else None
        return action_towards(
            self.config.action,
            self.driver.xyh[agent, self.t],
            float(self.kin.speed[agent]),
            target,
            float(self.sc.size[agent, 0]),
            class_limits(int(self.sc.kind[agent]), self.config.limits),
            self.dt,
            templates,
            self.names[agent],
        )

    def view(self) -> WorldView:
        """The world as it stands now (mid-step: who has moved so far)."""
        return WorldView(
            self.sc, self.driver.xyh, self.driver.valid, self.t, self.driver.moved(), self.external, self.npc
        )


def apply_actions(
    sims: Sequence[Simulation], agents: Sequence[int], actions: Sequence[np.ndarray | int]
) -> np.ndarray:
    """Next states ``[n,3]`` of external agent ``agents[i]`` of ``sims[i]`` under its (validated) action
    ``actions[i]``, each action type in one vectorized step (continuous actions: one bicycle step per
    class's limits, speed, braking and grip, :func:`~trajeglish_env.env.actions.class_limits`); the agents'
    kinematics are updated."""
    n = len(sims)
    now = np.stack([s.driver.xyh[a, s.t] for s, a in zip(sims, agents, strict=True)])
    speed = np.array([s.kin.speed[a] for s, a in zip(sims, agents, strict=True)], dtype=np.float64)
    dt = np.array([s.dt for s in sims])
    kind = np.array([s.sc.kind[a] for s, a in zip(sims, agents, strict=True)], dtype=np.int64)
    nxt, v_next = np.zeros((n, 3)), np.zeros(n)
    groups: dict[object, list[int]] = {}
    for i, s in enumerate(sims):
        key = (
            class_limits(int(kind[i]), s.config.limits)
            if s.config.action == "continuous"
            else s.config.action
        )
        groups.setdefault(key, []).append(i)
    for key, rows in groups.items():
        moved = np.stack([np.asarray(actions[i]) for i in rows])
        if key == "delta":
            nxt[rows] = delta_step(now[rows], moved)
        elif key == "token":
            tables = np.stack([sims[i].vocabulary.templates[kind[i]] for i in rows])  # type: ignore[union-attr]
            nxt[rows] = token_step(now[rows], tables, moved)
        else:
            length = np.array([sims[i].sc.size[agents[i], 0] for i in rows])
            nxt[rows], v_next[rows] = bicycle_step(now[rows], speed[rows], moved, length, key, dt[rows])  # type: ignore[arg-type]
            continue
        d = nxt[rows, :2] - now[rows, :2]
        forward = np.cos(now[rows, 2]) * d[:, 0] + np.sin(now[rows, 2]) * d[:, 1]
        v_next[rows] = np.hypot(d[:, 0], d[:, 1]) / dt[rows] * np.where(forward >= 0, 1.0, -1.0)
    yaw = wrap_angle(nxt[:, 2] - now[:, 2]) / dt
    accel = (v_next - speed) / dt
    for i, (s, a) in enumerate(zip(sims, agents, strict=True)):
        kin = s.kin
        kin.accel[a], kin.lateral[a], kin.yaw_rate[a], kin.speed[a] = (
            accel[i],
            v_next[i] * yaw[i],
            yaw[i],
            v_next[i],
        )
    return nxt


def shown_names(names: list[str], scenario: Scenario, agents: np.ndarray) -> str:
    """Up to 5 of ``agents`` by their episode names, each slot name with its car (``agent_0
    (vehicle_81)``), for a warning."""
    shown = []
    for a in agents[:5]:
        track = agent_name(scenario.kind[a], scenario.track_id[a])
        shown.append(names[a] if names[a] == track else f"{names[a]} ({track})")
    return ", ".join(shown) + (f" and {len(agents) - 5} more" if len(agents) > 5 else "")


def _warn_bad_starts(
    scenario: Scenario, ext: np.ndarray, names: list[str], edges: Any, margin: float
) -> None:
    """Name the external agents whose episode is lost before they act: overlapping another agent, or a
    vehicle off the road, at the current step (WOMD's parked cars and crowded pedestrians: 7 of the shared
    scene's 50 agents under ``external="all"``), as a reset names those without a goal."""
    cur = scenario.current_index
    xyh, valid = scenario.xyh[:, cur], scenario.valid[:, cur]
    hit = collisions(xyh, valid, scenario.size, ext)
    off = offroad(xyh[ext], scenario.size[ext], scenario.kind[ext], edges, margin)
    for flags, what in ((hit, "overlapping another agent"), (off, f"off the road (more than {margin:g} m)")):
        if flags.any():
            shown = shown_names(names, scenario, ext[flags])
            warn_at_caller(
                f"scene {scenario.scenario_id!r}: external agent(s) {shown} "
                f"start {what}: their first step already counts it (a penalty, the episode ended under the "
                "default RewardConfig)"
            )
