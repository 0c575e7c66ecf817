"""trajeglish_env: a multi-agent driving simulator whose traffic is driven by Trajeglish."""

from trajeglish_env.scenario import AgentKind, MapKind, Scenario, ScenarioError, SignalState
from trajeglish_env.scenario_io import load_scenario, load_scenarios, save_scenario, save_scenarios

__version__ = "0.2.0"  # = pyproject.toml's version (tests/test_structure.py); bumped with every release

# Heavy parts (torch, PettingZoo) load on first use. ``trajeglish_env.env`` is the environment subpackage
# and is callable: ``trajeglish_env.env(...)`` builds the wrapped AEC env (PettingZoo's ``env()``).
_LAZY = {
    "raw_env": "trajeglish_env.env.aec",
    "parallel_env": "trajeglish_env.env.parallel",
    "EgoEnv": "trajeglish_env.env.gym_ego",
    "EnvConfig": "trajeglish_env.env.config",
    "TrajeglishNPC": "trajeglish_env.env.config",
    "load_pretrained": "trajeglish_env.checkpoint",
}


def __getattr__(name: str) -> object:
    """Lazy exports (PEP 562): the environments and the pretrained model import torch/PettingZoo."""
    import importlib

    if name == "env":
        return importlib.import_module("trajeglish_env.env")
    if name in _LAZY:
        if name != "load_pretrained":
            importlib.import_module("trajeglish_env.env")
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'trajeglish_env' has no attribute {name!r}")


# Gymnasium single-ego envs (entry points are strings: nothing heavy is imported until one is made).
GYM_ENVS = {
    "trajeglish_env/Ego-v0": {},
    "trajeglish_env/EgoBev-v0": {"observation": "bev"},
    "trajeglish_env/EgoIDM-v0": {"npc": "idm"},
}
PETTINGZOO_ID = "trajeglish_env/Traffic-v0"
PETTINGZOO_ENTRY_POINTS = {
    "aec": "trajeglish_env.env.aec:env",
    "parallel": "trajeglish_env.env.parallel:parallel_env",
}


def register_gymnasium() -> None:
    """Register :data:`GYM_ENVS` with Gymnasium (idempotent), so that ``gymnasium.make(
    "trajeglish_env/Ego-v0")`` works after ``import trajeglish_env``, and ``gymnasium.make_vec(id, n,
    vectorization_mode="vector_entry_point")`` makes the batched env (one model call for all n scenes)."""
    from gymnasium.envs.registration import register, registry

    for env_id, kwargs in GYM_ENVS.items():
        if env_id not in registry:
            register(
                env_id,
                entry_point="trajeglish_env.env.gym_ego:EgoEnv",
                vector_entry_point="trajeglish_env.env.vector:BatchedEgoEnv",
                kwargs=kwargs,
            )


def register_pettingzoo() -> None:
    """Register the AEC and parallel envs with PettingZoo's registry (idempotent), so that
    ``pettingzoo.make("aec" | "parallel", PETTINGZOO_ID)`` works after ``import trajeglish_env``.

    The entry points are strings, so neither torch nor the env package is imported until one is made.
    """
    from pettingzoo.env_registry.registration import aec_registry, parallel_registry, register

    registries = {"aec": aec_registry, "parallel": parallel_registry}
    for env_type, entry_point in PETTINGZOO_ENTRY_POINTS.items():
        if PETTINGZOO_ID not in registries[env_type]:
            register(env_type, PETTINGZOO_ID, entry_point=entry_point)  # type: ignore[call-overload]


register_gymnasium()
register_pettingzoo()

__all__ = [
    "AgentKind",
    "EgoEnv",
    "EnvConfig",
    "GYM_ENVS",
    "MapKind",
    "PETTINGZOO_ID",
    "Scenario",
    "ScenarioError",
    "SignalState",
    "env",
    "load_pretrained",
    "load_scenario",
    "parallel_env",
    "raw_env",
    "register_gymnasium",
    "register_pettingzoo",
    "load_scenarios",
    "save_scenario",
    "save_scenarios",
    "__version__",
]
