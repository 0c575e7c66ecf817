"""Motion envelopes: deterministic one-step transitions spanning every motion an agent class can make, a
greedy cover of them by templates, and drift checks of tokenized tracks.

A vocabulary fitted on data alone only reaches the transitions seen in that data; a faster, reversing or
tighter-turning track then falls behind its tokenized state. :func:`envelope_transitions` enumerates
unicycle steps over a grid of (speed, acceleration, curvature) within a class's :class:`Envelope`, and
:func:`cover_templates` picks templates so that every envelope transition has one within ``radius``
(mean corner distance of the envelope's box), which fitting reserves in every candidate set.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from trajeglish_env.kinematics import VehicleLimits
from trajeglish_env.scenario import AgentKind
from trajeglish_env.tokenizer.distance import corner_distance
from trajeglish_env.tokenizer.tokenize import tokenize
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

DRIFT_TOLERANCE_M = 0.05  # held-out tracks: error beyond this counts as drift (the coverage target)


@dataclass(frozen=True)
class Envelope:
    """Motion limits of one class: speed in [min_speed, max_speed] m/s (negative: reversing), speed
    change up to ``max_accel`` / ``max_brake`` m/s^2, curvature up to min(1 / min_turn_radius,
    max_lateral_accel / v^2); the cover is measured with a ``length`` x ``width`` box (m) and must reach
    every envelope transition within ``radius`` m; its lattice reaches ``catch_up`` spacings beyond the
    speed and turn limits (see :func:`lattice_templates`)."""

    min_speed: float
    max_speed: float
    max_accel: float
    max_brake: float
    max_lateral_accel: float
    min_turn_radius: float
    length: float
    width: float
    radius: float = 0.03
    speed_step: float = 0.25
    curvatures: int = 25
    catch_up: float = 0.5

    def __post_init__(self) -> None:
        if not self.min_speed <= 0.0 < self.max_speed:
            raise ValueError(
                f"Envelope: need min_speed <= 0 < max_speed, got {self.min_speed}, {self.max_speed}"
            )
        for name in ("max_lateral_accel", "min_turn_radius", "length", "width", "radius", "speed_step"):
            if not getattr(self, name) > 0:
                raise ValueError(f"Envelope: {name} must be > 0, got {getattr(self, name)}")
        if self.max_accel < 0 or self.max_brake < 0 or self.curvatures < 1 or self.catch_up < 0:
            raise ValueError("Envelope: max_accel, max_brake, catch_up must be >= 0 and curvatures >= 1")

    def to_json(self) -> dict[str, float | int]:
        """The fields as a JSON-able dict (for vocabulary metadata)."""
        return {k: (int(v) if isinstance(v, int) else float(v)) for k, v in self.__dict__.items()}


def vehicle_envelope(limits: VehicleLimits | None = None, reverse_speed: float = 4.0) -> Envelope:
    """The env's vehicle limits (speed up to ``max_speed``, its brake/accel, lateral-accel and steering
    limit for a 4.8 m car) plus reversing at up to ``reverse_speed`` m/s (logged scenes reverse)."""
    lim = limits or VehicleLimits()
    length = 4.8
    radius = lim.wheelbase_ratio * length / np.tan(lim.max_steer)
    return Envelope(
        min_speed=-reverse_speed,
        max_speed=lim.max_speed,
        max_accel=max(lim.max_accel, 8.0),  # logged hard braking/acceleration exceeds the env's action
        max_brake=max(lim.max_brake, 8.0),
        max_lateral_accel=lim.max_lateral_accel,
        min_turn_radius=float(radius),
        length=length,
        width=2.0,
        radius=0.045,
    )


DEFAULT_ENVELOPES: dict[AgentKind, Envelope] = {
    AgentKind.VEHICLE: vehicle_envelope(),
    AgentKind.PEDESTRIAN: Envelope(
        min_speed=-2.5, max_speed=4.0, max_accel=4.0, max_brake=4.0, max_lateral_accel=6.0,
        min_turn_radius=0.3, length=0.8, width=0.8, speed_step=0.1,
    ),
    AgentKind.CYCLIST: Envelope(
        min_speed=-1.0, max_speed=15.0, max_accel=4.0, max_brake=6.0, max_lateral_accel=5.0,
        min_turn_radius=2.0, length=2.0, width=0.8, speed_step=0.2,
    ),
}  # fmt: skip


def unicycle_step(speed: np.ndarray, accel: np.ndarray, curvature: np.ndarray, dt: float) -> np.ndarray:
    """``[...,3]`` local (dx, dy, dh) of one step of length (v + v') dt / 2 along an arc of ``curvature``."""
    s = (2.0 * speed + accel * dt) * dt / 2.0
    dh = s * curvature
    dx = s * np.sinc(dh / np.pi)
    dy = s * (dh / 2.0) * np.sinc(dh / (2.0 * np.pi)) ** 2
    return np.stack(np.broadcast_arrays(dx, dy, dh), -1)


def envelope_transitions(env: Envelope, dt: float) -> np.ndarray:
    """Deterministic transitions ``[M,3]`` over a grid of start speed, speed change and curvature."""
    if not dt > 0:
        raise ValueError(f"envelope_transitions: dt must be > 0 s, got {dt}")
    count = int(np.ceil((env.max_speed - env.min_speed) / env.speed_step)) + 1
    speed = np.linspace(env.min_speed, env.max_speed, count)
    accel = np.array([-env.max_brake, -env.max_brake / 2, 0.0, env.max_accel / 2, env.max_accel])
    frac = np.linspace(-1.0, 1.0, env.curvatures)
    v, a, f = np.meshgrid(speed, accel, frac, indexing="ij")
    # The speed never crosses zero in one step (stop, then reverse) and stays within the envelope.
    a = np.where(
        v > 0, np.clip(a, -v / dt, (env.max_speed - v) / dt), np.clip(a, (env.min_speed - v) / dt, -v / dt)
    )
    mean = np.abs(v + a * dt / 2)
    kmax = np.minimum(1.0 / env.min_turn_radius, env.max_lateral_accel / np.maximum(mean, 1e-3) ** 2)
    steps = unicycle_step(v, a, f * kmax, dt).reshape(-1, 3)
    return np.unique(np.round(steps, 6), axis=0)


def _nearest_distance(points: np.ndarray, templates: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Distance ``[M]`` from each point to its nearest template (chunked over points)."""
    if len(templates) == 0:
        return np.full(len(points), np.inf)
    out = np.empty(len(points))
    for lo in range(0, len(points), 2048):
        d = corner_distance(points[lo : lo + 2048, None], templates[None], box)
        out[lo : lo + 2048] = d.min(1)
    return out


def cover_templates(
    points: np.ndarray, radius: float, box: np.ndarray, existing: np.ndarray | None = None
) -> np.ndarray:
    """Greedy cover: templates (drawn from ``points [M,3]``, in their order) until every point is within
    ``radius`` (mean corner distance of ``box`` = (length, width)) of one of them or of ``existing``."""
    box = np.asarray(box, dtype=np.float64)
    alive = np.ones(len(points), bool)
    if existing is not None and len(existing):
        alive = _nearest_distance(points, np.asarray(existing, np.float64), box) > radius
    chosen: list[np.ndarray] = []
    idx = np.flatnonzero(alive)
    while len(idx):
        pick = points[idx[0]]
        chosen.append(pick)
        idx = idx[corner_distance(pick, points[idx], box) > radius]
    return np.stack(chosen) if chosen else np.zeros((0, 3))


def lattice_templates(env: Envelope, dt: float, radius: float) -> np.ndarray:
    """Templates on the envelope's (arc length, heading change) surface, hexagonally packed: rows of arc
    length ``1.5 radius`` apart, heading changes ``min(sqrt(3) radius / half-diagonal, 1.5 radius / |s|)``
    apart within a row of arc length ``s`` (at speed, a heading error's lever over the next step outweighs
    the box's half-diagonal), odd counts (a straight template) on even rows and even counts on odd rows, so
    neighbouring rows interleave. Rows and headings reach ``env.catch_up`` spacings beyond the envelope's
    speed and turn limits: a track at a limit lags its tokenized state a little, and without templates
    that go faster or turn harder the lag only grows (measured on :func:`stress_tracks`: metres over 5 s)."""
    half = 0.5 * float(np.hypot(env.length, env.width))
    ds = 1.5 * radius
    lo = (env.min_speed - env.max_brake * dt / 2) * dt - env.catch_up * ds
    hi = (env.max_speed + env.max_accel * dt / 2) * dt + env.catch_up * ds
    rows = int(np.ceil((hi - lo) / ds))
    arc = np.linspace(lo + (hi - lo) / rows / 2, hi - (hi - lo) / rows / 2, rows)
    mag = np.maximum(np.abs(arc), 1e-9)
    dhs = np.minimum(np.sqrt(3.0) * radius / half, 1.5 * radius / mag)
    limit = np.minimum(mag / env.min_turn_radius, env.max_lateral_accel * dt * dt / mag)
    count = np.ceil(2.0 * (limit / dhs + env.catch_up)).astype(np.int64)
    odd = np.arange(rows) % 2 == 0
    count = np.maximum(np.where((count % 2 == 1) == odd, count, count + 1), 1)
    row = np.repeat(np.arange(rows), count)
    pos = np.arange(len(row)) - np.repeat(np.cumsum(count) - count, count)  # index within the row
    dh = dhs[row] * (pos - (count[row] - 1) / 2.0)
    s = arc[row]
    curvature = np.where(np.abs(s) > 1e-9, dh / np.where(np.abs(s) > 1e-9, s, 1.0), 0.0)
    return unicycle_step(s / dt, np.zeros_like(s), curvature, dt)


def envelope_cover(
    kind: AgentKind, dt: float, envelope: Envelope | None = None, radius: float | None = None
) -> np.ndarray:
    """Templates ``[K,3]`` covering ``kind``'s envelope (default :data:`DEFAULT_ENVELOPES`) within
    ``radius`` (default the envelope's): a lattice, patched greedily where an envelope transition is
    still farther than ``radius`` from it."""
    env = envelope or DEFAULT_ENVELOPES[kind]
    r = env.radius if radius is None else float(radius)
    lattice = lattice_templates(env, dt, r)
    points = envelope_transitions(env, dt)
    patch = cover_templates(points, r, np.array([env.length, env.width]), lattice)
    return np.concatenate([lattice, patch])


def envelope_error(
    templates: np.ndarray, kind: AgentKind, dt: float, envelope: Envelope | None = None
) -> float:
    """Largest one-step distance (m, envelope box) from an envelope transition to its nearest template."""
    env = envelope or DEFAULT_ENVELOPES[kind]
    points = envelope_transitions(env, dt)
    return float(_nearest_distance(points, templates, np.array([env.length, env.width])).max())


def stress_tracks(env: Envelope, dt: float, steps: int = 50) -> np.ndarray:
    """Deterministic tracks ``xyh [M, steps, 3]`` at the envelope's edges: start speeds 2 m/s apart over
    [min_speed, max_speed], braking at ``max_brake``, constant speed or accelerating at ``max_accel``
    (forward starts; reversing ones keep their speed), each turning at its full and half turn limit both
    ways (the limit follows the speed). The cover's one-step radius does not bound how far a tokenized
    track lags behind these; :func:`stress_error` measures it."""
    t = np.arange(steps)
    starts = np.unique(np.r_[np.arange(env.min_speed, env.max_speed, 2.0), env.max_speed])
    speeds = []
    for v0 in starts:
        accels = (-env.max_brake, 0.0, env.max_accel) if v0 > 0 else (0.0,)
        for a in accels:
            speeds.append(np.clip(v0 + a * dt * t, 0.0 if v0 > 0 else env.min_speed, env.max_speed))
    v = np.repeat(np.stack(speeds), 4, axis=0)  # [M, steps]
    frac = np.tile([-1.0, -0.5, 0.5, 1.0], len(speeds))[:, None]
    mean = np.maximum(np.abs(v[:, :-1] + v[:, 1:]) / 2, 1e-3)
    curvature = frac * np.minimum(1.0 / env.min_turn_radius, env.max_lateral_accel / mean**2)
    return integrate_steps(unicycle_step(v[:, :-1], np.diff(v, axis=1) / dt, curvature, dt))


def random_envelope_tracks(env: Envelope, dt: float, count: int, seed: int, steps: int = 50) -> np.ndarray:
    """``count`` tracks ``xyh [count, steps, 3]`` inside the envelope (not :func:`stress_tracks`'s grid): a
    random start speed, a constant speed change of up to the envelope's (reversing ones keep their speed)
    and a random share of the turn limit. Deterministic in ``seed``."""
    rng = np.random.default_rng(seed)
    v0 = rng.uniform(env.min_speed, env.max_speed, (count, 1))
    accel = rng.uniform(-env.max_brake, env.max_accel, (count, 1))
    v = np.where(v0 < 0, v0, np.clip(v0 + accel * dt * np.arange(steps), 0.0, env.max_speed))
    mean = np.maximum(np.abs(v[:, :-1] + v[:, 1:]) / 2, 1e-3)
    share = rng.uniform(-1.0, 1.0, (count, 1))
    curvature = share * np.minimum(1.0 / env.min_turn_radius, env.max_lateral_accel / mean**2)
    return integrate_steps(unicycle_step(v[:, :-1], np.diff(v, axis=1) / dt, curvature, dt))


def integrate_steps(local: np.ndarray) -> np.ndarray:
    """Tracks ``xyh [M, T+1, 3]`` from the origin of local steps ``[M, T, 3]`` (each in its state's frame)."""
    heading = np.concatenate([np.zeros((len(local), 1)), np.cumsum(local[..., 2], axis=1)], axis=1)
    c, s = np.cos(heading[:, :-1]), np.sin(heading[:, :-1])
    dx = c * local[..., 0] - s * local[..., 1]
    dy = s * local[..., 0] + c * local[..., 1]
    xy = np.concatenate([np.zeros((len(local), 1, 2)), np.cumsum(np.stack([dx, dy], -1), axis=1)], axis=1)
    return np.concatenate([xy, heading[..., None]], axis=-1)


def stress_error(
    vocab: MotionVocabulary, kind: AgentKind, dt: float, envelope: Envelope | None = None
) -> float:
    """Largest error (m, envelope box) of ``vocab``'s tokenization of ``kind``'s :func:`stress_tracks`."""
    env = envelope or DEFAULT_ENVELOPES[kind]
    xyh = stress_tracks(env, dt)
    m = len(xyh)
    size = np.tile([env.length, env.width], (m, 1))
    tok = tokenize(vocab, xyh, np.ones(xyh.shape[:2], bool), size, np.full(m, int(kind), np.int64))
    return float(np.nanmax(tok.error))


def drift_report(
    error: np.ndarray,
    valid: np.ndarray,
    kind: np.ndarray,
    names: list[str],
    tolerance: float = DRIFT_TOLERANCE_M,
    *,
    warn: bool = True,
    max_warnings: int = 5,
) -> dict[str, Any]:
    """Per class: max tokenization error (cm) and the share of tracks whose error ever exceeds
    ``tolerance`` m (``error [R,T]`` NaN where invalid, ``names [R]`` naming each track); warns naming the
    worst drifting tracks (at most ``max_warnings``, plus a count)."""
    worst = np.where(valid, np.nan_to_num(error, nan=0.0), 0.0).max(-1) if error.size else np.zeros(len(kind))
    drifting = worst > tolerance
    per_class: dict[str, Any] = {}
    for k in AgentKind:
        rows = (kind == int(k)) & valid.any(-1)
        if rows.any():
            per_class[k.name.lower()] = {
                "max_cm": round(float(worst[rows].max()) * 100, 3),
                "drift_share": round(float(drifting[rows].mean()), 5),
                "tracks": int(rows.sum()),
            }
    if warn and drifting.any():
        order = np.flatnonzero(drifting)[np.argsort(-worst[drifting], kind="stable")]
        shown = ", ".join(f"{names[i]} ({worst[i]:.3f} m)" for i in order[:max_warnings])
        more = f" and {len(order) - max_warnings} more" if len(order) > max_warnings else ""
        warnings.warn(
            f"tokenizer drift: {len(order)} track(s) drift beyond {tolerance} m from their true state: "
            f"{shown}{more}",
            stacklevel=2,
        )
    return {"tolerance_m": tolerance, "tracks_drifting": int(drifting.sum()), "per_class": per_class}
