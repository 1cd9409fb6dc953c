"""Ready-made problems with parameter presets."""

from .acc import PRESETS, ACCScenario, load_scenario

__all__ = ["PRESETS", "ACCScenario", "load_scenario"]
