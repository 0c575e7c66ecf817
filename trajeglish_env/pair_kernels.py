"""Compiled kernels of the guard's view of a pair (numba, when installed): the obstacles near each sampled
agent, the following rule's speed cap and the stall rule's history, number for number the NumPy code of
:mod:`~trajeglish_env.sampler.guard_geometry`, :mod:`~trajeglish_env.sampler.guard_follow` and
:mod:`~trajeglish_env.sampler.guard_stall` they stand in for.

Each of those is a few dozen array calls on arrays of a few agents by a few dozen, called once or twice per
model call; in a single env their overhead, not their arithmetic, is the cost (stop 88: about a tenth of a
step). The loops here run the same float64 operations in the same order (no fused multiply-adds: numba's
default; sines, cosines and hypotenuses from the same C library as NumPy's here, which the tests check),
so every cap, flag and neighbour order equals the NumPy path's (``tests/test_pair_kernels.py``). Loaded on
first use through :func:`~trajeglish_env.compiled.pair_compiled`; without numba the NumPy paths run.
"""

from __future__ import annotations

import math

import numpy as np

from trajeglish_env.guard_kernels import _jit, box_gap
from trajeglish_env.sampler.guard_ahead import AHEAD_MOST_STEPS
from trajeglish_env.sampler.guard_follow import (
    FOLLOW_GAP,
    FOLLOW_SIDE,
    FOLLOW_SLACK,
    GRIP_BRAKE_STEP,
    MAX_CURVATURE,
    SAME_WAY,
    STEP_SECONDS,
)
from trajeglish_env.sampler.guard_signals import DEPART_STEP
from trajeglish_env.sampler.guard_stall import DROVE_MOVE, RELEASE_STEPS

COS_SAME_WAY = float(np.cos(SAME_WAY))


@_jit
def follow_caps(
    origin: np.ndarray,
    size: np.ndarray,
    pace: np.ndarray,
    turn: np.ndarray,
    state: np.ndarray,
    sizes: np.ndarray,
    present: np.ndarray,
    velocity: np.ndarray,
    riders: np.ndarray,
    decel: float,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled (its NumPy twin is guard_follow.follow_caps)
    """``out [n]``: :func:`~trajeglish_env.sampler.guard_follow.follow_caps` of the same arguments."""
    dt = STEP_SECONDS
    for i in range(present.shape[0]):
        c, s = np.cos(origin[i, 2]), np.sin(origin[i, 2])
        least = pace[i] if (pace[i] >= 0.05 or np.isnan(pace[i])) else 0.05  # np.maximum keeps NaN
        bend = turn[i] / least
        if np.isnan(bend):
            bend = 0.0
        curvature = min(max(bend, -MAX_CURVATURE), MAX_CURVATURE)
        cap = np.inf
        for j in range(present.shape[1]):
            if not (present[i, j] and riders[i, j]):
                continue
            dx, dy = state[i, j, 0] - origin[i, 0], state[i, j, 1] - origin[i, 1]
            along, across = dx * c + dy * s, dy * c - dx * s
            if not along > 0:
                continue
            if not np.cos(state[i, j, 2] - origin[i, 2]) > COS_SAME_WAY:
                continue
            off_path = np.abs(across - curvature * along * along / 2)
            if not off_path < (size[i, 1] + sizes[i, j, 1]) / 2 + FOLLOW_SIDE:
                continue
            gap = along - (size[i, 0] + sizes[i, j, 0]) / 2
            v_ahead = max(velocity[i, j, 0] * c + velocity[i, j, 1] * s, 0.0)
            budget = gap - FOLLOW_GAP + v_ahead * v_ahead / (2 * decel)
            speed = decel * (np.sqrt(dt * dt + 2 * max(budget, 0.0) / decel) - dt)
            step = speed * dt
            if step < cap:
                cap = step
        if np.isfinite(cap):
            floor = 0.0 if np.isnan(pace[i]) else pace[i] - GRIP_BRAKE_STEP
            out[i] = max(cap, floor)
        else:
            out[i] = np.inf


@_jit
def _move(mxyh: np.ndarray, valid: np.ndarray, i: int, k: int, t: int) -> float:
    """Agent ``i``'s move (m) from step ``k - 1`` to ``k``; NaN where unknown (either state invalid, or
    after ``t``)."""  # pragma: no cover - compiled
    if not (valid[i, k] and valid[i, k - 1] and k <= t):
        return np.nan
    return math.hypot(mxyh[i, k, 0] - mxyh[i, k - 1, 0], mxyh[i, k, 1] - mxyh[i, k - 1, 1])


@_jit
def stalled(
    mxyh: np.ndarray, valid: np.ndarray, t: np.ndarray, min_steps: int, out: np.ndarray
) -> None:  # pragma: no cover - compiled (its NumPy twin is guard_stall.stalled)
    """``out [n]``: :func:`~trajeglish_env.sampler.guard_stall.stalled` of the same arguments."""
    for i in range(valid.shape[0]):
        last_stand = 0
        for k in range(1, valid.shape[1]):
            if _move(mxyh, valid, i, k, t[i]) < DEPART_STEP:
                last_stand = k
        start = 0  # the last step at or before the run's end that did not stand (0: none)
        for k in range(max(last_stand, 1), 0, -1):
            if not _move(mxyh, valid, i, k, t[i]) < DEPART_STEP:
                start = k
                break
        drove = False
        for k in range(1, start + 1):
            if _move(mxyh, valid, i, k, t[i]) > DROVE_MOVE:
                drove = True
                break
        run = last_stand - start
        out[i] = last_stand > 0 and run >= min_steps and t[i] - last_stand <= RELEASE_STEPS and drove


@_jit
def neighbours(
    origin: np.ndarray,
    size: np.ndarray,
    extent: np.ndarray,
    who: np.ndarray,
    state: np.ndarray,
    present: np.ndarray,
    sizes: np.ndarray,
    escape_rule: bool,
    into_ok: np.ndarray,
    now: np.ndarray,
    order: np.ndarray,
    count: np.ndarray,
    escape: np.ndarray,
    tangled: np.ndarray,
) -> None:  # pragma: no cover - compiled (its NumPy twin is guard_neighbours.neighbours)
    """The obstacles of :func:`~trajeglish_env.sampler.guard_neighbours.neighbours`: per pair,
    ``order [n,N]`` its near agents by (distance, index) then the others by index, ``count [n]`` how many
    are near, ``escape [n,N]`` (per agent) those kept only to be escaped, ``tangled [n]`` whether its box
    overlaps one already. ``into_ok [n,N]``: the agents that may have moved into its box this step (moved,
    present before and after, not external); ``now [n,N,3]`` their states before."""
    n, agents = present.shape
    dist, listed = np.empty(agents), np.zeros(agents, np.bool_)
    for i in range(n):
        tangled[i] = False
        used = 0
        ox, oy, oh, ol, ow = origin[i, 0], origin[i, 1], origin[i, 2], size[i, 0], size[i, 1]
        for j in range(agents):
            escape[i, j] = False
            dist[j] = np.hypot(state[i, j, 0] - ox, state[i, j, 1] - oy)
            reach = extent[i] + np.hypot(sizes[i, j, 0], sizes[i, j, 1]) / 2
            if j == who[i] or not (present[i, j] and dist[j] < reach):
                continue
            sl, sw = sizes[i, j, 0], sizes[i, j, 1]
            if box_gap(ox, oy, oh, ol, ow, state[i, j, 0], state[i, j, 1], state[i, j, 2], sl, sw) < 0:
                tangled[i] = True
                if not (escape_rule and into_ok[i, j]):
                    continue
                if box_gap(ox, oy, oh, ol, ow, now[i, j, 0], now[i, j, 1], now[i, j, 2], sl, sw) < 0:
                    continue  # overlapping before it moved too: tangled, not escapable
                escape[i, j] = True
            # insert j after every listed agent no farther than it: (distance, index) order
            at = used
            while at > 0 and dist[order[i, at - 1]] > dist[j]:
                order[i, at] = order[i, at - 1]
                at -= 1
            order[i, at] = j
            used += 1
        count[i] = used
        listed[:] = False
        for q in range(used):
            listed[order[i, q]] = True
        for j in range(agents):  # then the agents not near, by index
            if not listed[j]:
                order[i, used] = j
                used += 1


@_jit
def lanes_against(
    masks: np.ndarray, x0: float, y0: float, cell: float, xyh: np.ndarray, agree: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled (its NumPy twin is LaneDirections.against)
    """``out [m]``: :meth:`~trajeglish_env.sampler.lane_directions.LaneDirections.against` of boxes ``xyh
    [m,3]`` on the grid ``masks [ny,nx]`` at ``(x0, y0)`` of cells of side ``cell``."""
    ny, nx = masks.shape
    bins = agree.shape[0]
    width = 2 * np.pi / bins
    for i in range(xyh.shape[0]):
        fx, fy = np.floor((xyh[i, 0] - x0) / cell), np.floor((xyh[i, 1] - y0) / cell)
        if not (0 <= fx < nx and 0 <= fy < ny):  # off the grid (NaN too): no lane, never against
            out[i] = False
            continue
        bits = np.int64(masks[np.int64(fy), np.int64(fx)])
        heading = np.int64(np.floor(np.mod(xyh[i, 2], 2 * np.pi) / width)) % bins
        out[i] = bits != 0 and (bits & agree[heading]) == 0


@_jit
def blocked_core(
    cand: np.ndarray,
    size: np.ndarray,
    near_xyh: np.ndarray,
    near_size: np.ndarray,
    near_real: np.ndarray,
    near_escape: np.ndarray,
    step: np.ndarray,
    cap: np.ndarray,
    need_go: np.ndarray,
    need_stall: np.ndarray,
    pace: np.ndarray,
    change_limit: np.ndarray,
    collide: np.ndarray,
    escape: np.ndarray,
    off: np.ndarray,
    jump: np.ndarray,
) -> None:  # pragma: no cover - compiled (its NumPy twin: GuardGeometry.blocked_parts without numba)
    """The rules of :meth:`~trajeglish_env.sampler.guard_geometry.GuardGeometry.blocked_parts` that need no
    map, for candidate poses ``cand [m,c,3]`` (forward steps ``step [m,c]``) of ``m`` pairs: ``collide`` /
    ``escape [m,c]`` overlaps with an obstacle to avoid or only to escape; ``off [m,c]`` faster than the
    following ``cap [m]`` allows, or slower than a departure needs (``need_go [m]``, NaN: none); ``jump
    [m,c]`` a forward step changed by more than ``change_limit [m]`` from ``pace [m]``, or slower than a
    stalled rider's ``need_stall [m]``."""
    for i in range(step.shape[0]):
        own = np.hypot(size[i, 0], size[i, 1]) / 2
        for v in range(step.shape[1]):
            x, y, h = cand[i, v, 0], cand[i, v, 1], cand[i, v, 2]
            hard, soft = False, False
            for k in range(near_xyh.shape[1]):
                if not near_real[i, k]:
                    continue
                limit = own + np.hypot(near_size[i, k, 0], near_size[i, k, 1]) / 2
                dx, dy = x - near_xyh[i, k, 0], y - near_xyh[i, k, 1]
                if not dx * dx + dy * dy < limit * limit:  # circles apart: boxes apart
                    continue
                nx, ny, nh = near_xyh[i, k, 0], near_xyh[i, k, 1], near_xyh[i, k, 2]
                if (
                    box_gap(
                        x, y, h, size[i, 0], size[i, 1], nx, ny, nh, near_size[i, k, 0], near_size[i, k, 1]
                    )
                    < 0
                ):
                    if near_escape[i, k]:
                        soft = True
                    else:
                        hard = True
            collide[i, v], escape[i, v] = hard, soft
            s = step[i, v]
            off[i, v] = s > cap[i] + FOLLOW_SLACK or s < need_go[i]
            change = np.abs(s - pace[i]) / change_limit[i]
            jump[i, v] = (change > 1.0 and not np.isnan(change)) or s < need_stall[i]


@_jit
def memo_gather(
    keys_store: np.ndarray,
    values: np.ndarray,
    rows: np.ndarray,
    agents: np.ndarray,
    keys: np.ndarray,
    entries: np.ndarray,
    want: np.ndarray,
    got: np.ndarray,
) -> int:  # pragma: no cover - compiled (its NumPy twin: CandidateMemo.lookup without numba)
    """The memory part of :meth:`~trajeglish_env.sampler.candidate_memo.CandidateMemo.lookup`: slots whose
    stored key differs from ``keys [m,K]`` (compared first for every slot, then cleared and re-keyed in
    order) lose their answers; ``got [m,c]`` the stored answers at ``entries`` where ``want`` (NaN
    elsewhere). Returns how many wanted entries are not known yet (NaN)."""
    m = rows.shape[0]
    stale = np.zeros(m, np.bool_)
    for i in range(m):
        for q in range(keys.shape[1]):
            if not keys_store[rows[i], agents[i], q] == keys[i, q]:
                stale[i] = True
                break
    for i in range(m):
        if stale[i]:
            values[rows[i], agents[i], :] = np.nan
            keys_store[rows[i], agents[i], :] = keys[i, :]
    missing = 0
    for i in range(m):
        for j in range(entries.shape[1]):
            if want[i, j]:
                got[i, j] = values[rows[i], agents[i], entries[i, j]]
                if np.isnan(got[i, j]):
                    missing += 1
            else:
                got[i, j] = np.nan
    return missing


@_jit
def kept_up_poses(
    origin: np.ndarray, step: np.ndarray, distance: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled (its NumPy twin is guard_ahead.kept_up)
    """``out [n,J,3]``: :func:`~trajeglish_env.sampler.guard_ahead.kept_up` of poses ``origin [n,3]`` and
    motions ``step [n,3]`` kept up for each of ``distance [J]`` m."""
    for i in range(origin.shape[0]):
        sx, sy, turn = step[i, 0], step[i, 1], step[i, 2]
        move = np.hypot(sx, sy)
        straight = np.abs(turn) < 1e-6
        th = 1.0 if straight else turn
        c, s = np.cos(th), np.sin(th)
        det = (1 - c) * (1 - c) + s * s
        cx = ((1 - c) * sx - s * sy) / det
        cy = (s * sx + (1 - c) * sy) / det
        oc, os_ = np.cos(origin[i, 2]), np.sin(origin[i, 2])
        for q in range(distance.shape[0]):
            n = min(distance[q] / max(move, 1e-9), AHEAD_MOST_STEPS)
            cn, sn = np.cos(n * th), np.sin(n * th)
            x = n * sx if straight else cx - (cn * cx - sn * cy)
            y = n * sy if straight else cy - (sn * cx + cn * cy)
            out[i, q, 0] = origin[i, 0] + oc * x - os_ * y
            out[i, q, 1] = origin[i, 1] + os_ * x + oc * y
            out[i, q, 2] = (origin[i, 2] + n * turn + np.pi) % (2.0 * np.pi) - np.pi


@_jit
def guard_view(
    known: np.ndarray,
    rank: np.ndarray,
    controlled: np.ndarray,
    external: np.ndarray,
    xyh: np.ndarray,
    now: np.ndarray,
    rr: np.ndarray,
    who: np.ndarray,
    draft: np.ndarray,
    drafted: np.ndarray,
    moved: np.ndarray,
    after: np.ndarray,
) -> None:  # pragma: no cover - compiled (its NumPy twin is parallel.guard_view)
    """``moved [n,N]`` and ``after [n,N,3]`` of :func:`~trajeglish_env.sampler.parallel.guard_view` for pairs
    ``(rr, who)`` sorted by row (``draft [n]``: their carried drafts, -1 none; ``drafted [n,3]``: the next
    states those drafts give), from the rows' ``known``, acting ``rank``, ``controlled``/``external`` flags,
    states ``xyh`` and steps ``now``."""
    n, agents = moved.shape
    first, last = np.empty(agents, np.int64), np.empty(agents, np.int64)
    start = 0
    while start < n:
        r, stop = rr[start], start
        while stop < n and rr[stop] == r:
            stop += 1
        first[:], last[:] = n, -1  # per agent: the first and the last pair of the row that drafts it
        for q in range(start, stop):
            if draft[q] >= 0:
                if first[who[q]] == n:
                    first[who[q]] = q
                last[who[q]] = q
        t = now[r]
        for p in range(start, stop):
            own = rank[r, who[p]]
            for a in range(agents):
                # decided this step, but not a logged agent acting after it; or drafted by a pair before it
                seen = known[r, a, t] and not (
                    own >= 0 and rank[r, a] > own and not (controlled[r, a] or external[r, a])
                )
                seen = seen or first[a] < p
                moved[p, a] = seen
                source = drafted[last[a]] if seen and last[a] >= 0 else xyh[r, a, t + 1]
                after[p, a, 0], after[p, a, 1], after[p, a, 2] = source[0], source[1], source[2]
        start = stop
