"""Who moved into whom (partial control's split of the controlled agent's collisions)."""

from __future__ import annotations

import numpy as np

from trajeglish_env.metrics.collision_fault import collisions_by_fault

SIZE = np.tile([4.5, 2.0], (3, 1))  # agent 0 is the controlled one


def _standing(rollouts: int, steps: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Three cars in one lane standing at x = 0 (the controlled one), -20 and +20."""
    xyh = np.zeros((rollouts, 3, steps, 3))
    xyh[..., 0] = np.array([0.0, -20.0, 20.0])[None, :, None]
    return xyh, np.ones((rollouts, 3, steps), bool)


def test_driving_into_a_standing_car_is_at_fault_being_driven_into_is_not() -> None:
    xyh, valid = _standing(4)
    t = np.arange(12)
    xyh[1, 0, :, 0] = np.minimum(2.0 * t, 16.0)  # the controlled car drives into the car ahead
    xyh[2, 1, :, 0] = np.minimum(-20.0 + 2.0 * t, -4.0)  # the car behind drives into the controlled one
    xyh[3, 0, :, 0] = np.minimum(2.0 * t, 8.0)  # both drive into the same free spot: at fault
    xyh[3, 2, :, 0] = np.maximum(20.0 - 2.0 * t, 12.0)
    hit, at_fault = collisions_by_fault(xyh, valid, SIZE, agent=0, start=0)
    assert hit.tolist() == [False, True, True, True]
    assert at_fault.tolist() == [False, True, False, True]


def test_absent_agents_neither_collide_nor_count_and_one_appearing_on_it_is_not_its_fault() -> None:
    xyh, valid = _standing(2)
    xyh[:, 1, :, 0] = -2.0  # overlapping the controlled car from step 0 on ...
    valid[0, 1] = False  # ... but absent in rollout 0
    valid[1, 1, :5] = False  # ... and appearing there at step 5 in rollout 1
    hit, at_fault = collisions_by_fault(xyh, valid, SIZE, agent=0, start=0)
    assert hit.tolist() == [False, True] and at_fault.tolist() == [False, False]
    later = collisions_by_fault(xyh, valid, SIZE, agent=0, start=6)  # contact going on: still not its fault
    assert later[0].tolist() == [False, True] and later[1].tolist() == [False, False]
