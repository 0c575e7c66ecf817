"""External controllers for trajeglish_env agents (builds on trajeglish_env; never imported by it).

A :class:`Policy` has ``reset(env, agent)`` and ``act(env, agent, observation)``; :func:`play_episode`
plays an AEC episode with a policy per agent and :func:`evaluate` summarises several.
"""

from policies.base import ConstantVelocityPolicy, FunctionPolicy, Policy, RandomPolicy, ReplayPolicy
from policies.idm import IDMPolicy
from policies.learned import SB3Policy, TrajeglishPolicy
from policies.runner import EpisodeResult, evaluate, play_episode, policy_for, summarize

__all__ = [
    "ConstantVelocityPolicy",
    "EpisodeResult",
    "FunctionPolicy",
    "IDMPolicy",
    "Policy",
    "RandomPolicy",
    "ReplayPolicy",
    "SB3Policy",
    "TrajeglishPolicy",
    "evaluate",
    "play_episode",
    "policy_for",
    "summarize",
]
