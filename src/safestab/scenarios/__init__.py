"""Ready-made problems with parameter presets."""

from .acc import LIMITS, PRESETS, ACCScenario, MonteCarloSpec, ScenarioLimits, load_scenario

__all__ = ["LIMITS", "PRESETS", "ACCScenario", "MonteCarloSpec", "ScenarioLimits", "load_scenario"]
