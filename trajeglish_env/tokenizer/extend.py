"""Extending a trained model's vocabulary instead of replacing it: the old templates keep their token ids
and meaning, the new ones cover every motion of the class's envelope, and a trained model takes the new
tokens on with embeddings copied from the nearest old template (``train --init CKPT --vocab EXTENDED``).

A vocabulary that meets the 5 cm coverage target needs a 3 cm cover of the vehicle envelope (703
templates; README, "Motion vocabulary coverage"), which a model trained on the shipped 384 templates has
never seen. Appending that cover to the shipped templates keeps the model's knowledge (every old token
means what it meant) while a fine-tune learns to use the finer, faster, reversing templates, at a
fraction of the cost of training from scratch. Classes whose cover is smaller fill the rest of the shared
size with the envelope transitions farthest from every template they already have.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import numpy as np

from trajeglish_env.geometry import to_local
from trajeglish_env.scenario import AgentKind
from trajeglish_env.tokenizer.coverage import (
    DEFAULT_ENVELOPES,
    DRIFT_TOLERANCE_M,
    Envelope,
    envelope_cover,
    envelope_error,
    envelope_transitions,
    lattice_templates,
    stress_error,
    stress_tracks,
)
from trajeglish_env.tokenizer.distance import corner_distance
from trajeglish_env.tokenizer.tokenize import tokenize
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary, VocabularyError

VEHICLE_COVER_RADIUS = 0.03  # m: keeps every vehicle envelope track within 5 cm (README)
DEFAULT_DT = 0.1
CATCH_UP_TARGET_M = 0.04  # stress-track steps farther than this from their true state get a catch-up template
CATCH_UP_ROUNDS = 8


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


def catch_up_templates(
    fixed: np.ndarray, spare: np.ndarray, kind: AgentKind, env: Envelope, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Templates that bring the lagging states of greedily tokenized stress tracks back, each taking the
    place of the last of ``spare`` (templates in order of priority): where a track's tokenized state ends
    up more than :data:`CATCH_UP_TARGET_M` from the true one, the motion from the previous tokenized state
    to the true state is added (one per step, nearer than half the cover radius to none already added), and
    the tracks are tokenized again. A one-step cover does not bound a greedy tokenizer's lag; this closes
    the gaps where the lag builds up. Returns (added, the spares kept)."""
    xyh = stress_tracks(env, dt)
    m = len(xyh)
    size = np.tile([env.length, env.width], (m, 1))
    box = np.array([env.length, env.width])
    added = np.zeros((0, 3))
    for _ in range(CATCH_UP_ROUNDS):
        kept = spare[: len(spare) - len(added)]
        vocab = np.concatenate([fixed, added, kept])
        probe = MotionVocabulary(np.repeat(vocab[None], len(AgentKind), axis=0))
        tok = tokenize(probe, xyh, np.ones(xyh.shape[:2], bool), size, np.full(m, int(kind), np.int64))
        track, step = np.nonzero(np.nan_to_num(tok.error) > CATCH_UP_TARGET_M)
        if len(track) == 0 or len(added) >= len(spare):
            break
        needed = to_local(tok.xyh[track, step - 1], xyh[track, step])
        keep: list[np.ndarray] = []
        for motion in needed[np.argsort(-tok.error[track, step], kind="stable")]:
            if not keep or corner_distance(motion, np.stack(keep), box).min() > env.radius / 2:
                keep.append(motion)
        added = np.concatenate([added, np.stack(keep)])[: len(spare)]
    return added, spare[: len(spare) - len(added)]


def _envelope(kind: AgentKind, cover_radius: float) -> Envelope:
    """The class's default envelope; the vehicles' cover made within ``cover_radius`` m."""
    env = DEFAULT_ENVELOPES[kind]
    return dataclasses.replace(env, radius=cover_radius) if kind == AgentKind.VEHICLE else env


def extend_vocabulary(
    base: MotionVocabulary, size: int, cover_radius: float = VEHICLE_COVER_RADIUS
) -> MotionVocabulary:
    """``base``'s templates (ids 0..V-1 unchanged) followed, per class, by the class's envelope cover
    (vehicles within ``cover_radius`` m), templates where greedily tokenized stress tracks lag
    (:func:`catch_up_templates`) and, to reach ``size``, the envelope transitions farthest from every
    template so far. The metadata's ``extends`` and ``coverage`` record what was added and how
    close the result tokenizes the envelope (one step, and the stress tracks over 5 s)."""
    if not 0.005 <= cover_radius <= 0.5:
        raise ValueError(f"cover_radius: expected metres in [0.005, 0.5], got {cover_radius}")
    dt = float(base.metadata.get("dt", DEFAULT_DT))
    old = base.size
    added: list[np.ndarray] = []
    coverage: dict[str, Any] = {}
    for kind in AgentKind:
        env = _envelope(kind, cover_radius)
        box = np.array([env.length, env.width])
        cover = envelope_cover(kind, dt, env)
        room = size - old
        if len(cover) > room:
            raise ValueError(
                f"extend_vocabulary: class '{kind.name.lower()}' needs {len(cover)} templates to cover its "
                f"envelope within {env.radius} m, but {old} -> {size} adds {room}; "
                f"ask for a size of at least {old + len(cover)}"
            )
        pool = np.unique(
            np.concatenate([envelope_transitions(env, dt), lattice_templates(env, dt, env.radius / 2)]),
            axis=0,
        )
        have = np.concatenate([base.for_kind(kind), cover])
        fill = farthest_points(pool, have, room - len(cover), box)
        catch_up, fill = catch_up_templates(have, fill, kind, env, dt)
        added.append(np.concatenate([cover, catch_up, fill]))
        coverage[kind.name.lower()] = {
            "envelope": env.to_json(),
            "templates": len(cover),
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
            "base_coverage": base.metadata.get("coverage"),
        },
        "coverage": coverage,
        "nominal_vocab_size": size,
    }
    vocab = MotionVocabulary(templates, method=base.method, metadata=metadata)
    for kind in AgentKind:
        entry = coverage[kind.name.lower()]
        env = _envelope(kind, cover_radius)
        entry["max_error_m"] = round(envelope_error(vocab.for_kind(kind), kind, dt, env), 5)
        entry["stress_max_error_m"] = round(stress_error(vocab, kind, dt, env), 5)
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
            "catch_up": entry["catch_up"],
            "fill": entry["fill"],
            "envelope_max_cm": round(entry["max_error_m"] * 100, 2),
            "stress_max_cm": round(entry["stress_max_error_m"] * 100, 2),
            "within_5cm": entry["stress_max_error_m"] <= DRIFT_TOLERANCE_M,
        }
    return rows
