"""A safety filter's exported C step as a JAX function, with the derivative of its input.

:func:`native_step` runs the filter's whole step (rows from the state, the dual active-set
solver, statuses and flags) as one XLA custom call into the exported C
(:func:`~safestab.export.jax_function`), and attaches the derivative of the optimum on its
final active set, computed in JAX from the rows' derivatives (the solver's loop is not
differentiated, as in the JAX step).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import CompilationError, ParameterError
from ..formulas import MultiStatus
from ..formulas._kernels import margins, scaled_norm
from ..formulas.multi import FALLBACK_WEIGHT
from ..formulas.problem import MultiFormula
from .exporter import export_c
from .jax_kernel import jax_function

__all__ = ["native_step"]


def native_step(
    filt: Any,
    *,
    name: str = "native_step",
    compiler: str | None = None,
    cxx_compiler: str | None = None,
    march_native: bool = True,
    fallback: bool = False,
) -> Callable[[jax.Array], Any]:
    """The filter's step as one XLA custom call into its exported C, on the CPU.

    Parameters
    ----------
    filt : SafetyFilter
        A filter with the exact QP (the default formula), without run-time parameters.
    name : str
        Prefix of the C names.
    compiler, cxx_compiler : str, optional
        The C compiler (default ``$CC`` or ``cc``) and the C++ compiler of XLA's handler
        (default ``$CXX`` or ``c++``).
    march_native : bool
        Compile for this machine's CPU (default True; results are unchanged).
    fallback : bool
        Where no compiler is found or it fails: with ``False`` (default) raise, with ``True``
        warn and return the JAX step (``filt.step_fn``).

    Returns
    -------
    callable
        ``step(x)`` for states ``x`` of shape (..., n), returning a
        :class:`~safestab.FilterOutput` equal to ``filt.step_fn(x)`` to rounding (the same
        solver, compiled by the C compiler instead of XLA). Composes with ``jax.jit``,
        ``jax.vmap`` (a batch is one loop in C) and ``jax.jvp`` / ``jax.grad`` in ``x``: the
        derivative of ``u``, ``multipliers`` and ``slack`` is that of the optimum on the final
        active set (zero where ``formula_status`` is ``ITERATION_LIMIT`` or ``UNCERTIFIED``,
        and where the step failed). The filter's own parameters are compiled in: the function
        is not differentiable in them.

    Raises
    ------
    ParameterError
        If ``filt`` is not a :class:`~safestab.SafetyFilter` with the exact QP, or takes
        run-time parameters.
    CompilationError
        If a compiler is missing or fails (unless ``fallback``).
    UnsupportedPrimitiveError
        If the filter's functions use a primitive without a C translation.
    """
    from ..filters import SafetyFilter

    if not isinstance(filt, SafetyFilter) or not isinstance(filt.formula, MultiFormula):
        raise ParameterError(
            f"native_step needs a SafetyFilter with the exact QP (formula=None), got {filt!r}"
        )
    if filt.params_spec is not None:
        raise ParameterError(
            "native_step does not support filters with run-time parameters (params=...)"
        )
    try:
        call = jax_function(
            export_c(filt, name), compiler=compiler, cxx_compiler=cxx_compiler,
            march_native=march_native,
        )  # fmt: skip
    except CompilationError as exc:
        if not fallback:
            raise
        warnings.warn(
            f"native_step falls back on the JAX step: {str(exc).splitlines()[0]}",
            RuntimeWarning,
            stacklevel=2,
        )
        return filt.step_fn

    @jax.custom_jvp
    def step(x: jax.Array) -> Any:
        return call(x)

    @step.defjvp
    def step_jvp(primals: tuple, tangents: tuple) -> tuple:
        (x,), (dx,) = primals, tangents
        x = jnp.asarray(x, jnp.float64)
        out = call(x)
        batch = x.shape[:-1]
        count = int(np.prod(batch, dtype=int))
        flat = lambda v: v.reshape((count,) + v.shape[len(batch) :])  # noqa: E731
        du, dmu, dchi = jax.vmap(lambda *a: _tangent(filt, *a))(
            flat(x), flat(jnp.asarray(dx, jnp.float64)), flat(out.u), flat(out.status),
            flat(out.formula_status), flat(out.active), flat(out.multipliers), flat(out.slack),
        )  # fmt: skip
        unflat = lambda v: v.reshape(batch + v.shape[1:])  # noqa: E731
        zero = lambda v: np.zeros(v.shape, jax.dtypes.float0)  # noqa: E731
        dout = jax.tree_util.tree_map(zero, out)
        dout = dataclasses.replace(dout, u=unflat(du), multipliers=unflat(dmu), slack=unflat(dchi))
        return out, dout

    return step


def _problem(filt: Any, a, b, c, d, u_nom, relaxed):
    """The solver's problem in ``z = (u, w_chi, s)``: rows ``G z <= r``, ``z0``, weight ``P``.

    ``u`` the input, ``w_chi = chi sqrt(slack_weight)`` the soft CLFs' scaled slacks,
    ``s`` the last-resort phase's scaled CBF slacks (columns only where ``relaxed``); the
    objective is ``1/2 (z - z0)' P (z - z0)`` with ``P = diag(H, I, I)``, as the solver's
    whitened coordinates (:mod:`safestab.formulas.multi`).
    """
    p_, m = b.shape
    k = d.shape[0]
    prm = filt.params
    mg_v = margins(a, b, a, b, prm["kappa"], 0.0, prm["phi"], 0.0)
    mg_c = margins(c, d, c, d, 0.0, prm["rho"], 0.0, prm["varphi"])
    if filt.cbf_margin is not None:  # as the solver: c + d.u >= rho Gamma + cbf_margin
        mg_c = mg_c._replace(B=mg_c.B + filt.cbf_margin)
    eye = jnp.eye(m)
    limits = filt.u_min is not None
    Gu = jnp.concatenate([b, -d] + ([eye, -eye] if limits else []), axis=0)
    r = jnp.concatenate(
        [-mg_v.A, -mg_c.B]
        + ([jnp.asarray(filt.u_max, float), -jnp.asarray(filt.u_min, float)] if limits else []),
        axis=0,
    )
    N = Gu.shape[0]
    H = jnp.eye(m) if filt.H is None else jnp.asarray(filt.H, float)
    cols = [Gu]
    soft = filt.slack_weight is not None and p_ > 0
    if soft:
        inv = 1.0 / jnp.sqrt(jnp.asarray(filt.slack_weight, float))
        cols.append(jnp.zeros((N, p_)).at[jnp.arange(p_), jnp.arange(p_)].set(-inv))
    L = jnp.linalg.cholesky(H)
    dw = jax.scipy.linalg.solve_triangular(L, -d.T, lower=True).T  # the CBF rows, whitened
    nrm = scaled_norm(dw)
    relax = (
        jnp.zeros((N, k))
        .at[p_ + jnp.arange(k), jnp.arange(k)]
        .set(-jnp.where(nrm > 0, nrm, 1.0) / np.sqrt(FALLBACK_WEIGHT))
    )
    cols.append(jnp.where(relaxed, relax, 0.0))
    G = jnp.concatenate(cols, axis=1)
    z0 = jnp.concatenate([jnp.zeros(m) if u_nom is None else u_nom, jnp.zeros(G.shape[1] - m)])
    D = G.shape[1]
    P = jnp.eye(D).at[:m, :m].set(H)
    return G, r, z0, P, soft


def _tangent(filt, x, dx, u, status, formula_status, active, mult, chi):
    """Tangents ``(du, dmu, dchi)`` of one state's answer, on its final active set.

    The KKT system ``P (z - z0) + G_A' mu_A = 0``, ``G_A z = r_A`` differentiated with the
    active set held fixed (the solver adds only rows independent of the active ones, so the
    system is regular): the derivative of the optimum inside its active set's region, as the
    JAX step's (:func:`safestab.formulas._dual_active_set.solve_dual`).
    """
    S = MultiStatus
    relaxed = formula_status == S.CBF_RELAXED
    solved = (formula_status == S.SOLVED) | (formula_status == S.CLF_DROPPED) | relaxed
    ok_u = jnp.all(jnp.isfinite(u))
    rows, drows = jax.jvp(lambda x: filt.rows(x), (x,), (dx,))
    b, d = rows[1], rows[3]
    p_, m = b.shape
    k = d.shape[0]
    (G, r, z0, P, soft), (dG, dr, dz0, _, _) = jax.jvp(
        lambda rw: _problem(filt, *rw, relaxed), (rows,), (drows,)
    )
    mu = jnp.where(active, mult, 0.0)
    # the primal point in z: u, the soft slacks' w (phase 1 only), the relaxed slacks' s
    parts = [jnp.where(jnp.isfinite(u), u, 0.0)]
    if soft:
        parts.append(chi * jnp.sqrt(jnp.asarray(filt.slack_weight, float)))
    s = -(G[:, G.shape[1] - k :].T @ mu)
    parts.append(jnp.where(relaxed, s, 0.0))
    z = jnp.concatenate(parts)
    D = G.shape[1]
    act = active
    GA = jnp.where(act[:, None], G, 0.0)
    top = jnp.concatenate([P, GA.T], axis=1)
    bottom = jnp.concatenate([GA, jnp.diag(jnp.where(act, 0.0, 1.0))], axis=1)
    M = jnp.concatenate([top, bottom], axis=0)
    rhs1 = P @ dz0 - dG.T @ mu
    rhs2 = jnp.where(act, dr - dG @ z, 0.0)
    sol = jnp.linalg.solve(M, jnp.concatenate([rhs1, rhs2]))
    dz, dmu = sol[:D], sol[D:]
    keep = solved & ok_u  # u is NaN where the step failed
    du = jnp.where(keep, dz[:m], 0.0)
    dmu = jnp.where(solved & act, dmu, 0.0)
    if soft:
        inv = 1.0 / jnp.sqrt(jnp.asarray(filt.slack_weight, float))
        dchi = jnp.where(formula_status == S.SOLVED, inv * dz[m : m + p_], 0.0)
    else:
        dchi = jnp.zeros(chi.shape)
    return du, dmu, dchi
