"""safestab: safe stabilization of control-affine systems under model uncertainty.

Importing safestab switches JAX to 64-bit floats (``jax_enable_x64``): every numerical routine
here is written for float64.
"""

import jax

jax.config.update("jax_enable_x64", True)

from .certificates import CBF, CLF, LieTerms, lie_terms  # noqa: E402
from .controllers import ControlOutput, UniversalController  # noqa: E402
from .errors import (  # noqa: E402
    CompilationError,
    DimensionError,
    InfeasibleError,
    NonFiniteError,
    NumericalError,
    ParameterError,
    SafeStabError,
    ScenarioError,
    UnsupportedPrimitiveError,
)
from .export import NativeController, export_c  # noqa: E402
from .formulas import (  # noqa: E402
    Compatibility,
    CompatibilityCase,
    FormulaResult,
    KKTResiduals,
    Region,
    cbf_universal,
    clf_cbf,
    clf_cbf_relaxed,
    clf_sontag,
    compatibility,
    kkt_residuals,
    project_box,
    saturate_safety_first,
)
from .robust import (  # noqa: E402
    ProbabilisticCompatibility,
    RobustMargins,
    UncertaintyModel,
    joint_probability,
    probabilistic_compatibility,
    robust_lie_terms,
    robust_margins,
)
from .simulation import Trajectory, rk4_step, simulate  # noqa: E402
from .systems import ControlAffineSystem  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "CBF",
    "CLF",
    "ControlAffineSystem",
    "ControlOutput",
    "LieTerms",
    "UniversalController",
    "lie_terms",
    "ProbabilisticCompatibility",
    "RobustMargins",
    "UncertaintyModel",
    "joint_probability",
    "probabilistic_compatibility",
    "robust_lie_terms",
    "robust_margins",
    "DimensionError",
    "InfeasibleError",
    "NonFiniteError",
    "NumericalError",
    "ParameterError",
    "SafeStabError",
    "ScenarioError",
    "CompilationError",
    "UnsupportedPrimitiveError",
    "Compatibility",
    "CompatibilityCase",
    "FormulaResult",
    "KKTResiduals",
    "Region",
    "cbf_universal",
    "clf_cbf",
    "clf_cbf_relaxed",
    "clf_sontag",
    "compatibility",
    "kkt_residuals",
    "project_box",
    "saturate_safety_first",
    "Trajectory",
    "rk4_step",
    "simulate",
    "NativeController",
    "export_c",
]
