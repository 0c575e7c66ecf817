"""The stall rule of guarded sampling (``SamplingConfig.guard_stall_steps``), masked with the speed-change
rule (and widened with it first when nothing else is left): a vehicle or cyclist that drove, then stood
still for at least that many steps, and now has the way clear (no box within
:data:`CLEAR_GAP` m ahead in its lane, no red light within reach, not
under the green rule, which governs stop lines) must set off at pace: as under the green rule, its
candidates moving less than :data:`DEPART_STEP`, or less than :data:`DEPART_GAIN` more than its last step,
are masked until it moves :data:`DEPART_PACE` m a step (1.5 m/s) or :data:`RELEASE_STEPS` steps have passed.
A rider is pushed only while the model itself gives moving less than :data:`FROZEN_MASS` (it has frozen);
once pushed, it stays under the rule through its departure.

Why: once a guarded vehicle stands (the guard slowed it for a crossing car, the model stopped it), the model
reads its own standstill and keeps drawing standstills, the way ahead clear or not (in ``make demo``'s
episode an NPC stood at the crossing from 3.8 s to the end with the crossing empty, the model's mass on
moving tokens 0.000). Agents that have not driven in the log's
history or the rollout (parked cars) are never pushed."""

from __future__ import annotations

import numpy as np

from trajeglish_env.compiled import pair_compiled
from trajeglish_env.sampler.guard_signals import DEPART_GAIN, DEPART_PACE, DEPART_STEP

# Steps of the departure phase after a stall: the rule holds for at most this many steps after the last
# standing one (DEPART_PACE / DEPART_GAIN = 15 steps from standstill to pace, with 5 to spare).
RELEASE_STEPS = 20
# Metres a step above which an agent drives (the env's and the metrics' standing speed, 0.5 m/s).
DROVE_MOVE = 0.05
# The model's probability of a moving token under which a stalled rider is pushed: the demo's stalled NPC
# had 0.000 (the model copying its own standstill); a rider the model means to set off some time keeps its
# own timing (on the bundled SUMO scenes every rider the rule pushed had under 2 %: the model had frozen).
FROZEN_MASS = 0.02


def stall_candidates(pace: np.ndarray, clear: np.ndarray) -> np.ndarray:
    """``[n]`` the pairs the stall rule may apply to before their history is read: a known last move under
    :data:`DEPART_PACE` (vehicles and cyclists: pedestrians' pace is NaN) and the way ``clear``."""
    with np.errstate(invalid="ignore"):
        return clear & (pace < DEPART_PACE)


def stalled(mxyh: np.ndarray, valid: np.ndarray, t: np.ndarray, min_steps: int) -> np.ndarray:
    """``[n]`` from the model states ``mxyh [n,T,3]`` / ``valid [n,T]`` of n agents up to their steps ``t
    [n]``: those whose last run of standing steps (moving less than :data:`DEPART_STEP` m each) lasted at
    least ``min_steps`` steps, ended at most :data:`RELEASE_STEPS` steps before ``t`` (or at ``t``), and
    came after a step that drove (more than :data:`DROVE_MOVE` m). Compiled where numba is available
    (:mod:`~trajeglish_env.pair_kernels`)."""
    kernels = pair_compiled()
    if kernels is not None:
        out = np.empty(len(valid), bool)
        kernels.stalled(
            np.ascontiguousarray(mxyh, np.float64), valid, t.astype(np.int64), int(min_steps), out
        )
        return out
    n, T = valid.shape
    k = np.arange(1, T)
    move = np.hypot(*(mxyh[:, 1:, :2] - mxyh[:, :-1, :2]).transpose(2, 0, 1))  # [n,T-1] step k-1 -> k
    known = valid[:, 1:] & valid[:, :-1] & (k[None] <= t[:, None])
    stands = known & (move < DEPART_STEP)
    drives = known & (move > DROVE_MOVE)
    last_stand = np.where(stands, k, 0).max(axis=1)  # 0: never stood
    # per step: the last step at or before it that did not stand (the run of standing steps starts after it)
    broke = np.maximum.accumulate(np.where(~stands, k, 0), axis=1)
    rows = np.arange(n)
    start = broke[rows, np.maximum(last_stand - 1, 0)]  # the run ending at last_stand began after this step
    run = last_stand - start
    drove = np.logical_or.accumulate(drives, axis=1)[rows, np.maximum(start - 1, 0)] & (start > 0)
    return (last_stand > 0) & (run >= min_steps) & (t - last_stand <= RELEASE_STEPS) & drove


def departure_need(pace: np.ndarray) -> np.ndarray:
    """``[m]`` the least forward step (m) a departing rider's candidate must make after a last step of
    ``pace [m]`` (NaN: none known): :data:`DEPART_GAIN` more than its last one, at least :data:`DEPART_STEP`,
    at most :data:`DEPART_PACE` (the green rule's mask)."""
    return np.where(np.isnan(pace), DEPART_STEP, np.clip(pace + DEPART_GAIN, DEPART_STEP, DEPART_PACE))


def frozen(probs: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """``[m]`` riders whose probabilities ``probs [m,V]`` (the draw's) put less than :data:`FROZEN_MASS` on
    their moving tokens ``moving [m,V]``: the model has stopped meaning to move."""
    return (probs * moving).sum(axis=1) < FROZEN_MASS


# Metres between a rider's front and the box ahead of it under which the green rule does not push it on
# (SUMO's standstill gap, minGap); boxes whose centres lie within the widths' half sum plus CLEAR_SIDE m of
# its centre line count as ahead.
CLEAR_GAP, CLEAR_SIDE = 2.5, 0.25


def way_clear(
    origin: np.ndarray, size: np.ndarray, near_xyh: np.ndarray, near_size: np.ndarray, near_real: np.ndarray
) -> np.ndarray:
    """``[n]`` no obstacle ``near_xyh [n,K,3]`` (``near_size``, ``near_real [n,K]``) within
    :data:`CLEAR_GAP` m ahead of the front of the box at ``origin [n,3]`` (``size [n,2]``), in its lane."""
    c, s = np.cos(origin[:, 2])[:, None], np.sin(origin[:, 2])[:, None]
    dx, dy = near_xyh[..., 0] - origin[:, None, 0], near_xyh[..., 1] - origin[:, None, 1]
    along, across = dx * c + dy * s, np.abs(dy * c - dx * s)
    ahead = (along > 0) & (along < (size[:, 0, None] + near_size[..., 0]) / 2 + CLEAR_GAP)
    beside = across < (size[:, 1, None] + near_size[..., 1]) / 2 + CLEAR_SIDE
    return ~(near_real & ahead & beside).any(axis=1)
