"""The road ahead of guarded sampling (``SamplingConfig.guard_road_ahead``): a vehicle's candidate motion,
kept up (the same speed and turn rate: an arc), should stay on the road for some metres, as far as any
of its candidates can.

Why: the one-step road-edge rule lets a vehicle that drives straight at a bend run up to the edge, where
every moving candidate is masked, and then stand there for good (the model copies its own standstill):
guarded vehicles stood in 7.0 % of their racetrack steps against the log's 0 (docs/evaluation.md, stop
58). Looking along each candidate's arc, the guard masks the straight-on motions while the bend is still
ahead and turning ones remain.

A candidate's *reach* is how many of :data:`AHEAD_CHECKS` evenly spaced points of its arc (up to the set
distance) its box passes on the road in a row. Among the candidates the one-step rules allow, those that
move (at least :data:`AHEAD_MIN_MOVE` m a step) and reach less far than the farthest-reaching of them are
masked. The rule never masks standing or creeping candidates, and never leaves a vehicle without a move
the one-step rules allow. It does not weigh the model's mass: the kept candidates may be ones the model
all but rules out (a swerve of 0.03 %), and keeping only those that hold a share of the mass (1 %, 10 %)
froze more vehicles (docs/evaluation.md, stop 58)."""

from __future__ import annotations

import numpy as np

from trajeglish_env.compiled import pair_compiled
from trajeglish_env.geometry import to_global
from trajeglish_env.sampler.guard_edges import RoadView

AHEAD_CHECKS = 2  # points of a candidate's kept-up arc checked, evenly spaced up to the set distance
AHEAD_MIN_MOVE = 0.1  # m a step under which a candidate is not looked ahead (standing, creeping)
AHEAD_MOST_STEPS = 30.0  # a slow candidate's arc is followed for at most this many steps (3 s)


def kept_up(origin: np.ndarray, step: np.ndarray, distance: np.ndarray | float) -> np.ndarray:
    """Poses ``[...,3]`` reached from ``origin [...,3]`` by the motion ``step [...,3]`` (dx, dy and the
    heading change of one step, in the frame of the pose it starts from) kept up for ``distance`` m of
    travel, or :data:`AHEAD_MOST_STEPS` steps if that comes first (fractions of a step included)."""
    move = np.hypot(step[..., 0], step[..., 1])
    n = np.minimum(distance / np.maximum(move, 1e-9), AHEAD_MOST_STEPS)
    turn = step[..., 2]
    straight = np.abs(turn) < 1e-6
    th = np.where(straight, 1.0, turn)
    # a step turning by th is a rotation by th about the point c with (I - R(th)) c = d; n steps rotate
    # the start (the origin of its frame) about c by n th
    c, s = np.cos(th), np.sin(th)
    det = (1 - c) ** 2 + s * s
    cx = ((1 - c) * step[..., 0] - s * step[..., 1]) / det
    cy = (s * step[..., 0] + (1 - c) * step[..., 1]) / det
    cn, sn = np.cos(n * th), np.sin(n * th)
    x = np.where(straight, n * step[..., 0], cx - (cn * cx - sn * cy))
    y = np.where(straight, n * step[..., 1], cy - (sn * cx + cn * cy))
    return to_global(origin, np.stack([x, y, n * turn], -1))


def road_reach(
    edges: RoadView,
    sel: np.ndarray,
    origin: np.ndarray,
    size: np.ndarray,
    step: np.ndarray,
    distance: float,
    look: np.ndarray,
) -> np.ndarray:
    """``[m,c]`` how many points of the kept-up arcs of the candidates to ``look`` at ``[m,c]`` (pairs ``sel
    [m]`` at ``origin [m,3]``, boxes ``size [m,2]``, motions ``step [m,c,3]``), spaced ``distance`` /
    :data:`AHEAD_CHECKS` m apart, their boxes pass on the road before the first that is off it;
    :data:`AHEAD_CHECKS` for the others."""
    reach = np.full(step.shape[:2], AHEAD_CHECKS, np.int64)
    i, j = np.nonzero(look)
    if not len(i):
        return reach
    k = np.arange(1, AHEAD_CHECKS + 1)
    kernels = pair_compiled()
    if kernels is not None:  # the same poses, compiled (pair_kernels.kept_up_poses)
        pose = np.empty((len(i), AHEAD_CHECKS, 3))
        floats = (np.ascontiguousarray(a, np.float64) for a in (origin[i], step[i, j]))
        kernels.kept_up_poses(*floats, np.asarray(distance * k / AHEAD_CHECKS, np.float64), pose)
    else:
        pose = kept_up(origin[i, None], step[i, j, None], distance * k / AHEAD_CHECKS)  # [n,J,3]
    off = edges.beyond(sel[i], pose, size[i])  # [n,J]: one pass for every point
    reach[i, j] = np.where(off.any(axis=1), np.argmax(off, axis=1), AHEAD_CHECKS)
    return reach


def ahead_masks(reach: np.ndarray, look: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where only some candidates of each pair are known: of the looked-at ones ``look [m,c]`` (``reach
    [m,c]``), those masked for sure (they reach less far than another known one) and those *unsure*
    (short of the full reach, so an unknown candidate might reach farther)."""
    best = np.where(look, reach, -1).max(axis=1, initial=-1)[:, None]
    masked = look & (reach < best)
    return masked, look & ~masked & (reach < AHEAD_CHECKS)


def ahead_of_all(reach: np.ndarray, look: np.ndarray) -> np.ndarray:
    """``[m,c]`` the looked-at candidates the rule masks when every candidate of the pairs is known: those
    that reach less far than the farthest, none where that passes no point."""
    best = np.where(look, reach, 0).max(axis=1, initial=0)[:, None]
    return look & (reach < best)
