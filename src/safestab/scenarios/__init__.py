"""Ready-made problems with parameter presets."""

from ..controller_names import CONTROLLERS
from ._mc_schema import check_controllers
from ._schema import LIMITS, ScenarioLimits
from .acc import PRESETS, ACCScenario, MonteCarloSpec, load_scenario
from .loading import KINDS, load, parse_override, scenario_kind
from .obstacle import ObstacleScenario, load_obstacle_scenario

__all__ = [
    "CONTROLLERS",
    "KINDS",
    "LIMITS",
    "PRESETS",
    "ACCScenario",
    "MonteCarloSpec",
    "ObstacleScenario",
    "ScenarioLimits",
    "check_controllers",
    "load",
    "load_obstacle_scenario",
    "load_scenario",
    "parse_override",
    "scenario_kind",
]
