"""Realism scores of a set of rollouts of one scene (WOSAC meta-metric, spec §3-4), and their mean.

``score_rollouts`` builds the full-length trajectories (logged history + submitted future, boxes fixed
at the current step), computes every feature for the log and all rollouts in one batch, turns them into
per-feature likelihood scores, and adds the diagnostics (ADE, minADE, collision / off-road / red-light
rates).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields

import numpy as np

from trajeglish_env.metrics.config import BUCKETS, FEATURE_NAMES, MetricsConfig, get_config
from trajeglish_env.metrics.features import MetricScene, RealismFeatures, compute_features, prepare_scene
from trajeglish_env.metrics.likelihood import (
    bernoulli_log_likelihood,
    histogram_log_likelihood,
    masked_score,
)
from trajeglish_env.metrics.log_details import LogDetails
from trajeglish_env.scenario import Scenario

__all__ = [
    "RealismScores",
    "average_displacement_errors",
    "displacement_errors",
    "mean_scores",
    "min_average_displacement_error",
    "rollout_trajectories",
    "score_rollouts",
]


@dataclass(frozen=True)
class RealismScores:
    """Realism of the rollouts of one scene (or the mean over scenes, see :func:`mean_scores`).

    Feature scores are likelihoods in [0, 1]; buckets are weighted averages of their features; the
    meta-metric is the weighted sum of all features. ``ade``/``min_ade`` in metres; the rates are
    fractions of (rollout, evaluated agent) pairs.
    """

    config: str
    scenario_id: str
    num_rollouts: int
    num_evaluated: int
    linear_speed: float
    linear_acceleration: float
    angular_speed: float
    angular_acceleration: float
    distance_to_nearest_object: float
    collision_indication: float
    time_to_collision: float
    distance_to_road_edge: float
    offroad_indication: float
    traffic_light_violation: float
    kinematic: float
    interactive: float
    map_based: float
    metametric: float
    ade: float
    min_ade: float
    collision_rate: float
    offroad_rate: float
    traffic_light_violation_rate: float

    def feature_scores(self) -> dict[str, float]:
        """The ten per-feature likelihood scores by feature name."""
        return {name: getattr(self, name) for name in FEATURE_NAMES}

    def to_dict(self) -> dict[str, object]:
        """All fields as plain Python values (for JSON)."""
        return asdict(self)


def _speed_mask(valid: np.ndarray) -> np.ndarray:
    """True at t where steps t - 1 and t + 1 are valid (never the first or last step)."""
    out = np.zeros_like(valid)
    out[..., 1:-1] = valid[..., :-2] & valid[..., 2:]
    return out


def rollout_trajectories(
    scene: MetricScene, future_xyz: np.ndarray, future_heading: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full-length ``xyz [B, N, T, 3]``, ``heading`` and ``valid`` for the log (B = 0) followed by the
    rollouts (logged history, submitted future; the future of a rollout is valid throughout)."""
    r = future_xyz.shape[0]
    c = scene.current + 1
    xyz = np.repeat(scene.log_xyz[None], r + 1, axis=0)
    heading = np.repeat(scene.log_heading[None], r + 1, axis=0)
    valid = np.repeat(scene.log_valid[None], r + 1, axis=0)
    xyz[1:, :, c:] = future_xyz
    heading[1:, :, c:] = future_heading
    valid[1:, :, c:] = True
    return xyz, heading, valid


def average_displacement_errors(rollouts: np.ndarray, log: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """ADE ``[R, N]``: mean distance from ``rollouts [R, N, T, D]`` to ``log [N, T, D]`` over the steps
    where ``valid [N, T]`` (NaN for an agent with no valid step)."""
    rollouts, log, valid = np.asarray(rollouts), np.asarray(log), np.asarray(valid, dtype=bool)
    if rollouts.ndim != 4 or rollouts.shape[1:] != log.shape or log.shape[:2] != valid.shape:
        raise ValueError(
            f"average_displacement_errors: expected rollouts [R, N, T, D], log [N, T, D] and valid [N, T]; "
            f"got {rollouts.shape}, {log.shape}, {valid.shape}"
        )
    error = np.linalg.norm(rollouts - log[None], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(valid, error, 0).sum(axis=-1) / valid.sum(axis=-1)


def min_average_displacement_error(ade: np.ndarray) -> float:
    """minADE of the challenge: the best *joint* rollout, ``min_r mean_n ADE[r, n]`` of ``ade [R, N]``."""
    return float(np.asarray(ade).mean(axis=1).min())


def displacement_errors(scene: MetricScene, xyz: np.ndarray) -> np.ndarray:
    """ADE ``[R, E]`` of the evaluated agents of rollouts ``xyz [R, N, T, 3]`` (full length, 3-D), over
    the log-valid steps of the *whole* scene: the history counts with zero error, as in the reference."""
    ev = scene.evaluated
    return average_displacement_errors(xyz[:, ev], scene.log_xyz[ev], scene.log_valid[ev])


def _validated_rollouts(
    scene: MetricScene, rollouts_xyh: np.ndarray, agent_ids: np.ndarray, rollouts_z: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Rollouts reordered to the scene's simulated agents: ``xyz [R, N, T_f, 3]`` and ``heading``."""
    where = f"scenario {scene.scenario_id!r}"
    xyh = np.asarray(rollouts_xyh)
    n, t_f = scene.num_simulated, scene.num_future
    ids = np.asarray(agent_ids).astype(np.int64).reshape(-1)
    missing, unknown = np.setdiff1d(scene.track_id, ids), np.setdiff1d(ids, scene.track_id)
    if len(missing) or len(unknown):
        raise ValueError(
            f"{where}: the rollouts must hold exactly its {n} simulated agents (those valid at the current "
            f"step), they hold {len(ids)}: missing object id(s) {missing.tolist()[:10]}, not simulated "
            f"{unknown.tolist()[:10]}"
        )
    uniq, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        twice = uniq[counts > 1]
        raise ValueError(f"{where}: object id(s) {twice.tolist()[:10]} appear more than once in the rollouts")
    if xyh.ndim == 4 and xyh.shape[2] != t_f:
        raise ValueError(
            f"{where}: the rollouts hold {xyh.shape[2]} future steps; WOSAC scores {t_f} (the log's steps "
            "after the current one)"
        )
    if xyh.ndim != 4 or xyh.shape[1:] != (n, t_f, 3) or xyh.shape[0] < 1:
        raise ValueError(
            f"{where}: rollouts_xyh must be [R, {n} simulated agents, {t_f} future steps, 3], got {xyh.shape}"
        )
    order = np.argsort(ids)[np.searchsorted(np.sort(ids), scene.track_id)]  # row of each scene agent
    xyh = xyh[:, order].astype(np.float32)
    if rollouts_z is None:
        z = np.broadcast_to(scene.log_xyz[None, :, scene.current, 2, None], xyh.shape[:3])
    else:
        z = np.asarray(rollouts_z, dtype=np.float32)
        if z.shape != xyh.shape[:3]:
            raise ValueError(f"{where}: rollouts_z must be [R, N, T_f] = {xyh.shape[:3]}, got {z.shape}")
        z = z[:, order]
    xyz = np.concatenate([xyh[..., :2], z[..., None]], axis=-1)
    if not (np.isfinite(xyz).all() and np.isfinite(xyh[..., 2]).all()):
        r, i = np.argwhere(~np.isfinite(np.concatenate([xyz, xyh[..., 2:]], -1)).all(axis=(2, 3)))[0]
        raise ValueError(f"{where}: rollout {r}, object {scene.track_id[i]}: non-finite values")
    return xyz, xyh[..., 2]


def _feature_scores(
    cfg: MetricsConfig, scene: MetricScene, log: RealismFeatures, sim: RealismFeatures
) -> tuple[dict[str, float], dict[str, float]]:
    """Per-feature scores and the simulated indicator rates."""
    ev = scene.evaluated
    valid = scene.log_valid[ev, scene.current + 1 :]
    speed_mask = _speed_mask(valid)
    vehicle = scene.is_vehicle[ev, None]
    masks = {
        "linear_speed": speed_mask,
        "angular_speed": speed_mask,
        "linear_acceleration": _speed_mask(speed_mask),
        "angular_acceleration": _speed_mask(speed_mask),
        "distance_to_nearest_object": valid,
        "time_to_collision": valid & vehicle if cfg.ttc_vehicles_only else valid,
        "distance_to_road_edge": valid,
    }
    scores: dict[str, float] = {}
    for name, mask in masks.items():
        estimator = cfg.feature(name).estimator
        ll = histogram_log_likelihood(getattr(log, name)[0], getattr(sim, name), estimator)
        scores[name] = masked_score(ll, mask)
    indicators = {
        "collision_indication": (log.collision, sim.collision, valid),
        "offroad_indication": (log.offroad, sim.offroad, valid),
        "traffic_light_violation": (
            log.traffic_light_violation,
            sim.traffic_light_violation,
            valid & vehicle,
        ),
    }
    for name, (log_flag, sim_flag, mask) in indicators.items():
        estimator = cfg.feature(name).estimator
        ll = bernoulli_log_likelihood((log_flag[0] & mask).any(-1), (sim_flag & mask).any(-1), estimator)
        scores[name] = float(np.exp(ll.mean()))
    rates = {
        "collision_rate": float((sim.collision & valid).any(-1).mean()),
        "offroad_rate": float((sim.offroad & valid).any(-1).mean()),
        "traffic_light_violation_rate": float((sim.traffic_light_violation & valid).any(-1).mean()),
    }
    return scores, rates


def _aggregates(cfg: MetricsConfig, scores: dict[str, float]) -> dict[str, float]:
    """Bucket scores (weighted averages) and the meta-metric (weighted sum) of feature scores."""
    out = {"metametric": float(sum(cfg.feature(f).weight * scores[f] for f in FEATURE_NAMES))}
    for bucket, names in BUCKETS.items():
        total = sum(cfg.feature(f).weight for f in names)
        if total <= 0:
            raise ValueError(f"config {cfg.name!r}: bucket {bucket!r} has no weight")
        out[bucket] = float(sum(cfg.feature(f).weight * scores[f] for f in names) / total)
    return out


def score_rollouts(
    scenario: Scenario,
    rollouts_xyh: np.ndarray,
    agent_ids: Sequence[int] | np.ndarray,
    config: str | MetricsConfig = "2025",
    *,
    rollouts_z: np.ndarray | None = None,
    details: LogDetails | None = None,
) -> RealismScores:
    """Realism scores of ``R`` rollouts of ``scenario`` against its log.

    ``rollouts_xyh [R, N, T_f, 3]`` (x, y, heading) over the ``T_f`` steps after ``current_index`` for the
    N agents valid at the current step, whose track ids are ``agent_ids [N]`` (any order; every simulated
    agent exactly once). ``rollouts_z [R, N, T_f]`` defaults to each agent's logged z at the current step
    (0 for planar scenes). ``details`` are the raw log values (:func:`read_womd_details`); without them
    the scene is treated as planar (exact for generated scenes, approximate for WOMD).
    """
    cfg = get_config(config)
    scene = prepare_scene(scenario, details)
    future_xyz, future_heading = _validated_rollouts(scene, rollouts_xyh, np.asarray(agent_ids), rollouts_z)
    xyz, heading, valid = rollout_trajectories(scene, future_xyz, future_heading)
    both = compute_features(scene, xyz, heading, valid)
    log = RealismFeatures(**{f.name: getattr(both, f.name)[:1] for f in fields(both)})
    sim = RealismFeatures(**{f.name: getattr(both, f.name)[1:] for f in fields(both)})
    scores, rates = _feature_scores(cfg, scene, log, sim)
    per_rollout = displacement_errors(scene, xyz[1:])
    return RealismScores(
        config=cfg.name,
        scenario_id=scene.scenario_id,
        num_rollouts=int(future_xyz.shape[0]),
        num_evaluated=scene.num_evaluated,
        **scores,
        **_aggregates(cfg, scores),
        ade=float(per_rollout.mean()),
        min_ade=min_average_displacement_error(per_rollout),
        **rates,
    )


def mean_scores(results: Sequence[RealismScores], config: str | MetricsConfig | None = None) -> RealismScores:
    """Dataset-level scores: the plain mean of every field over scenes (buckets recomputed from the mean
    feature scores, which equals their mean since they are linear), but ``num_rollouts`` and
    ``num_evaluated`` are totals over them, as the ``scenario_id`` label says."""
    if not results:
        raise ValueError("mean_scores: no results to average")
    cfg = get_config(config if config is not None else results[0].config)
    numeric = [f.name for f in fields(RealismScores) if f.name not in ("config", "scenario_id")]
    values = {name: np.array([getattr(r, name) for r in results], dtype=np.float64) for name in numeric}
    undefined = [r.scenario_id for k, r in enumerate(results) if any(np.isnan(v[k]) for v in values.values())]
    if undefined:  # e.g. time_to_collision of a scene whose evaluated agents hold no vehicle (spec §3.4)
        warnings.warn(
            f"mean_scores: {len(undefined)} of {len(results)} scene(s) ({', '.join(undefined[:3])}) have an "
            "undefined (NaN) score, e.g. time_to_collision where no evaluated agent is a vehicle: each "
            "field is averaged over the scenes where it is defined",
            stacklevel=2,
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a field undefined in every scene stays NaN
        mean = {name: float(np.nanmean(v)) for name, v in values.items()}
    mean.update(_aggregates(cfg, {f: mean[f] for f in FEATURE_NAMES}))
    mean["num_rollouts"] = int(sum(r.num_rollouts for r in results))
    mean["num_evaluated"] = int(sum(r.num_evaluated for r in results))
    label = f"mean of {len(results)} scenes (num_rollouts, num_evaluated: totals over them)"
    return RealismScores(config=cfg.name, scenario_id=label, **mean)
