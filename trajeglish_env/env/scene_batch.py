"""B scenes stepped together: the one control path of every environment (the AEC env is a batch of one).

A :class:`SceneBatch` owns the NPC driver of its rows (the Trajeglish engine or rule-based NPCs, see
:mod:`~trajeglish_env.env.drivers`), the per-step geometry pass and one :class:`Simulation` per scene.
A timestep of a scene: :meth:`SceneBatch.advance` lets the NPCs act until external agents must act (it
pauses each scene at its next external agent), :meth:`SceneBatch.supply` applies their actions, and so on
until the step is complete; :meth:`SceneBatch.finish` then scores it. Every intra-timestep order works:
the driver asks for each external agent at its place in the order, and a scene's results do not depend
on the other scenes of the batch.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from trajeglish_env.env.batch_outcomes import BatchGeometry
from trajeglish_env.env.config import EnvConfig, TrajeglishNPC
from trajeglish_env.env.drivers import EngineRows, NPCRows, PolicyCopies, RuleRows
from trajeglish_env.env.npc import NPCPolicy, make_npc_policy
from trajeglish_env.env.observations import EgoState
from trajeglish_env.env.simulation import AgentReport, Roles, Simulation, apply_actions, episode_horizon
from trajeglish_env.env.threads import AdaptiveThreads, torch_threads_scope
from trajeglish_env.scenario import Scenario


def load_npc_checkpoint(checkpoint: Any, device: str | None = None) -> Any:
    """A checkpoint for Trajeglish NPCs: None -> the shipped model, a path, or a Checkpoint (checked); on
    ``device`` when one is given (see :func:`~trajeglish_env.checkpoint.on_device`)."""
    if device is not None:
        from trajeglish_env.checkpoint import on_device

        return on_device(load_npc_checkpoint(checkpoint), device)
    from trajeglish_env.checkpoint import (
        Checkpoint,
        CheckpointError,
        check_compatible,
        load_checkpoint,
        load_pretrained,
    )

    if checkpoint is None:
        try:
            return load_pretrained()
        except CheckpointError as exc:
            raise CheckpointError(
                f"{exc}. Trajeglish NPCs need a model: pass npc=TrajeglishNPC(checkpoint=PATH) or a "
                "rule-based NPC policy (npc='idm', 'replay' or 'constant_velocity')"
            ) from exc
    if isinstance(checkpoint, (str, os.PathLike)):
        return load_checkpoint(checkpoint)
    if not isinstance(checkpoint, Checkpoint):
        raise TypeError(f"npc checkpoint: expected a path or a Checkpoint, got {type(checkpoint).__name__}")
    check_compatible(checkpoint.config, checkpoint.vocabulary, where="npc checkpoint")
    return checkpoint


def trajeglish_settings(spec: object) -> TrajeglishNPC | None:
    """The Trajeglish settings of an ``EnvConfig.npc`` value (None for rule-based NPCs)."""
    if spec == "trajeglish":
        return TrajeglishNPC()
    if isinstance(spec, TrajeglishNPC):
        return spec
    if isinstance(spec, str) or isinstance(spec, NPCPolicy):
        return None
    raise TypeError(
        f"npc: expected a policy name, a TrajeglishNPC or an object with reset() and act() "
        f"(trajeglish_env.env.npc.NPCPolicy), got {type(spec).__name__}"
    )


class SceneBatch:
    """``num_scenes`` scene rows under one NPC driver (see the module docstring). ``torch_threads``: an
    int, None to leave torch alone, or ``"auto"`` (:class:`~trajeglish_env.env.threads.AdaptiveThreads`:
    several threads for big batches, one while other processes compete for the cores). The count holds
    only while the batch runs the model: the caller's torch work keeps the caller's setting."""

    def __init__(self, num_scenes: int, config: EnvConfig, torch_threads: int | str | None = None):
        if not isinstance(num_scenes, (int, np.integer)) or num_scenes < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_scenes!r}")
        if not (torch_threads in ("auto", None) or (isinstance(torch_threads, int) and torch_threads >= 1)):
            raise ValueError(
                f"torch_threads must be 'auto', None or a positive integer, got {torch_threads!r}"
            )
        self.num_scenes = int(num_scenes)
        settings = trajeglish_settings(config.npc)
        self.checkpoint = None
        if settings is not None:
            self.checkpoint = load_npc_checkpoint(settings.checkpoint, settings.device)
            settings = settings.with_checkpoint(self.checkpoint)  # loaded once; copies share it
            config = config.with_overrides(npc=settings)
        self.config, self.settings = config, settings
        self.vocabulary = self.checkpoint.vocabulary if self.checkpoint is not None else None
        # token actions need a vocabulary: without a model, the shipped model's (the one its NPCs give), so a
        # token policy trained against rule-based NPCs plays against the model's
        if config.action == "token" and self.vocabulary is None:
            from trajeglish_env.checkpoint import load_pretrained

            self.vocabulary = load_pretrained().vocabulary
        self.threads: AdaptiveThreads | None = None
        self._fixed_threads: int | None = None  # the count when it does not adapt (None: torch left alone)
        self.rows = self._make_rows(torch_threads)
        self.geometry = BatchGeometry()
        self.sims: list[Simulation | None] = [None] * self.num_scenes

    def _make_rows(self, torch_threads: int | str | None) -> NPCRows:
        npc = self.config.npc
        if self.settings is None:
            if isinstance(npc, str):  # partials, not lambdas: an env with rule-based NPCs pickles
                return RuleRows(self.num_scenes, functools.partial(make_npc_policy, npc))
            # a user's policy object: the first slot plays it, every other slot its own copy (PolicyCopies)
            return RuleRows(self.num_scenes, PolicyCopies(npc), fresh_each_start=False)
        from trajeglish_env.env.engine_shards import ShardedEngineRows, engine_shards
        from trajeglish_env.sampler.engine import BatchEngine

        def make_engine(rows: int) -> BatchEngine:
            assert self.settings is not None
            return BatchEngine(
                self.checkpoint,  # type: ignore[arg-type]
                rows,
                self.settings.sampling,
                self.settings.torch_cache_dtype,
            )

        first, entering = self.config.order == "first", self.settings.drive_entering
        device = str(next(self.checkpoint.model.parameters()).device)  # type: ignore[union-attr]
        shards = engine_shards(self.num_scenes, torch_threads, device)
        if shards > 1:  # two shards in threads of one torch thread each, instead of two torch threads
            self._fixed_threads = 1
            return ShardedEngineRows(make_engine, self.num_scenes, shards, first, entering)
        if torch_threads == "auto":
            self.threads = AdaptiveThreads(self.num_scenes)
        elif torch_threads is not None:
            self._fixed_threads = int(torch_threads)
        return EngineRows(make_engine(self.num_scenes), externals_first=first, entering=entering)

    # ------------------------------------------------------------------ scenes
    def start(self, scene: int, scenario: Scenario, rng: np.random.Generator) -> Simulation:
        """(Re)start row ``scene`` on ``scenario`` with an episode stream ``rng``. Any time: an unfinished
        step of the other scenes is undone, and the next :meth:`advance` redoes it (the same draws)."""
        roles = Roles.draw(scenario, self.config, rng)
        horizon = episode_horizon(scenario, self.config)
        self._check_horizon(scenario, horizon)
        with self.torch_threads():
            row = self.rows.start(
                scene, scenario, roles.mask(scenario.num_agents), horizon, roles.priority, roles.seed
            )
        sim = self.sims[scene] = Simulation(scenario, self.config, self.vocabulary, roles, row, horizon)
        return sim

    def _check_horizon(self, scenario: Scenario, horizon: int) -> None:
        """A rule-based NPC policy bound to the log cannot play past its end: refuse, naming the limit."""
        policy = self.config.npc
        max_steps = getattr(make_npc_policy(policy) if isinstance(policy, str) else policy, "max_steps", None)
        if max_steps is None or self.settings is not None:
            return
        limit = int(max_steps(scenario, scenario.current_index))
        if horizon > limit:
            name = policy if isinstance(policy, str) else type(policy).__name__
            raise ValueError(
                f"scenario {scenario.scenario_id!r}: max_cycles={horizon} but {name!r} NPCs can play only "
                f"the {limit} steps of its log after the current index; use npc='trajeglish' or "
                "'constant_velocity' for episodes longer than the log"
            )

    @property
    def model_threads(self) -> int | None:
        """The torch threads the batch's model calls run on now (None: torch left alone, the caller's)."""
        return self.threads.threads if self.threads is not None else self._fixed_threads

    def torch_threads(self) -> Any:
        """A context in which torch runs the batch's thread count (the caller's count again after it)."""
        return torch_threads_scope(self.model_threads)

    def stop(self, scene: int) -> None:
        """Row ``scene`` has no agents left: it stops stepping until it is started again."""
        if self.sims[scene] is not None:
            self.rows.stop(scene)
            self.sims[scene] = None

    def sim(self, scene: int) -> Simulation:
        """The running simulation of row ``scene``."""
        sim = self.sims[scene]
        if sim is None:
            raise RuntimeError(f"scene {scene} is not running: reset it first")
        return sim

    # ------------------------------------------------------------------ the step protocol
    def advance(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Let the NPCs act until every stepping scene waits for a live external agent: ``(scenes,
        agents)``, one per waiting scene; None once the step is complete in every scene. Retired external
        agents are taken out of the scene when their turn comes."""
        if self.threads is not None:  # every stepping API comes here (the AEC env's steps too)
            self.threads.tick()
        with self.torch_threads():
            while True:
                waiting = self.rows.advance()
                if waiting is None:
                    return None
                scenes, agents = waiting
                retired = np.array([self.sims[s].retired[a] for s, a in zip(scenes, agents, strict=True)])  # type: ignore[union-attr]
                if not retired.any():
                    return scenes, agents
                gone = int(retired.sum())
                self.rows.supply(scenes[retired], agents[retired], np.zeros((gone, 3)), np.zeros(gone, bool))

    def supply(self, scenes: Sequence[int], agents: Sequence[int], actions: Sequence[Any]) -> None:
        """Apply (already validated) actions of external agents ``agents[i]`` of scenes ``scenes[i]``."""
        if not len(scenes):
            return
        sims = [self.sim(s) for s in scenes]
        nxt = apply_actions(sims, agents, actions)
        with self.torch_threads():
            self.rows.supply(
                np.asarray(scenes, dtype=np.int64),
                np.asarray(agents, dtype=np.int64),
                nxt,
                np.ones(len(scenes), bool),
            )

    def play(self, scenes: Sequence[int], agents: Sequence[int], actions: Sequence[Any]) -> None:
        """Finish the current step of every stepping scene, each external agent acting with its action from
        ``actions`` (validated; one per live external agent of those scenes) when its turn comes."""
        sims = [self.sim(s) for s in scenes]
        nxt = apply_actions(sims, agents, actions) if len(scenes) else np.zeros((0, 3))
        n = max((s.sc.num_agents for s in self.sims if s is not None), default=0)
        states = np.zeros((self.num_scenes, n, 3))
        given = np.zeros((self.num_scenes, n), dtype=bool)
        states[list(scenes), list(agents)] = nxt
        given[list(scenes), list(agents)] = True
        with self.torch_threads():
            while (waiting := self.advance()) is not None:
                rows, who = waiting
                missing = ~given[rows, who]
                if missing.any():
                    s, a = int(rows[missing][0]), int(who[missing][0])
                    raise RuntimeError(f"scene {s}: no action was given for {self.sim(s).names[a]}")
                self.rows.supply(rows, who, states[rows, who], np.ones(len(rows), bool))

    def finish(self, scenes: Sequence[int]) -> list[dict[str, AgentReport]]:
        """Score the step just completed in ``scenes`` (their geometry in one pass): per scene, the reports
        of its live external agents (finished ones are retired)."""
        sims = [self.sim(s) for s in scenes]
        computed = self.geometry.outcomes([s.state for s in sims]) if sims else []
        return [sim.report(*sim.finish_step(c)) for sim, c in zip(sims, computed, strict=True)]

    # ------------------------------------------------------------------ observations
    def observe(self, scenes: Sequence[int], agents: Sequence[int]) -> list[np.ndarray]:
        """Observations of external agent ``agents[i]`` of scene ``scenes[i]`` now (a scene may appear
        several times); the geometry of all of them in one pass (``bev``: only the rasters per agent)."""
        if not len(scenes):
            return []
        states = [self.sim(s).state for s in scenes]
        if self.config.observation == "vector":
            return list(self.geometry.observations(states, agents))
        return self._bev(list(scenes), np.asarray(agents, dtype=np.int64))

    def _bev(self, scenes: list[int], agents: np.ndarray) -> list[np.ndarray]:
        """``bev`` rasters: the scenes' pictures and the observers' own features computed once for all
        of them, then each agent's raster drawn."""
        position: dict[int, int] = {}
        for s in scenes:
            position.setdefault(s, len(position))
        sims = [self.sim(s) for s in position]
        states = [sim.state for sim in sims]
        pictures = self.geometry.pictures(states)
        index = np.array([position[s] for s in scenes], dtype=np.int64)
        ego = self.geometry.ego_features(states, index, agents, pictures)
        out = []
        for k, (b, agent) in enumerate(zip(index.tolist(), agents.tolist(), strict=True)):
            state = EgoState(
                agent=agent,
                speed=float(ego.speed[k]),
                accel=float(ego.accel[k]),
                yaw_rate=float(ego.yaw_rate[k]),
                route_fraction=float(ego.route_fraction[k]),
                lateral=float(ego.lateral[k]),
                heading_error=float(ego.heading_error[k]),
                route_ahead=ego.route_ahead[k],
            )
            out.append(sims[b].observer.observe(state, pictures, b))  # type: ignore[union-attr]
        return out
