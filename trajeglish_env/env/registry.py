"""Registration with Gymnasium and PettingZoo, both done by the plain ``import trajeglish_env``.

Gymnasium: ``trajeglish_env/Ego-v0`` (vector observations, continuous actions, Trajeglish NPCs),
``trajeglish_env/EgoBev-v0`` (bev observations), ``trajeglish_env/EgoIDM-v0`` (IDM NPCs, no model).
PettingZoo: ``pettingzoo.make("aec" | "parallel", "trajeglish_env/Traffic-v0")``.

The functions live in the top-level package (which must not import this subpackage: it loads torch);
this module re-exports them for code that imports them from ``trajeglish_env.env``.
"""

from __future__ import annotations

from trajeglish_env import GYM_ENVS, PETTINGZOO_ID, register_gymnasium, register_pettingzoo

__all__ = ["GYM_ENVS", "PETTINGZOO_ID", "register_gymnasium", "register_pettingzoo"]
