"""Typed settings of the environment: which agents are external, their order, the NPC policy, the action
and observation types, rewards, vehicle limits, episode length and rendering (frozen dataclasses)."""

from __future__ import annotations

import difflib
import math
import numbers
import os
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

from trajeglish_env.kinematics import VehicleLimits
from trajeglish_env.sampler.config import OFFROAD_MARGIN, SamplingConfig

if TYPE_CHECKING:
    from trajeglish_env.env.npc import NPCPolicy

ACTION_TYPES = ("token", "continuous", "delta")
OBSERVATION_TYPES = ("vector", "bev")
ORDERS = ("first", "last", "random")
AGENT_NAMES = ("track", "slot")
NPC_NAMES = ("trajeglish", "replay", "constant_velocity", "idm")
MIN_BEV_RESOLUTION = 0.05  # m per pixel: finer rasters sample each box at millions of points
# The envs' own keyword arguments besides EnvConfig's fields (named in the unknown-option error).
ENV_KEYWORDS = ("scenes", "config", "render_mode")


@dataclass(frozen=True)
class RandomAgents:
    """``k`` external agents drawn at every reset among the agents present at the current step.

    ``with_sdc``: the sdc is always one of them (your ego plus ``k - 1`` others drawn); ``at_most``: a
    scene with fewer than ``k`` agents present gives all of them (else it is an error at reset)."""

    k: int
    with_sdc: bool = False
    at_most: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.k, int) or self.k < 1:
            raise ValueError(f"RandomAgents.k must be a positive integer, got {self.k!r}")
        for name in ("with_sdc", "at_most"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"RandomAgents.{name} must be a bool, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class TrajeglishNPC:
    """NPCs driven by a Trajeglish model: ``checkpoint`` (a path or a loaded ``Checkpoint``; None: the
    shipped model) sampled with ``sampling`` (:class:`~trajeglish_env.sampler.config.SamplingConfig`: the
    one sampling configuration of the project, with the same defaults everywhere; its ``seed`` is unused
    here, since every episode draws its own). ``drive_entering``: the agents the log brings in after the
    episode's first step are NPCs too, driven by the model from their first logged step (False: they replay
    the log, which cannot react and runs into NPCs that did not drive as the log did). ``device``: the torch
    device the model decodes on (``"cpu"``, ``"cuda"``, ``"cuda:1"``; None: where the checkpoint is, the
    CPU for a loaded file); the env's own state and geometry stay on the host either way."""

    checkpoint: Any = None
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    drive_entering: bool = True
    device: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.sampling, SamplingConfig):
            raise TypeError(
                f"TrajeglishNPC.sampling must be a SamplingConfig, got {type(self.sampling).__name__}"
            )
        if not isinstance(self.drive_entering, bool):
            raise TypeError(f"TrajeglishNPC.drive_entering must be a bool, got {self.drive_entering!r}")
        if self.device is not None:
            import torch

            try:
                torch.device(self.device)
            except (RuntimeError, TypeError) as exc:
                raise ValueError(
                    f"TrajeglishNPC.device must name a torch device ('cpu', 'cuda', 'cuda:1') or be None, "
                    f"got {self.device!r}"
                ) from exc
        ok = self.checkpoint is None or isinstance(self.checkpoint, (str, os.PathLike))
        if not ok and not hasattr(self.checkpoint, "vocabulary"):
            raise TypeError(
                "TrajeglishNPC.checkpoint must be None (the shipped model), a path or a Checkpoint, "
                f"got {type(self.checkpoint).__name__}"
            )

    def with_checkpoint(self, checkpoint: Any) -> TrajeglishNPC:
        """The same settings with a (loaded) checkpoint."""
        return replace(self, checkpoint=checkpoint)

    @property
    def torch_cache_dtype(self) -> Any:
        """The torch dtype of the decoder caches."""
        return self.sampling.torch_cache_dtype


@dataclass(frozen=True)
class ObservationConfig:
    """Sizes of the observations: ``neighbours`` nearest agents, ``map_points`` nearest map points
    (polylines resampled every ``map_spacing`` m), ``route_points`` route points ``route_spacing`` m apart,
    ``signals`` nearest traffic-signal stop points with their state (0: none, the default; see
    :mod:`~trajeglish_env.env.signal_features`), all within ``radius`` m; the bev raster is ``bev_size`` x
    ``bev_size`` pixels of ``bev_resolution`` m."""

    neighbours: int = 8
    map_points: int = 32
    map_spacing: float = 3.0
    route_points: int = 10
    route_spacing: float = 5.0
    radius: float = 50.0
    bev_size: int = 64
    bev_resolution: float = 1.0
    signals: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in (int, "int"):  # counts and sizes: whole numbers (NumPy's too), never a bool
                least = 0 if f.name == "signals" else 1
                if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < least:
                    raise ValueError(f"ObservationConfig.{f.name} must be an int >= {least}, got {value!r}")
                object.__setattr__(self, f.name, int(value))
            elif isinstance(value, bool) or not isinstance(value, numbers.Real) or not value > 0:
                raise ValueError(f"ObservationConfig.{f.name} must be a number > 0, got {value!r}")
        if self.bev_resolution < MIN_BEV_RESOLUTION:  # the raster samples each box at half a pixel
            raise ValueError(
                f"ObservationConfig.bev_resolution must be >= {MIN_BEV_RESOLUTION} m per pixel, got "
                f"{self.bev_resolution!r}"
            )


@dataclass(frozen=True)
class RewardConfig:
    """Reward terms per external agent and step, and what ends its episode.

    progress: ``progress`` x (metres gained along the logged route) / (route length, at least 10 m);
    collision / offroad: added once, when it happens (off-road: a vehicle's box corner more than
    ``offroad_margin`` m beyond a road edge; logged roundabout turns cut up to ~1 m); comfort:
    ``comfort`` x (longitudinal and lateral acceleration beyond ``comfort_accel`` m/s^2, in units of
    ``comfort_accel``, at most ``comfort_cap`` of them a step: the most a ``continuous`` action reaches is
    about 2.8, while ``delta`` and ``token`` steps read 3 cm of tracking jitter as 3 m/s^2 and a jerky step as
    hundreds, more than a collision's penalty); goal: added once, when the end of the route (within
    ``goal_tolerance`` m) is
    first reached (``info["goal"]`` says whether the agent is there this step). Routes shorter than
    ``min_route_length`` m (agents parked in the log) have no goal. Bad values (a non-finite weight, a
    non-positive ``comfort_accel``, a negative margin or tolerance) are refused, naming the field.
    """

    progress: float = 1.0
    collision: float = -1.0
    offroad: float = -1.0
    comfort: float = -0.005
    comfort_accel: float = 3.0
    comfort_cap: float = 3.0
    offroad_margin: float = OFFROAD_MARGIN
    goal: float = 0.0
    goal_tolerance: float = 2.0
    min_route_length: float = 5.0
    terminate_on_collision: bool = True
    terminate_on_offroad: bool = True
    terminate_on_goal: bool = True

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name.startswith("terminate_on_"):
                if not isinstance(value, bool):
                    raise ValueError(f"RewardConfig.{f.name} must be a bool, got {value!r}")
            elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"RewardConfig.{f.name} must be a finite number, got {value!r}")
        if self.comfort_accel <= 0:
            raise ValueError(
                f"RewardConfig.comfort_accel must be > 0 (rewards divide by it), got {self.comfort_accel}"
            )
        if self.comfort_cap < 0:
            raise ValueError(
                f"RewardConfig.comfort_cap must be >= 0 (units of comfort_accel), got {self.comfort_cap}"
            )
        for name in ("offroad_margin", "goal_tolerance", "min_route_length"):
            if getattr(self, name) < 0:
                raise ValueError(f"RewardConfig.{name} must be >= 0 m, got {getattr(self, name)}")


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines an environment besides its scenes.

    external: ``"sdc"`` (default), ``"all"``, a tuple of track ids, or :class:`RandomAgents`; the other
      agents present at the current step are NPCs (agents that appear later enter where the log has them;
      Trajeglish NPCs then drive them, ``TrajeglishNPC.drive_entering``, rule-based NPCs replay them).
    agent_names: ``"track"`` (default): an external agent is named by class and track id
      (``vehicle_68``), so each scene has its own names and ``possible_agents`` is set at every reset;
      ``"slot"``: ``agent_0`` .. ``agent_{n-1}`` in the order ``external`` gives them (the sdc is
      ``agent_0``), and ``possible_agents`` is those n names for the env's life, as PettingZoo's stock
      wrappers and multi-agent libraries built on ``possible_agents`` expect (n: 1 for ``"sdc"``, the
      tuple's length, or ``RandomAgents.k``; ``"all"`` has no fixed n: take ``RandomAgents(k,
      at_most=True)``).
    order: intra-timestep position of the external agents: ``"first"`` (before every NPC: NPCs react to
      them within the step), ``"last"`` (after the NPCs of their model context), ``"random"`` (a random
      order of all agents per episode), or a tuple of agent names acting first, in that order.
    npc: ``"trajeglish"`` (the shipped model; or a :class:`TrajeglishNPC`), ``"replay"``,
      ``"constant_velocity"``, ``"idm"``, or any object with the NPC interface
      (:class:`trajeglish_env.env.npc.NPCPolicy`).
    action / observation: one of :data:`ACTION_TYPES` / :data:`OBSERVATION_TYPES`.
    max_cycles: steps per episode (None: the rest of the scene's log).
    render_size / render_radius / render_legend: rendered frames' pixels, the metres they show around the
      followed agent, and whether each carries the key of the colours (which agent is yours).
    torch_threads: torch intra-op threads while the env runs the model: ``"auto"`` (default,
      :class:`~trajeglish_env.env.threads.AdaptiveThreads`) starts on one and takes a second core once a
      look at the machine finds it free (a step's call decodes about 48 positions: +8-16 % on two cores),
      back to one while other processes keep the cores busy; an int fixes the count; the caller's count is
      back after every env call; None leaves torch alone.
    """

    external: str | tuple[int, ...] | RandomAgents = "sdc"
    agent_names: str = "track"
    order: str | tuple[str, ...] = "first"
    npc: str | TrajeglishNPC | NPCPolicy = "trajeglish"
    action: str = "continuous"
    observation: str = "vector"
    reward: RewardConfig = field(default_factory=RewardConfig)
    limits: VehicleLimits = field(default_factory=VehicleLimits)
    obs: ObservationConfig = field(default_factory=ObservationConfig)
    max_cycles: int | None = None
    render_size: int = 480
    render_radius: float = 40.0
    render_legend: bool = False
    torch_threads: int | str | None = "auto"

    def __post_init__(self) -> None:
        ext = self.external
        if isinstance(ext, list):
            object.__setattr__(self, "external", ext := tuple(ext))
        if isinstance(ext, str):
            if ext not in ("sdc", "all"):
                raise ValueError(
                    f"EnvConfig.external: expected 'sdc', 'all', track ids or RandomAgents, got {ext!r}"
                )
        elif isinstance(ext, tuple):
            if not ext or not all(isinstance(i, (int,)) or hasattr(i, "__index__") for i in ext):
                raise ValueError(f"EnvConfig.external: expected a non-empty tuple of track ids, got {ext!r}")
            object.__setattr__(self, "external", tuple(int(i) for i in ext))
        elif not isinstance(ext, RandomAgents):
            raise ValueError(
                f"EnvConfig.external: expected 'sdc', 'all', track ids or RandomAgents, got {ext!r}"
            )
        if self.agent_names not in AGENT_NAMES:
            raise ValueError(
                f"EnvConfig.agent_names: expected one of {AGENT_NAMES}, got {self.agent_names!r}"
            )
        if self.agent_names == "slot" and ext == "all":
            raise ValueError(
                "EnvConfig.agent_names='slot' needs a fixed number of external agents, and external='all' "
                "has none: take RandomAgents(k, at_most=True) (every agent of a scene with at most k of "
                "them, k slot names)"
            )
        order = self.order
        if isinstance(order, list):
            object.__setattr__(self, "order", order := tuple(order))
        if isinstance(order, str) and order not in ORDERS:
            raise ValueError(
                f"EnvConfig.order: expected one of {ORDERS} or a tuple of agent names, got {order!r}"
            )
        if isinstance(order, tuple) and not all(isinstance(a, str) for a in order):
            raise ValueError(f"EnvConfig.order: an explicit order is a tuple of agent names, got {order!r}")
        if isinstance(self.npc, str) and self.npc not in NPC_NAMES:
            raise ValueError(
                f"EnvConfig.npc: expected one of {NPC_NAMES} or an NPC policy object, got {self.npc!r}"
                + (
                    f" (a checkpoint? pass npc=TrajeglishNPC({self.npc!r}))"
                    if self.npc.endswith((".pt", ".pth")) or "/" in self.npc
                    else ""
                )
            )
        if self.action not in ACTION_TYPES:
            raise ValueError(f"EnvConfig.action: expected one of {ACTION_TYPES}, got {self.action!r}")
        if self.observation not in OBSERVATION_TYPES:
            raise ValueError(
                f"EnvConfig.observation: expected one of {OBSERVATION_TYPES}, got {self.observation!r}"
            )
        cycles = self.max_cycles
        if cycles is not None:
            if not isinstance(cycles, numbers.Integral) or isinstance(cycles, bool) or cycles < 1:
                raise ValueError(f"EnvConfig.max_cycles must be a positive integer or None, got {cycles!r}")
            object.__setattr__(self, "max_cycles", int(cycles))
        if not isinstance(self.render_legend, bool):
            raise TypeError(f"EnvConfig.render_legend must be a bool, got {self.render_legend!r}")
        size = self.render_size
        if not isinstance(size, numbers.Integral) or isinstance(size, bool):
            raise TypeError(
                f"render_size: expected a positive int (the square picture's side in pixels), got {size!r}"
            )
        if size < 16 or not self.render_radius > 0:
            raise ValueError(
                f"EnvConfig.render_size must be >= 16 pixels and render_radius > 0 m, "
                f"got {size!r} and {self.render_radius!r}"
            )
        object.__setattr__(self, "render_size", int(size))
        threads = self.torch_threads
        if not (
            threads in ("auto", None)
            or (isinstance(threads, numbers.Integral) and not isinstance(threads, bool) and threads >= 1)
        ):
            raise ValueError(
                f"EnvConfig.torch_threads must be 'auto', None or an integer >= 1, got {threads!r}"
            )
        if isinstance(threads, numbers.Integral):
            object.__setattr__(self, "torch_threads", int(threads))

    @property
    def slot_names(self) -> list[str] | None:
        """The fixed external agent names of ``agent_names="slot"`` (None for ``"track"``)."""
        if self.agent_names != "slot":
            return None
        ext = self.external
        count = 1 if ext == "sdc" else ext.k if isinstance(ext, RandomAgents) else len(ext)  # type: ignore[arg-type]
        return [f"agent_{j}" for j in range(count)]

    def with_overrides(self, **overrides: Any) -> EnvConfig:
        """A copy with some fields replaced (unknown names are refused, naming the valid ones)."""
        known = {f.name for f in fields(self)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            valid = sorted(known | set(ENV_KEYWORDS))
            close = {name: difflib.get_close_matches(name, valid, n=1) for name in unknown}
            hints = [
                f"{match[0]!r}" + (f" for {name!r}" if len(unknown) > 1 else "")
                for name, match in close.items()
                if match
            ]
            hint = f" (did you mean {', '.join(hints)}?)" if hints else ""
            raise TypeError(f"unknown environment option(s) {unknown}{hint}; valid options: {valid}")
        return replace(self, **overrides)
