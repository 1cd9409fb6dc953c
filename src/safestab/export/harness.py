"""Compare exported C with the JAX step: tolerance scales, and a C test program.

Rounding differs between XLA and the C code (XLA fuses ``a*b + c`` into FMAs, sums in another
order and has its own ``exp``), so equal means equal to a relative tolerance. Relative to what
matters: where the formula's input ``u = -lambda1 b + lambda2 d`` is a difference of two large
terms (region P3), the rounding of either computation is relative to those terms, not to
``u``. :func:`comparison_scales` gives, per output and state, the magnitude the rounding is
relative to; :func:`compare` and the C harness accept ``|native - jax| <= rtol (|jax| +
scale)``. Integer and boolean outputs (regions, flags) must be identical.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ..errors import DimensionError
from .exporter import ExportedC

__all__ = [
    "DEFAULT_RTOL",
    "HARNESS_FLAGS",
    "cbf_condition_scale",
    "compare",
    "comparison_scales",
    "write_harness",
]

#: Default relative tolerances: double agrees with XLA's float64 to rounding (measured
#: differences are below 1e-14 of the scales, docs/export.md); float has a unit roundoff of
#: 6e-8, and errors grow by the few dozen operations of a step.
DEFAULT_RTOL = {"double": 1e-12, "float": 1e-5}

#: Flags the harness (and the exported code) must compile with, warning-free.
HARNESS_FLAGS = (
    "-std=c99",
    "-Wall",
    "-Wextra",
    "-Werror",
    "-pedantic",
    "-O2",
    "-ffp-contract=off",
)

_INPUT_LEAVES = ("u", "u_unconstrained")


def comparison_scales(controller: Any, out: Any, states: Any) -> list[np.ndarray]:
    """Per output leaf, the magnitude its rounding error is relative to.

    Parameters
    ----------
    controller : UniversalController or SafetyFilter
        The controller whose step produced ``out``. For a filter, every real leaf's scale is
        its largest magnitude over the N states: the solver's point is recomputed from its
        final active set by one backward-stable projection, in C as in JAX, so the two agree
        to rounding of the inputs' size where they end on the same active set (the integer
        leaves, statuses and active sets, must be identical).
    out : ControlOutput
        The JAX step at ``states`` (leaves with a leading axis N).
    states : array of shape (N, n)
        The states of ``out``.

    Returns
    -------
    list of arrays
        One per leaf (in pytree order), broadcastable to the leaf: for ``u`` and
        ``u_unconstrained``, ``|lambda1| |b| + |lambda2| |d|`` per state (the terms the formula
        subtracts; multipliers from :func:`~safestab.clf_cbf` or
        :func:`~safestab.clf_cbf_relaxed` on the step's own Lie terms), plus the sensitivity of
        ``u`` to the rounding of the margins ``A = a + kappa zeta`` and ``B = rho Gamma - c``
        (in P1 and P2 ``|b| / |b|^2`` and ``|d| / |d|^2`` times their magnitudes, in P3 the
        products in the multipliers' numerators over the Gram determinant); for other real
        leaves the largest magnitude of that leaf over the N states; zeros for integer leaves.

    Notes
    -----
    The magnitude of a margin is that of its summands, not of its value: ``a`` and ``c`` are
    themselves sums (``L_f V = dV/dx . f`` term by term, the class-K term, and with a GP
    ``dV/dx . m + sum_i |dV/dx_i| beta_i sigma_i``), which can cancel to far below their parts.
    With a :class:`~safestab.learning.FastGP` the mean's and the std's own rounding scales
    (:meth:`~safestab.learning.FastGP.rounding_scales`, its variance is a difference) are
    included as well. The Lie terms ``terms.a``, ``terms.c``, ``terms.b``, ``terms.d`` are
    compared per state relative to their summands, and the relaxed formula's ``slack``
    relative to the CLF multiplier's rounding scale (never less than the leaf's largest
    magnitude).
    """
    from ..filters import SafetyFilter
    from ..formulas import Region, clf_cbf, clf_cbf_relaxed

    if isinstance(controller, SafetyFilter):
        return _largest_magnitudes(out)
    x = np.asarray(states, float)
    xj = jax.numpy.asarray(x)
    a, b, c, d = (np.asarray(t) for t in out.terms)
    if x.ndim != 2 or x.shape[0] != a.shape[0]:
        raise DimensionError(f"states must have shape ({a.shape[0]}, n), got {x.shape}")
    p = dict(controller.params)
    phi, varphi = (np.asarray(w) for w in jax.vmap(controller.weights_point)(xj))
    p.update(phi=phi, varphi=varphi)
    if controller.slack_weight is None:
        res = clf_cbf(a, b, c, d, parallel_rtol=controller.parallel_rtol, **p)
    else:
        res = clf_cbf_relaxed(a, b, c, d, slack_weight=controller.slack_weight, **p)
    lam = np.abs(np.asarray(res.multipliers))
    bn = np.linalg.norm(b, axis=-1)
    dn = np.linalg.norm(d, axis=-1)
    u_scale = lam[..., 0] * bn + lam[..., 1] * dn

    a_sum, c_sum, b_mag, d_mag = _summand_magnitudes(controller, x)

    # The margins A = a + kappa zeta and B = rho Gamma - c: their rounding is relative to the
    # summands' magnitudes. In region P3 the multipliers are (w, v) / det with
    # v = A b.d + B |b|^2 and w = A |d|^2 + B b.d (Gram form; relaxed: |b|^2 + 1/slack_weight),
    # whose two products can cancel as well.
    inv_slack = 0.0 if controller.slack_weight is None else 1.0 / controller.slack_weight
    kappa, rho = controller.params["kappa"], controller.params["rho"]
    bb, dd, bd = bn**2 + inv_slack, dn**2, np.abs(np.sum(b * d, axis=-1))
    a_mag = np.abs(a) + a_sum + kappa * np.sqrt(a * a + phi * bn**4)
    b_mag = np.abs(c) + c_sum + rho * np.sqrt(c * c + varphi * dn**4)
    cross = b[..., :, None] * d[..., None, :] - b[..., None, :] * d[..., :, None]
    det = 0.5 * np.sum(cross * cross, axis=(-2, -1)) + inv_slack * dd
    region = np.asarray(out.region)
    with np.errstate(divide="ignore", invalid="ignore"):
        clf_part = np.where(bb > 0, a_mag / bb * bn, 0.0)
        cbf_part = np.where(dd > 0, b_mag / dd * dn, 0.0)
        gram = ((a_mag * dd + b_mag * bd) * bn + (a_mag * bd + b_mag * bb) * dn) / det
    u_scale = u_scale + np.select(
        [region == Region.P1, region == Region.P2, (region == Region.P3) & (det > 0)],
        [clf_part, cbf_part, gram],
        clf_part + cbf_part,
    )
    # the relaxed formula's slack chi = lambda1 / slack_weight: rounded like the CLF
    # multiplier, A / (|b|^2 + 1/slack_weight) in P1 and the Gram numerator over det in P3
    with np.errstate(divide="ignore", invalid="ignore"):
        lam1_scale = np.select(
            [region == Region.P1, (region == Region.P3) & (det > 0)],
            [np.where(bb > 0, a_mag / bb, 0.0), (a_mag * dd + b_mag * bd) / det],
            0.0,
        )
    slack_scale = inv_slack * lam1_scale
    per_state = {
        "terms.a": np.abs(a) + a_sum,
        "terms.c": np.abs(c) + c_sum,
        "slack": slack_scale,
        "terms.b": b_mag,
        "terms.d": d_mag,
    }
    u_scale = u_scale[..., None]
    scales = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(out)[0]:
        leaf = np.asarray(leaf)
        name = ".".join(str(getattr(k, "name", k)) for k in path)
        if leaf.dtype.kind != "f":
            scales.append(np.zeros(()))
        elif name in _INPUT_LEAVES:
            scales.append(u_scale)
        elif name in per_state:
            # the terms a, c are sums whose parts can cancel (module docstring): rounded
            # relative to their summands, at least the leaf's largest magnitude as before
            scale = np.maximum(per_state[name], _largest_magnitude(leaf))
            scales.append(scale.reshape(scale.shape + (1,) * (leaf.ndim - scale.ndim)))
        else:
            scales.append(_largest_magnitude(leaf))
    return scales


def _summand_magnitudes(controller: Any, x: np.ndarray) -> tuple[Any, Any, Any, Any]:
    """Per state, the magnitudes of the summands of ``a``, ``c`` and of ``b``, ``d`` (N, m).

    ``a = dV/dx . f + class-K term`` and ``c`` likewise (summed term by term), with a GP
    ``+ dV/dx . m -+ sum_i |dV/dx_i| beta_i sigma_i``, including the GP cache's own rounding
    scales (:meth:`~safestab.learning.FastGP.rounding_scales`); ``d = dh/dx g`` term by term.
    """
    from ..certificates import lie_terms_point

    xj = jax.numpy.asarray(x)
    sys_, clf, cbf = controller.system, controller.clf, controller.cbf
    dv = np.asarray(jax.vmap(clf.grad)(xj))
    dh = np.asarray(jax.vmap(cbf.grad)(xj))
    grad_v, grad_h = np.abs(dv), np.abs(dh)
    f = np.asarray(jax.vmap(sys_.f)(xj))
    g = np.asarray(jax.vmap(sys_.g)(xj))
    nominal = jax.vmap(lambda s: lie_terms_point(sys_, clf, cbf, s))(xj)
    a_class_k = np.abs(np.asarray(nominal.a) - np.sum(dv * f, -1))
    c_class_k = np.abs(np.asarray(nominal.c) - np.sum(dh * f, -1))
    a_sum = np.sum(grad_v * np.abs(f), -1) + a_class_k
    c_sum = np.sum(grad_h * np.abs(f), -1) + c_class_k
    if controller.uncertainty is not None:
        unc = controller.uncertainty
        mean, std = (np.asarray(t) for t in jax.vmap(unc.mean_std)(xj))
        beta = np.broadcast_to(np.asarray(controller.gp_beta, float), (x.shape[1],))
        spread = np.abs(mean) + beta * std
        if hasattr(unc, "rounding_scales"):
            mean_scale, std_scale = unc.rounding_scales(x)
            spread = spread + mean_scale + beta * std_scale
        a_sum = a_sum + np.sum(grad_v * spread, -1)
        c_sum = c_sum + np.sum(grad_h * spread, -1)
    b_mag = np.einsum("ki,kij->kj", grad_v, np.abs(g))
    d_mag = np.einsum("ki,kij->kj", grad_h, np.abs(g))
    return a_sum, c_sum, b_mag, d_mag


def cbf_condition_scale(controller: Any, out: Any, states: Any) -> np.ndarray:
    """Per state, the magnitude the CBF condition ``c + d.u - rho Gamma`` is rounded relative to.

    ``|c| + (summands of c) + rho Gamma + sum_i (|d_i| + |dh/dx| |g_i|) |u_i|`` at the step's
    own ``u``: an evaluation with relative precision ``eps`` errs by a small multiple of
    ``eps`` times this (the harness certifies ``rtol`` times it for each term).

    Parameters
    ----------
    controller : UniversalController
    out : ControlOutput
        The step at ``states`` (leading axis N).
    states : array of shape (N, n)

    Returns
    -------
    array of shape (N,)
    """
    x = np.asarray(states, float)
    _, c_sum, _, d_mag = _summand_magnitudes(controller, x)
    c, d = np.asarray(out.terms.c), np.asarray(out.terms.d)
    u = np.abs(np.nan_to_num(np.asarray(out.u)))
    _, varphi = (np.asarray(w) for w in jax.vmap(controller.weights_point)(jax.numpy.asarray(x)))
    gamma = np.sqrt(c * c + varphi * np.sum(d * d, -1) ** 2)
    rho = float(controller.params["rho"])
    return np.abs(c) + c_sum + rho * gamma + np.sum((np.abs(d) + d_mag) * u, -1)


def _largest_magnitude(leaf: np.ndarray) -> np.ndarray:
    """The largest finite magnitude of a real leaf over the states (zero if none)."""
    finite = np.abs(leaf[np.isfinite(leaf)])
    return np.asarray(finite.max() if finite.size else 0.0)


def _largest_magnitudes(out: Any) -> list[np.ndarray]:
    """Per leaf, :func:`_largest_magnitude` (zero for integer leaves)."""
    leaves = [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(out)]
    return [_largest_magnitude(x) if x.dtype.kind == "f" else np.zeros(()) for x in leaves]


def compare(
    native: Sequence[Any], reference: Sequence[Any], scales: Sequence[Any], rtol: float
) -> dict[int, int]:
    """Count mismatching elements per leaf index (only leaves with mismatches are listed).

    Real leaves match where ``|native - ref| <= rtol (|ref| + scale)`` or both are NaN;
    integer and boolean leaves must be equal.
    """
    bad: dict[int, int] = {}
    for i, (got, want, scale) in enumerate(zip(native, reference, scales, strict=True)):
        got, want = np.asarray(got), np.asarray(want)
        if want.dtype.kind == "f":
            got64 = got.astype(np.float64)
            ok = np.abs(got64 - want) <= rtol * (np.abs(want) + scale)
            ok |= np.isnan(got64) & np.isnan(want)
            ok |= got64 == want  # equal infinities
        else:
            ok = got == want
        count = int(np.sum(~ok))
        if count:
            bad[i] = count
    return bad


def _c_array(e_lit: Any, values: np.ndarray, ctype: str, name: str) -> list[str]:
    items = [e_lit(v) for v in values.reshape(-1)]
    lines = [f"static const {ctype} {name}[{max(len(items), 1)}] = {{"]
    row: list[str] = []
    for item in items or ["0"]:
        row.append(item)
        if sum(len(s) + 2 for s in row) > 92:
            lines.append("    " + ", ".join(row) + ",")
            row = []
    if row:
        lines.append("    " + ", ".join(row) + ",")
    lines[-1] = lines[-1].rstrip(",")
    return lines + ["};"]


def write_harness(
    exported: ExportedC,
    states: Any,
    expected: Any,
    out_dir: str | Path,
    *,
    scales: Sequence[Any] | None = None,
    rtol: float | None = None,
) -> Path:
    """Write ``<name>_harness.c``: a C program that checks ``<name>_step`` on recorded states.

    The program calls ``<name>_step`` on every state, compares every output with the
    expected one (see :func:`compare`) and the returned status with the expected status,
    prints the first mismatches and a summary, and exits with 1 on any mismatch, 0 otherwise.
    Build it with ``cc -std=c99 -Wall -Wextra -Werror -pedantic -O2 -ffp-contract=off
    <name>.c <name>_harness.c -lm``.

    Parameters
    ----------
    exported : ExportedC
    states : array of shape (N, n)
    expected : pytree
        The JAX outputs at ``states`` (same structure as the exported function's, with a
        leading axis N).
    out_dir : path
        Folder of ``<name>.c`` and ``<name>.h``.
    scales : list of arrays, optional
        Per leaf, broadcastable to (N, *leaf_shape) (default: the largest magnitude of each
        leaf); :func:`comparison_scales` gives the right ones for a controller.
    rtol : float, optional
        Default :data:`DEFAULT_RTOL` of the precision.

    Returns
    -------
    Path
        The harness source.

    Raises
    ------
    DimensionError
        If ``states`` or ``expected`` do not fit the exported function.
    """
    from ._cgen import Emitter

    states = np.asarray(states, dtype=np.float64)
    if states.ndim != 2 or states.shape[1] != exported.n_states or len(states) == 0:
        raise DimensionError(
            f"states must have shape (N, {exported.n_states}) with N >= 1, got {states.shape}"
        )
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(expected)]
    n_cases = len(states)
    if len(leaves) != len(exported.leaves) or any(
        got.shape != (n_cases, *leaf.shape)
        for got, leaf in zip(leaves, exported.leaves, strict=True)
    ):
        raise DimensionError(
            "expected must be the exported function's outputs at the N states, with shapes "
            f"{[(n_cases, *leaf.shape) for leaf in exported.leaves]}, got "
            f"{[x.shape for x in leaves]}"
        )
    if scales is None:
        scales = [
            np.asarray(np.nanmax(np.abs(x)) if x.dtype.kind == "f" and x.size else 0.0)
            for x in leaves
        ]
    rtol = DEFAULT_RTOL[exported.precision] if rtol is None else float(rtol)
    e = Emitter(exported.precision)
    d = Emitter("double")
    name, up = exported.name, exported.name.upper()
    real = e.real
    status = np.where(~np.all(np.isfinite(states), axis=1), 1, 0)
    for x in leaves:
        if x.dtype.kind == "f":
            bad = ~np.isfinite(x.reshape(n_cases, -1)).all(axis=1)
            status = status | np.where(bad, 2, 0)

    src = [
        f"/* {name}_harness.c: checks {name}_step against the JAX step at {n_cases} recorded",
        " * states (generated by safestab; exits 1 on any mismatch). Build and run:",
        f" *   cc -std=c99 -Wall -Wextra -Werror -pedantic -O2 -ffp-contract=off {name}.c "
        f"{name}_harness.c -lm -o {name}_harness && ./{name}_harness",
        " */",
        "#include <math.h>",
        "#include <stdio.h>",
        f'#include "{name}.h"',
        "",
        f"#define N_CASES {n_cases}",
        f"#define RTOL {rtol!r}",
        "",
    ]
    src += _c_array(lambda v: e.lit(v, np.float64), states, real, "states")
    src += _c_array(lambda v: str(int(v)), status, "int", "want_status")
    checks = []
    for i, (leaf, want) in enumerate(zip(exported.leaves, leaves, strict=True)):
        if leaf.size == 0:
            continue
        if i == exported.primary:
            elem = f"{leaf.name}[j]"
        elif leaf.shape == ():
            elem = f"info.{leaf.name}"
        else:
            elem = f"info.{leaf.name}[j]"
        loop = f"        for (int j = 0; j < {leaf.size}; ++j) failures += "
        if leaf.dtype.kind == "f":
            scale = np.broadcast_to(np.asarray(scales[i], dtype=np.float64), want.shape)
            src += _c_array(lambda v: d.lit(v, np.float64), want, "double", f"want_{i}")
            src += _c_array(lambda v: d.lit(v, np.float64), scale, "double", f"scale_{i}")
            checks.append(
                f'{loop}check_real("{leaf.path}", k, j, (double){elem}, '
                f"want_{i}[k * {leaf.size} + j], scale_{i}[k * {leaf.size} + j]);"
            )
        else:
            src += _c_array(lambda v: str(int(v)), want, "long long", f"want_{i}")
            checks.append(
                f'{loop}check_int("{leaf.path}", k, j, (long long){elem}, '
                f"want_{i}[k * {leaf.size} + j]);"
            )
    prim = exported.leaves[exported.primary]
    prim_ct = e.io_ctype(prim.dtype)
    src += [
        "",
        "static long reported = 0;",
        "",
        "static long check_real(const char *what, long k, int j, double got, double want,",
        "                        double scale)",
        "{",
        "    const double tol = RTOL * (fabs(want) + scale);",
        "    if (want != want ? got != got : (got == want || fabs(got - want) <= tol)) return 0;",
        "    if (reported++ < 20)",
        '        printf("state %ld: %s[%d] = %.17g, expected %.17g (tolerance %.3g)\\n",',
        "               k, what, j, got, want, tol);",
        "    return 1;",
        "}",
        "",
        "static long check_int(const char *what, long k, int j, long long got, long long want)",
        "{",
        "    if (got == want) return 0;",
        "    if (reported++ < 20)",
        '        printf("state %ld: %s[%d] = %lld, expected %lld\\n", k, what, j, got, want);',
        "    return 1;",
        "}",
        "",
        "int main(void)",
        "{",
        "    long failures = 0;",
        "    for (long k = 0; k < N_CASES; ++k) {",
        f"        {prim_ct} {prim.name}[{up}_N_OUT];",
        f"        {name}_info info;",
        f"        const int status = {name}_step(states + k * {up}_N_STATES, {prim.name}, &info);",
        '        failures += check_int("status", k, 0, status, want_status[k]);',
        *checks,
        "    }",
        f'    printf("{name}_harness: %d states, %ld mismatches (rtol %g)\\n", N_CASES, failures, '
        "RTOL);",
        "    return failures ? 1 : 0;",
        "}",
        "",
    ]
    path = Path(out_dir).absolute() / f"{name}_harness.c"  # valid after a chdir
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(src))
    tmp.replace(path)
    return path
