"""trajeglish_env: a multi-agent driving simulator whose traffic is driven by Trajeglish."""

from trajeglish_env.scenario import AgentKind, MapKind, Scenario, ScenarioError, SignalState
from trajeglish_env.scenario_io import load_scenario, load_scenarios, save_scenario, save_scenarios

__version__ = "0.1.0"

__all__ = [
    "AgentKind",
    "MapKind",
    "Scenario",
    "ScenarioError",
    "SignalState",
    "load_scenario",
    "load_scenarios",
    "save_scenario",
    "save_scenarios",
    "__version__",
]
