"""The checks of ``TrainConfig``'s colliding- and off-road-mass term settings (training/blocked_mass.py,
training/offroad_mass.py), kept apart so that the config stays a list of fields."""

from __future__ import annotations

from typing import Any

from trajeglish_env.training.blocked_mass import TERM_FORMS


def check_term_form(field: str, form: str, weight: float) -> None:
    """Refuse an unknown form of a mass term, or a form set for a term that is off."""
    if form not in TERM_FORMS:
        raise ValueError(f"TrainConfig.{field} must be one of {TERM_FORMS}, got {form!r}")
    if form != "mass" and not weight:
        raise ValueError(f"TrainConfig.{field} needs its term's weight > 0 (the term it shapes)")


def check_mass_terms(config: Any) -> None:
    """Refuse a ``TrainConfig`` whose mass-term settings contradict each other, naming the field."""
    if not config.collision_weight >= 0:
        raise ValueError(f"TrainConfig.collision_weight must be >= 0, got {config.collision_weight}")
    if not (config.offroad_weight >= 0 and config.offroad_positions >= 1):
        raise ValueError(f"TrainConfig: offroad_weight >= 0 and offroad_positions >= 1, got {config}")
    if config.offroad_weight and config.closed_loop_top_k:
        raise ValueError(
            "TrainConfig: offroad_weight masks are cut at logged states; closed_loop_top_k rolls "
            "them out (use one or the other)"
        )
    if config.collision_sources and not config.collision_weight:
        raise ValueError("TrainConfig.collision_sources needs collision_weight > 0 (the term it limits)")
    check_term_form("collision_form", config.collision_form, config.collision_weight)
    check_term_form("offroad_form", config.offroad_form, config.offroad_weight)
    if not config.offroad_horizon >= 1:
        raise ValueError(f"TrainConfig.offroad_horizon must be >= 1 step, got {config.offroad_horizon}")
    if config.offroad_horizon > 1 and not config.offroad_weight:
        raise ValueError("TrainConfig.offroad_horizon needs offroad_weight > 0 (the term it widens)")
    if not config.collision_horizon >= 1:
        raise ValueError(f"TrainConfig.collision_horizon must be >= 1 step, got {config.collision_horizon}")
    if config.collision_horizon > 1 and not config.collision_weight:  # accepted with no effect before
        raise ValueError("TrainConfig.collision_horizon needs collision_weight > 0 (the term it widens)")
    if config.collision_rolled_out_only and not config.collision_weight:
        raise ValueError(
            "TrainConfig.collision_rolled_out_only needs collision_weight > 0 (the term it limits)"
        )
