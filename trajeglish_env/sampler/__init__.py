"""Closed-loop rollouts: full or partial control, any scene size (spatial/temporal sliding window).

Names load lazily, so that the torch-free :mod:`~trajeglish_env.sampler.config` can be imported alone.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_WHERE = {
    "RolloutEngine": "engine",
    "Rollouts": "rollouts",
    "rollout": "rollouts",
    "SamplingConfig": "config",
    "DEFAULT_TEMPERATURE": "config",
    "SubsetPlan": "subsets",
    "plan_subsets": "subsets",
}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'trajeglish_env.sampler' has no attribute {name!r}")
    return getattr(import_module(f"trajeglish_env.sampler.{_WHERE[name]}"), name)
