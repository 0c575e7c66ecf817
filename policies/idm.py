"""The Intelligent Driver Model as an external agent's policy (the env's IDM NPC logic, per agent)."""

from __future__ import annotations

from typing import Any

from trajeglish_env.env.controllers import RuleBasedController


class IDMPolicy:
    """IDM along the agent's logged path with the leader found on that path; the resulting state is
    turned into the env's action type (path position and speed re-synchronised every step)."""

    def __init__(self) -> None:
        self.controller = RuleBasedController("idm")

    def reset(self, env: Any, agent: str) -> None:
        """Prepare for a new episode of ``agent`` (the IDM state of the last one is dropped)."""
        self.controller.reset()

    def act(self, env: Any, agent: str, observation: Any) -> Any:
        """The action of ``agent`` at its turn."""
        return self.controller.action(env, agent)
