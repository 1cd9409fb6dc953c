"""Benchmark rows of issue 24: the formulas inside a user's own ``jax.jit``, and gradients.

1. *Formula in a user's jit*: ``clf_cbf`` on 10,000 random Lie terms, called once per state
   from Python (each call checks its arguments and dispatches), against the same function
   inside the user's ``jax.jit(jax.vmap(...))`` (no dispatch per state). States per second.
2. *Gradient of u*: the Jacobian of ``u`` with respect to the Lie terms and the parameters
   ``(a, b, c, d, kappa, rho)`` of one two-input problem, from the closed form (``jax.jacrev``
   of ``clf_cbf``) and from qpax's differentiable QP (cbfpy's solver; implicit
   differentiation of its KKT system) on the same QP (the margins computed the same way),
   both jitted: the time of one Jacobian (median of single calls), of a batch of 1,000
   (``vmap``, median of 3), and their differences, from each other and from central
   differences of each solver's solution, relative to the Jacobian's size, over the problems
   of 200 random ones inside P1, P2 and P3 (region P4 has the Jacobian 0).

``python benchmarks/run.py --only jax`` (or ``python benchmarks/jax_native.py``) runs them
and writes ``docs/performance_jax.json`` and the block between the ``jax`` markers of
``docs/performance.md``.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import safestab as ss
from _page import machine, median_us, save_results

P = {"kappa": 0.5, "rho": 0.2, "phi": 1.0, "varphi": 0.5}
BEGIN, END = "<!-- jax:begin -->", "<!-- jax:end -->"
COMMAND = "python benchmarks/run.py --only jax"


def _theta(rng, n):
    """Flat problems ``(a, b1, b2, c, d1, d2, kappa, rho)``."""
    t = rng.standard_normal((n, 6)) * np.array([2, 1, 1, 2, 1, 1])
    return np.concatenate([t, np.full((n, 1), P["kappa"]), np.full((n, 1), P["rho"])], 1)


def _ours(th):
    res = ss.clf_cbf(
        th[0], th[1:3], th[3], th[4:6], kappa=th[6], rho=th[7], phi=P["phi"], varphi=P["varphi"]
    )
    return res.u


def _qpax(th):
    import qpax

    a, b, c, d, kappa, rho = th[0], th[1:3], th[3], th[4:6], th[6], th[7]
    A = a + kappa * ss.zeta(a, b, P["phi"])  # the margins, through the public zeta
    B = rho * ss.zeta(c, d, P["varphi"]) - c
    G = jnp.stack([b, -d])
    h = jnp.stack([-A, -B])
    return qpax.solve_qp_primal(
        jnp.eye(2), jnp.zeros(2), jnp.zeros((0, 2)), jnp.zeros(0), G, h,
        solver_tol=1e-10, target_kappa=1e-9,
    )  # fmt: skip


def _best(fn, repeat=3):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def run(repeat: int = 2000) -> dict:
    rng = np.random.default_rng(0)
    res: dict = {"machine": machine(), "command": COMMAND}

    # 1. the formula inside a user's jit, against a call per state
    n = 10_000
    th = _theta(rng, n)
    a, b, c, d = th[:, 0], th[:, 1:3], th[:, 3], th[:, 4:6]
    eager_n = 300
    t0 = time.perf_counter()
    for i in range(eager_n):
        ss.clf_cbf(a[i], b[i], c[i], d[i], **P).u.block_until_ready()
    eager_per_s = eager_n / (time.perf_counter() - t0)
    user = jax.jit(jax.vmap(lambda a, b, c, d: ss.clf_cbf(a, b, c, d, **P).u))
    args = tuple(jnp.asarray(v) for v in (a, b, c, d))
    user(*args).block_until_ready()
    jit_per_s = n / _best(lambda: user(*args), 5)
    one = jax.jit(lambda a, b, c, d: ss.clf_cbf(a, b, c, d, **P).u)
    states = [tuple(jnp.asarray(v[i]) for v in (a, b, c, d)) for i in range(64)]
    res["formula"] = {
        "eager_call_per_s": eager_per_s,
        "user_jit_vmap_per_s": jit_per_s,
        "speedup": jit_per_s / eager_per_s,
        "user_jit_single_us": median_us(lambda s: one(*s).block_until_ready(), states, repeat),
        "eager_single_us": 1e6 / eager_per_s,
    }

    # 2. the gradient of u: closed form against qpax
    jac_ours = jax.jit(jax.jacrev(_ours))
    jac_qpax = jax.jit(jax.jacrev(_qpax))
    probs = [jnp.asarray(t) for t in _theta(rng, 200)]
    regions = [int(ss.clf_cbf(t[0], t[1:3], t[3], t[4:6], **P).region) for t in probs]
    inner = [t for t, r in zip(probs, regions, strict=True) if r in (1, 2, 3)]
    # columns of a, c, kappa, rho (they enter the QP's right-hand side only) and of b, d
    # (they enter its matrix); each Jacobian also against central differences (step 1e-6) of
    # its own solver's solution
    rhs_cols, mat_cols = [0, 3, 6, 7], [1, 2, 4, 5]
    qp_u = jax.jit(_qpax)
    diffs: dict[str, list[float]] = {"rhs": [], "matrix": [], "ours_fd": [], "qpax_fd": []}
    diffs["u"] = [float(np.abs(np.asarray(qp_u(t)) - np.asarray(_ours(t))).max()) for t in inner]
    # the Jacobians are compared where the two solutions agree (qpax's iterations can stop
    # short of the optimum: a wrong point has a wrong derivative for another reason)
    same = [t for t, du in zip(inner, diffs["u"], strict=True) if du <= 1e-6]
    for t in same:
        jo, jq = np.asarray(jac_ours(t)), np.asarray(jac_qpax(t))
        scale = max(np.abs(jo).max(), 1e-300)
        diffs["rhs"].append(float(np.abs(jo - jq)[:, rhs_cols].max() / scale))
        diffs["matrix"].append(float(np.abs(jo - jq)[:, mat_cols].max() / scale))
        for name, fn, jac in (("ours_fd", _ours, jo), ("qpax_fd", qp_u, jq)):
            fd = np.stack(
                [(np.asarray(fn(t + 1e-6 * e)) - np.asarray(fn(t - 1e-6 * e))) / 2e-6
                 for e in np.eye(8)], -1,
            )  # fmt: skip
            diffs[name].append(float(np.abs(jac - fd).max() / scale))
    batch = jnp.asarray(_theta(rng, 1000))
    jb_ours, jb_qpax = jax.jit(jax.vmap(jax.jacrev(_ours))), jax.jit(jax.vmap(jax.jacrev(_qpax)))
    jb_ours(batch).block_until_ready()
    jb_qpax(batch).block_until_ready()
    res["gradient"] = {
        "ours_us": median_us(lambda t: jac_ours(t).block_until_ready(), inner, repeat),
        "qpax_us": median_us(lambda t: jac_qpax(t).block_until_ready(), inner, repeat // 4),
        "ours_batch_per_s": 1000 / _best(lambda: jb_ours(batch)),
        "qpax_batch_per_s": 1000 / _best(lambda: jb_qpax(batch)),
        "agreement_rhs_max_rel": float(np.max(diffs["rhs"])),
        "agreement_matrix_max_rel": float(np.max(diffs["matrix"])),
        "agreement_matrix_median_rel": float(np.median(diffs["matrix"])),
        "ours_vs_differences_max_rel": float(np.max(diffs["ours_fd"])),
        "qpax_vs_differences_max_rel": float(np.max(diffs["qpax_fd"])),
        "solution_max_abs_difference": float(np.max(diffs["u"])),
        "solutions_differ_by_more_than_1e-6": int(sum(du > 1e-6 for du in diffs["u"])),
        "problems": len(inner),
        "problems_compared": len(same),
        "regions": {str(r): regions.count(r) for r in sorted(set(regions))},
    }
    return res


def markdown(r: dict) -> str:
    f, g = r["formula"], r["gradient"]
    return "\n".join(
        [
            BEGIN,
            "## Formulas in a user's jit, and gradients (issue 24)",
            "",
            "`clf_cbf` on random two-input problems (seed 0): called once per state from "
            "Python (argument checks and a dispatch each), and inside the user's own "
            "`jax.jit(jax.vmap(...))` over 10,000 states. The Jacobian of `u` with respect to "
            "`(a, b, c, d, kappa, rho)` from the closed form (`jax.jacrev`, jitted) and from "
            "qpax's differentiable QP on the same QP (jitted; implicit differentiation of its "
            "KKT system): one problem (median of single calls) and a batch of 1,000 (`vmap`, "
            f"median of 3). Load average {r['machine']['load_average_at_start']:.1f} at the "
            "start (a shared machine: ratios are from the same run).",
            "",
            "| row | closed form | baseline | ratio |",
            "|---|---|---|---|",
            f"| `clf_cbf` in a user's `jit(vmap)`, states/s (baseline: one eager call per "
            f"state) | {f['user_jit_vmap_per_s']:.3g} | {f['eager_call_per_s']:.3g} | "
            f"{f['speedup']:.0f}x |",
            f"| `clf_cbf` in a user's `jit`, one state, us (baseline: eager call) | "
            f"{f['user_jit_single_us']:.1f} | {f['eager_single_us']:.0f} | "
            f"{f['eager_single_us'] / f['user_jit_single_us']:.0f}x |",
            f"| Jacobian of u (8 inputs), one problem, us (baseline: qpax) | "
            f"{g['ours_us']:.1f} | {g['qpax_us']:.0f} | {g['qpax_us'] / g['ours_us']:.0f}x |",
            f"| Jacobian of u, batch of 1,000, problems/s (baseline: qpax) | "
            f"{g['ours_batch_per_s']:.3g} | {g['qpax_batch_per_s']:.3g} | "
            f"{g['ours_batch_per_s'] / g['qpax_batch_per_s']:.0f}x |",
            "",
            f"Of {g['problems']} problems inside P1 to P3, qpax's solution differs from the "
            f"closed form's by more than 1e-6 on {g['solutions_differ_by_more_than_1e-6']} "
            f"(by up to {g['solution_max_abs_difference']:.1e}). On the other "
            f"{g['problems_compared']} the two Jacobians agree to "
            f"{g['agreement_rhs_max_rel']:.1e} (relative to the Jacobian's size) in the "
            "columns of a, c, kappa and rho, which enter the QP's right-hand side only; in "
            "the columns of b and d, which enter its constraint matrix, they differ by up to "
            f"{g['agreement_matrix_max_rel']:.1e} (median "
            f"{g['agreement_matrix_median_rel']:.1e}). Against central differences (step "
            "1e-6) of each solver's own solution the closed form's Jacobian is within "
            f"{g['ours_vs_differences_max_rel']:.1e} and qpax's within "
            f"{g['qpax_vs_differences_max_rel']:.1e}: qpax's derivative with respect to the "
            "constraint matrix is wrong on these problems, although its solution is right. "
            "The closed form's derivative is also checked against 80-digit "
            "differences in `tests/test_jax_native.py`. qpax runs with `solver_tol=1e-10` and "
            "`target_kappa=1e-9` (its default smooths the derivative). "
            f"Regenerate with `{r['command']}`; machine: {r['machine']['platform']}, "
            f"{r['machine']['cpus']} CPUs, JAX {r['machine']['jax']}.",
            "",
            END,
        ]
    )


def main(out: Path) -> None:
    save_results(out, "performance_jax.json", run(), markdown, BEGIN, END)


if __name__ == "__main__":
    main(Path(__file__).resolve().parents[1] / "docs")
