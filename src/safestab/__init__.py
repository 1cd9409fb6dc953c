"""safestab: safe stabilization of control-affine systems under model uncertainty.

Importing safestab switches JAX to 64-bit floats (``jax_enable_x64``): every numerical routine
here is written for float64. It also turns on JAX's persistent compilation cache in a user
cache folder (``SAFESTAB_COMPILATION_CACHE=off`` before the import keeps it off; see
:mod:`safestab._cache`), and a cache of GP fits (``SAFESTAB_FIT_CACHE=off`` keeps it off; see
:mod:`safestab.learning._fit_cache`). Unless JAX has started already, it adds
``--xla_cpu_use_fusion_emitters=false`` to ``XLA_FLAGS``, which halves the compilation of
the filter's solver on the CPU (``SAFESTAB_XLA_FLAGS=off`` keeps it out; see
:mod:`safestab._xla_flags` for when else it is left out).
"""

import jax

jax.config.update("jax_enable_x64", True)

from ._xla_flags import configure_from_environment as _configure_xla_flags  # noqa: E402

_configure_xla_flags()  # before JAX first compiles: XLA reads XLA_FLAGS once (_xla_flags.py)

from ._cache import (  # noqa: E402
    compilation_cache_dir,
    disable_compilation_cache,
    enable_compilation_cache,
)
from ._cache import configure_from_environment as _configure_cache  # noqa: E402

_configure_cache()  # JAX's persistent compilation cache (safestab/_cache.py)

from .learning._fit_cache import (  # noqa: E402
    configure_fit_cache_from_environment as _configure_fit_cache,
)
from .learning._fit_cache import (  # noqa: E402
    disable_fit_cache,
    enable_fit_cache,
    fit_cache_dir,
)

_configure_fit_cache()  # the GP fit cache (safestab/learning/_fit_cache.py)

from ._version import __version__ as __version__  # noqa: E402
from .certificates import CBF, CLF, LieTerms, high_order_cbf, lie_terms  # noqa: E402
from .controllers import (  # noqa: E402
    CBFController,
    Controller,
    ControlOutput,
    SontagController,
    StepStatus,
    UniversalController,
    has_input,
)
from .errors import (  # noqa: E402
    CompilationError,
    DimensionError,
    InfeasibleError,
    InputTypeError,
    ModelError,
    NonFiniteError,
    NumericalError,
    OutputError,
    ParameterError,
    RelativeDegreeError,
    SafeStabError,
    ScenarioError,
    UnsupportedPrimitiveError,
)
from .export import NativeController, export_c  # noqa: E402
from .filters import FilterOutput, SafetyFilter  # noqa: E402
from .formulas import (  # noqa: E402
    DEFAULT_PARALLEL_RTOL,
    SATISFIED_RTOL,
    Compatibility,
    CompatibilityCase,
    ConditionFlags,
    FormulaResult,
    KKTResiduals,
    MultiResult,
    MultiStatus,
    Region,
    cbf_universal,
    clf_cbf,
    clf_cbf_multi,
    clf_cbf_relaxed,
    clf_sontag,
    compatibility,
    conditions_satisfied,
    kkt_residuals,
    project_box,
    saturate_safety_first,
    zeta,
)
from .policy import PolicyController  # noqa: E402
from .robust import (  # noqa: E402
    ProbabilisticCompatibility,
    RobustMargins,
    UncertaintyModel,
    joint_probability,
    probabilistic_compatibility,
    robust_lie_terms,
    robust_margins,
)
from .simulation import Trajectory, closed_loop, rk4_step, simulate  # noqa: E402
from .systems import ControlAffineSystem  # noqa: E402

__all__ = [
    "CBF",
    "CLF",
    "ControlAffineSystem",
    "ControlOutput",
    "SontagController",
    "CBFController",
    "StepStatus",
    "has_input",
    "SafetyFilter",
    "FilterOutput",
    "PolicyController",
    "LieTerms",
    "Controller",
    "UniversalController",
    "lie_terms",
    "high_order_cbf",
    "ProbabilisticCompatibility",
    "RobustMargins",
    "UncertaintyModel",
    "joint_probability",
    "probabilistic_compatibility",
    "robust_lie_terms",
    "robust_margins",
    "DimensionError",
    "InfeasibleError",
    "InputTypeError",
    "ModelError",
    "NonFiniteError",
    "NumericalError",
    "OutputError",
    "ParameterError",
    "RelativeDegreeError",
    "SafeStabError",
    "ScenarioError",
    "DEFAULT_PARALLEL_RTOL",
    "SATISFIED_RTOL",
    "CompilationError",
    "UnsupportedPrimitiveError",
    "Compatibility",
    "CompatibilityCase",
    "ConditionFlags",
    "FormulaResult",
    "KKTResiduals",
    "MultiResult",
    "MultiStatus",
    "Region",
    "cbf_universal",
    "clf_cbf",
    "clf_cbf_multi",
    "clf_cbf_relaxed",
    "clf_sontag",
    "compatibility",
    "conditions_satisfied",
    "kkt_residuals",
    "project_box",
    "saturate_safety_first",
    "zeta",
    "Trajectory",
    "closed_loop",
    "rk4_step",
    "simulate",
    "NativeController",
    "export_c",
    "compilation_cache_dir",
    "disable_compilation_cache",
    "enable_compilation_cache",
    "disable_fit_cache",
    "enable_fit_cache",
    "fit_cache_dir",
]
