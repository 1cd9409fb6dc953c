"""Safety filters: several CBFs and CLFs, limits, a nominal input, in closed form.

Limits are inside the problem, and the objective may be weighted.

:class:`SafetyFilter` is to :func:`~safestab.formulas.clf_cbf_multi` what
:class:`~safestab.controllers.UniversalController` is to :func:`~safestab.formulas.clf_cbf`:
a state-to-input map with statuses and flags, jitted and batched.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._batching import over_batch
from ._numerics import as_scalar
from ._params import ParamSpec, bind, make_spec, merge_specs, trace_shape
from ._validation import check_finite, check_real, is_concrete, traced_results
from .certificates import CBF, CLF, check_actuated
from .controllers import Controller, StepStatus, barrier_message, has_input
from .errors import DimensionError, InfeasibleError, ModelError, NonFiniteError, ParameterError
from .formulas import MultiStatus
from .formulas._checks import check_max_iter, check_params
from .formulas._kernels import condition_flags, margins, satisfied_rtol
from .formulas.passthrough import PassThrough
from .formulas.problem import UNITS, MultiFormula, Problem
from .formulas.smooth import SmoothFilter
from .robust import UncertaintyModel, robust_margins
from .sampled import check_sampled, sampled_shift
from .systems import ControlAffineSystem

__all__ = ["SafetyFilter", "FilterOutput"]


@dataclasses.dataclass(frozen=True)
class FilterOutput:
    """One safety-filter step, batched over the leading axes of ``x``.

    Attributes
    ----------
    u : array of shape (..., m)
        The input (NaN where ``status`` says the step produced none: statuses 1 to 7).
    status : int array of shape (...,)
        A :class:`~safestab.controllers.StepStatus`: ``OK`` says that an input was computed,
        certified by the solver, and that it meets every CBF condition (and the limits): the
        step is safe in the setting of the conditions. Where it does not, the status names
        why and ``u`` is still the filter's input: ``CBF_UNACTUATED`` (a violated barrier's
        ``L_g h`` is zero), ``CBF_INFEASIBLE`` (the limits and the barriers, or two barriers,
        conflict: ``formula_status`` ``CBF_RELAXED``, ``u`` their best compromise inside the
        limits), ``UNCERTIFIED`` (the solver stopped uncertified). Statuses 1 to 7 mean no
        input (``u`` NaN).
    formula_status : int array of shape (...,)
        A :class:`~safestab.formulas.MultiStatus`: solved, or which fallback was used.
    active : bool array of shape (..., rows)
        Active rows (CLFs, CBFs, upper limits, lower limits).
    multipliers : array of shape (..., rows)
    slack : array of shape (..., p)
        CLF slacks (a relaxed CBF shows in ``formula_status`` and ``cbf_satisfied``).
    cbf_satisfied : bool array of shape (..., k)
        Per CBF, judged against the condition's own magnitudes.
    clf_satisfied : bool array of shape (..., p)
        Per CLF (without slack), likewise.
    """

    u: jax.Array
    status: jax.Array
    formula_status: jax.Array
    active: jax.Array
    multipliers: jax.Array
    slack: jax.Array
    cbf_satisfied: jax.Array
    clf_satisfied: jax.Array

    @property
    def safety_certified(self) -> jax.Array:
        """Bool array (...,): the input is certified to keep every barrier and limit.

        True exactly where ``status`` is OK, the solver's KKT certificate holds for the whole
        problem or for its CBF-and-limits part (``formula_status`` ``SOLVED`` or
        ``CLF_DROPPED``) and every CBF condition holds at ``u``, judged against its own
        magnitudes. False where the limits and a CBF conflict (``CBF_RELAXED``), where the
        solver stopped uncertified, and where the step failed. (A property, not a field: the
        exported C step's outputs are unchanged.) Equal to ``status == OK``.
        """
        solved = (self.formula_status == MultiStatus.SOLVED) | (
            self.formula_status == MultiStatus.CLF_DROPPED
        )
        return (self.status == StepStatus.OK) & solved & jnp.all(self.cbf_satisfied, -1)

    @property
    def incompatible(self) -> jax.Array:
        """Bool array (...,): the problem was not solved whole (``formula_status`` not SOLVED).

        A fallback was used (a hard CLF dropped, the CBFs relaxed against the limits) or the
        solver stopped uncertified; never for the pass-through formula of a
        :class:`~safestab.PolicyController`, which solves nothing.
        """
        return self.formula_status != MultiStatus.SOLVED


jax.tree_util.register_dataclass(
    FilterOutput, data_fields=[f.name for f in dataclasses.fields(FilterOutput)], meta_fields=[]
)


def check_output(out: Any, strict: bool) -> None:
    """The checks of a filter step's outputs (the JAX step's and the native one's).

    Raises
    ------
    ModelError
        Where the uncertainty model returned a negative standard deviation (always).
    NonFiniteError
        With ``strict``, where a step failed (a non-finite state, model or input).
    InfeasibleError
        With ``strict``, where a fallback was used, the solver stopped uncertified or a CBF
        condition is violated; the message names the first such state.
    """
    if traced_results((out.u, out.status), strict, "the filter's step"):
        return
    status = np.atleast_1d(np.asarray(out.status)).reshape(-1)
    if np.any(status == StepStatus.NEGATIVE_STD):
        raise ModelError("the uncertainty model returned a negative standard deviation")
    if strict:
        raise_where_failed(out)


def raise_where_failed(out: Any) -> None:
    """The ``strict=True`` check of a filter step (JAX or native) on its outputs.

    Raises
    ------
    NonFiniteError
        Where a step failed (a non-finite state, model or input).
    InfeasibleError
        Where a fallback was used, the solver stopped uncertified or a CBF condition is
        violated; the message names the first such state.
    """
    status = np.atleast_1d(np.asarray(out.status)).reshape(-1)
    fstat = np.atleast_1d(np.asarray(out.formula_status)).reshape(-1)
    no_input = ~np.asarray(has_input(status))
    if np.any(no_input):
        i = int(np.flatnonzero(no_input)[0])
        name = StepStatus(int(status[i])).name
        raise NonFiniteError(f"filter step failed with status {name} at state index {i}")
    cbf_ok = np.asarray(out.cbf_satisfied).reshape(fstat.shape[0], -1).all(-1)
    failing = (status != StepStatus.OK) | (fstat != MultiStatus.SOLVED) | ~cbf_ok
    if np.any(failing):
        i = int(np.argmax(failing))
        name = StepStatus(int(status[i])).name
        detail = f"formula_status {MultiStatus(int(fstat[i])).name}"
        if status[i] == StepStatus.OK:  # certified and safe, but a hard CLF was dropped
            raise InfeasibleError(
                f"the CBF and CLF conditions and limits cannot all be met at state index {i} "
                f"({detail}: the CLF rows were dropped)"
            )
        raise InfeasibleError(barrier_message(name, f"state index {i}", detail=detail))


def _barrier_status(
    status: Any, formula_status: Any, cbf_ok: Any, d: Any, box_ok: Any = None
) -> jax.Array:
    """``status`` with the reason named where the filter's input misses a barrier.

    ``CBF_UNACTUATED`` where a violated barrier's ``d = L_g h`` is zero; else
    ``CBF_INFEASIBLE`` where the solver relaxed the CBFs (they conflict with the limits or
    with each other), or where a violated barrier alone cannot be met by any input within the
    limits (``box_ok`` (..., k), given for the pass-through formula, which solves nothing);
    ``UNCERTIFIED`` where it stopped uncertified; ``CBF_UNMET`` where a CBF flag fails at an
    otherwise certified answer.
    """
    S, M = StepStatus, MultiStatus
    unmet = ~cbf_ok  # (..., k)
    unactuated = jnp.any(unmet & jnp.all(d == 0, -1), -1)
    certified = (formula_status == M.SOLVED) | (formula_status == M.CLF_DROPPED)
    boxed_out = jnp.asarray(False) if box_ok is None else jnp.any(unmet & ~box_ok, -1)
    reason = jnp.where(
        unactuated,
        S.CBF_UNACTUATED,
        jnp.where(
            (formula_status == M.CBF_RELAXED) | boxed_out,
            S.CBF_INFEASIBLE,
            jnp.where(certified, S.CBF_UNMET, S.UNCERTIFIED),
        ),
    )
    failed = unactuated | ~certified | jnp.any(unmet, -1)
    return jnp.where((status == S.OK) & failed, reason, status).astype(jnp.int32)


def _as_tuple(value: Any, kind: type, name: str) -> tuple:
    try:
        items = (value,) if isinstance(value, kind) else tuple(value)
    except TypeError:
        items = (value,)
    if not all(isinstance(v, kind) for v in items):
        raise TypeError(f"{name} must be a {kind.__name__} or a sequence of them")
    return items


class SafetyFilter(Controller):
    """Minimally modify a nominal input so that every CBF (and CLF) condition holds.

    A :class:`~safestab.controllers.Controller` with the several-row formula
    (:class:`~safestab.formulas.problem.MultiFormula`, attribute ``formula``); like
    :class:`~safestab.UniversalController`, a JAX value whose leaves are its numeric
    parameters (:meth:`tunables`, :meth:`replace`).

    Solves, at each state, ``min 1/2 (u - u_nom)^T H (u - u_nom) + 1/2 m sum chi_j^2`` subject
    to every CBF condition, every CLF condition (with slack ``chi_j`` when ``slack_weight`` is
    given) and the input limits, exactly (:func:`~safestab.formulas.clf_cbf_multi`).

    Parameters
    ----------
    system : ControlAffineSystem
    cbfs : CBF or sequence of CBF
        ``k >= 1`` barriers (plain or :func:`~safestab.certificates.high_order_cbf`).
    clfs : CLF or sequence of CLF, optional
        ``p >= 0`` Lyapunov functions.
    u_nom : callable or array of shape (m,), optional
        The nominal input: a function of one state (n,) returning (m,), or a constant.
        Zero when omitted (then the filter is the universal formula with several rows).
    H : array of shape (m, m), optional
        Positive definite weight of the objective.
    kappa, rho, phi, varphi : float
        As for :class:`~safestab.controllers.UniversalController` (shared by the rows).
    slack_weight : float, optional
        CLF slack weight; hard CLFs when omitted.
    u_min, u_max : float or array of shape (m,), optional
        Limits inside the problem; one alone is a one-sided box, and an entry of ``-inf``
        (``u_min``) or ``+inf`` (``u_max``) leaves that side of that input unbounded (its row
        never becomes active, so the optimum is exact).
    uncertainty : UncertaintyModel, optional
        GP-robust terms (Lemma 3) for every row.
    gp_beta : float or array of shape (n,)
    robust_clf_layer : float, optional
        With an uncertainty model only: the boundary layer ``eps >= 0`` on every CLF row's
        robust term, as for :class:`~safestab.UniversalController` (docs/learning.md);
        default none (Lemma 3's term).
    params : pytree, optional
        An example of run-time parameters for the filter's own callable: with it, a callable
        ``u_nom`` takes ``(x, p)`` (a set-point, say). The system and the certificates declare
        their own; all declared examples must agree, and one ``p`` reaches every function:
        ``step(x, params=p)``, ``step_fn(x, p)``. New values of ``p`` never recompile.
    sample_time, ddh_bound : optional
        The sampled-data margin (both or neither): the hold time ``T`` (s) and a bound ``M``
        on ``-d^2h/dt^2`` along the true plant's held flow, a scalar or one per CBF (shape
        (k,)); every CBF condition is shifted by ``M T / 2 + max(0, alpha(h) - h / T)``, which
        keeps each ``h >= 0`` over the hold intervals (as for
        :class:`~safestab.UniversalController`; :mod:`safestab.sampled`, docs/deployed.md).
    formula : SmoothFilter, optional
        A smooth closed-form filter of one CBF around ``u_nom`` instead of the exact QP
        (:mod:`safestab.formulas.smooth`: ``ExplicitFilter()``, ``SontagFilter(sigma)``,
        ``HalfSontagFilter(sigma)``, ``SoftplusFilter(sigma)``, each with the
        input-to-state-safe ``epsilon``); then one CBF, no CLF, no limits, no ``H``, no slack
        and ``rho = 0``. Default: the exact QP.
    max_iter : int, optional
        Iteration bound of the solver per phase (default: as
        :func:`~safestab.formulas.clf_cbf_multi`); where it is reached, ``formula_status`` is
        ``ITERATION_LIMIT``.
    cbf_margin : float, optional
        A tightening of every CBF condition, in the units of ``dh/dt``: the problem enforces
        ``c + d.u >= rho Gamma + cbf_margin``, and ``cbf_satisfied`` reports
        ``c + d.u - rho Gamma >= cbf_margin / 2`` (as for
        :class:`~safestab.UniversalController`). With twice a bound on the error of
        evaluating the condition, a step whose flag says satisfied keeps the exact condition
        (:func:`~safestab.export.float_safety.float_safe_controller` sets it for a float
        export). Default: none.
    precision : {"double", "float"}
        The precision the step is evaluated in: the solver's tolerances, its certificate and
        the flags' tolerance are those of its rounding. ``"float"`` for a step exported in
        float (the JAX step still computes in float64, with float's tolerances, so that the
        two take the same decisions); default ``"double"``.

    Raises
    ------
    DimensionError, ParameterError, InputTypeError, TypeError
        For invalid arguments, named.
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        cbfs: CBF | Sequence[CBF],
        *,
        clfs: CLF | Sequence[CLF] = (),
        u_nom: Callable[[jax.Array], jax.Array] | Any = None,
        H: Any = None,
        kappa: float = 0.0,
        rho: float = 0.0,
        phi: float = 0.0,
        varphi: float = 0.0,
        slack_weight: float | None = None,
        u_min: Any = None,
        u_max: Any = None,
        uncertainty: UncertaintyModel | None = None,
        gp_beta: Any = 2.0,
        robust_clf_layer: float | None = None,
        params: Any = None,
        max_iter: int | None = None,
        sample_time: float | None = None,
        ddh_bound: Any = None,
        formula: SmoothFilter | None = None,
        cbf_margin: float | None = None,
        precision: str = "double",
    ) -> None:
        init_args = {k: v for k, v in locals().items() if k not in ("self", "__class__")}
        self.cbfs = _as_tuple(cbfs, CBF, "cbfs")
        self.clfs = _as_tuple(clfs, CLF, "clfs")
        monitor = isinstance(formula, PassThrough)
        if not self.cbfs and not monitor:
            raise ParameterError("give at least one CBF")
        if formula is not None and not monitor:
            self._check_smooth(
                formula, self.clfs, self.cbfs, rho, slack_weight, u_min, u_max, H, cbf_margin
            )
        max_iter = check_max_iter(max_iter)
        if precision not in UNITS:
            raise ParameterError(f"precision must be one of {sorted(UNITS)}, got {precision!r}")
        if cbf_margin is not None:
            self._check_nonnegative_scalar("cbf_margin", cbf_margin)
        if sample_time is not None and not self.cbfs:
            raise ParameterError(
                "sample_time shifts the barriers' conditions: give cbfs= (none were given)"
            )
        sample_time, ddh_bound = check_sampled(sample_time, ddh_bound, len(self.cbfs))
        check_params((), kappa=kappa, rho=rho, phi=phi, varphi=varphi)
        if slack_weight is not None:
            check_params((), slack_weight=slack_weight)
        n, m = system.n_states, system.n_inputs
        for cert in self.clfs + self.cbfs:
            cert.check(n)
        u_min, u_max = self._check_limits(u_min, u_max, m)
        own_spec = make_spec(params, "the filter")
        u_nom_of: Callable | None = None
        if u_nom is not None and callable(u_nom):
            shape = getattr(trace_shape("u_nom", u_nom, n, own_spec), "shape", None)
            if shape != (m,):
                raise DimensionError(f"u_nom(x) must return shape ({m},), got {shape}")
            u_nom_of = bind(u_nom, own_spec is not None)
        elif u_nom is not None:
            check_real("u_nom", u_nom)
            check_finite("u_nom", u_nom)
            if np.shape(u_nom) != (m,):
                raise DimensionError(f"u_nom must have shape ({m},), got {np.shape(u_nom)}")
            const = jnp.asarray(u_nom, dtype=float)
            u_nom = lambda x: const  # noqa: E731
            u_nom_of = bind(u_nom, False)
        if H is not None:
            check_real("H", H)
            check_finite("H", H)
            if np.shape(H) != (m, m):
                raise DimensionError(f"H must have shape ({m}, {m}), got {np.shape(H)}")
            if is_concrete(H):  # a traced H is checked on its shape only
                Hn = np.asarray(H, dtype=float)
                if not np.allclose(Hn, Hn.T, rtol=1e-12, atol=0.0) or np.any(
                    np.linalg.eigvalsh(Hn) <= 0
                ):
                    raise ParameterError("H must be symmetric positive definite")
                H = Hn
            else:
                H = jnp.asarray(H, dtype=float)
        gp_beta = self._check_uncertainty(uncertainty, gp_beta, n)
        self._check_robust_clf_layer(robust_clf_layer, uncertainty)
        #: The run-time parameters' structure shared by every function (None: none).
        self.params_spec: ParamSpec | None = merge_specs(
            [system.params_spec, *(c.params_spec for c in self.clfs + self.cbfs), own_spec]
        )
        example = getattr(self.params_spec, "example", None)
        for i, cb in enumerate(self.cbfs):
            check_actuated(system, cb, f"cbfs[{i}]" if len(self.cbfs) > 1 else "cbfs", example)
        self.system = system
        self.u_nom = u_nom
        self._u_nom_of = u_nom_of
        self.H = H
        self.params = {"kappa": kappa, "rho": rho, "phi": phi, "varphi": varphi}
        self.slack_weight = slack_weight
        self.u_min, self.u_max = u_min, u_max
        self.uncertainty = uncertainty
        self.gp_beta = gp_beta
        self.robust_clf_layer = None if robust_clf_layer is None else as_scalar(robust_clf_layer)
        #: The hold time ``T`` (s) and the bound(s) ``M`` of the sampled-data margin (None).
        self.sample_time = None if sample_time is None else as_scalar(sample_time)
        self.ddh_bound = ddh_bound
        #: The formula object that solves each step's problem: the several-row QP
        #: (:class:`~safestab.formulas.problem.MultiFormula`), or a smooth one-barrier filter.
        self.formula = MultiFormula(max_iter, precision) if formula is None else formula
        #: The precision the step is evaluated in (its tolerances), and the CBF margin (None).
        self.precision = precision
        self.cbf_margin = None if cbf_margin is None else as_scalar(cbf_margin)
        self._remember(SafetyFilter, init_args)

    _CHILDREN = ("clfs", "cbfs")

    def _leaf_names(self) -> tuple[str, ...]:
        names = ["kappa", "rho", "phi", "varphi"]
        names += ["slack_weight"] if self.slack_weight is not None else []
        names += ["u_min", "u_max"] if self.u_min is not None else []
        names += ["H"] if self.H is not None else []
        names += ["gp_beta"] if self.uncertainty is not None else []
        names += ["robust_clf_layer"] if self.robust_clf_layer is not None else []
        names += ["sample_time", "ddh_bound"] if self.sample_time is not None else []
        names += ["cbf_margin"] if self.cbf_margin is not None else []
        return tuple(names)

    def _point(self, x: jax.Array, p: Any = None, given: tuple | None = None):
        f, g = self.system.f_of(x, p), self.system.g_of(x, p)
        a = (
            jnp.stack([cl.grad_of(x, p) @ f + cl.rate_term(cl.fn_of(x, p)) for cl in self.clfs])
            if self.clfs
            else jnp.zeros(0)
        )
        b = (
            jnp.stack([cl.grad_of(x, p) @ g for cl in self.clfs])
            if self.clfs
            else jnp.zeros((0, g.shape[1]))
        )
        hs = [cb.fn_of(x, p) for cb in self.cbfs]
        if self.cbfs:
            alphas = jnp.stack([cb.rate_term(h) for cb, h in zip(self.cbfs, hs, strict=True)])
            c = jnp.stack([cb.grad_of(x, p) @ f for cb in self.cbfs]) + alphas
            d = jnp.stack([cb.grad_of(x, p) @ g for cb in self.cbfs])
        else:  # a PolicyController without barriers
            c, d = jnp.zeros(0), jnp.zeros((0, g.shape[1]))
        if self.sample_time is not None:  # the sampled-data margin: a shift of each c
            c = c - sampled_shift(jnp.stack(hs), alphas, self.sample_time, self.ddh_bound)
        S = StepStatus
        status = jnp.where(jnp.all(jnp.isfinite(x)), S.OK, S.NONFINITE_STATE)
        finite = jnp.all(jnp.isfinite(a)) & jnp.all(jnp.isfinite(b)) & jnp.all(jnp.isfinite(c))
        finite = finite & jnp.all(jnp.isfinite(d))
        status = jnp.where((status == S.OK) & ~finite, S.NONFINITE_MODEL, status)
        degree_ok = jnp.all(
            jnp.stack([True] + [cb.relative_degree_holds(self.system, x, p) for cb in self.cbfs])
        )
        status = jnp.where((status == S.OK) & ~degree_ok, S.RELATIVE_DEGREE, status)
        if self.uncertainty is not None:
            mean, std = self.uncertainty.mean_std(x) if given is None else given
            beta = jnp.asarray(self.gp_beta)
            for i, cl in enumerate(self.clfs):
                gv = cl.grad_of(x, p)
                a = a.at[i].add(robust_margins(gv, gv, mean, std, beta, self._clf_layer).delta_V)
            for i, cb in enumerate(self.cbfs):
                gh = cb.grad_of(x, p)
                c = c.at[i].add(robust_margins(gh, gh, mean, std, beta).delta_h)
            unc_ok = jnp.all(jnp.isfinite(mean)) & jnp.all(jnp.isfinite(std))
            status = jnp.where((status == S.OK) & ~unc_ok, S.NONFINITE_UNCERTAINTY, status)
            status = jnp.where((status == S.OK) & jnp.any(std < 0), S.NEGATIVE_STD, status)
        return (a, b, c, d, self.nominal_input(x, p)), status.astype(jnp.int32)

    def rows(self, x: jax.Array, p: Any = None) -> tuple:
        """The problem's terms at one state ``x`` (n,), unchecked: ``(a, b, c, d, u_nom)``.

        ``a`` (p,), ``b`` (p, m) of the CLFs, ``c`` (k,), ``d`` (k, m) of the CBFs (robust
        terms and the sampled-data shift included) and the nominal input (m,) or None: what
        the solver receives at ``x`` (a ``cbf_margin`` is added to each CBF condition's
        right-hand side there, not to ``c``). Differentiable (the native step's derivative
        uses it).
        """
        return self._point(x, p)[0]

    @property
    def max_iter(self) -> int | None:
        """The solver's iteration bound per phase (the formula's; None: from the size)."""
        return getattr(self.formula, "max_iter", None)

    @staticmethod
    def _check_smooth(
        formula, clfs, cbfs, rho, slack_weight, u_min, u_max, H, cbf_margin=None
    ) -> None:
        """A smooth filter formula: one CBF, no CLF, limits, weight, slack, ``rho`` or margin."""
        if not isinstance(formula, SmoothFilter):
            raise ParameterError(
                "formula must be None (the exact QP) or a smooth filter of "
                "safestab.formulas (ExplicitFilter, SontagFilter, HalfSontagFilter, "
                f"SoftplusFilter), got {formula!r}"
            )
        extra = [
            name
            for name, given in (
                ("a CLF", bool(clfs)),
                (f"{len(cbfs)} CBFs", len(cbfs) > 1),
                ("u_min/u_max", u_min is not None or u_max is not None),
                ("H", H is not None),
                ("slack_weight", slack_weight is not None),
                ("rho > 0", is_concrete(rho) and float(rho) != 0.0),
                ("cbf_margin", cbf_margin is not None),
            )
            if given
        ]
        if extra:
            raise ParameterError(
                f"{type(formula).__name__} filters one CBF around u_nom; it takes no "
                f"{', '.join(extra)} (the exact QP, formula=None, does)"
            )

    def nominal_input(self, x: jax.Array, p: Any = None) -> jax.Array | None:
        """The nominal input ``u_nom`` at one state ``x`` (n,), shape (m,); None without one.

        ``p``: the run-time parameters (unchecked), when the filter takes them.
        """
        return self._u_nom_of(x, p) if self._u_nom_of is not None else None

    def _step(
        self, x: jax.Array, p: Any = None, given: tuple | None = None, u_nom: Any = None
    ) -> FilterOutput:
        (a, b, c, d, own), status = over_batch(lambda s: self._point(s, p, given), x)
        p = self.params
        batch = x.shape[:-1]
        if u_nom is not None:  # the caller's nominal input, for this call
            u_nom = jnp.broadcast_to(
                jnp.asarray(u_nom, dtype=float), batch + (self.system.n_inputs,)
            )
        else:
            u_nom = own
        lo = hi = None
        if self.u_min is not None:
            m = self.system.n_inputs
            lo = jnp.broadcast_to(jnp.asarray(self.u_min), batch + (m,))
            hi = jnp.broadcast_to(jnp.asarray(self.u_max), batch + (m,))
        H = None if self.H is None else jnp.broadcast_to(jnp.asarray(self.H), batch + self.H.shape)
        # the CBF margin: the problem's conditions tightened by it, the flags' by half
        margin = self.cbf_margin
        problem = Problem(
            a, b, c, d, p["kappa"], p["rho"], p["phi"], p["varphi"],
            slack_weight=self.slack_weight, u_min=lo, u_max=hi, u_nom=u_nom, H=H,
            cbf_margin=margin,
        )  # fmt: skip
        res = self.formula.solve(problem)
        u = res.u
        ub = u[..., None, :]
        rtol = satisfied_rtol(UNITS[self.precision])
        mg_c = margins(c, d, c, d, 0.0, p["rho"], 0.0, p["varphi"])
        if margin is not None:
            mg_c = mg_c._replace(B=mg_c.B + 0.5 * margin)
        _, cbf_ok = condition_flags(c, d, c, d, ub, mg_c, 0.0, p["rho"], rtol)
        mg_v = margins(a, b, a, b, p["kappa"], 0.0, p["phi"], 0.0)
        clf_ok, _ = condition_flags(a, b, a, b, ub, mg_v, p["kappa"], 0.0, rtol)
        finite = jnp.all(jnp.isfinite(u), -1)
        if u_nom is not None:  # a non-finite nominal input is named, not clipped or solved
            finite = finite & jnp.all(jnp.isfinite(u_nom), -1)
        status = jnp.where((status == StepStatus.OK) & ~finite, StepStatus.NONFINITE_INPUT, status)
        ok = status == StepStatus.OK
        box_ok = None
        if isinstance(self.formula, PassThrough) and lo is not None:
            # each barrier alone, at the box input that maximises d_i.u (0 where d_ij = 0;
            # an infinite corner meets the condition)
            best = jnp.where(d > 0, hi[..., None, :], jnp.where(d < 0, lo[..., None, :], 0.0))
            _, box_ok = condition_flags(c, d, c, d, best, mg_c, 0.0, p["rho"], rtol)
        status = _barrier_status(status, res.status, cbf_ok, d, box_ok)
        return FilterOutput(
            u=jnp.where(ok[..., None], u, jnp.nan),
            status=status.astype(jnp.int32),
            formula_status=res.status,
            active=res.active,
            multipliers=res.multipliers,
            slack=res.slack,
            cbf_satisfied=ok[..., None] & cbf_ok,
            clf_satisfied=ok[..., None] & clf_ok,
        )

    def step(
        self, x: Any, *, params: Any = None, strict: bool = False, u_nom: Any = None
    ) -> FilterOutput:
        """The filtered input and diagnostics at states ``x`` of shape (..., n).

        Parameters
        ----------
        x : array of shape (..., n)
        params : pytree, optional
            The run-time parameters, required when the system, a certificate or the filter
            declared ``params=example`` (shared by every state of the batch).
        strict : bool
            Raise where a step failed, a fallback was used or a CBF condition is violated.
        u_nom : array of shape (m,) or (..., m), optional
            The nominal input of this call (another policy's action, say), in place of the
            filter's own ``u_nom``; broadcast over the batch of ``x``. Jitted code passes it as
            ``controller_step(filter, x, p, u_nom)``.

        Returns
        -------
        FilterOutput

        Raises
        ------
        InputTypeError, DimensionError, NonFiniteError
            For an invalid ``x`` or ``params`` leaf; with ``strict=True`` also where a step
            failed.
        ParameterError
            If ``params`` is missing where declared, given where not, or has another
            structure than the declared example.
        ModelError
            If the uncertainty model returns a negative standard deviation.
        InfeasibleError
            With ``strict=True``, where a fallback was used, the solver stopped uncertified
            (``ITERATION_LIMIT``, ``UNCERTIFIED``) or a CBF condition is violated.
        """
        if u_nom is not None:
            m, batch = self.system.n_inputs, np.shape(x)[:-1]
            check_real("u_nom", u_nom)
            check_finite("u_nom", u_nom)
            shape = np.shape(u_nom)
            if not shape or shape[-1] != m or len(shape) > 1 and shape[:-1] != batch:
                raise DimensionError(
                    f"u_nom must have shape ({m},) or the batch of x plus ({m},) = "
                    f"{batch + (m,)}, got {shape}"
                )
            u_nom = jnp.asarray(u_nom, dtype=float)
        return self._checked_step(x, params, strict, u_nom)

    _owner = "filter"

    def _check_step(self, x: jax.Array, out: FilterOutput, strict: bool, p: Any) -> None:
        check_output(out, strict)
