"""The environments: a PettingZoo AEC core whose agent order is the intra-timestep order (NPCs driven by
Trajeglish or rule-based policies act between the external agents), its parallel form, and a Gymnasium
single-ego env. See :class:`~trajeglish_env.env.aec.raw_env` for spaces, rewards and options.

This module is callable: ``trajeglish_env.env(...)`` is ``trajeglish_env.env.env(...)`` (the wrapped AEC
env), so the package reads like a PettingZoo environment module (``env``, ``raw_env``, ``parallel_env``).
"""

import sys
import types
from typing import Any

from trajeglish_env.env.aec import env, raw_env
from trajeglish_env.env.config import (
    ACTION_TYPES,
    NPC_NAMES,
    OBSERVATION_TYPES,
    ORDERS,
    EnvConfig,
    ObservationConfig,
    RandomAgents,
    RewardConfig,
    TrajeglishNPC,
    VehicleLimits,
)
from trajeglish_env.env.gym_ego import EgoEnv
from trajeglish_env.env.npc import (
    IDMNPC,
    ConstantVelocityNPC,
    IDMParams,
    NPCPolicy,
    ReplayNPC,
    make_npc_policy,
)
from trajeglish_env.env.parallel import parallel_env
from trajeglish_env.env.registry import register_gymnasium, register_pettingzoo
from trajeglish_env.env.scene_batch import load_npc_checkpoint
from trajeglish_env.env.world import WorldView

register_gymnasium()
register_pettingzoo()


class _CallableModule(types.ModuleType):
    """Module type whose call builds the wrapped AEC env."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return env(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule

__all__ = [
    "ACTION_TYPES",
    "IDMNPC",
    "NPC_NAMES",
    "OBSERVATION_TYPES",
    "ORDERS",
    "ConstantVelocityNPC",
    "EgoEnv",
    "EnvConfig",
    "IDMParams",
    "NPCPolicy",
    "ObservationConfig",
    "RandomAgents",
    "ReplayNPC",
    "RewardConfig",
    "TrajeglishNPC",
    "VehicleLimits",
    "WorldView",
    "env",
    "load_npc_checkpoint",
    "make_npc_policy",
    "parallel_env",
    "raw_env",
]
