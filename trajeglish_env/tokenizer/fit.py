"""Fit vocabularies (k-disks and the baselines) from scene directories, and evaluate them (CLI back end).

``fit_from_directory`` backs ``trajeglish tokenizer fit`` and ``evaluate_directory`` backs
``trajeglish tokenizer eval``; both return JSON-able dicts. Sampling methods (k-disks, k-means) draw
several candidate sets per class (k-disks: for the paper's epsilon and a few multiples of it; k-means:
several k-means++ seeds) and keep the one with the lowest mean corner distance when tokenizing held-out
trajectories of that class. A class with too few transitions (fewer than
``MIN_TRANSITIONS_PER_TEMPLATE`` per template) borrows the vehicle templates, with a warning and a note in
the vocabulary's metadata; the vehicle class itself must have enough data.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from trajeglish_env.scenario import AgentKind
from trajeglish_env.tokenizer.baselines import kmeans_templates, xy_grid_templates, xyh_grid_templates
from trajeglish_env.tokenizer.coverage import (
    DEFAULT_ENVELOPES,
    Envelope,
    envelope_cover,
    envelope_error,
    stress_error,
)
from trajeglish_env.tokenizer.data import TrajectorySet, load_trajectories
from trajeglish_env.tokenizer.discretization import collision_rates, evaluate_vocabulary, plot_error_vs_length
from trajeglish_env.tokenizer.kdisks import default_epsilon, sample_kdisks
from trajeglish_env.tokenizer.tokenize import tokenize
from trajeglish_env.tokenizer.vocabulary import KIND_NAMES, MotionVocabulary

METHODS = ("xyh-grid", "xy-grid", "k-means", "k-disks")
PAPER_VOCAB_SIZES = (128, 256, 384, 512)
VOCAB_SIZES = (*PAPER_VOCAB_SIZES, 640, 768, 1024)  # the paper's sizes and larger (docs/vocabulary.md)
MIN_TRANSITIONS_PER_TEMPLATE = 10
# k-disks tries the paper's epsilon and these multiples of it (data unlike WOMD may want another radius).
EPSILON_SCALES = (0.75, 1.0, 1.5, 2.0)
MAX_FIT_TRANSITIONS = 400_000  # per class; a deterministic subsample above this keeps fitting to minutes
COVERED_METHODS = ("k-disks", "k-means")  # the sampled methods reserve templates for the motion envelope
MIN_DATA_SHARE = 0.5  # at least this share of V stays for templates sampled from data


def _log(msg: str) -> None:
    print(f"[tokenizer] {msg}", file=sys.stderr, flush=True)


def _subsample(points: np.ndarray, limit: int, rng: np.random.Generator) -> np.ndarray:
    if len(points) <= limit:
        return points
    return points[np.sort(rng.choice(len(points), limit, replace=False))]


def _heldout_error(
    candidate: np.ndarray, kind: int, heldout: TrajectorySet | None, fallback: np.ndarray
) -> float:
    """Mean corner distance (m) of ``candidate`` templates: on held-out trajectories of ``kind`` if any,
    else the one-step error on ``fallback`` transitions (unit-free nearest distance, 4.5 m x 2 m box)."""
    templates = np.repeat(candidate[None], len(AgentKind), 0)
    vocab = MotionVocabulary(templates, method="candidate")
    if heldout is not None:
        rows = heldout.kind == kind
        if (heldout.valid[rows][:, 1:] & heldout.valid[rows][:, :-1]).any():
            tok = tokenize(
                vocab, heldout.xyh[rows], heldout.valid[rows], heldout.size[rows], heldout.kind[rows]
            )
            measured = tok.valid & ~tok.anchored
            return float(tok.error[measured].mean())
    start = np.zeros((len(fallback), 1, 3))
    traj = np.concatenate([start, fallback[:, None]], 1)[None]
    size = np.broadcast_to(np.array([4.5, 2.0]), (1, len(fallback), 2)).copy()
    tok = tokenize(vocab, traj, np.ones(traj.shape[:-1], bool), size, np.full((1, len(fallback)), kind))
    return float(np.nanmean(tok.error[..., 1]))


def fit_vocabulary(
    method: str,
    vocab_size: int,
    fit: TrajectorySet,
    heldout: TrajectorySet | None = None,
    *,
    seed: int = 0,
    trials: int = 8,
    epsilon: float | None = None,
    epsilon_scales: Sequence[float] = EPSILON_SCALES,
    coverage: bool = True,
    min_data_share: float = MIN_DATA_SHARE,
    cover_radius: float | None = None,
) -> MotionVocabulary:
    """Fit a vocabulary by ``method`` (one of METHODS) of nominal size ``vocab_size`` on ``fit``.

    With ``coverage`` (k-disks and k-means), every candidate set starts with the templates of
    :func:`envelope_cover` for the class (every transition of the class's motion envelope, up to the env's
    40 m/s, reversing and tight turns, within the envelope's radius) and samples the rest from data; the
    metadata's ``coverage`` records per class the envelope, the reserved templates, the max one-step
    error on the envelope and the max error of tokenizing the envelope's ``stress_tracks`` (a track at
    a limit can lag more than one step's error). At least ``min_data_share`` of the templates stay for
    data: a cover that does not fit is made at a wider radius (recorded, with a warning). The envelope
    templates all lie on the unicycle surface, so on their own they cannot correct a tokenized state that
    is off it (lateral slip, noise): with a small data share, real tracks tokenize worse
    (docs/vocabulary.md). ``cover_radius`` (m) replaces the vehicle envelope's radius (4.5 cm): a 3 cm
    cover (703 templates, e.g. V = 1024 with ``min_data_share=0.2``) keeps every envelope track within
    5 cm. The result depends only on the inputs (deterministic).

    k-disks draws ``trials`` candidate sets for each epsilon in ``epsilon * epsilon_scales`` (``epsilon``
    defaults to the paper's value for ``vocab_size``; ``epsilon_scales=(1.0,)`` is exactly the paper's
    procedure) and k-means ``trials`` seeds; the candidate with the lowest error on ``heldout`` wins.
    """
    if method not in METHODS:
        raise ValueError(f"unknown tokenizer method {method!r}; expected one of {METHODS}")
    envelopes = cover_envelopes(cover_radius)
    counts = fit.transition_counts()
    needed = MIN_TRANSITIONS_PER_TEMPLATE * vocab_size
    if method != "xyh-grid" and counts["vehicle"] < needed:
        raise ValueError(
            f"{method}: the vehicle class has {counts['vehicle']} transitions; "
            f"fitting {vocab_size} templates needs at least {needed} "
            f"({MIN_TRANSITIONS_PER_TEMPLATE} per template). Generate more scenes."
        )
    eps = default_epsilon(vocab_size) if epsilon is None else float(epsilon)
    metadata: dict[str, Any] = {
        "nominal_vocab_size": vocab_size,
        "seed": seed,
        "fit_transitions": counts,
        "fit_scenes": fit.num_scenes,
        "borrowed": {},
        "dt": fit.dt,
    }
    epsilons = [round(eps * scale, 6) for scale in epsilon_scales] if method == "k-disks" else [0.0]
    if method in ("k-disks", "k-means"):
        metadata["trials"] = trials
        metadata["heldout_error_cm"] = {}
    covered = coverage and method in COVERED_METHODS
    if covered:
        metadata["coverage"] = {}
    if method == "k-disks":
        metadata["epsilon_candidates_m"] = epsilons
        metadata["epsilon_m"] = {}
    templates: list[np.ndarray | None] = [None] * len(AgentKind)
    for kind in AgentKind:  # three classes, each fitted on all of its transitions at once
        name = kind.name.lower()
        if kind != AgentKind.VEHICLE and method != "xyh-grid" and counts[name] < needed:
            continue
        rng = np.random.default_rng(np.random.SeedSequence([seed, int(kind), vocab_size]))
        transitions = _subsample(fit.transitions(kind), MAX_FIT_TRANSITIONS, rng)
        if method == "xyh-grid":
            templates[kind] = xyh_grid_templates(vocab_size)
        elif method == "xy-grid":
            templates[kind] = xy_grid_templates(vocab_size, transitions)
        else:
            reserved = (
                _reserve(kind, vocab_size, fit.dt, metadata, min_data_share, envelopes[kind])
                if covered
                else np.zeros((0, 3))
            )
            best, errors = _best_candidate(
                method, transitions, int(kind), vocab_size, heldout, seed, trials, epsilons, reserved
            )
            templates[kind] = best
            metadata["heldout_error_cm"][name] = errors
            if method == "k-disks":
                metadata["epsilon_m"][name] = min(errors, key=lambda e: e[2])[0]
    for kind in AgentKind:
        if templates[kind] is None:
            name = kind.name.lower()
            warnings.warn(
                f"tokenizer {method}: class '{name}' has only {counts[name]} transitions (< {needed} needed "
                f"for {vocab_size} templates); it uses the vehicle templates",
                stacklevel=2,
            )
            metadata["borrowed"][name] = "vehicle"
            templates[kind] = templates[AgentKind.VEHICLE]
            if covered:
                metadata["coverage"][name] = {
                    "borrowed": "vehicle",
                    "max_error_m": round(envelope_error(templates[kind], kind, fit.dt, envelopes[kind]), 5),
                }
    vocab = MotionVocabulary(np.stack(templates), method=method, metadata=metadata)  # type: ignore[arg-type]
    if covered:  # how far a tokenized track lags at the envelope's limits (more than one step's error)
        for kind in AgentKind:
            entry = metadata["coverage"][kind.name.lower()]
            entry["stress_max_error_m"] = round(stress_error(vocab, kind, fit.dt, envelopes[kind]), 5)
    return vocab


def cover_envelopes(cover_radius: float | None = None) -> dict[AgentKind, Envelope]:
    """Every class's motion envelope, the vehicles' cover made within ``cover_radius`` m when given."""
    envelopes = dict(DEFAULT_ENVELOPES)
    if cover_radius is not None:
        if not 0.005 <= cover_radius <= 0.5:
            raise ValueError(f"cover_radius: expected metres in [0.005, 0.5], got {cover_radius}")
        vehicle = envelopes[AgentKind.VEHICLE]
        envelopes[AgentKind.VEHICLE] = dataclasses.replace(vehicle, radius=float(cover_radius))
    return envelopes


def _reserve(
    kind: AgentKind,
    vocab_size: int,
    dt: float,
    metadata: dict[str, Any],
    min_data_share: float,
    env: Envelope,
) -> np.ndarray:
    """The envelope cover of ``kind`` (radius widened by 15 % steps, with a warning, until at least
    ``min_data_share`` of the vocabulary is left for data); records it in ``metadata["coverage"]``."""
    if not 0.0 < min_data_share < 1.0:
        raise ValueError(f"min_data_share: expected a share in (0, 1), got {min_data_share}")
    room = vocab_size - max(1, int(np.ceil(min_data_share * vocab_size)))
    radius = env.radius
    cover = envelope_cover(kind, dt, env, radius)
    while len(cover) > room:
        radius *= 1.15
        cover = envelope_cover(kind, dt, env, radius)
    name = kind.name.lower()
    if radius > env.radius:
        warnings.warn(
            f"tokenizer coverage: class '{name}' needs more than {room} of {vocab_size} templates to cover "
            f"its motion envelope within {env.radius} m; covered within {radius:.4f} m instead",
            stacklevel=3,
        )
    metadata["coverage"][name] = {
        "envelope": env.to_json(),
        "templates": len(cover),
        "radius_m": round(radius, 5),
        "min_data_share": min_data_share,
        "max_error_m": round(envelope_error(cover, kind, dt, env), 5),
    }
    return cover


def _best_candidate(
    method: str,
    transitions: np.ndarray,
    kind: int,
    vocab_size: int,
    heldout: TrajectorySet | None,
    seed: int,
    trials: int,
    epsilons: Sequence[float],
    reserved: np.ndarray | None = None,
) -> tuple[np.ndarray, list[list[float]]]:
    """Draw candidate template sets (k-disks per epsilon, or k-means seeds); keep the best on ``heldout``.

    Every candidate starts with the ``reserved`` templates (the envelope cover) and samples the rest.

    Returns the best set and ``[epsilon_m, trial, heldout_error_cm]`` for every candidate.
    """
    reserved = np.zeros((0, 3)) if reserved is None else reserved
    sampled = vocab_size - len(reserved)
    best, best_err, errors = None, np.inf, []
    bar = tqdm(
        total=len(epsilons) * trials,
        desc=f"tokenizer {AgentKind(kind).name.lower()} candidates",
        unit="set",
        file=sys.stderr,
        leave=False,
        disable=None,  # shown on a terminal
    )
    for eps in epsilons:
        for trial in range(trials):
            bar.update(1)
            rng = np.random.default_rng(
                np.random.SeedSequence([seed, kind, vocab_size, trial, int(eps * 1e6)])
            )
            if method == "k-disks":
                candidate = sample_kdisks(transitions, sampled, eps, rng)
            else:
                candidate = kmeans_templates(_subsample(transitions, 100_000, rng), sampled, rng)
            candidate = np.concatenate([reserved, candidate])
            err = _heldout_error(candidate, kind, heldout, transitions[:20000])
            errors.append([eps, trial, round(err * 100, 4)])
            if err < best_err:
                best, best_err = candidate, err
            bar.set_postfix(best_cm=f"{best_err * 100:.2f}")
    bar.close()
    assert best is not None
    return best, errors


def _load(
    data: str | os.PathLike[str] | Sequence[str | os.PathLike[str]], max_scenes: int | None
) -> TrajectorySet:
    paths = [data] if isinstance(data, (str, os.PathLike)) else list(data)
    sets = [load_trajectories(p, max_scenes) for p in paths]
    return sets[0] if len(sets) == 1 else concat_sets(sets)


def concat_sets(sets: Sequence[TrajectorySet]) -> TrajectorySet:
    """Concatenate trajectory sets (padding to the longest), renumbering scenes."""
    steps = max(s.xyh.shape[1] for s in sets)
    if len({s.dt for s in sets}) != 1:
        raise ValueError(f"cannot mix time steps {sorted({s.dt for s in sets})} s in one trajectory set")

    def pad(a: np.ndarray, fill: float | bool) -> np.ndarray:
        width = [(0, 0)] * a.ndim
        width[1] = (0, steps - a.shape[1])
        return np.pad(a, width, constant_values=fill)

    offsets = np.cumsum([0] + [s.num_scenes for s in sets[:-1]])
    return TrajectorySet(
        xyh=np.concatenate([pad(s.xyh, 0.0) for s in sets]),
        valid=np.concatenate([pad(s.valid, False) for s in sets]),
        size=np.concatenate([s.size for s in sets]),
        kind=np.concatenate([s.kind for s in sets]),
        scene=np.concatenate([s.scene + o for s, o in zip(sets, offsets, strict=True)]),
        num_scenes=int(sum(s.num_scenes for s in sets)),
        dt=sets[0].dt,
    )


def fit_from_directory(
    data_dir: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    vocab_size: int = 384,
    seed: int = 0,
    out: str | os.PathLike[str] | None = None,
    *,
    method: str = "k-disks",
    trials: int = 8,
    epsilon_scales: Sequence[float] = EPSILON_SCALES,
    heldout_every: int = 5,
    max_scenes: int | None = None,
    coverage: bool = True,
    min_data_share: float = MIN_DATA_SHARE,
    cover_radius: float | None = None,
) -> dict[str, Any]:
    """Fit a vocabulary on the scenes of ``data_dir`` (one or several directories), save it to ``out``.

    ``coverage`` reserves templates for every class's motion envelope, ``min_data_share`` and
    ``cover_radius`` as in :func:`fit_vocabulary`.

    Every ``heldout_every``-th scene is held out to choose among trials and to report the error.
    """
    start = time.perf_counter()
    data = _load(data_dir, max_scenes)
    fit, heldout = data.split(heldout_every)
    _log(
        f"fitting {method} V={vocab_size} on {fit.num_scenes} scenes ({fit.transition_counts()} transitions)"
    )
    vocab = fit_vocabulary(
        method,
        vocab_size,
        fit,
        heldout,
        seed=seed,
        trials=trials,
        epsilon_scales=epsilon_scales,
        coverage=coverage,
        min_data_share=min_data_share,
        cover_radius=cover_radius,
    )
    sources = [str(data_dir)] if isinstance(data_dir, (str, os.PathLike)) else [str(p) for p in data_dir]
    vocab.metadata["data"] = sources
    report = evaluate_vocabulary(vocab, heldout, collisions=False)
    report.pop("error_vs_length")
    result: dict[str, Any] = {
        "method": method,
        "vocab_size": vocab_size,
        "templates": vocab.size,
        "seed": seed,
        "scenes": data.num_scenes,
        "heldout_scenes": heldout.num_scenes,
        "transitions": fit.transition_counts(),
        "borrowed": vocab.metadata["borrowed"],
        "coverage": vocab.metadata.get("coverage"),
        "heldout": report,
        "seconds": round(time.perf_counter() - start, 2),
    }
    if out is not None:
        result["out"] = str(vocab.save(out))
    return result


def evaluate_directory(
    data_dir: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    vocab_sizes: Sequence[int] = PAPER_VOCAB_SIZES,
    methods: Sequence[str] = METHODS,
    out_dir: str | os.PathLike[str] | None = None,
    *,
    fit_data: str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | None = None,
    seed: int = 0,
    trials: int = 4,
    epsilon_scales: Sequence[float] = EPSILON_SCALES,
    heldout_every: int = 5,
    collisions: bool = True,
    max_scenes: int | None = None,
    coverage: bool = True,
    min_data_share: float = MIN_DATA_SHARE,
    cover_radius: float | None = None,
) -> dict[str, Any]:
    """Fit every method at every size and evaluate on held-out trajectories (the paper's comparison table).

    Without ``fit_data``, ``data_dir`` is split by scene (every ``heldout_every``-th scene held out for
    evaluation; the rest fit, with its own inner split for choosing trials). With ``fit_data``, vocabularies
    are fitted there and all of ``data_dir`` is evaluated. Writes ``tokenizer_error_vs_length.png`` and the
    fitted vocabularies into ``out_dir`` when given. ``coverage``, ``min_data_share`` and ``cover_radius``
    as in :func:`fit_vocabulary`; each
    result's ``drift`` reports per class the max error and the share of tracks drifting beyond 5 cm (with
    a warning naming the worst tracks).
    """
    start = time.perf_counter()
    data = _load(data_dir, max_scenes)
    if fit_data is None:
        fit_all, evaluation = data.split(heldout_every)
    else:
        fit_all, evaluation = _load(fit_data, max_scenes), data
    fit, choose = fit_all.split(heldout_every)
    if not evaluation.num_scenes or not fit.num_scenes:
        which = "held-out" if not evaluation.num_scenes else "fitting"
        raise ValueError(
            f"tokenizer eval: no {which} scenes: --data {_shown(data_dir)} holds {data.num_scenes} scenes"
            + (
                f" and every {heldout_every}th is held out, so at least {heldout_every} are needed (or pass "
                "--fit-data)"
                if fit_data is None
                else f", --fit-data {_shown(fit_data)} {fit_all.num_scenes}"
            )
        )
    raw = collision_rates(evaluation, evaluation.xyh, evaluation.valid) if collisions else None
    results: list[dict[str, Any]] = []
    table: dict[str, dict[str, float | None]] = {m: {} for m in methods}
    for vocab_size in vocab_sizes:
        for method in methods:
            t0 = time.perf_counter()
            vocab = fit_vocabulary(
                method,
                vocab_size,
                fit,
                choose,
                seed=seed,
                trials=trials,
                epsilon_scales=epsilon_scales,
                coverage=coverage,
                min_data_share=min_data_share,
                cover_radius=cover_radius,
            )
            res = evaluate_vocabulary(vocab, evaluation, collisions=collisions, raw_collisions=raw)
            res.update(
                vocab_size=vocab_size,
                borrowed=vocab.metadata["borrowed"],
                coverage=vocab.metadata.get("coverage"),
                seconds=round(time.perf_counter() - t0, 2),
            )
            results.append(res)
            table[method][str(vocab_size)] = res["mean_cm"]
            _log(f"{method:8s} V={vocab_size}: {res['mean_cm']} cm ({res['templates']} templates)")
            if out_dir is not None:
                vocab.save(Path(out_dir) / f"tokenizer_{method}_v{vocab_size}.npz")
    summary: dict[str, Any] = {
        "table_cm": table,
        "kinds": list(KIND_NAMES),
        "eval_scenes": evaluation.num_scenes,
        "eval_transitions": evaluation.transition_counts(),
        "fit_scenes": fit_all.num_scenes,
        "results": results,
        "seconds": round(time.perf_counter() - start, 2),
    }
    if out_dir is not None:
        summary["plot"] = str(plot_error_vs_length(results, Path(out_dir) / "tokenizer_error_vs_length.png"))
    return summary


def evaluate_vocabulary_file(
    vocab: MotionVocabulary | str | os.PathLike[str],
    data_dir: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    *,
    collisions: bool = True,
    max_scenes: int | None = None,
) -> dict[str, Any]:
    """Evaluate a given vocabulary (object or file) on all scenes of ``data_dir`` (e.g. the WOMD sample)."""
    if not isinstance(vocab, MotionVocabulary):
        vocab = MotionVocabulary.load(vocab)
    data = _load(data_dir, max_scenes)
    result = evaluate_vocabulary(vocab, data, collisions=collisions)
    result["scenes"] = data.num_scenes
    result["transitions"] = data.transition_counts()
    return result


def _shown(paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]) -> str:
    """Paths as a command line shows them (an error message's)."""
    return str(paths) if isinstance(paths, (str, os.PathLike)) else " ".join(map(str, paths))
