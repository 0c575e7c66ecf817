"""Who moved into whom: one agent's collisions in rollouts, told apart by which side moved into the other.

Partial-control evaluation replays every agent but one from the log; the replayed agents do not react, so
many of the controlled agent's collisions are theirs. At each rollout's first collision, an agent whose
new box overlaps the controlled agent's box of the step before moved into it (as does one that only just
appeared there); the controlled agent is at fault when it overlaps any other agent, i.e. one that was
elsewhere: it moved into them, or both moved into the same free spot. "Struck" (not at fault) therefore
says that every agent it overlaps moved into its previous box; the controlled agent may have moved into
theirs too (both driving into each other counts as struck: a turning sdc met by a logged car holding 8 m/s,
the ego-evaluation audit of stop 82), so ``at_fault_rate`` is a lower bound of the collisions the
controlled agent had a part in.
"""

from __future__ import annotations

import numpy as np

from trajeglish_env.metrics.boxes import box_collisions


def collisions_by_fault(
    xyh: np.ndarray, valid: np.ndarray, size: np.ndarray, agent: int, start: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per rollout (``xyh [R,N,T,3]``, ``valid [R,N,T]``, box ``size [N,2]``): whether ``agent``'s box
    overlaps another's after step ``start``, and whether it is at fault at the first such step (see the
    module docstring). Both ``[R]`` bool."""
    others = np.flatnonzero(np.arange(xyh.shape[1]) != agent)
    own = xyh[:, agent, start:][:, None]  # [R,1,H+1,3], from step ``start``
    oth, ok = xyh[:, others, start:], valid[:, others, start:]
    own_size, oth_size = size[agent], size[others][None, :, None]
    hit = box_collisions(own[:, :, 1:], own_size, oth[:, :, 1:], oth_size) & ok[:, :, 1:]  # [R,O,H]
    collided = hit.any(axis=(1, 2))
    first = np.argmax(hit.any(axis=1), axis=1)  # [R] index of the first colliding step (of H)
    rows = np.arange(len(hit))
    own_before = own[rows, 0, first][:, None]  # [R,1,3]
    into_me = box_collisions(oth[rows, :, first + 1], oth_size[:, :, 0], own_before, own_size)
    into_me |= ~ok[rows, :, first]  # appeared where the agent is
    at_fault = collided & (hit[rows, :, first] & ~into_me).any(axis=1)
    return collided, at_fault
