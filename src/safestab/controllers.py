"""Controllers: objects that map a state to an input through a closed-form formula.

Data flows one way: system + certificates -> Lie terms ``(a, b, c, d)`` -> (GP-robust terms)
-> formula -> input limits -> ``u``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np

from ._batching import over_batch
from .certificates import CBF, CLF, LieTerms, lie_terms_point
from .errors import DimensionError, InfeasibleError, ParameterError
from .formulas import (
    DEFAULT_PARALLEL_RTOL,
    Region,
    _check_box,
    _check_params,
    _combined,
    _compatibility,
    _margins,
    _saturate_safety_first,
)
from .robust import UncertaintyModel, check_beta, robust_lie_terms
from .systems import ControlAffineSystem

__all__ = ["ControlOutput", "UniversalController"]

#: Relative tolerance of the ``cbf_satisfied`` / ``clf_satisfied`` flags: a condition that the
#: formula makes hold with equality is still reported satisfied after rounding (float64
#: rounding of ``c + d.u`` is a few 1e-16 of the magnitudes involved).
SATISFIED_RTOL = 1e-9


@dataclasses.dataclass(frozen=True)
class ControlOutput:
    """Everything one controller step computes, batched over the leading axes of ``x``.

    Attributes
    ----------
    u : array of shape (..., m)
        The input applied (after input limits, if any).
    u_unconstrained : array of shape (..., m)
        The formula's input before limits.
    region : int array of shape (...,)
        :class:`~safestab.formulas.Region` of the formula.
    compatible : bool array of shape (...,)
        Whether the (possibly GP-robust) CLF and CBF conditions are compatible at ``x``.
    cbf_satisfied : bool array of shape (...,)
        Whether ``u`` (after limits) satisfies the CBF condition used by the formula.
    clf_satisfied : bool array of shape (...,)
        Whether ``u`` (after limits) satisfies the CLF condition (without slack).
    slack : array of shape (...,)
        The CLF slack of the relaxed formula (0 otherwise).
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
    terms: LieTerms


jax.tree_util.register_dataclass(
    ControlOutput,
    data_fields=[f.name for f in dataclasses.fields(ControlOutput)],
    meta_fields=[],
)


class UniversalController:
    """The universal formula bound to a system, a CLF, a CBF and parameters.

    Parameters
    ----------
    system : ControlAffineSystem
        The (nominal) model ``f``, ``g``.
    clf : CLF
    cbf : CBF
    kappa, rho : float
        >= 0 (see :func:`~safestab.formulas.clf_cbf`).
    phi, varphi : float
        >= 0, weights in ``zeta`` and ``Gamma``.
    slack_weight : float, optional
        When given, the relaxed formula (Theorem 3) with this weight; otherwise the combined
        formula (Theorem 1, or Theorem 2 with an uncertainty model).
    u_min, u_max : array of shape (m,), optional
        Input limits; both or neither.
    saturation : {"project", "safety_first"}
        How limits are enforced: ``"project"`` is the paper's projection, eq. (26);
        ``"safety_first"`` (single input only) keeps the CBF condition whenever some input in
        the box can (:func:`~safestab.formulas.saturate_safety_first`).
    uncertainty : UncertaintyModel, optional
        A model of ``omega(x)`` (mean and standard deviation). With it the controller uses the
        GP-robust terms of Lemma 3, i.e. Theorem 2 (or Theorem 3 with ``slack_weight``).
    gp_beta : float or array of shape (n,)
        Confidence scaling ``beta_i`` of the uncertainty model (Lemma 2); default 2.
    parallel_rtol : float
        Tolerance of the parallel test.

    Raises
    ------
    ParameterError
        If a parameter is out of range, ``u_min > u_max``, or only one limit is given.
    DimensionError
        If the certificates or limits do not fit the system, or ``saturation="safety_first"``
        with more than one input.
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
    ) -> None:
        _check_params(kappa=kappa, rho=rho, phi=phi, varphi=varphi, parallel_rtol=parallel_rtol)
        if slack_weight is not None:
            _check_params(slack_weight=slack_weight)
        clf.check(system.n_states)
        cbf.check(system.n_states)
        m = system.n_inputs
        if (u_min is None) != (u_max is None):
            raise ParameterError("give both u_min and u_max, or neither")
        if u_min is not None:
            u_min = np.broadcast_to(np.asarray(u_min, float), (m,)).copy()
            u_max = np.broadcast_to(np.asarray(u_max, float), (m,)).copy()
            _check_box(u_min, u_max)
        if saturation not in ("project", "safety_first"):
            raise ParameterError(
                f"saturation must be 'project' or 'safety_first', got {saturation!r}"
            )
        if saturation == "safety_first" and m != 1:
            raise DimensionError(
                f"saturation='safety_first' needs a single-input system, got n_inputs={m}"
            )
        if uncertainty is not None:
            if not hasattr(uncertainty, "mean_std"):
                raise TypeError("uncertainty must provide mean_std(x) -> (mean, std)")
            if getattr(uncertainty, "n_states", system.n_states) != system.n_states:
                raise DimensionError(
                    f"uncertainty.n_states must equal system.n_states = {system.n_states}, "
                    f"got {uncertainty.n_states}"
                )
            gp_beta = check_beta(gp_beta, system.n_states)
        self.system = system
        self.clf = clf
        self.cbf = cbf
        self.params = {"kappa": kappa, "rho": rho, "phi": phi, "varphi": varphi}
        self.slack_weight = slack_weight
        self.u_min = u_min
        self.u_max = u_max
        self.saturation = saturation
        self.uncertainty = uncertainty
        self.gp_beta = gp_beta if uncertainty is not None else None
        self.parallel_rtol = parallel_rtol
        #: The fused, jitted step (terms, GP, formula, limits, flags) without argument checks,
        #: for one state (n,) or a batch (..., n); for loops and benchmarks.
        self.step_fn = jax.jit(self._step)
        #: Like ``step_fn`` but returning only ``u``, so XLA drops the diagnostics.
        self.input_fn = jax.jit(lambda x: self._step(x).u)

    def __repr__(self) -> str:
        kind = "relaxed" if self.slack_weight is not None else "clf_cbf"
        gp = ", GP-robust" if self.uncertainty is not None else ""
        return f"UniversalController({self.system.name}, formula={kind}{gp}, params={self.params})"

    # -- the pipeline, one state at a time (vmapped for batches) --------------------------

    def terms_point(self, x: jax.Array) -> LieTerms:
        """The (GP-robust when an uncertainty model is set) Lie terms at one state."""
        terms = lie_terms_point(self.system, self.clf, self.cbf, x)
        if self.uncertainty is None:
            return terms
        mean, std = self.uncertainty.mean_std(x)
        beta = jnp.asarray(self.gp_beta)
        return robust_lie_terms(terms, self.clf.grad(x), self.cbf.grad(x), mean, std, beta)

    def _step(self, x: jax.Array) -> ControlOutput:
        terms = over_batch(self.terms_point, x)
        a, b, c, d = terms
        p = self.params
        inv_slack = 0.0 if self.slack_weight is None else 1.0 / self.slack_weight
        res = _combined(
            a, b, c, d, p["kappa"], p["rho"], p["phi"], p["varphi"], inv_slack, self.parallel_rtol
        )
        comp = _compatibility(
            a, b, c, d, p["kappa"], p["rho"], p["phi"], p["varphi"], self.parallel_rtol
        )
        u = res.u
        if self.u_min is not None:
            lo, hi = jnp.asarray(self.u_min), jnp.asarray(self.u_max)
            if self.saturation == "safety_first":
                u, _ = _saturate_safety_first(u, c, d, p["rho"], p["varphi"], lo, hi)
            else:
                u = jnp.clip(u, lo, hi)
        A, B = _margins(a, b, c, d, p["kappa"], p["rho"], p["phi"], p["varphi"])
        bu = jnp.sum(b * u, -1)
        du = jnp.sum(d * u, -1)
        # u = -lambda1 b + lambda2 d is rounded relative to its terms, which in P3 can be far
        # larger than |u|: the flags' tolerance scales with those terms.
        bn, dn = jnp.linalg.norm(b, axis=-1), jnp.linalg.norm(d, axis=-1)
        lam = res.multipliers
        u_terms = (
            jnp.linalg.norm(u, axis=-1) + jnp.abs(lam[..., 0]) * bn + jnp.abs(lam[..., 1]) * dn
        )
        tol_v = SATISFIED_RTOL * (jnp.abs(A) + bn * u_terms)
        tol_h = SATISFIED_RTOL * (jnp.abs(B) + dn * u_terms)
        return ControlOutput(
            u=u,
            u_unconstrained=res.u,
            region=res.region,
            compatible=comp.compatible,
            cbf_satisfied=du - B >= -tol_h,
            clf_satisfied=bu + A <= tol_v,
            slack=res.slack,
            terms=terms,
        )

    # -- public, checked entry points ---------------------------------------------------

    def step(self, x: Any, *, strict: bool = False) -> ControlOutput:
        """Compute the input and its diagnostics at states ``x`` of shape (..., n).

        Parameters
        ----------
        x : array of shape (..., n)
        strict : bool
            Raise :class:`~safestab.errors.InfeasibleError` if at some state the formula's
            conditions are incompatible or the applied input violates the CBF condition.

        Returns
        -------
        ControlOutput

        Raises
        ------
        DimensionError
            If ``x`` has the wrong last axis.
        NonFiniteError
            If ``x`` contains NaN or inf.
        InfeasibleError
            With ``strict=True``, as above.
        """
        x = self.system.check_state(x)
        out = self.step_fn(x)
        if strict:
            bad = np.asarray(out.region == Region.INCOMPATIBLE) | ~np.asarray(out.cbf_satisfied)
            if np.any(bad):
                idx = np.argwhere(np.atleast_1d(bad))[0].tolist()
                raise InfeasibleError(
                    f"the CBF condition cannot be met at state index {idx} "
                    f"(region {Region(int(np.atleast_1d(out.region)[tuple(idx)])).name}); "
                    "use slack_weight for the relaxed formula or relax the input limits"
                )
        return out

    def __call__(self, x: Any) -> jax.Array:
        """The input at states ``x`` of shape (..., n); shape (..., m)."""
        return self.step(x).u
