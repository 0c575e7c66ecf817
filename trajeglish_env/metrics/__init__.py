"""Realism metrics of simulated rollouts (Waymo Sim Agents / WOSAC, 2024 and 2025), in NumPy.

Typical use::

    scores = score_rollouts(scenario, rollouts_xyh, agent_ids, config="2025")
    print(scores.metametric, scores.to_dict())

For score parity with the official tool on WOMD scenes pass the raw log values
(``details=next(read_womd_details(path))``) and the submitted z (``rollouts_z``). The definitions are
in ``shared/docs/wosac_metrics.md``; the geometry helpers (box collisions, road-edge distances) are
usable on their own.
"""

from trajeglish_env.metrics.boxes import box_collisions, box_signed_distance
from trajeglish_env.metrics.config import (
    BUCKETS,
    CONFIGS,
    FEATURE_NAMES,
    BernoulliEstimator,
    FeatureConfig,
    HistogramEstimator,
    MetricsConfig,
    get_config,
)
from trajeglish_env.metrics.features import MetricScene, RealismFeatures, compute_features, prepare_scene
from trajeglish_env.metrics.interaction import InteractionFeatures, interaction_features
from trajeglish_env.metrics.kinematics import kinematic_features
from trajeglish_env.metrics.log_details import LogDetails
from trajeglish_env.metrics.road_edges import (
    RoadEdges,
    box_bottom_corners,
    distance_to_road_edge,
    signed_distance_to_road_edges,
)
from trajeglish_env.metrics.scoring import (
    RealismScores,
    average_displacement_errors,
    displacement_errors,
    mean_scores,
    min_average_displacement_error,
    rollout_trajectories,
    score_rollouts,
)
from trajeglish_env.metrics.submission import (
    SubmissionFormatError,
    SubmittedRollouts,
    encode_submission,
    read_submission,
)
from trajeglish_env.metrics.traffic_lights import TrafficSignals, red_light_violations
from trajeglish_env.metrics.womd_details import read_womd_details

__all__ = [
    "BUCKETS",
    "CONFIGS",
    "FEATURE_NAMES",
    "BernoulliEstimator",
    "FeatureConfig",
    "HistogramEstimator",
    "InteractionFeatures",
    "LogDetails",
    "MetricScene",
    "MetricsConfig",
    "RealismFeatures",
    "RealismScores",
    "RoadEdges",
    "SubmissionFormatError",
    "SubmittedRollouts",
    "TrafficSignals",
    "average_displacement_errors",
    "box_bottom_corners",
    "box_collisions",
    "box_signed_distance",
    "compute_features",
    "displacement_errors",
    "distance_to_road_edge",
    "encode_submission",
    "get_config",
    "interaction_features",
    "kinematic_features",
    "mean_scores",
    "min_average_displacement_error",
    "prepare_scene",
    "read_submission",
    "read_womd_details",
    "red_light_violations",
    "rollout_trajectories",
    "score_rollouts",
    "signed_distance_to_road_edges",
]
