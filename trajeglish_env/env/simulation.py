"""One episode of one scene, apart from any RL API: roles, intra-timestep order, the step driver, the
external agents' kinematics and routes, observations and per-step outcomes. The AEC env
(:mod:`trajeglish_env.env.aec`) is a thin PettingZoo adapter around it."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from trajeglish_env.env.actions import bicycle_step, delta_step, token_step
from trajeglish_env.env.batch_geometry import edge_rows
from trajeglish_env.env.batch_outcomes import BatchGeometry
from trajeglish_env.env.config import EnvConfig, RandomAgents
from trajeglish_env.env.drivers import EngineDriver, OrderedDriver, StepDriver
from trajeglish_env.env.npc import NPCPolicy
from trajeglish_env.env.observations import EgoState, Picture, make_observer
from trajeglish_env.env.rewards import StepOutcome, road_edges, step_reward
from trajeglish_env.env.routes import logged_paths
from trajeglish_env.env.world import WorldView
from trajeglish_env.geometry import wrap_angle
from trajeglish_env.scenario import AgentKind, Scenario
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary


def agent_name(kind: int, track_id: int) -> str:
    """PettingZoo-style agent name, e.g. ``vehicle_2406``."""
    return f"{AgentKind(int(kind)).name.lower()}_{int(track_id)}"


def agent_names(scenario: Scenario) -> list[str]:
    """Names of every agent of a scene, in index order."""
    return [agent_name(k, i) for k, i in zip(scenario.kind, scenario.track_id, strict=True)]


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
        if spec.k > len(pool):
            raise ValueError(
                f"scenario {sid!r}: RandomAgents(k={spec.k}) but only {len(pool)} agents are present"
            )
        return rng.choice(pool, size=spec.k, replace=False).astype(np.int64)
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


@dataclass
class Kinematics:
    """Per-agent speed, last accelerations and yaw rate of the external agents (arrays over all agents)."""

    speed: np.ndarray
    accel: np.ndarray
    lateral: np.ndarray
    yaw_rate: np.ndarray


class Simulation:
    """A running episode (see the module docstring). ``npc`` is an NPCPolicy, or a Checkpoint for Trajeglish
    NPCs sampled with ``settings`` (a TrajeglishNPC), in their own engine or in row ``shared[1]`` of a
    batched environment's engine ``shared[0]``."""

    def __init__(
        self,
        scenario: Scenario,
        config: EnvConfig,
        npc: object,
        vocabulary: MotionVocabulary | None,
        rng: np.random.Generator,
        settings: object = None,
        shared: tuple[object, int] | None = None,
    ):
        self.sc, self.config, self.vocabulary = scenario, config, vocabulary
        cur = scenario.current_index
        self.dt = float(scenario.dt)
        remaining = scenario.num_steps - 1 - cur
        self.horizon = config.max_cycles if config.max_cycles is not None else remaining
        if self.horizon < 1:
            raise ValueError(f"scenario {scenario.scenario_id!r}: no steps after the current index {cur}")
        self.names = agent_names(scenario)
        self.external_index = select_external(scenario, config.external, rng)
        self.external = np.zeros(scenario.num_agents, dtype=bool)
        self.external[self.external_index] = True
        self.npc = scenario.valid[:, cur] & ~self.external
        self.priority = acting_priority(config.order, self.external_index, self.names, rng)
        seed = int(rng.integers(2**31 - 1))
        self.driver: StepDriver
        if isinstance(npc, NPCPolicy):
            self.driver = OrderedDriver(npc, scenario, self.external, self.horizon, self.priority, seed)
        else:
            self.driver = EngineDriver(
                npc,
                scenario,
                self.external,
                self.horizon,
                self.priority,
                seed,
                settings,
                externals_first=config.order == "first",
                shared=shared,
            )
        self.retired = np.zeros(scenario.num_agents, dtype=bool)
        ext = self.external_index
        speed = scenario.speed()[:, cur]
        prev = max(cur - 1, 0)
        turn = wrap_angle(scenario.xyh[:, cur, 2] - scenario.xyh[:, prev, 2]) / self.dt
        turn = np.where(scenario.valid[:, prev] & (cur > 0), turn, 0.0)
        zeros = np.zeros(scenario.num_agents)
        self.kin = Kinematics(speed.copy(), zeros.copy(), zeros.copy(), turn)
        # routes: each external agent's logged path from the current step on
        self.routes = logged_paths(scenario.xyh[ext, cur:], scenario.valid[ext, cur:], spacing=1.0)
        self.route_row = np.full(scenario.num_agents, -1, dtype=np.int64)  # agent -> its route's row
        self.route_row[ext] = np.arange(len(ext))
        self.progress = np.zeros(len(ext))
        self.collision_steps = np.zeros(len(ext), dtype=np.int64)  # steps spent in collision / off-road
        self.offroad_steps = np.zeros(len(ext), dtype=np.int64)
        self.last_collision = np.zeros(len(ext), dtype=bool)
        self.last_offroad = np.zeros(len(ext), dtype=bool)
        self.has_goal = self.routes.length >= config.reward.min_route_length
        self.observer = make_observer(config.observation, scenario, config.obs)
        self.edges = road_edges(scenario)
        self.edge_columns, self.edge_links = edge_rows(self.edges)
        self.geometry = BatchGeometry()  # this scene's own; a batched env computes all its scenes at once
        self.prepared: tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] | None = None
        self.steps = 0

    # ------------------------------------------------------------------ the step protocol
    @property
    def t(self) -> int:
        return self.driver.t

    def advance(self) -> int | None:
        """The next external agent (index) whose action is needed, or None when the step is complete.
        Retired external agents are taken out of the scene when their turn comes."""
        while True:
            agent = self.driver.advance()
            if agent is None or not self.retired[agent]:
                return agent
            self.driver.supply(agent, np.zeros(3), valid=False)

    def ready_for_batch(self) -> bool:
        """With a shared engine (a batched env): True once every live external agent of this step has
        acted (retired ones are taken out now), i.e. the NPCs can be decoded with the other scenes."""
        if not getattr(self.driver, "shared", False) or self.driver.t >= self.driver.T - 1:
            return False
        for agent in self.driver.external_order():
            if not self.retired[agent]:
                return False
            self.driver.supply(int(agent), np.zeros(3), valid=False)
        return True

    def external_order(self) -> list[int]:
        """Live external agents still to act this step, in order."""
        return [int(a) for a in self.driver.external_order() if not self.retired[a]]

    def apply(self, agent: int, action: np.ndarray | int) -> None:
        """Turn an (already validated) action of external ``agent`` into its next state."""
        apply_actions([self], [agent], [action])

    def next_state(self, agent: int, action: np.ndarray | int) -> tuple[np.ndarray, np.float64]:
        """Next state and speed of external ``agent`` under a ``delta`` or ``token`` action."""
        now = self.driver.xyh[agent, self.t]
        if self.config.action == "delta":
            nxt = delta_step(now, np.asarray(action))
        else:
            assert self.vocabulary is not None
            nxt = token_step(now, self.vocabulary.templates[self.sc.kind[agent]], int(action))  # type: ignore[arg-type]
        d = nxt[:2] - now[:2]
        forward = np.cos(now[2]) * d[0] + np.sin(now[2]) * d[1]
        return nxt, np.float64(np.hypot(*d) / self.dt * (1.0 if forward >= 0 else -1.0))

    def finish_step(
        self, computed: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
    ) -> tuple[np.ndarray, StepOutcome]:
        """Outcome of the step just completed for the live external agents (returned with it).
        ``computed`` (or :attr:`prepared` ``(step, computed)`` of this step, used once): this scene's entry
        of :meth:`BatchGeometry.outcomes` when a batched env has computed every scene's at once."""
        if computed is None and self.prepared is not None and self.prepared[0] == self.t:
            computed = self.prepared[1]  # computed by the batched env for this very step
        self.prepared = None
        live, hit, off, s_new = computed if computed is not None else self.geometry.outcomes([self])[0]
        rows = self.route_row[live]
        gained = s_new - self.progress[rows]
        self.progress[rows] = s_new
        goal = self.has_goal[rows] & (s_new >= self.routes.length[rows] - self.config.reward.goal_tolerance)
        # collisions and off-road excursions are penalised once, when they start
        new_hit, new_off = hit & (self.last_collision[rows] == 0), off & (self.last_offroad[rows] == 0)
        self.collision_steps[rows] += hit
        self.offroad_steps[rows] += off
        self.last_collision[rows], self.last_offroad[rows] = hit, off
        outcome = step_reward(
            self.config.reward,
            gained,
            self.routes.length[rows],
            new_hit,
            new_off,
            goal,
            self.kin.accel[live],
            self.kin.lateral[live],
        )
        self.steps += 1
        return live, replace(outcome, collision=hit, offroad=off)

    def retire(self, agent: int) -> None:
        """Take a finished external agent out of the scene from the next step on."""
        self.retired[agent] = True

    @property
    def horizon_reached(self) -> bool:
        return self.steps >= self.horizon

    # ------------------------------------------------------------------ observations and introspection
    def view(self) -> WorldView:
        """The world as it stands now (mid-step: who has moved so far)."""
        return WorldView(
            self.sc, self.driver.xyh, self.driver.valid, self.t, self.driver.moved(), self.external, self.npc
        )

    def observe(self, agent: int) -> np.ndarray:
        """Observation of external ``agent`` now."""
        if self.config.observation == "vector":
            return self.geometry.observations([self], [agent])[0]
        pictures = self.geometry.pictures([self])
        ego = self.geometry.ego_features([self], np.zeros(1, np.int64), np.array([agent]), pictures)
        state = EgoState(
            agent=agent,
            speed=float(ego.speed[0]),
            accel=float(ego.accel[0]),
            yaw_rate=float(ego.yaw_rate[0]),
            route_fraction=float(ego.route_fraction[0]),
            lateral=float(ego.lateral[0]),
            heading_error=float(ego.heading_error[0]),
            route_ahead=ego.route_ahead[0],
        )
        n = self.sc.num_agents
        picture = Picture(
            pictures.state[0, :n], pictures.present[0, :n], pictures.velocity[0, :n], pictures.moved[0, :n]
        )
        return self.observer.observe(state, picture)  # type: ignore[union-attr]


def apply_actions(
    sims: Sequence[Simulation], agents: Sequence[int], actions: Sequence[np.ndarray | int]
) -> None:
    """:meth:`Simulation.apply` of action ``actions[i]`` to external agent ``agents[i]`` of ``sims[i]``,
    for all at once: continuous actions sharing vehicle limits go through one bicycle step, and the states
    for a shared engine (a batched env's) reach it in one supply."""
    n = len(sims)
    now = np.stack([s.driver.xyh[a, s.t] for s, a in zip(sims, agents, strict=True)])
    speed = np.array([s.kin.speed[a] for s, a in zip(sims, agents, strict=True)], dtype=np.float64)
    dt = np.array([s.dt for s in sims])
    nxt, v_next = np.zeros((n, 3)), np.zeros(n)
    groups: dict[object, list[int]] = {}
    for i, s in enumerate(sims):
        if s.config.action == "continuous":
            groups.setdefault(s.config.limits, []).append(i)
        else:
            nxt[i], v_next[i] = s.next_state(agents[i], actions[i])
    for limits, rows in groups.items():
        length = np.array([sims[i].sc.size[agents[i], 0] for i in rows])
        moved = np.stack([np.asarray(actions[i]) for i in rows])
        nxt[rows], v_next[rows] = bicycle_step(now[rows], speed[rows], moved, length, limits, dt[rows])  # type: ignore[arg-type]
    yaw = wrap_angle(nxt[:, 2] - now[:, 2]) / dt
    accel = (v_next - speed) / dt
    engines: dict[int, list[int]] = {}
    for i, (s, a) in enumerate(zip(sims, agents, strict=True)):
        kin = s.kin
        kin.accel[a], kin.lateral[a], kin.yaw_rate[a], kin.speed[a] = (
            accel[i],
            v_next[i] * yaw[i],
            yaw[i],
            v_next[i],
        )
        if getattr(s.driver, "shared", False):
            engines.setdefault(id(s.driver.engine), []).append(i)
        else:
            s.driver.supply(a, nxt[i], valid=True)
    for rows in engines.values():
        engine = sims[rows[0]].driver.engine
        engine.supply(
            np.array([sims[i].driver.row for i in rows]), np.array([agents[i] for i in rows]), nxt[rows]
        )
