"""Extending a trained model's vocabulary instead of replacing it: the old templates keep their token ids
and meaning, the new ones cover every motion of the class's envelope, and a trained model takes the new
tokens on with embeddings copied from the nearest old template (``train --init CKPT --vocab EXTENDED``).

A vocabulary that meets the 5 cm coverage target needs a 3 cm cover of the vehicle envelope (703
templates; docs/vocabulary.md), which a model trained on the shipped 384 templates has
never seen. Appending that cover to the shipped templates keeps the model's knowledge (every old token
means what it meant) while a fine-tune learns to use the finer, faster, reversing templates, at a
fraction of the cost of training from scratch. The vehicle cover also spans the env's kinematic bicycle
(:mod:`~trajeglish_env.tokenizer.bicycle`), catch-up templates close the gaps where a greedily tokenized
track lags, and classes whose cover is smaller fill the rest of the shared size with the envelope
transitions farthest from every template they already have (V = 2048 for the shipped 384).
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from trajeglish_env.geometry import to_local
from trajeglish_env.kinematics import VehicleLimits
from trajeglish_env.scenario import AgentKind
from trajeglish_env.tokenizer.bicycle import (
    BICYCLE_LENGTHS,
    bicycle_random_tracks,
    bicycle_stress_tracks,
    bicycle_transitions,
)
from trajeglish_env.tokenizer.coverage import (
    DEFAULT_ENVELOPES,
    DRIFT_TOLERANCE_M,
    Envelope,
    cover_templates,
    envelope_cover,
    envelope_error,
    envelope_transitions,
    lattice_templates,
    random_envelope_tracks,
    stress_tracks,
)
from trajeglish_env.tokenizer.distance import corner_distance
from trajeglish_env.tokenizer.tokenize import tokenize
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary, VocabularyError

VEHICLE_COVER_RADIUS = 0.03  # m: keeps every vehicle envelope track within 5 cm (docs/vocabulary.md)
DEFAULT_DT = 0.1
# a track's first step farther than this from its true state gets a catch-up template
CATCH_UP_TARGET_M = 0.035
CATCH_UP_ROUNDS = 40
CATCH_UP_RANDOM = 500  # random tracks (unicycle and, for vehicles, bicycle each) beside the stress tracks
CATCH_UP_SEED = 0


def _nearest(points: np.ndarray, templates: np.ndarray, box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index and distance ``[M]`` of each point's nearest template (mean corner distance of ``box``)."""
    index = np.empty(len(points), np.int64)
    dist = np.empty(len(points))
    for lo in range(0, len(points), 1024):  # chunks of points bound the [chunk, V] distance matrix
        d = corner_distance(points[lo : lo + 1024, None], templates[None], box)
        index[lo : lo + 1024] = d.argmin(1)
        dist[lo : lo + 1024] = d.min(1)
    return index, dist


def farthest_points(pool: np.ndarray, have: np.ndarray, count: int, box: np.ndarray) -> np.ndarray:
    """``count`` points of ``pool [M,3]``, each in turn the one farthest from ``have`` and those already
    chosen (deterministic: the first of equals): every pick shrinks the largest gap of the cover most."""
    if count > len(pool):
        raise ValueError(f"farthest_points: {count} points asked of a pool of {len(pool)}")
    _, gap = _nearest(pool, have, box)
    chosen = np.empty(count, np.int64)
    for i in range(count):
        chosen[i] = int(np.argmax(gap))
        gap = np.minimum(gap, corner_distance(pool[chosen[i]], pool, box))
    return pool[chosen]


def _track_errors(vocab: np.ndarray, kind: AgentKind, xyh: np.ndarray, size: np.ndarray):  # noqa: ANN202
    """Greedy tokenization of tracks ``xyh [M,T,3]`` (boxes ``size [M,2]``) with ``vocab [V,3]`` as the
    class's templates."""
    probe = MotionVocabulary(np.repeat(vocab[None], len(AgentKind), axis=0))
    m = len(xyh)
    return tokenize(probe, xyh, np.ones(xyh.shape[:2], bool), size, np.full(m, int(kind), np.int64))


def catch_up_templates(
    fixed: np.ndarray, spare: np.ndarray, kind: AgentKind, targets: ClassTargets
) -> tuple[np.ndarray, np.ndarray]:
    """Templates that bring the lagging states of greedily tokenized tracks back, each taking the place of
    the last of ``spare`` (templates in order of priority): at the first step where a track's tokenized
    state is more than :data:`CATCH_UP_TARGET_M` from the true one, the motion from the previous tokenized
    state to the true state is added (nearer than half the cover radius to none already added; later steps
    of the track lag because of that one), and the tracks are tokenized again, until none lags. A one-step
    cover does not bound a greedy tokenizer's lag; this closes the gaps where it builds up. Returns (added,
    the spares kept)."""
    xyh, size, box = targets.tracks, targets.sizes, targets.box
    added = np.zeros((0, 3))
    for _ in range(CATCH_UP_ROUNDS):
        kept = spare[: len(spare) - len(added)]
        tok = _track_errors(np.concatenate([fixed, added, kept]), kind, xyh, size)
        lagging = np.nan_to_num(tok.error) > CATCH_UP_TARGET_M
        track = np.flatnonzero(lagging.any(1))
        if len(track) == 0 or len(added) >= len(spare):
            break
        step = lagging[track].argmax(1)
        needed = to_local(tok.xyh[track, step - 1], xyh[track, step])
        keep: list[np.ndarray] = []
        for motion in needed[np.argsort(-tok.error[track, step], kind="stable")]:
            if not keep or corner_distance(motion, np.stack(keep), box).min() > targets.radius / 2:
                keep.append(motion)
        added = np.concatenate([added, np.stack(keep)])[: len(spare)]
    return added, spare[: len(spare) - len(added)]


@dataclass(frozen=True)
class ClassTargets:
    """What an extension must reach for one class: the ``cover`` it reserves, the ``pool`` its fill is drawn
    from, stress ``tracks [M,T,3]`` of boxes ``sizes [M,2]`` its catch-up follows, and the class ``box`` and
    cover ``radius`` (m) distances are measured with."""

    cover: np.ndarray
    pool: np.ndarray
    tracks: np.ndarray
    sizes: np.ndarray
    box: np.ndarray
    radius: float
    bicycle: int = 0  # templates of the cover that reach the env's bicycle motions (vehicles)


def class_targets(kind: AgentKind, base: np.ndarray, cover_radius: float, dt: float) -> ClassTargets:
    """The envelope cover, fill pool and stress tracks of ``kind``; vehicles also the env's kinematic
    bicycle (:mod:`bicycle`) for every length of :data:`BICYCLE_LENGTHS`."""
    env = _envelope(kind, cover_radius)
    box = np.array([env.length, env.width])
    cover = envelope_cover(kind, dt, env)
    pool = [envelope_transitions(env, dt), lattice_templates(env, dt, env.radius / 2)]
    tracks = [stress_tracks(env, dt), random_envelope_tracks(env, dt, CATCH_UP_RANDOM, CATCH_UP_SEED)]
    sizes = [np.tile(box, (len(t), 1)) for t in tracks]
    bicycle = 0
    if kind == AgentKind.VEHICLE:
        limits = VehicleLimits()
        for length in BICYCLE_LENGTHS:
            points = bicycle_transitions(limits, length, dt)
            more = cover_templates(points, env.radius, box, np.concatenate([base, cover]))
            cover, bicycle = np.concatenate([cover, more]), bicycle + len(more)
            pool.append(points)
            tracks.append(bicycle_stress_tracks(limits, length, dt))
            sizes.append(np.tile([length, env.width], (len(tracks[-1]), 1)))
        lengths = (min(BICYCLE_LENGTHS), max(BICYCLE_LENGTHS))
        xyh, length = bicycle_random_tracks(limits, lengths, dt, CATCH_UP_RANDOM, CATCH_UP_SEED)
        tracks.append(xyh)
        sizes.append(np.stack([length, np.full(len(length), env.width)], 1))
    return ClassTargets(
        cover, np.unique(np.concatenate(pool), axis=0), np.concatenate(tracks), np.concatenate(sizes), box,
        env.radius, bicycle,
    )  # fmt: skip


def _envelope(kind: AgentKind, cover_radius: float) -> Envelope:
    """The class's default envelope; the vehicles' cover made within ``cover_radius`` m."""
    env = DEFAULT_ENVELOPES[kind]
    return dataclasses.replace(env, radius=cover_radius) if kind == AgentKind.VEHICLE else env


def extend_vocabulary(
    base: MotionVocabulary, size: int, cover_radius: float = VEHICLE_COVER_RADIUS
) -> MotionVocabulary:
    """``base``'s templates (ids 0..V-1 unchanged) followed, per class, by the class's envelope cover
    (vehicles within ``cover_radius`` m, the env's kinematic bicycle included), templates where greedily
    tokenized stress tracks lag (:func:`catch_up_templates`) and, to reach ``size``, the envelope
    transitions farthest from every template so far. The metadata's ``extends`` and ``coverage`` record
    what was added and how close the result tokenizes the envelope (one step, and the stress tracks over
    5 s: ``stress_max_error_m`` covers the unicycle and bicycle tracks alike)."""
    if not 0.005 <= cover_radius <= 0.5:
        raise ValueError(f"cover_radius: expected metres in [0.005, 0.5], got {cover_radius}")
    dt = float(base.metadata.get("dt", DEFAULT_DT))
    old = base.size
    added: list[np.ndarray] = []
    coverage: dict[str, Any] = {}
    targets: dict[AgentKind, ClassTargets] = {}
    for kind in AgentKind:
        env = _envelope(kind, cover_radius)
        t = targets[kind] = class_targets(kind, base.for_kind(kind), cover_radius, dt)
        room = size - old
        if len(t.cover) > room:
            raise ValueError(
                f"extend_vocabulary: class '{kind.name.lower()}' needs {len(t.cover)} templates to cover its "
                f"envelope within {env.radius} m, but {old} -> {size} adds {room}; "
                f"ask for a size of at least {old + len(t.cover)}"
            )
        have = np.concatenate([base.for_kind(kind), t.cover])
        fill = farthest_points(t.pool, have, room - len(t.cover), t.box)
        catch_up, fill = catch_up_templates(have, fill, kind, t)
        added.append(np.concatenate([t.cover, catch_up, fill]))
        coverage[kind.name.lower()] = {
            "envelope": env.to_json(),
            "templates": len(t.cover),
            "bicycle": t.bicycle,
            "catch_up": len(catch_up),
            "fill": len(fill),
            "radius_m": env.radius,
        }
    templates = np.concatenate([base.templates, np.stack(added)], axis=1)
    metadata = {
        **base.metadata,
        "extends": {
            "base_size": old,
            "base_method": base.method,
            "cover_radius_m": cover_radius,
            "bicycle_lengths_m": list(BICYCLE_LENGTHS),
            "base_coverage": base.metadata.get("coverage"),
        },
        "coverage": coverage,
        "nominal_vocab_size": size,
    }
    vocab = MotionVocabulary(templates, method=base.method, metadata=metadata)
    for kind in AgentKind:
        entry, t = coverage[kind.name.lower()], targets[kind]
        entry["max_error_m"] = round(
            envelope_error(vocab.for_kind(kind), kind, dt, _envelope(kind, cover_radius)), 5
        )
        tok = _track_errors(vocab.for_kind(kind), kind, t.tracks, t.sizes)
        entry["stress_max_error_m"] = round(float(np.nanmax(tok.error)), 5)
        if entry["stress_max_error_m"] > DRIFT_TOLERANCE_M:
            warnings.warn(
                f"extend_vocabulary: class '{kind.name.lower()}''s stress tracks lag up to "
                f"{entry['stress_max_error_m'] * 100:.1f} cm behind their tokenized states (> "
                f"{DRIFT_TOLERANCE_M * 100:.0f} cm); a larger size leaves room to catch up",
                stacklevel=2,
            )
    return vocab


def is_extension(base: MotionVocabulary, extended: MotionVocabulary) -> bool:
    """Whether ``extended`` holds ``base``'s templates, unchanged, as its first ids (and more after)."""
    t, e = base.templates, extended.templates
    return e.shape[1] > t.shape[1] and e.shape[0] == t.shape[0] and np.array_equal(e[:, : t.shape[1]], t)


def embedding_sources(base: MotionVocabulary, extended: MotionVocabulary) -> np.ndarray:
    """``[K, V']`` the base token whose trained embedding each token of ``extended`` starts from: itself
    for the base ids, the nearest base template (class box) for the added ones."""
    if not is_extension(base, extended):
        raise VocabularyError(
            f"the vocabulary ({extended.method}, {list(extended.templates.shape)}) does not extend the "
            f"checkpoint's ({base.method}, {list(base.templates.shape)}): its first {base.size} templates "
            "of each class must be the checkpoint's, unchanged"
        )
    out = np.empty((extended.num_kinds, extended.size), np.int64)
    for kind in AgentKind:
        env = DEFAULT_ENVELOPES[kind]
        box = np.array([env.length, env.width])
        out[kind, : base.size] = np.arange(base.size)
        out[kind, base.size :], _ = _nearest(extended.for_kind(kind)[base.size :], base.for_kind(kind), box)
    return out


def extension_report(vocab: MotionVocabulary) -> dict[str, Any]:
    """Per class: templates added, one-step envelope error and stress-track error (cm), within 5 cm?"""
    rows: dict[str, Any] = {"size": vocab.size, "base_size": vocab.metadata["extends"]["base_size"]}
    for name, entry in vocab.metadata["coverage"].items():
        rows[name] = {
            "cover": entry["templates"],
            "bicycle": entry["bicycle"],
            "catch_up": entry["catch_up"],
            "fill": entry["fill"],
            "envelope_max_cm": round(entry["max_error_m"] * 100, 2),
            "stress_max_cm": round(entry["stress_max_error_m"] * 100, 2),
            "within_5cm": entry["stress_max_error_m"] <= DRIFT_TOLERANCE_M,
        }
    return rows
