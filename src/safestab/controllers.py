"""Controllers: objects that map a state to an input through a closed-form formula.

Data flows one way: system + certificates -> Lie terms ``(a, b, c, d)`` -> (GP-robust terms)
-> formula -> input limits -> ``u``.
"""

from __future__ import annotations

import dataclasses
from enum import IntEnum
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np

from ._batching import over_batch
from ._numerics import as_scalar
from ._params import ParamSpec, bind, make_spec, merge_specs, resolve, trace_shape
from ._validation import check_real, is_concrete, traced_results
from ._values import ControllerValue
from .certificates import CBF, CLF, LieTerms, check_actuated, lie_terms_point
from .errors import (
    DimensionError,
    InfeasibleError,
    InputTypeError,
    ModelError,
    NonFiniteError,
    ParameterError,
)
from .formulas import DEFAULT_PARALLEL_RTOL, SATISFIED_RTOL, Region
from .formulas._checks import check_box, check_params
from .formulas._kernels import condition_flags, saturate_single
from .formulas.problem import (
    CBFFormula,
    CombinedFormula,
    Formula,
    MultiFormula,
    Problem,
    RelaxedFormula,
    SontagFormula,
)
from .robust import UncertaintyModel, check_beta, check_uncertainty_model, robust_lie_terms
from .sampled import check_sampled, sampled_shift
from .systems import ControlAffineSystem

__all__ = [
    "ControlOutput",
    "Controller",
    "StepStatus",
    "INPUT_STATUSES",
    "controller_step",
    "controller_input",
    "has_input",
    "UniversalController",
    "SontagController",
    "CBFController",
]


class StepStatus(IntEnum):
    """What a controller step achieved: ``OK``, no input at all, or an input that misses a barrier.

    ``OK`` means that an input was computed and that it meets every CBF condition the
    controller enforces (every formula but Sontag's CLF formula enforces its CBFs), judged
    against the condition's own magnitudes: read ``status == OK`` as "safe at this sample",
    in the setting of the conditions (continuous time at the sample, with the input held;
    docs/deployed.md). The CLF condition is reported by the flags (``clf_satisfied``,
    ``region``, ``formula_status``): the relaxed formulas and the safety-first fallbacks give
    it up by design.

    Statuses 1 to 7 come with ``u = NaN`` and every flag False: the step did not produce an
    input, and says why (the first failing stage). Statuses 8 and above come with a finite
    input, the controller's best, that does not meet every CBF condition, and name why
    (:data:`INPUT_STATUSES` lists the statuses that carry an input).
    """

    OK = 0
    NONFINITE_STATE = 1  #: the state itself contains NaN or inf (a diverging plant, say)
    NONFINITE_MODEL = 2  #: f, g, V, h or a gradient gave NaN or inf at a finite state
    NONFINITE_UNCERTAINTY = 3  #: the uncertainty model's mean or std is NaN or inf
    NEGATIVE_STD = 4  #: the uncertainty model returned a negative standard deviation
    NONFINITE_INPUT = 5  #: the formula's exact input overflows float64 (rescale the problem)
    NEGATIVE_WEIGHT = 6  #: a state-dependent phi(x) or varphi(x) is negative
    RELATIVE_DEGREE = 7  #: a high-order CBF's L_g h is not zero here (degree 2 fails)
    #: a CBF condition fails where that barrier's ``L_g h`` is zero: no input moves ``h``
    #: here (a barrier of relative degree 2 needs :func:`~safestab.high_order_cbf`)
    CBF_UNACTUATED = 8
    #: no input meets every CBF condition (within the input limits, where given): the limits
    #: and a barrier conflict, or the barriers conflict with each other; ``u`` is the
    #: controller's best compromise inside the limits
    CBF_INFEASIBLE = 9
    #: the applied input breaks a CBF condition that some input within the limits meets
    #: (the paper's projection onto the limits, eq. (26), can do this; the safety filter and
    #: ``saturation="safety_first"`` do not)
    CBF_UNMET = 10
    #: the safety filter's solver did not certify its input (``MultiStatus``
    #: ``ITERATION_LIMIT`` or ``UNCERTIFIED``): ``u`` is inside the limits, nothing else is
    #: promised
    UNCERTIFIED = 11


#: The statuses whose step carries a finite input: ``OK`` and the statuses from 8 on.
INPUT_STATUSES = (
    StepStatus.OK,
    StepStatus.CBF_UNACTUATED,
    StepStatus.CBF_INFEASIBLE,
    StepStatus.CBF_UNMET,
    StepStatus.UNCERTIFIED,
)


def has_input(status: Any) -> Any:
    """Bool array: where a step's ``status`` carries a finite input (:data:`INPUT_STATUSES`).

    Host data (a NumPy array, a list) gives a NumPy array, without compiling a program for its
    shape; a JAX array or a tracer a JAX array.
    """
    xp = jnp if isinstance(status, jax.Array) else np
    status = xp.asarray(status)
    return (status == StepStatus.OK) | (status >= StepStatus.CBF_UNACTUATED)


@dataclasses.dataclass(frozen=True)
class ControlOutput:
    """Everything one controller step computes, batched over the leading axes of ``x``.

    Attributes
    ----------
    u : array of shape (..., m)
        The input applied (after input limits, if any); NaN where ``status`` says the step
        produced no input (statuses 1 to 7, see :class:`StepStatus`).
    u_unconstrained : array of shape (..., m)
        The formula's input before limits.
    region : int array of shape (...,)
        :class:`~safestab.formulas.Region` of the formula.
    compatible : bool array of shape (...,)
        Whether the (possibly GP-robust) CLF and CBF conditions are compatible at ``x``
        (Lemma 1, the same decision as the hard formula's region).
    cbf_satisfied : bool array of shape (...,)
        Whether ``u`` (after limits) satisfies the CBF condition used by the formula, judged
        against the condition's own magnitudes
        (:func:`~safestab.formulas.conditions_satisfied`).
    clf_satisfied : bool array of shape (...,)
        Whether ``u`` (after limits) satisfies the CLF condition (without slack), likewise.
    slack : array of shape (...,)
        The CLF slack of the relaxed formula (0 otherwise).
    status : int array of shape (...,)
        A :class:`StepStatus` per state. ``OK`` says that an input was computed and that it
        meets the CBF condition the formula enforces (Sontag's CLF formula enforces none);
        where it does not, the status names why (``CBF_UNACTUATED``, ``CBF_INFEASIBLE``,
        ``CBF_UNMET``) and ``u`` is still the controller's input.
    terms : LieTerms
        The terms the formula used (GP-robust ones when an uncertainty model is given).
    """

    u: jax.Array
    u_unconstrained: jax.Array
    region: jax.Array
    compatible: jax.Array
    cbf_satisfied: jax.Array
    clf_satisfied: jax.Array
    slack: jax.Array
    status: jax.Array
    terms: LieTerms

    @property
    def safety_certified(self) -> jax.Array:
        """Bool array (...,): an input was computed and it meets the CBF condition.

        False where ``status`` is not OK, and where the applied input (after limits) breaks
        the CBF condition, judged against the condition's own magnitudes (where the limits
        and the barrier conflict, say). Equal to ``status == OK`` for every formula that
        enforces the CBF (all but Sontag's CLF formula).
        """
        return (self.status == StepStatus.OK) & self.cbf_satisfied

    @property
    def incompatible(self) -> jax.Array:
        """Bool array (...,): the conditions the formula used were incompatible (Lemma 1)."""
        return (~self.compatible) | (self.region == Region.INCOMPATIBLE)


jax.tree_util.register_dataclass(
    ControlOutput,
    data_fields=[f.name for f in dataclasses.fields(ControlOutput)],
    meta_fields=[],
)


def barrier_message(name: str, where: str, x: Any = None, detail: str = "") -> str:
    """The ``strict=True`` message for a step whose input misses a barrier, by status name.

    ``where`` names the state ("state index 3"); ``x`` its value; ``detail`` an addition
    (the solver's :class:`~safestab.formulas.MultiStatus`, say).
    """
    at = where + ("" if x is None else f" (x = {np.asarray(x).tolist()})")
    extra = f", {detail}" if detail else ""
    if name == "UNCERTIFIED":
        return f"the solver did not certify its input at {at} (status {name}{extra})"
    if name == "CBF_UNMET":
        return (
            f"the CBF condition is not met at {at} (status {name}{extra}): the applied input "
            "breaks it where an input within the limits meets it; use "
            "saturation='safety_first' or a SafetyFilter with the limits"
        )
    why = {
        "CBF_UNACTUATED": "L_g h = 0 there, so no input moves h; for a barrier the input "
        "acts on through its derivative, use high_order_cbf",
        "CBF_INFEASIBLE": "no input within the limits meets every CBF condition (the limits "
        "and a barrier, or two barriers, conflict); relax the limits or the barrier",
    }[name]
    return f"the CBF condition cannot be met at {at} (status {name}{extra}): {why}"


def _all_finite(*arrays: jax.Array) -> jax.Array:
    ok = jnp.asarray(True)
    for arr in arrays:
        fin = jnp.isfinite(arr)
        ok = ok & (fin if fin.ndim == 0 else jnp.all(fin))
    return ok


@jax.jit
def controller_step(ctrl: Controller, x: jax.Array, p: Any = None, u_nom: Any = None) -> Any:
    """The fused step of ``ctrl`` at states ``x`` (..., n), unchecked: ``ctrl.step_fn``.

    One jitted function of the package, with the controller as its argument (as
    ``diffrax.diffeqsolve`` takes its solver): its numeric parameters are arguments of the
    compiled program, so every controller of one tree structure (built alike, or
    :meth:`~safestab.Controller.replace` with new numbers) runs the program compiled for the
    first, and nothing jitted is kept on a controller. ``p``: the run-time parameters;
    ``u_nom`` (a :class:`~safestab.SafetyFilter` only): this call's nominal input, (m,) or
    (..., m).
    """
    if u_nom is None:
        return ctrl._step(x, p)
    return ctrl._step(x, p, u_nom=u_nom)


@jax.jit
def controller_input(ctrl: Controller, x: jax.Array, p: Any = None) -> jax.Array:
    """``controller_step(ctrl, x, p).u`` alone, so XLA drops the diagnostics: ``ctrl.input_fn``."""
    return ctrl._step(x, p).u


class Controller(ControllerValue):
    """A controller: a system, certificates, a formula object, limits and an uncertainty model.

    The one kind of controller value. :class:`UniversalController` builds it with one CLF,
    one CBF and a single-pair formula (:class:`~safestab.formulas.problem.CombinedFormula`,
    ``RelaxedFormula``, ``SontagFormula``, ``CBFFormula``) and returns a
    :class:`ControlOutput`; :class:`~safestab.SafetyFilter` builds it with any number of
    CLFs and CBFs and the several-row formula
    (:class:`~safestab.formulas.problem.MultiFormula`) and returns a
    :class:`~safestab.FilterOutput`; :class:`~safestab.PolicyController` runs a user's own law
    through the filter's step with a formula that enforces nothing. All are pytrees whose
    leaves are their numeric parameters (:meth:`tunables`, :meth:`replace`), run by
    :func:`~safestab.simulate` and exported by :func:`~safestab.export_c` alike.

    Each step computes the certificates' Lie terms at the state, the GP-robust terms when an
    uncertainty model is set (Lemma 3), the formula's :class:`~safestab.formulas.problem.Problem`
    and its solution, the limits and the flags, in one jitted function ``step_fn``.
    """

    system: ControlAffineSystem
    formula: Formula
    params_spec: ParamSpec | None
    clfs: tuple[CLF, ...]  #: every CLF (a UniversalController: its one)
    cbfs: tuple[CBF, ...]  #: every CBF
    uncertainty: Any  #: the GP-robust terms' model (None: none)
    #: The boundary layer on the robust CLF term(s); None: Lemma 3's term.
    robust_clf_layer: Any = None

    @property
    def _clf_layer(self) -> Any:
        """``robust_clf_layer`` as :func:`~safestab.robust.robust_margins` takes it (0: none)."""
        return 0.0 if self.robust_clf_layer is None else self.robust_clf_layer

    @staticmethod
    def _check_nonnegative_scalar(name: str, value: Any) -> None:
        """Check a real scalar that must be finite and >= 0 (where concrete, not traced)."""
        check_real(name, value)
        if np.ndim(value) != 0:
            raise DimensionError(f"{name} must be a scalar, got shape {np.shape(value)}")
        if is_concrete(value) and not (np.isfinite(float(value)) and float(value) >= 0):
            raise ParameterError(f"{name} must be a finite number >= 0, got {float(value)!r}")

    @classmethod
    def _check_robust_clf_layer(cls, layer: Any, uncertainty: Any) -> None:
        """``robust_clf_layer``: a finite scalar >= 0, and only with an uncertainty model."""
        if layer is None:
            return
        cls._check_nonnegative_scalar("robust_clf_layer", layer)
        if uncertainty is None:
            raise ParameterError(
                "robust_clf_layer smooths the GP-robust CLF term: it needs uncertainty= "
                "(a model of omega), got none"
            )

    @staticmethod
    def _check_uncertainty(uncertainty: Any, gp_beta: Any, n: int) -> Any:
        """Check the uncertainty model and return ``gp_beta`` checked (as given without one)."""
        if uncertainty is None:
            return gp_beta
        check_uncertainty_model(uncertainty, n)
        return check_beta(gp_beta, n)

    @classmethod
    def _check_limits(cls, u_min: Any, u_max: Any, m: int) -> tuple[Any, Any]:
        """The limits as (m,) arrays, ``u_min <= u_max``; each a scalar or shape (m,).

        One side alone is a one-sided box: the other side is infinite (as is an entry of
        ``-inf`` in ``u_min`` or ``+inf`` in ``u_max``). Neither: ``(None, None)``.
        """
        if u_min is None and u_max is None:
            return None, None
        if u_min is None:
            u_min = -np.inf
        if u_max is None:
            u_max = np.inf
        u_min, u_max = cls._limit("u_min", u_min, m), cls._limit("u_max", u_max, m)
        check_box(u_min, u_max)
        return u_min, u_max

    @staticmethod
    def _limit(name: str, value: Any, m: int) -> Any:
        check_real(name, value)
        if not is_concrete(value):
            if np.ndim(value) not in (0, 1) or np.shape(value) not in ((), (m,)):
                raise DimensionError(
                    f"{name} must be a scalar or have shape (n_inputs,) = ({m},), "
                    f"got shape {np.shape(value)}"
                )
            return jnp.broadcast_to(jnp.asarray(value, dtype=float), (m,))
        arr = np.asarray(value, dtype=float)
        if arr.ndim == 0:
            return np.full((m,), float(arr))
        if arr.shape != (m,):
            raise DimensionError(
                f"{name} must be a scalar or have shape (n_inputs,) = ({m},), got shape {arr.shape}"
            )
        return arr.copy()

    def _check_step(self, x: jax.Array, out: Any, strict: bool, p: Any) -> None:
        """Raise for the step's output as ``step`` documents (subclasses)."""
        raise NotImplementedError

    def step(self, x: Any, *, params: Any = None, strict: bool = False) -> Any:
        """The input and its diagnostics at states ``x`` of shape (..., n) (see subclasses)."""
        return self._checked_step(x, params, strict)

    def _checked_step(self, x: Any, params: Any, strict: bool, u_nom: Any = None) -> Any:
        """``step``'s checks of ``x`` and ``params``, the jitted step, its output's checks.

        ``u_nom``: a filter's nominal input for this call (checked by the filter's ``step``).
        """
        check_real("x", x)
        x = self.system.check_state(x)
        p = resolve(self.params_spec, params, f"the {self._owner}")
        out = controller_step(self.on_device(), x, p, u_nom)
        self._check_step(x, out, strict, p)
        return out

    @property
    def step_fn(self) -> Any:
        """The fused, jitted step without argument checks: ``step_fn(x)``, ``step_fn(x, p)``.

        For one state (n,) or a batch (..., n), with the run-time parameters ``p`` (shared by
        the batch) where the controller takes them; for loops and benchmarks.
        :func:`controller_step` with this controller as its argument: controllers of one
        tree structure share its compiled program.
        """
        # p always passed (None by default): one cache entry of the jitted function, which a
        # loop calling controller_step(ctrl, x, p) reuses
        return lambda x, p=None: controller_step(self, x, p)

    @property
    def input_fn(self) -> Any:
        """Like :attr:`step_fn`, returning only ``u`` (:func:`controller_input`)."""
        return lambda x, p=None: controller_input(self, x, p)

    def step_with_uncertainty(
        self, x: jax.Array, mean: jax.Array, std: jax.Array, p: Any = None
    ) -> Any:
        """The step at one state with the uncertainty model's mean and std there given.

        For a caller that needs the model's values at ``x`` itself too (the Monte Carlo
        study checks Lemma 2's band at every visited state): the model is then evaluated once
        per step instead of twice (XLA does not merge the two evaluations; measured, the check
        doubled the cost of a GP-robust step). Unchecked and jittable, like ``step_fn``.

        Parameters
        ----------
        x : array of shape (n,)
        mean, std : arrays of shape (n,)
            What ``uncertainty.mean_std(x)`` returns.
        p : pytree, optional
            The run-time parameters, when the controller takes them.

        Returns
        -------
        ControlOutput or FilterOutput
            As :meth:`step`.

        Raises
        ------
        ParameterError
            If the controller has no uncertainty model.
        DimensionError
            If ``x`` is not one state of shape (n,).
        """
        if self.uncertainty is None:
            raise ParameterError(
                f"step_with_uncertainty needs a {self._owner} with an uncertainty model"
            )
        if jnp.ndim(x) != 1:
            raise DimensionError(f"x must be one state of shape (n,), got shape {jnp.shape(x)}")
        return self._step(x, p, (mean, std))

    _owner = "controller"

    def __call__(self, x: Any, params: Any = None) -> jax.Array:
        """The input at states ``x`` of shape (..., n); shape (..., m)."""
        return self.step(x, params=params).u


class UniversalController(Controller):
    """The universal formula bound to a system, a CLF, a CBF and parameters.

    A controller is a JAX value (a pytree whose leaves are its numeric parameters, see
    :meth:`tunables`): it can be passed to a jitted function, vmapped over its parameters
    and differentiated with respect to them; :meth:`replace` changes an argument.

    Parameters
    ----------
    system : ControlAffineSystem
        The (nominal) model ``f``, ``g``.
    clf : CLF or None
        None with ``formula="cbf"``: the CBF formula alone, eq. (6), with no CLF (its terms
        ``a = b = 0``; ``clf_satisfied`` is then True).
    cbf : CBF or None
        None with ``formula="sontag"``: Sontag's CLF formula alone, eq. (3), with no CBF.
    kappa, rho : float
        >= 0 (see :func:`~safestab.formulas.clf_cbf`).
    phi, varphi : float or callable
        >= 0, weights in ``zeta`` and ``Gamma``; or, as the paper defines them, non-negative
        functions of the state (one state of shape (n,) to a scalar), checked at run time: a
        negative value gives the step status ``NEGATIVE_WEIGHT``.
    slack_weight : float, optional
        When given, the relaxed formula (Theorem 3) with this weight; otherwise the combined
        formula (Theorem 1, or Theorem 2 with an uncertainty model).
    u_min, u_max : float or array of shape (m,), optional
        Input limits; one alone is a one-sided box, and an entry of ``-inf`` (``u_min``) or
        ``+inf`` (``u_max``) leaves that side of that input unbounded.
    saturation : {"project", "safety_first"}
        How limits are enforced: ``"project"`` is the paper's projection, eq. (26);
        ``"safety_first"`` (single input only) keeps the CBF condition whenever some input in
        the box can (:func:`~safestab.formulas.saturate_safety_first`).
    uncertainty : UncertaintyModel, optional
        A model of ``omega(x)`` (mean and standard deviation, each of shape (n,) at one state).
        With it the controller uses the GP-robust terms of Lemma 3, i.e. Theorem 2 (or
        Theorem 3 with ``slack_weight``).
    gp_beta : float or array of shape (n,)
        Confidence scaling ``beta_i`` of the uncertainty model (Lemma 2); default 2.
    parallel_rtol : float
        Tolerance of the parallel test.
    formula : {"combined", "sontag", "cbf"} or Formula
        ``"combined"`` (default): the universal formula (Theorems 1-3). ``"sontag"``: Sontag's
        CLF formula alone, eq. (3) (region ``P1``, or ``P4`` where ``b = 0``); ``"cbf"``: the
        CBF formula alone, eq. (6) (region ``P2``, or ``P4`` where ``d = 0``). Both
        certificates are still evaluated, so the flags and ``compatible`` report on both
        conditions, for comparison studies (see :class:`SontagController`,
        :class:`CBFController`). Or a formula object of
        :mod:`safestab.formulas.problem` (``CombinedFormula(parallel_rtol)``,
        ``RelaxedFormula()`` with ``slack_weight``, ``SontagFormula()``, ``CBFFormula()``):
        the string is a name for one of them, and the attribute ``formula`` always holds the
        object.
    params : pytree, optional
        An example of run-time parameters for the controller's own callables: with it,
        callable ``phi`` and ``varphi`` take ``(x, p)``. The system and the certificates
        declare their own (``params=`` on each); all declared examples must agree, and one
        ``p`` reaches every function: ``step(x, params=p)``, ``step_fn(x, p)``,
        ``simulate(..., params=p)``. New values of ``p`` never recompile.
    cbf_margin : float, optional
        A tightening of the CBF condition, in the units of ``dh/dt``: the formula enforces
        ``c + d.u >= rho Gamma + cbf_margin`` instead of ``>= rho Gamma``, and
        ``cbf_satisfied`` reports ``c + d.u - rho Gamma >= cbf_margin / 2`` (up to the
        rounding of the condition). With a margin of twice a bound on the error of evaluating
        the condition (a lower precision, a model error), a step whose flag says satisfied
        keeps the exact condition: :func:`~safestab.export.export_scenario` uses it for the
        float export (docs/export.md, "Float that stays safe"). Default: none (0).
    sample_time, ddh_bound : float, optional
        The sampled-data margin (both or neither): the controller is run every
        ``sample_time`` s with its input held (zero-order hold), and ``ddh_bound`` is a bound
        ``M >= 0`` on ``-d^2h/dt^2`` along the true plant's flow with the input held, over the
        states the loop visits and the inputs it applies (units of ``h`` per s^2;
        :func:`~safestab.sampled.ddh_bound` estimates one). The CBF condition is then shifted
        to ``c + d.u >= rho Gamma + M T / 2 + max(0, alpha(h) - h / T)``, which keeps
        ``h >= 0`` over every hold interval where it holds at the sample, not only at the
        samples (:mod:`safestab.sampled`, docs/deployed.md); ``terms.c`` and the flags are
        those of the shifted condition. Default: none (the continuous-time condition).
    robust_clf_layer : float, optional
        With an uncertainty model only: a boundary layer ``eps >= 0`` (in the units of
        ``dV/dx``) on the CLF's robust term, which Lemma 3 makes proportional to ``|dV/dx|``
        and which therefore asks for an input that does not vanish at the goal (a sampled
        loop chatters there). The term is multiplied by ``|dV/dx| / sqrt(|dV/dx|^2 + eps^2)``;
        safety (the CBF's term) is unchanged, and the CLF guarantee (for the CLF's linear
        rate ``lam``) becomes practical: ``V`` converges exponentially to a sublevel set
        ``V <= eps M / (2 lam)``, ``M`` the largest ``|beta sigma|`` on it
        (:func:`~safestab.robust.robust_margins`, docs/learning.md). Default: none (Lemma 3).

    Attributes
    ----------
    params : dict
        The constants ``kappa``, ``rho``, ``phi``, ``varphi`` (not the run-time parameters).
    params_spec : ParamSpec or None
        The run-time parameters' structure shared by every function (None: none).
    step_fn : callable
        The fused, jitted step ``step_fn(x)`` or, with run-time parameters,
        ``step_fn(x, p)``; unchecked.
    input_fn : callable
        Like ``step_fn``, returning only ``u``.

    Raises
    ------
    ParameterError
        If a parameter is out of range, ``u_min > u_max``, only one limit is given, or
        ``formula`` is unknown (or ``"sontag"``/``"cbf"`` with ``slack_weight``).
    DimensionError
        If the certificates, limits or the uncertainty model's outputs do not fit the system,
        a parameter is not a scalar, or ``saturation="safety_first"`` with more than one input.
    InputTypeError
        If a parameter or limit is bool, complex or a string.
    TypeError
        If ``uncertainty`` does not provide ``mean_std``.
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        clf: CLF,
        cbf: CBF,
        *,
        kappa: float,
        rho: float,
        phi: float,
        varphi: float,
        slack_weight: float | None = None,
        u_min: Any = None,
        u_max: Any = None,
        saturation: Literal["project", "safety_first"] = "project",
        uncertainty: UncertaintyModel | None = None,
        gp_beta: Any = 2.0,
        parallel_rtol: float = DEFAULT_PARALLEL_RTOL,
        formula: Literal["combined", "sontag", "cbf"] = "combined",
        params: Any = None,
        cbf_margin: float | None = None,
        robust_clf_layer: float | None = None,
        sample_time: float | None = None,
        ddh_bound: float | None = None,
    ) -> None:
        init_args = {k: v for k, v in locals().items() if k not in ("self", "__class__")}
        formula_obj = self._formula_object(formula, slack_weight, parallel_rtol)
        sample_time, ddh_bound = check_sampled(sample_time, ddh_bound)
        if not (isinstance(clf, CLF) or clf is None and isinstance(formula_obj, CBFFormula)):
            raise InputTypeError(
                f"clf must be a CLF, got {type(clf).__name__}; without a CLF, use "
                "formula='cbf' (the CBF formula, eq. (6)), or SafetyFilter(system, cbfs) for "
                "the minimal change of a nominal input"
                if clf is None
                else f"clf must be a CLF (or None with formula='cbf'), got {type(clf).__name__}"
            )
        if not (isinstance(cbf, CBF) or cbf is None and isinstance(formula_obj, SontagFormula)):
            raise InputTypeError(
                f"cbf must be a CBF (or None with formula='sontag'), got {type(cbf).__name__} "
                "(several: SafetyFilter)"
            )
        check_params((), kappa=kappa, rho=rho, parallel_rtol=parallel_rtol)
        own_spec = make_spec(params, "the controller")
        for name, weight in (("phi", phi), ("varphi", varphi)):
            if callable(weight):
                out = trace_shape(name, weight, system.n_states, own_spec)
                shape = getattr(out, "shape", None)
                if shape != ():
                    raise DimensionError(
                        f"{name}(x) must return a scalar for a state of shape "
                        f"({system.n_states},), got {shape}"
                    )
            else:
                check_params((), **{name: weight})
        if slack_weight is not None:
            check_params((), slack_weight=slack_weight)
        if cbf_margin is not None:
            self._check_nonnegative_scalar("cbf_margin", cbf_margin)
        self._check_robust_clf_layer(robust_clf_layer, uncertainty)
        certs = [c for c in (clf, cbf) if c is not None]
        for cert in certs:
            cert.check(system.n_states)
        self.params_spec: ParamSpec | None = merge_specs(
            [system.params_spec, *(c.params_spec for c in certs), own_spec]
        )
        if cbf is not None and not isinstance(formula_obj, SontagFormula):  # enforced
            check_actuated(system, cbf, "cbf", getattr(self.params_spec, "example", None))
        m = system.n_inputs
        u_min, u_max = self._check_limits(u_min, u_max, m)
        if saturation not in ("project", "safety_first"):
            raise ParameterError(
                f"saturation must be 'project' or 'safety_first', got {saturation!r}"
            )
        if saturation == "safety_first" and m != 1:
            raise DimensionError(
                f"saturation='safety_first' needs a single-input system, got n_inputs={m}"
            )
        gp_beta = self._check_uncertainty(uncertainty, gp_beta, system.n_states)
        self.system = system
        self.clf = clf
        self.cbf = cbf
        self.params = {
            "kappa": as_scalar(kappa),
            "rho": as_scalar(rho),
            "phi": phi if callable(phi) else as_scalar(phi),
            "varphi": varphi if callable(varphi) else as_scalar(varphi),
        }
        takes = own_spec is not None
        self._phi_of = bind(phi, takes) if callable(phi) else None
        self._varphi_of = bind(varphi, takes) if callable(varphi) else None
        self.slack_weight = None if slack_weight is None else as_scalar(slack_weight)
        self.u_min = u_min
        self.u_max = u_max
        self.saturation = saturation
        self.uncertainty = uncertainty
        self.gp_beta = gp_beta if uncertainty is not None else None
        if isinstance(formula_obj, CombinedFormula):
            parallel_rtol = formula_obj.parallel_rtol  # the object's setting, not the default
        self.parallel_rtol = float(parallel_rtol)
        #: The formula object (:mod:`safestab.formulas.problem`) that maps the step's problem
        #: to its input.
        self.formula: Formula = formula_obj
        #: The hard combined formula, whose case is Lemma 1's compatibility (``compatible``).
        self._combined = (
            formula_obj
            if isinstance(formula_obj, CombinedFormula)
            else CombinedFormula(self.parallel_rtol)
        )
        self.cbf_margin = None if cbf_margin is None else as_scalar(cbf_margin)
        self.robust_clf_layer = None if robust_clf_layer is None else as_scalar(robust_clf_layer)
        #: The hold time ``T`` (s) and the bound ``M`` of the sampled-data margin (None: none).
        self.sample_time = None if sample_time is None else as_scalar(sample_time)
        self.ddh_bound = None if ddh_bound is None else as_scalar(ddh_bound)
        self._remember(UniversalController, init_args)

    _CHILDREN = ("clf", "cbf")

    @property
    def clfs(self) -> tuple[CLF, ...]:
        """The controller's CLFs, ``(clf,)`` or ``()``: the same view as a filter's."""
        return () if self.clf is None else (self.clf,)

    @property
    def cbfs(self) -> tuple[CBF, ...]:
        """The controller's CBFs, ``(cbf,)`` or ``()``: the same view as a filter's."""
        return () if self.cbf is None else (self.cbf,)

    def _leaf_names(self) -> tuple[str, ...]:
        names = ["kappa", "rho"]
        names += [w for w in ("phi", "varphi") if not callable(self.params[w])]
        names += ["slack_weight"] if self.slack_weight is not None else []
        names += ["u_min", "u_max"] if self.u_min is not None else []
        names += ["gp_beta"] if self.uncertainty is not None else []
        names += ["cbf_margin"] if self.cbf_margin is not None else []
        names += ["robust_clf_layer"] if self.robust_clf_layer is not None else []
        names += ["sample_time", "ddh_bound"] if self.sample_time is not None else []
        return tuple(names)

    @staticmethod
    def _formula_object(formula: Any, slack_weight: Any, parallel_rtol: Any) -> Formula:
        """The formula object for the ``formula`` argument (a name or an object)."""
        names = {"combined": CombinedFormula, "sontag": SontagFormula, "cbf": CBFFormula}
        if isinstance(formula, str) and formula in names:
            if formula != "combined" and slack_weight is not None:
                raise ParameterError(
                    f"slack_weight applies to the combined formula, not {formula!r}"
                )
            if formula == "combined":
                if slack_weight is not None:
                    return RelaxedFormula()
                check_params((), parallel_rtol=parallel_rtol)
                return CombinedFormula(float(parallel_rtol))
            return names[formula]()
        if isinstance(formula, MultiFormula):
            raise ParameterError(
                "MultiFormula (several CLFs and CBFs, limits inside the problem) is the "
                "SafetyFilter's formula: use SafetyFilter(system, cbfs, clfs=...)"
            )
        if isinstance(formula, Formula):
            relaxed = isinstance(formula, RelaxedFormula)
            if relaxed != (slack_weight is not None):
                raise ParameterError(
                    "RelaxedFormula needs slack_weight, and slack_weight needs RelaxedFormula "
                    f"(or formula='combined'); got {type(formula).__name__} with "
                    f"slack_weight={slack_weight!r}"
                )
            return formula
        raise ParameterError(
            "formula must be 'combined', 'sontag', 'cbf' or a formula object "
            f"(safestab.formulas.problem), got {formula!r}"
        )

    def __repr__(self) -> str:
        kinds = {SontagFormula: "sontag", CBFFormula: "cbf", RelaxedFormula: "relaxed"}
        kind = kinds.get(type(self.formula), "clf_cbf")
        gp = ", GP-robust" if self.uncertainty is not None else ""
        return f"UniversalController({self.system.name}, formula={kind}{gp}, params={self.params})"

    # -- the pipeline, one state at a time (vmapped for batches) --------------------------

    def terms_point(self, x: jax.Array, p: Any = None) -> LieTerms:
        """The (GP-robust when an uncertainty model is set) Lie terms at one state.

        ``p``: the run-time parameters (unchecked), when the controller takes them.
        """
        return self._terms_status_point(x, p)[0]

    def weights_point(self, x: jax.Array, p: Any = None) -> tuple[jax.Array, jax.Array]:
        """``phi`` and ``varphi`` at one state ``x`` (n,): scalars (constants or functions of x).

        ``p``: the run-time parameters (unchecked), when the controller takes them.
        """
        phi, varphi = self.params["phi"], self.params["varphi"]
        return (
            jnp.asarray(self._phi_of(x, p) if self._phi_of is not None else phi, dtype=float),
            jnp.asarray(
                self._varphi_of(x, p) if self._varphi_of is not None else varphi, dtype=float
            ),
        )

    def _terms_status_point(
        self, x: jax.Array, p: Any = None, given: tuple | None = None
    ) -> tuple[LieTerms, jax.Array, tuple]:
        terms = lie_terms_point(self.system, self.clf, self.cbf, x, p)
        weights = self.weights_point(x, p)
        S = StepStatus
        model_ok = jnp.where(
            _all_finite(*terms, *weights),
            jnp.where((weights[0] < 0) | (weights[1] < 0), S.NEGATIVE_WEIGHT, S.OK),
            S.NONFINITE_MODEL,
        )
        if self.cbf is not None:
            model_ok = jnp.where(
                (model_ok == S.OK) & ~self.cbf.relative_degree_holds(self.system, x, p),
                S.RELATIVE_DEGREE,
                model_ok,
            )
        status = jnp.where(~_all_finite(x), S.NONFINITE_STATE, model_ok)
        if self.uncertainty is not None:
            mean, std = self.uncertainty.mean_std(x) if given is None else given
            beta = jnp.asarray(self.gp_beta)
            grads = tuple(
                jnp.zeros(self.system.n_states) if c is None else c.grad_of(x, p)
                for c in (self.clf, self.cbf)
            )
            terms = robust_lie_terms(terms, *grads, mean, std, beta, self._clf_layer)
            status = jnp.where(
                status != S.OK,
                status,
                jnp.where(
                    ~_all_finite(mean, std),
                    S.NONFINITE_UNCERTAINTY,
                    jnp.where(jnp.any(std < 0), S.NEGATIVE_STD, S.OK),
                ),
            )
        if self.sample_time is not None and self.cbf is not None:  # a shift of c
            h = self.cbf.fn_of(x, p)
            shift = sampled_shift(h, self.cbf.rate_term(h), self.sample_time, self.ddh_bound)
            terms = terms._replace(c=terms.c - shift)
        return terms, status.astype(jnp.int32), weights

    def _step(self, x: jax.Array, p: Any = None, given: tuple | None = None) -> ControlOutput:
        terms, status, (phi, varphi) = over_batch(
            lambda s: self._terms_status_point(s, p, given), x
        )
        a, b, c, d = terms
        p = self.params
        # a negative weight is reported by the status; the formula runs on 0 meanwhile
        phi, varphi = jnp.maximum(phi, 0.0), jnp.maximum(varphi, 0.0)
        problem = Problem(
            a, b, c, d, p["kappa"], p["rho"], phi, varphi,
            slack_weight=self.slack_weight, cbf_margin=self.cbf_margin,
        )  # fmt: skip
        mg = problem.margins()  # the CBF condition enforced (with the margin)
        # flags: the condition with half the margin (see cbf_margin)
        mg_flags = (
            mg
            if self.cbf_margin is None
            else problem.replace(cbf_margin=0.5 * self.cbf_margin).margins()
        )
        hard = self._combined.solution(problem.replace(slack_weight=None))
        res = hard if self.formula is self._combined else self.formula.solve(problem)
        u = res.u
        if self.u_min is not None:
            lo, hi = jnp.asarray(self.u_min), jnp.asarray(self.u_max)
            if self.saturation == "safety_first":
                u, _ = saturate_single(u, mg.B, d, lo, hi)
            else:
                u = jnp.clip(u, lo, hi)
        clf_ok, cbf_ok = condition_flags(
            a, b, c, d, u, mg_flags, p["kappa"], p["rho"], SATISFIED_RTOL
        )
        finite_out = jnp.all(jnp.isfinite(res.u), -1) & jnp.isfinite(res.slack)
        status = jnp.where(
            (status == StepStatus.OK) & ~finite_out, StepStatus.NONFINITE_INPUT, status
        ).astype(jnp.int32)
        ok = status == StepStatus.OK
        if not isinstance(self.formula, SontagFormula):  # the formula enforces the CBF
            status = self._barrier_status(status, cbf_ok, a, b, c, d, mg_flags)
        nan = jnp.full_like(u, jnp.nan)
        return ControlOutput(
            u=jnp.where(ok[..., None], u, nan),
            u_unconstrained=jnp.where(ok[..., None], res.u, nan),
            region=res.region,
            compatible=ok & (hard.case > 0),
            cbf_satisfied=ok & cbf_ok,
            clf_satisfied=ok & clf_ok,
            slack=res.slack,
            status=status,
            terms=terms,
        )

    def _barrier_status(self, status, cbf_ok, a, b, c, d, mg) -> jax.Array:
        """``status`` with the reason named where an input was computed but breaks the CBF.

        ``CBF_UNACTUATED`` where ``d = L_g h`` is zero (no input moves ``h``);
        ``CBF_INFEASIBLE`` where no input within the limits meets the condition (judged by
        the same flag at the box corner that maximises ``d.u``); ``CBF_UNMET`` where one
        does (the projection onto the limits broke the condition).
        """
        S = StepStatus
        unmet = (status == S.OK) & ~cbf_ok
        if self.u_min is not None:
            lo, hi = jnp.asarray(self.u_min), jnp.asarray(self.u_max)
            # the box input that maximises d.u (0 where d_j = 0: an infinite bound there
            # would make 0 * inf); an infinite corner meets the condition, as it should
            best = jnp.where(d > 0, hi, jnp.where(d < 0, lo, 0.0))
            _, box_ok = condition_flags(
                a, b, c, d, best, mg, self.params["kappa"], self.params["rho"], SATISFIED_RTOL
            )
        else:
            box_ok = jnp.asarray(True)
        reason = jnp.where(
            jnp.all(d == 0, -1), S.CBF_UNACTUATED, jnp.where(box_ok, S.CBF_UNMET, S.CBF_INFEASIBLE)
        )
        return jnp.where(unmet, reason, status).astype(jnp.int32)

    # -- public, checked entry points ---------------------------------------------------

    def diagnose(self, x: Any, params: Any = None) -> str:
        """Name the parts of the model that are not finite or invalid at one state ``x``.

        Evaluates ``f``, ``g``, ``V``, ``h``, their gradients and the uncertainty model at
        ``x`` (shape (n,)) eagerly (with the run-time ``params``, when the controller takes
        them); for messages and debugging.
        """
        x = jnp.asarray(x, dtype=float)
        p = resolve(self.params_spec, params, "the controller")
        parts = {
            "x": x,
            "f(x)": self.system.f_of(x, p),
            "g(x)": self.system.g_of(x, p),
        }
        for sym, cert in (("V", self.clf), ("h", self.cbf)):
            if cert is not None:
                parts[f"{sym}(x)"] = cert.fn_of(x, p)
                parts[f"grad {sym}(x)"] = cert.grad_of(x, p)
        if self.uncertainty is not None:
            mean, std = self.uncertainty.mean_std(x)
            parts["uncertainty mean"] = mean
            parts["uncertainty std"] = std
        phi, varphi = self.weights_point(x, p)
        parts["phi(x)"], parts["varphi(x)"] = phi, varphi
        bad = [name for name, val in parts.items() if not bool(np.all(np.isfinite(val)))]
        if self.uncertainty is not None and bool(np.any(np.asarray(parts["uncertainty std"]) < 0)):
            bad.append("uncertainty std (negative)")
        bad += [f"{n} (negative)" for n, w in (("phi(x)", phi), ("varphi(x)", varphi)) if w < 0]
        return ", ".join(bad) if bad else "none"

    def _raise_for_status(
        self, x: jax.Array, out: ControlOutput, strict: bool, p: Any = None
    ) -> None:
        if traced_results((out.u, out.status, x), strict, "the controller's step"):
            return
        status = np.atleast_1d(np.asarray(out.status))
        xs = np.asarray(x).reshape((-1, self.system.n_states))
        flat = status.reshape(-1)
        neg = np.flatnonzero(flat == StepStatus.NEGATIVE_STD)
        if neg.size:
            i = int(neg[0])
            raise ModelError(
                f"the uncertainty model returned a negative standard deviation at state index "
                f"{i} (x = {xs[i].tolist()}); a standard deviation must be >= 0"
            )
        if not strict:
            return
        badi = np.flatnonzero(flat != StepStatus.OK)
        if badi.size:
            i = int(badi[0])
            name = StepStatus(int(flat[i])).name
            if flat[i] in INPUT_STATUSES:
                raise InfeasibleError(barrier_message(name, f"state index {i}", xs[i]))
            if flat[i] == StepStatus.RELATIVE_DEGREE:
                raise ModelError(
                    f"controller step failed with status {name} at state index {i} "
                    f"(x = {xs[i].tolist()}): L_g h is not zero there, so the high-order CBF's "
                    "relative degree 2 does not hold"
                )
            if flat[i] == StepStatus.NEGATIVE_WEIGHT:
                raise ModelError(
                    f"controller step failed with status {name} at state index {i} "
                    f"(x = {xs[i].tolist()}): {self.diagnose(xs[i], p)}; phi and varphi must be "
                    ">= 0"
                )
            raise NonFiniteError(
                f"controller step failed with status {name} at state index {i} "
                f"(x = {xs[i].tolist()}); not finite: {self.diagnose(xs[i], p)}"
            )
        infeasible = np.asarray(out.region == Region.INCOMPATIBLE) | ~np.asarray(out.cbf_satisfied)
        if np.any(infeasible):
            idx = np.argwhere(np.atleast_1d(infeasible))[0].tolist()
            region = Region(int(np.atleast_1d(np.asarray(out.region))[tuple(idx)])).name
            raise InfeasibleError(
                f"the CBF condition cannot be met at state index {idx} (region {region}); "
                "use slack_weight for the relaxed formula or relax the input limits"
            )

    def step(self, x: Any, *, params: Any = None, strict: bool = False) -> ControlOutput:
        """Compute the input and its diagnostics at states ``x`` of shape (..., n).

        Parameters
        ----------
        x : array of shape (..., n)
        params : pytree, optional
            The run-time parameters, required when the system, a certificate or the
            controller declared ``params=example`` (same structure and leaf shapes; shared by
            every state of the batch). One compiled step serves every value.
        strict : bool
            Raise if at some state the step did not produce a finite input (naming the cause
            and the non-finite parts of the model), the conditions are incompatible, or the
            applied input violates the CBF condition.

        Returns
        -------
        ControlOutput

        Raises
        ------
        InputTypeError
            If ``x`` (or a leaf of ``params``) is bool, complex or a string.
        DimensionError
            If ``x`` has the wrong last axis, or a leaf of ``params`` the wrong shape.
        ParameterError
            If ``params`` is missing where declared, given where not, or has another
            structure than the declared example.
        NonFiniteError
            If ``x`` or ``params`` contains NaN or inf; with ``strict=True``, if a step's
            status is not OK.
        ModelError
            If the uncertainty model returns a negative standard deviation (always); with
            ``strict=True``, if ``phi(x)`` or ``varphi(x)`` is negative.
        InfeasibleError
            With ``strict=True``, if the conditions are incompatible or the CBF condition is
            violated by the applied input.
        """
        return super().step(x, params=params, strict=strict)

    def _check_step(self, x: jax.Array, out: ControlOutput, strict: bool, p: Any) -> None:
        self._raise_for_status(x, out, strict, p)


class SontagController(UniversalController):
    """Sontag's CLF formula, eq. (3), as a controller (``formula="sontag"``).

    ``u = -(a + kappa zeta) / |b|^2 b`` (0 where ``b = 0``). Takes the same arguments as
    :class:`UniversalController` except ``slack_weight`` and ``formula``; the CBF is still
    evaluated, so ``cbf_satisfied`` says whether the CLF-only input happens to be safe.
    """

    def __init__(self, system: ControlAffineSystem, clf: CLF, cbf: CBF, **kwargs: Any) -> None:
        super().__init__(system, clf, cbf, formula="sontag", **kwargs)


class CBFController(UniversalController):
    """The CBF formula, eq. (6), as a controller (``formula="cbf"``).

    ``u = (rho Gamma - c) / |d|^2 d`` (0 where ``d = 0``). Takes the same arguments as
    :class:`UniversalController` except ``slack_weight`` and ``formula``; the CLF is still
    evaluated, so ``clf_satisfied`` reports on the CLF condition.
    """

    def __init__(self, system: ControlAffineSystem, clf: CLF, cbf: CBF, **kwargs: Any) -> None:
        super().__init__(system, clf, cbf, formula="cbf", **kwargs)
