"""Reference solutions of the formulas' QPs by a numerical solver (qpsolvers).

For tests and benchmarks only; the closed forms in :mod:`safestab.formulas` never call this.
Needs the optional dependencies ``pip install safestab[qp]`` (Clarabel by default, OSQP, and
any other solver qpsolvers knows).
"""

from __future__ import annotations

import dataclasses
import decimal
import warnings
from typing import Any

import numpy as np

from .errors import DimensionError, ParameterError

__all__ = ["ReferenceSolution", "solve_formula_qp", "margins_numpy"]

#: Tight tolerances for Clarabel, so that agreement tests at 1e-6 relative are meaningful.
CLARABEL_TIGHT = {
    "tol_gap_abs": 1e-12,
    "tol_gap_rel": 1e-12,
    "tol_feas": 1e-12,
    "tol_ktratio": 1e-10,
}
OSQP_TIGHT = {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iter": 100_000, "polish": True}


@dataclasses.dataclass(frozen=True)
class ReferenceSolution:
    """A solver's answer for one point.

    Attributes
    ----------
    u : array of shape (m,) or None
        The input, or None when the solver found no solution.
    slack : float
        The CLF slack (0 for the hard problem).
    found : bool
        Whether the solver reports success.
    status : str
        ``"solved"``, or the warnings the solver emitted (for example Clarabel's
        ``AlmostSolved``), which are captured here rather than raised.
    """

    u: np.ndarray | None
    slack: float
    found: bool
    status: str = "solved"


def margins_numpy(a, b, c, d, *, kappa, rho, phi, varphi):
    """Return ``(A, B)`` computed straight from the paper's definitions, in 300-digit decimals.

    ``A = a + kappa sqrt(a^2 + phi |b|^4)`` and ``B = rho sqrt(c^2 + varphi |d|^4) - c``.
    Evaluated with :mod:`decimal` at 300 significant digits and rounded once to float, so the
    cancellation in ``rho Gamma - c`` cannot hurt: this is a more accurate oracle than the
    float64 closed forms it checks, and written independently of :mod:`safestab.formulas`.
    """
    with decimal.localcontext() as ctx:
        ctx.prec = 300  # exact squares of float expansions: sqrt(c^2) - c is exactly 0
        D = decimal.Decimal
        b2 = sum(D(float(x)) ** 2 for x in np.ravel(b))
        d2 = sum(D(float(x)) ** 2 for x in np.ravel(d))
        a_, c_ = D(float(a)), D(float(c))
        A = a_ + D(float(kappa)) * (a_ * a_ + D(float(phi)) * b2 * b2).sqrt()
        B = D(float(rho)) * (c_ * c_ + D(float(varphi)) * d2 * d2).sqrt() - c_
        return float(A), float(B)


def solve_formula_qp(
    a: float,
    b: Any,
    c: float,
    d: Any,
    *,
    kappa: float,
    rho: float,
    phi: float,
    varphi: float,
    slack_weight: float | None = None,
    u_min: Any = None,
    u_max: Any = None,
    solver: str = "clarabel",
    tight: bool = True,
    **solver_options: Any,
) -> ReferenceSolution:
    """Solve the CLF-CBF QP of one point with a numerical solver.

    ``min 1/2|u|^2 (+ 1/2 slack_weight chi^2)`` subject to ``b u - chi <= -A`` and
    ``d u >= B`` (``chi = 0`` when ``slack_weight`` is None), optionally with box bounds.

    Parameters
    ----------
    a, c : float
    b, d : arrays of shape (m,)
    kappa, rho, phi, varphi : float
    slack_weight : float, optional
        Solve the relaxed problem with this weight.
    u_min, u_max : arrays of shape (m,), optional
        Box bounds on ``u``.
    solver : str
        A qpsolvers solver name (``"clarabel"``, ``"osqp"``, ``"quadprog"``, ...).
    tight : bool
        Use tight tolerances for Clarabel and OSQP (ignored for other solvers).
    **solver_options
        Passed to the solver.

    Returns
    -------
    ReferenceSolution

    Raises
    ------
    DimensionError
        If ``b`` or ``d`` is not a vector, or their sizes differ.
    ParameterError
        If ``slack_weight <= 0``.
    """
    import qpsolvers

    b = np.asarray(b, dtype=float)
    d = np.asarray(d, dtype=float)
    if b.ndim != 1 or d.shape != b.shape:
        raise DimensionError(f"b and d must be vectors of equal size, got {b.shape} and {d.shape}")
    if slack_weight is not None and not slack_weight > 0:
        raise ParameterError(f"slack_weight must be > 0, got {slack_weight!r}")
    m = b.size
    A, B = margins_numpy(a, b, c, d, kappa=kappa, rho=rho, phi=phi, varphi=varphi)
    relaxed = slack_weight is not None
    n = m + 1 if relaxed else m
    P = np.eye(n)
    G = np.zeros((2, n))
    G[0, :m] = b
    G[1, :m] = -d
    if relaxed:
        P[m, m] = slack_weight
        G[0, m] = -1.0
    h = np.array([-A, -B])
    lb = ub = None
    if u_min is not None:
        lb = np.full(n, -np.inf)
        lb[:m] = u_min
    if u_max is not None:
        ub = np.full(n, np.inf)
        ub[:m] = u_max
    options = dict(solver_options)
    if tight and solver == "clarabel":
        options = {**CLARABEL_TIGHT, **options}
    if tight and solver == "osqp":
        options = {**OSQP_TIGHT, **options}
    if solver in qpsolvers.sparse_solvers:
        import scipy.sparse as sp

        P, G = sp.csc_matrix(P), sp.csc_matrix(G)
    problem = qpsolvers.Problem(P, np.zeros(n), G, h, lb=lb, ub=ub)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = qpsolvers.solve_problem(problem, solver=solver, **options)
    status = "; ".join(str(w.message) for w in caught) or "solved"
    if not sol.found or sol.x is None or not np.all(np.isfinite(sol.x)):
        return ReferenceSolution(u=None, slack=float("nan"), found=False, status=status)
    return ReferenceSolution(
        u=np.asarray(sol.x[:m]),
        slack=float(sol.x[m]) if relaxed else 0.0,
        found=True,
        status=status,
    )


class ReferenceController:
    """Solve a :class:`~safestab.controllers.UniversalController`'s QP with a numerical solver.

    Uses the controller's own (possibly GP-robust) Lie terms, so the two differ only in how
    the QP is solved. Input limits, when the controller has them, are applied afterwards
    exactly as the controller applies them (the projection of eq. (26)), so outputs are
    comparable one to one.

    Parameters
    ----------
    controller : UniversalController
    solver : str
        A qpsolvers name: ``"clarabel"`` (default), ``"osqp"``, ``"quadprog"``, ...
    tight : bool
        Tight tolerances for Clarabel and OSQP.

    Raises
    ------
    ParameterError
        If the controller takes run-time parameters (not supported here).
    """

    def __init__(self, controller: Any, solver: str = "clarabel", *, tight: bool = True) -> None:
        import jax

        if getattr(controller, "params_spec", None) is not None:
            raise ParameterError(
                "ReferenceController does not support controllers with run-time parameters "
                "(params=...); solve_formula_qp on the controller's terms_point(x, p) instead"
            )
        self.controller = controller
        self.solver = solver
        self.tight = tight
        self._terms = jax.jit(controller.terms_point)

    def __call__(self, x: Any) -> np.ndarray:
        """Input at one state ``x`` of shape (n,); NaN entries where the solver fails."""
        c = self.controller
        a, b, cc, d = (np.asarray(t) for t in self._terms(c.system.check_state(x)))
        sol = solve_formula_qp(
            float(a),
            b,
            float(cc),
            d,
            slack_weight=c.slack_weight,
            solver=self.solver,
            tight=self.tight,
            **c.params,
        )
        if not sol.found or sol.u is None:
            return np.full(c.system.n_inputs, np.nan)
        u = sol.u
        if c.u_min is not None and c.saturation == "project":
            u = np.clip(u, c.u_min, c.u_max)
        return u
