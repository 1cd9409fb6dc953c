"""Closed-form universal formulas over the Lie terms ``(a, b, c, d)``.

Every formula here is a pure, jittable function of batched arrays. Nothing here knows about
systems, certificates or Gaussian processes: callers compute

* ``a = L_f V + lambda V`` and ``b = L_g V`` (CLF side), shapes ``(...,)`` and ``(..., m)``,
* ``c = L_f h + beta h`` and ``d = L_g h`` (CBF side), shapes ``(...,)`` and ``(..., m)``,

and pass them in. See ``docs/theory.md`` for the derivations.

Notation used throughout (the paper's, with the corrections listed in ``docs/theory.md``)::

    zeta  = sqrt(a^2 + phi |b|^4)        Gamma = sqrt(c^2 + varphi |d|^4)
    A     = a + kappa zeta               B     = rho Gamma - c
    CLF condition:  b u <= -A            CBF condition:  d u >= B

The package has one idea per module: ``single`` (Sontag's CLF formula and the CBF formula),
``two_constraint`` (the combined and relaxed formulas), ``compatibility_check`` (Lemma 1),
``limits`` (input limits), ``output_checks`` (KKT residuals and the condition flags of an
output), ``multi`` (several
CLFs and CBFs, limits inside the problem, weighted objectives) and ``results`` (the result
types). The public functions check their arguments and call the unchecked kernels of
the internal modules ``_kernels`` and ``_dual_active_set``, which the controllers call as well.

Every function composes with ``jax.jit``, ``jax.vmap``, ``jax.grad`` and ``jax.jacfwd``.
Under a transformation the checks that need values are skipped (shapes and dtypes are still
checked) and the outputs are returned as computed. Derivatives are exact inside each region
(and inside each active set of the several-row solver, which is differentiated on its final
active set); on a boundary between regions they are those of the region picked there, and
they are never NaN where the value is finite (docs/jax.md).
"""

from ._kernels import DEFAULT_PARALLEL_RTOL, SATISFIED_RTOL
from .compatibility_check import compatibility
from .limits import project_box, saturate_safety_first
from .multi import MultiResult, MultiStatus, clf_cbf_multi
from .output_checks import conditions_satisfied, kkt_residuals
from .passthrough import PassThrough
from .problem import (
    CBFFormula,
    CombinedFormula,
    Formula,
    MultiFormula,
    Problem,
    RelaxedFormula,
    SontagFormula,
)
from .results import (
    Compatibility,
    CompatibilityCase,
    ConditionFlags,
    FormulaResult,
    KKTResiduals,
    Region,
)
from .single import cbf_universal, clf_sontag, zeta
from .smooth import (
    ExplicitFilter,
    HalfSontagFilter,
    SmoothFilter,
    SoftplusFilter,
    SontagFilter,
)
from .two_constraint import clf_cbf, clf_cbf_relaxed

__all__ = [
    "DEFAULT_PARALLEL_RTOL",
    "SATISFIED_RTOL",
    "Region",
    "CompatibilityCase",
    "FormulaResult",
    "Compatibility",
    "KKTResiduals",
    "ConditionFlags",
    "zeta",
    "clf_sontag",
    "cbf_universal",
    "clf_cbf",
    "clf_cbf_relaxed",
    "compatibility",
    "project_box",
    "saturate_safety_first",
    "kkt_residuals",
    "conditions_satisfied",
    "MultiResult",
    "MultiStatus",
    "clf_cbf_multi",
    "Problem",
    "Formula",
    "PassThrough",
    "SontagFormula",
    "CBFFormula",
    "CombinedFormula",
    "RelaxedFormula",
    "MultiFormula",
    "SmoothFilter",
    "ExplicitFilter",
    "SontagFilter",
    "HalfSontagFilter",
    "SoftplusFilter",
]
