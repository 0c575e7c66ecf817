"""Realism-metric configurations: one likelihood estimator and one weight per feature (WOSAC 2024 / 2025).

The numbers are those of the official challenge configs (see ``shared/docs/wosac_metrics.md`` §3.5).
A config is a frozen dataclass with one field per feature, so a typo is an error, not a silent default.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

__all__ = [
    "BUCKETS",
    "CONFIGS",
    "FEATURE_NAMES",
    "BernoulliEstimator",
    "FeatureConfig",
    "HistogramEstimator",
    "MetricsConfig",
    "get_config",
]


@dataclass(frozen=True)
class HistogramEstimator:
    """Histogram of the simulated samples on ``num_bins`` equal bins of ``[min_value, max_value]``.

    Values are clipped into the range; ``pseudocount`` is added to every bin before normalising.
    """

    min_value: float
    max_value: float
    num_bins: int
    pseudocount: float = 0.1

    def __post_init__(self) -> None:
        if not (self.max_value > self.min_value and self.num_bins >= 1 and self.pseudocount > 0):
            raise ValueError(f"invalid histogram estimator {self}")


@dataclass(frozen=True)
class BernoulliEstimator:
    """Probability of a boolean from the simulated samples, with ``pseudocount`` added to both outcomes."""

    pseudocount: float = 0.001

    def __post_init__(self) -> None:
        if not self.pseudocount > 0:
            raise ValueError(f"invalid Bernoulli estimator {self}")


@dataclass(frozen=True)
class FeatureConfig:
    """How one feature is scored: its likelihood estimator and its weight in the meta-metric."""

    estimator: HistogramEstimator | BernoulliEstimator
    weight: float


@dataclass(frozen=True)
class MetricsConfig:
    """One realism configuration: a :class:`FeatureConfig` per feature, plus reference-code switches.

    ``ttc_vehicles_only``: the time-to-collision score averages over vehicles only (the official code
    since 2025, also applied to the 2024 config); False reproduces the 2024-era code.
    """

    name: str
    linear_speed: FeatureConfig
    linear_acceleration: FeatureConfig
    angular_speed: FeatureConfig
    angular_acceleration: FeatureConfig
    distance_to_nearest_object: FeatureConfig
    collision_indication: FeatureConfig
    time_to_collision: FeatureConfig
    distance_to_road_edge: FeatureConfig
    offroad_indication: FeatureConfig
    traffic_light_violation: FeatureConfig
    ttc_vehicles_only: bool = True

    def feature(self, name: str) -> FeatureConfig:
        """The config of feature ``name`` (one of :data:`FEATURE_NAMES`)."""
        if name not in FEATURE_NAMES:
            raise KeyError(f"unknown realism feature {name!r}; expected one of {FEATURE_NAMES}")
        return getattr(self, name)


FEATURE_NAMES: tuple[str, ...] = tuple(
    f.name for f in fields(MetricsConfig) if f.name not in ("name", "ttc_vehicles_only")
)

# Leaderboard buckets: a weighted average of their features' scores.
BUCKETS: dict[str, tuple[str, ...]] = {
    "kinematic": ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration"),
    "interactive": ("distance_to_nearest_object", "collision_indication", "time_to_collision"),
    "map_based": ("distance_to_road_edge", "offroad_indication", "traffic_light_violation"),
}


def _hist(lo: float, hi: float, bins: int, weight: float) -> FeatureConfig:
    return FeatureConfig(HistogramEstimator(lo, hi, bins), weight)


def _bernoulli(weight: float) -> FeatureConfig:
    return FeatureConfig(BernoulliEstimator(), weight)


CONFIG_2025 = MetricsConfig(
    name="2025",
    linear_speed=_hist(0.0, 25.0, 10, 0.05),
    linear_acceleration=_hist(-12.0, 12.0, 11, 0.05),
    angular_speed=_hist(-0.628, 0.628, 11, 0.05),
    angular_acceleration=_hist(-3.14, 3.14, 11, 0.05),
    distance_to_nearest_object=_hist(-5.0, 40.0, 10, 0.10),
    collision_indication=_bernoulli(0.25),
    time_to_collision=_hist(0.0, 5.0, 10, 0.10),
    distance_to_road_edge=_hist(-20.0, 40.0, 10, 0.05),
    offroad_indication=_bernoulli(0.25),
    traffic_light_violation=_bernoulli(0.05),
)

CONFIG_2024 = replace(
    CONFIG_2025,
    name="2024",
    distance_to_road_edge=_hist(-20.0, 40.0, 10, 0.10),
    traffic_light_violation=_bernoulli(0.0),
)

# the 2024 challenge as its leaderboard scored it: the code of that year took the time to collision of every
# evaluated object, the current code of vehicles only (docs/wosac_metrics.md §3.4)
CONFIG_2024_ERA = replace(CONFIG_2024, name="2024-era", ttc_vehicles_only=False)

CONFIGS: dict[str, MetricsConfig] = {"2024": CONFIG_2024, "2024-era": CONFIG_2024_ERA, "2025": CONFIG_2025}


def get_config(config: str | MetricsConfig) -> MetricsConfig:
    """A config by name ("2024", "2024-era" or "2025"), or the given :class:`MetricsConfig` itself."""
    if isinstance(config, MetricsConfig):
        return config
    if config not in CONFIGS:
        raise ValueError(f"unknown metrics config {config!r}; expected one of {sorted(CONFIGS)}")
    return CONFIGS[config]
