"""A wall-clock budget (``train --minutes``) and a schedule fitted to it (``--fit-steps``).

The step rate after the 5th step (the loaders' first, prefetched batches come faster), measured over at
least 10 steps and a tenth of the budget, first sets the schedule's length. From then on, once the
learning rate decays, the length is refitted after every step to the rate over the last tenth of the
budget (at least 10 steps; validation and checkpoints included) and the rest of the budget, the decay
going on linearly from the learning rate reached (:meth:`TrainConfig.refitted`: no jump). A run that
slows down (or speeds up) after the first measure still ends its schedule as the budget ends, the
learning rate at 0 but for about a step's decrement; a fit made once ran out of time with the learning
rate at 10-30 % of its peak.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
import torch.distributed as dist

if TYPE_CHECKING:
    from trajeglish_env.training.train import TrainConfig

FIRST_STEP, LEAST_STEP, LEAST_SHARE = 5, 15, 0.1  # the first measure: from step 5, to step 15 and 10 %


@dataclass
class ScheduleFit:
    """The fitting of a new run's schedule to the budget that ends at ``deadline`` (``budget`` seconds
    long); ``most``: the longest schedule allowed (``--steps``)."""

    deadline: float
    budget: float
    most: int
    marks: deque[tuple[int, float]] = field(default_factory=deque)  # (step, clock) of the rate's span
    fitted: bool = False

    def after_step(
        self, config: TrainConfig, step: int, now: float, device: torch.device, world: int
    ) -> TrainConfig:
        """The schedule to go on with after ``step`` steps at clock ``now`` (every rank takes rank 0's)."""
        if step >= FIRST_STEP:
            self.marks.append((step, now))
        span = LEAST_SHARE * self.budget  # the rate's span: the last tenth of the budget, 10 steps or more
        while len(self.marks) > LEAST_STEP - FIRST_STEP + 1 and now - self.marks[1][1] >= span:
            self.marks.popleft()
        if step <= FIRST_STEP or step >= config.steps:  # not measured yet, or over: never prolonged
            return config
        since, then = self.marks[0]
        if self.fitted:
            due = config.decaying(step)  # the same on every rank: no clock read
        else:
            due = rank0_says(step >= LEAST_STEP and now - then >= span, device, world)
        if not due:
            return config
        self.fitted = True
        rate = (step - since) / max(now - then, 1e-9)
        return config.refitted(step, steps_in_time(self.most, step, rate, self.deadline - now, device, world))


def steps_in_time(most: int, step: int, rate: float, left: float, device: torch.device, world: int) -> int:
    """The schedule's length when the steps that fit in ``left`` seconds at ``rate`` steps/s follow
    ``step`` (at least one), at most ``most``; under torchrun every rank takes rank 0's."""
    steps = float(min(most, step + max(1, int(max(0.0, left) * rate))))
    if world > 1:
        flag = torch.tensor([steps], device=device, dtype=torch.float64)
        dist.broadcast(flag, src=0)
        steps = float(flag.item())
    return int(steps)


def out_of_time(deadline: float | None, now: float, device: torch.device, world: int) -> bool:
    """Whether the wall-clock budget is spent at clock ``now``; under torchrun every rank takes rank 0's."""
    return deadline is not None and rank0_says(now >= deadline, device, world)


def rank0_says(flag: bool, device: torch.device, world: int) -> bool:
    """``flag`` as rank 0 sees it (under torchrun: a decision on a clock every rank must take alike)."""
    if world > 1:
        value = torch.tensor([float(flag)], device=device)
        dist.broadcast(value, src=0)
        flag = bool(value.item())
    return flag
