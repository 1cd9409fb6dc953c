"""Ready-made problems with parameter presets."""

from .acc import LIMITS, PRESETS, ACCScenario, ScenarioLimits, load_scenario

__all__ = ["LIMITS", "PRESETS", "ACCScenario", "ScenarioLimits", "load_scenario"]
