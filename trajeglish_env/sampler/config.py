"""The one sampling configuration of Trajeglish NPCs, shared by the env, the CLI, the policies and the
evaluation (importing it loads no torch)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from trajeglish_env.cores import native_bfloat16
from trajeglish_env.sampler.subsets import SUBSET_RULES

CACHE_DTYPES = ("float32", "bfloat16")
# The shipped model's most realistic temperature measured (WOSAC meta-metric 0.573, vs 0.560 at 0.5 and
# 0.564 at 1.0, with the fewest collisions; docs/evaluation.md).
DEFAULT_TEMPERATURE = 0.75
# Metres a vehicle's box corner may reach beyond a road edge before it is off the road: the env's
# ``RewardConfig.offroad_margin`` default (and the off-road loss term's); the guard uses GUARD_ROAD_MARGIN.
OFFROAD_MARGIN = 0.5
DEFAULT_GUARD = True
# Metres a guarded vehicle's box corner may reach beyond a road edge: 0, the WOSAC off-road threshold (a
# corner beyond the edge at all is off the road), stricter than the env's reward margin above.
GUARD_ROAD_MARGIN = 0.0
# Metres along its kept-up motion a guarded vehicle's candidate should stay on the road, as far as any
# candidate can (:mod:`~trajeglish_env.sampler.guard_ahead`); 0: the one-step road-edge rule alone.
GUARD_ROAD_AHEAD = 5.0
# Metres by which a guarded vehicle's forward step may change from its last one (0.5 m in a 0.1 s step: 5 m/s
# in 0.1 s; tokenized logged vehicles change by up to 0.4 m on highway-env, 0.3 m on SUMO, 0.55 m in 99.9 %
# of WOMD steps; cyclists half); 0: no speed-change rule.
GUARD_STEP_CHANGE = 0.5
# Steps a guarded vehicle or cyclist that drove may stand with the way clear before it must set off
# (:mod:`~trajeglish_env.sampler.guard_stall`; 1 s: development scenes stood least at 10 of 10, 20 and
# none, realism alike);
# 0: no stall rule.
GUARD_STALL_STEPS = 10
# Deceleration (m/s^2) at which a guarded vehicle or cyclist must still be able to stop behind the box ahead
# (:mod:`~trajeglish_env.sampler.guard_follow`); 0: no following rule.
GUARD_FOLLOW_DECEL = 4.0
# How the agents of a step are decoded (see :mod:`~trajeglish_env.sampler.parallel`): "parallel" (fixed-point
# iteration over a whole run of agents per model call) or "sequential" (one model call per sampled agent).
INTRA_STEP_MODES = ("parallel", "sequential")
# The dtype the model's linear layers multiply in when sampling: "auto" is bfloat16 for batches of at least
# AUTO_BFLOAT16_ROWS rows on a CPU with native bfloat16 arithmetic (AVX512-BF16 / AMX: 4-7x float32's
# matrix throughput), float32 elsewhere.
COMPUTE_DTYPES = ("auto", "float32", "bfloat16")
# Below this many rows (scenes or rollouts decoded together) bfloat16's casts and separate bias sums cost
# more than its faster products save: a single env (one row, 24 agents) steps 3 % faster in float32. From 2
# rows on the calls' products (a row decodes about 48 positions a call) are large enough for bfloat16 to
# win: 2 scenes +3 %, 4 +15 %, 8 +24 % with one thread, +8 % with two (docs/speed.md, "Bfloat16 from two
# rows"; stop 41 had measured the opposite up to 16 rows, before the row buckets of stop 44).
AUTO_BFLOAT16_ROWS = 2


@dataclass(frozen=True)
class SamplingConfig:
    """How tokens are drawn: ``temperature`` (0: argmax) and nucleus ``top_p``; the decoder caches'
    ``cache_dtype`` (``"bfloat16"`` halves their memory traffic, ~1.2x faster batched stepping on CPU, and
    moves the shipped model's held-out NLL by 1e-5 nats; ``"float32"``: full precision); how scenes larger
    than the model's context are split (``subsets``: ``"overlap"``, the paper's rule, or ``"cover"``,
    fewest contexts); the sliding window in time (``prime_steps`` re-fed when a window restarts, default
    steps // 4; ``recompute_every``, default model steps - prime_steps); and the ``seed`` of
    :func:`~trajeglish_env.sampler.rollout` (environments draw their seeds from their own streams).

    ``guard``: guarded sampling (:mod:`~trajeglish_env.sampler.guard`). When an agent is sampled, the
    next states of the agents that moved before it in the step are known, so the candidate tokens whose
    box would overlap one of them (or the current box of an agent that has not moved yet: a logged agent
    acting after it too, whose log is known ahead but whose move the step's order hides), or that would
    put a corner of a vehicle's box more than ``guard_road_margin`` m beyond a road edge (default
    :data:`GUARD_ROAD_MARGIN`; a vehicle off the road already may not go farther off), are masked before
    the token is drawn, and so are those that would take a vehicle or cyclist across the stop line of a
    red light on its lane; with ``guard_road_ahead`` > 0 (default :data:`GUARD_ROAD_AHEAD` m) the moving
    candidates whose motion, kept up, stays on the road a shorter way (up to that distance) than another
    allowed candidate's are masked too (:mod:`~trajeglish_env.sampler.guard_ahead`: vehicles turn where
    the road bends instead of running up to its edge and standing there); with ``guard_green`` (default
    on) a vehicle or cyclist behind the stop line of a
    green light on its lane, the way ahead clear, may not stand still (the model reads no signals, so
    without it a queue stopped at red stays stopped at green); with ``guard_step_change`` > 0 (default
    :data:`GUARD_STEP_CHANGE` m) a vehicle's candidates whose forward step differs from its last one by
    more than that (cyclists: half) are masked, so a redraw never stops a car dead from speed; with
    ``guard_stall_steps`` > 0 (default :data:`GUARD_STALL_STEPS`) a vehicle or cyclist that drove, then
    stood that many steps, and has the way clear must set off at pace (:mod:`~trajeglish_env.sampler.
    guard_stall`: the model, reading its own standstill, keeps a car stopped for good); with
    ``guard_wrong_way`` (default on) a vehicle may not turn or drive onto a lane against every lane there
    (:mod:`~trajeglish_env.sampler.lane_directions`: the masks of the other rules left it swerving into the
    oncoming lane); with ``guard_follow_decel`` > 0 (default :data:`GUARD_FOLLOW_DECEL` m/s^2) a vehicle or
    cyclist may not go faster than lets it stop behind the box ahead braking at that
    (:mod:`~trajeglish_env.sampler.guard_follow`: the collision rule alone let a follower hold its speed to
    the last step, then stop from 19 m/s in 0.1 s). An agent
    whose box overlaps the current box
    already is left out (no move undoes that overlap); with ``guard_escape`` (default on) one that *moved*
    into it in this step (a logged agent driving into the box, the guard's remaining collisions in partial
    control; not boxes overlapping the step before, as a log's parked cars can) stays an obstacle, so a
    candidate that moves out of its way is drawn where one exists; not an external
    agent (an env's ego): the collision it drives into is its own, and the env reports it. When that leaves
    nothing, the speed-change rule widens to the gentlest change the others leave, then those agents are
    left out, then the map rules are dropped, then the guard.

    ``intra_step``: how the agents of a timestep are decoded (:data:`INTRA_STEP_MODES`). Both draw each
    agent's token from the model's conditional given the tokens of the agents before it, with the agent's
    own counter-based number; "parallel" needs about 2 model calls a step instead of one per agent. The two
    agree token for token (a position's numbers do not depend on the call that decodes it; docs/
    architecture.md).

    ``compute_dtype``: the dtype the model's linear layers multiply in (:data:`COMPUTE_DTYPES`; inputs and
    weights rounded to it, float32 accumulation). ``"auto"`` (default) is bfloat16 for batches of at least
    :data:`AUTO_BFLOAT16_ROWS` rows where the CPU does it natively (the shipped model's held-out NLL moves by
    about 1e-4 nats, see docs/architecture.md), else float32; a rollout then depends on that choice, so
    set ``"float32"`` for rollouts identical across machines of either kind and batches of any size. CUDA
    devices always compute in float32."""

    temperature: float = DEFAULT_TEMPERATURE
    top_p: float = 1.0
    cache_dtype: str = "bfloat16"
    subsets: str = "overlap"
    prime_steps: int | None = None
    recompute_every: int | None = None
    seed: int = 0
    guard: bool = DEFAULT_GUARD
    guard_road_margin: float = GUARD_ROAD_MARGIN
    guard_green: bool = True
    guard_escape: bool = True
    guard_road_ahead: float = GUARD_ROAD_AHEAD
    guard_step_change: float = GUARD_STEP_CHANGE
    guard_stall_steps: int = GUARD_STALL_STEPS
    guard_wrong_way: bool = True
    guard_follow_decel: float = GUARD_FOLLOW_DECEL
    intra_step: str = "parallel"
    compute_dtype: str = "auto"

    def __post_init__(self) -> None:
        if not isinstance(self.guard, bool):
            raise TypeError(f"SamplingConfig.guard must be a bool, got {self.guard!r}")
        for name in ("guard_green", "guard_escape", "guard_wrong_way"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"SamplingConfig.{name} must be a bool, got {getattr(self, name)!r}")
        if not (self.guard_road_ahead >= 0):
            raise ValueError(f"SamplingConfig.guard_road_ahead must be >= 0 (m), got {self.guard_road_ahead}")
        if not (self.guard_step_change >= 0):
            raise ValueError(
                f"SamplingConfig.guard_step_change must be >= 0 (m), got {self.guard_step_change}"
            )
        stall = self.guard_stall_steps
        if isinstance(stall, bool) or not isinstance(stall, int) or stall < 0:
            raise ValueError(
                "SamplingConfig.guard_stall_steps must be an int >= 0 (steps; 0: no stall rule), "
                f"got {stall!r}"
            )
        if not (self.guard_follow_decel >= 0):
            raise ValueError(
                f"SamplingConfig.guard_follow_decel must be >= 0 (m/s^2; 0: no following rule), "
                f"got {self.guard_follow_decel}"
            )
        if not (self.guard_road_margin >= 0):
            raise ValueError(
                f"SamplingConfig.guard_road_margin must be >= 0 (m), got {self.guard_road_margin}"
            )
        if not (self.temperature >= 0):
            raise ValueError(f"SamplingConfig.temperature must be >= 0, got {self.temperature}")
        if not (0 < self.top_p <= 1):
            raise ValueError(f"SamplingConfig.top_p must be in (0, 1], got {self.top_p}")
        if self.cache_dtype not in CACHE_DTYPES:
            raise ValueError(
                f"SamplingConfig.cache_dtype must be one of {CACHE_DTYPES}, got {self.cache_dtype!r}"
            )
        if self.intra_step not in INTRA_STEP_MODES:
            raise ValueError(
                f"SamplingConfig.intra_step must be one of {INTRA_STEP_MODES}, got {self.intra_step!r}"
            )
        if self.compute_dtype not in COMPUTE_DTYPES:
            raise ValueError(
                f"SamplingConfig.compute_dtype must be one of {COMPUTE_DTYPES}, got {self.compute_dtype!r}"
            )
        if self.subsets not in SUBSET_RULES:
            raise ValueError(f"SamplingConfig.subsets must be one of {SUBSET_RULES}, got {self.subsets!r}")

    @property
    def torch_cache_dtype(self) -> Any:
        """The torch dtype of the decoder caches."""
        import torch

        return getattr(torch, self.cache_dtype)

    def torch_compute_dtype(self, device: Any = "cpu", rows: int | None = None) -> Any:
        """The torch dtype the linear layers multiply in on ``device`` for a batch of ``rows`` rows
        (``"auto"`` resolved; ``rows`` None: a large batch)."""
        import torch

        if torch.device(device).type != "cpu":
            return torch.float32
        return getattr(torch, self.for_rows(rows).compute_dtype)

    def for_rows(self, rows: int | None) -> SamplingConfig:
        """This config with ``compute_dtype="auto"`` resolved for a CPU batch of ``rows`` rows (None: a
        large batch): what split envs and split rollouts hand their workers, so that each shard decodes
        in the dtype one process of all the rows would."""
        if self.compute_dtype != "auto":
            return self
        large = rows is None or rows >= AUTO_BFLOAT16_ROWS
        return replace(self, compute_dtype="bfloat16" if large and native_bfloat16() else "float32")

    def prime(self, model_steps: int) -> int:
        """Steps of known motion re-fed when a window (re)starts."""
        prime = max(1, model_steps // 4) if self.prime_steps is None else self.prime_steps
        if not 0 <= prime < model_steps:
            raise ValueError(f"prime_steps={prime} must be in 0..{model_steps - 1} (the model's context)")
        return prime

    def every(self, model_steps: int) -> int:
        """Steps between window restarts."""
        prime = self.prime(model_steps)
        every = self.recompute_every or model_steps - prime
        if not 1 <= every <= model_steps - prime:
            raise ValueError(
                f"recompute_every={every} must be in 1..{model_steps - prime} "
                f"(the model's {model_steps} steps minus prime_steps={prime})"
            )
        return every
