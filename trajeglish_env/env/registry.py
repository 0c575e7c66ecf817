"""Registration with Gymnasium (single-ego envs, done by ``import trajeglish_env``) and PettingZoo.

Gymnasium: ``trajeglish_env/Ego-v0`` (vector observations, continuous actions, Trajeglish NPCs),
``trajeglish_env/EgoBev-v0`` (bev observations), ``trajeglish_env/EgoIDM-v0`` (IDM NPCs, no model).
PettingZoo: ``pettingzoo.make("aec" | "parallel", "trajeglish_env/Traffic-v0")`` once
``trajeglish_env.env`` is imported.
"""

from __future__ import annotations

from trajeglish_env import GYM_ENVS, register_gymnasium

PETTINGZOO_ID = "trajeglish_env/Traffic-v0"

__all__ = ["GYM_ENVS", "PETTINGZOO_ID", "register_gymnasium", "register_pettingzoo"]


def register_pettingzoo() -> None:
    """Register the AEC and parallel envs with PettingZoo's registry (idempotent)."""
    from pettingzoo.env_registry.registration import aec_registry, parallel_registry, register

    if PETTINGZOO_ID not in aec_registry:
        register("aec", PETTINGZOO_ID, entry_point="trajeglish_env.env.aec:env")
    if PETTINGZOO_ID not in parallel_registry:
        register("parallel", PETTINGZOO_ID, entry_point="trajeglish_env.env.parallel:parallel_env")
