"""Candidates for the filter's CPU kernel inside JAX, measured side by side in one run.

Problems: the point robot of ``benchmarks/filter.py`` among 8 discs (2 inputs, |u_i| <= 1,
12 rows) and an adaptive cruise control filter with CBF-CLF-Helper's parameters (one soft
CLF, one CBF, force limits: 4 rows). Candidates, each called inside a user's ``jax.jit``:

* ``xla``: the filter's JAX step (``step_fn``), the baseline;
* ``pure_callback``: ``jax.pure_callback`` into the compiled exported step
  (``NativeController``'s cffi function; ``vmap_method="broadcast_all"``: a batch is one
  loop in C), no derivative;
* ``ffi``: :func:`safestab.export.native_step`: an XLA custom call (``jax.ffi``) into the
  same compiled C, with the derivative on the final active set (``custom_jvp``).

Columns: *one call* is the median of ``--calls`` calls on one state (cycling over 64 states
prepared as device arrays), the median of 3 rounds; *vmap* is ``jax.jit(jax.vmap(step))``
over 1,000 states (median of 5), states per second; *first call* is the time from nothing
to the first answer (export and C/C++ compilation for the native ones; tracing and XLA
compilation for each, the persistent compilation cache off); *max |du|* and *same status*
compare with the XLA step on the 1,000 states. daqp and quadprog solve the same rows
prebuilt (their Python call, not inside JAX) where installed.

    python benchmarks/filter_kernel.py [--calls 500]

Prints the table only (the results are not written to the docs).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("SAFESTAB_COMPILATION_CACHE", "off")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import safestab as ss  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from filter import RADIUS, robot_filter  # noqa: E402

BATCH = 1_000


def acc_filter() -> ss.SafetyFilter:
    """Adaptive cruise control (CBF-CLF-Helper's ACC): state (p, v, z), input the force."""
    mass, f0, f1, f2, v_lead, v_des, t_h, grav = 1650.0, 0.1, 5.0, 0.25, 10.0, 24.0, 1.8, 9.81

    def f(x):
        v = x[1]
        drag = f0 + f1 * v + f2 * v**2
        return jnp.array([v, -drag / mass, v_lead - v])

    system = ss.ControlAffineSystem(
        f, lambda x: jnp.array([[0.0], [1.0 / mass], [0.0]]), 3, name="acc"
    )
    clf = ss.CLF(lambda x: (x[1] - v_des) ** 2, lam=5.0)
    cbf = ss.CBF(lambda x: x[2] - t_h * x[1], beta=5.0)
    lim = 0.3 * mass * grav
    return ss.SafetyFilter(
        system, cbf, clfs=clf, slack_weight=2e-2, H=np.array([[2.0 / mass**2]]),
        u_min=-lim, u_max=lim,
    )  # fmt: skip


def robot_states(rng, obstacles, n):
    x = rng.uniform(-5, 5, (4 * n, 2))
    h = np.sum((x[:, None] - obstacles) ** 2, -1) - RADIUS**2
    return x[np.all(h > 0.1, -1)][:n]


def acc_states(rng, n):
    return np.stack([np.zeros(n), rng.uniform(10, 30, n), rng.uniform(40, 120, n)], axis=-1)


def callback_step(nat, filt):
    """``jax.pure_callback`` into the NativeController's batched C loop (values only)."""
    n = filt.system.n_states
    ex = nat.exported
    used = [i for i, leaf in enumerate(ex.leaves) if leaf.size > 0]

    def host(x):
        x = np.ascontiguousarray(np.asarray(x, np.float64))
        leaves, _ = nat.function.columns(x.reshape(-1, n))
        return tuple(leaves[i].reshape(x.shape[:-1] + ex.leaves[i].shape) for i in used)

    def step(x):
        shapes = tuple(
            jax.ShapeDtypeStruct(x.shape[:-1] + ex.leaves[i].shape, ex.leaves[i].dtype)
            for i in used
        )
        outs = jax.pure_callback(host, shapes, x, vmap_method="broadcast_all")
        full = [jnp.zeros(x.shape[:-1] + leaf.shape, leaf.dtype) for leaf in ex.leaves]
        for i, v in zip(used, outs, strict=True):
            full[i] = v
        return ex.treedef.unflatten(full)

    return step


def one_call_us(fn, states, calls):
    """Median over 3 rounds of the median time of one call (us)."""
    jax.block_until_ready(fn(states[0]))
    rounds = []
    for _ in range(3):
        ts = np.empty(calls)
        for i in range(calls):
            s = states[i % len(states)]
            t = time.perf_counter()
            jax.block_until_ready(fn(s))
            ts[i] = time.perf_counter() - t
        rounds.append(np.median(ts))
    return 1e6 * float(np.median(rounds))


def per_second(fn, x):
    jax.block_until_ready(fn(x))
    ts = []
    for _ in range(5):
        t = time.perf_counter()
        jax.block_until_ready(fn(x))
        ts.append(time.perf_counter() - t)
    return x.shape[0] / float(np.median(ts))


def qp_rows(filt, states):
    """daqp / quadprog arguments of the filter's problem at each state (built, not timed)."""
    m = filt.system.n_inputs
    H = np.eye(m) if filt.H is None else np.asarray(filt.H)
    daqp_args, quad_args = [], []
    for x in states:
        a, b, c, d, u_nom = (None if v is None else np.asarray(v) for v in filt.rows(x))
        u_nom = np.zeros(m) if u_nom is None else u_nom
        # rows G u <= r (CLF rows with a slack column when soft), objective in (u, slack)
        p = b.shape[0]
        soft = filt.slack_weight is not None and p > 0
        G = np.concatenate([b, -d])
        r = np.concatenate([-a, c])
        if soft:
            G = np.concatenate([G, np.concatenate([-np.eye(p), np.zeros((len(c), p))])], 1)
            Hf = np.zeros((m + p, m + p))
            Hf[:m, :m] = H
            Hf[m:, m:] = filt.slack_weight * np.eye(p)
            lin = np.concatenate([-H @ u_nom, np.zeros(p)])
        else:
            Hf, lin = H, -H @ u_nom
        nv = Hf.shape[0]
        lo_v = np.full(nv, -1e30)
        hi_v = np.full(nv, 1e30)
        if filt.u_min is not None:
            lo_v[:m], hi_v[:m] = np.asarray(filt.u_min), np.asarray(filt.u_max)
        daqp_args.append(
            (Hf, lin, np.ascontiguousarray(G), np.concatenate([hi_v, r]),
             np.concatenate([lo_v, np.full(len(r), -1e30)]), np.zeros(nv + len(r), np.int32))
        )  # fmt: skip
        box = np.concatenate([np.eye(nv)[:m], -np.eye(nv)[:m]]) if filt.u_min is not None else None
        C = G if box is None else np.concatenate([G, box])
        rr = r if box is None else np.concatenate([r, hi_v[:m], -lo_v[:m]])
        quad_args.append((Hf + 1e-12 * np.eye(nv) * soft, -lin, np.ascontiguousarray(-C.T), -rr))
    return daqp_args, quad_args


def run_problem(name, filt, states, calls):
    from safestab.export import NativeController, native_step

    print(f"\n== {name}: {len(filt.cbfs)} CBF(s), {len(filt.clfs)} CLF(s); load "
          f"{os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip
    x = jnp.asarray(states)
    one = [jnp.asarray(s) for s in states[:64]]
    rows = {}

    # each candidate is a step function (x -> FilterOutput) that a user's jit traces; the
    # first call builds it and runs the user's jitted function returning u once
    t = time.perf_counter()
    xla = filt.step_fn
    jax.block_until_ready(jax.jit(lambda s: xla(s).u)(one[0]))
    rows["xla"] = {"first_s": time.perf_counter() - t, "fn": xla}
    ref = jax.jit(xla)(x)

    t = time.perf_counter()
    cb = callback_step(NativeController(filt, name="kcb"), filt)
    jax.block_until_ready(jax.jit(lambda s: cb(s).u)(one[0]))
    rows["pure_callback"] = {"first_s": time.perf_counter() - t, "fn": cb}

    t = time.perf_counter()
    ffi = native_step(filt, name="kffi")
    jax.block_until_ready(jax.jit(lambda s: ffi(s).u)(one[0]))
    rows["ffi"] = {"first_s": time.perf_counter() - t, "fn": ffi}

    for key, r in rows.items():
        fn = r["fn"]
        got = jax.jit(jax.vmap(fn))(x)
        r["max_du"] = float(np.nanmax(np.abs(np.asarray(got.u) - np.asarray(ref.u))))
        r["same_status"] = float(
            np.mean((np.asarray(got.status) == np.asarray(ref.status))
                    & (np.asarray(got.formula_status) == np.asarray(ref.formula_status)))
        )  # fmt: skip
        r["one_us"] = one_call_us(jax.jit(lambda s, fn=fn: fn(s).u), one, calls)
        vm = jax.jit(jax.vmap(lambda s, fn=fn: fn(s).u))
        r["per_s"] = per_second(vm, x)
        print(f"  {key}: one call {r['one_us']:.1f} us, vmap {r['per_s']:.3g}/s, first call "
              f"{r['first_s']:.1f} s", flush=True)  # fmt: skip
    # the derivative: jvp of u inside a user's jit, one state
    _, t_ref = jax.jvp(filt.step_fn, (x,), (jnp.ones_like(x),))
    _, t_ffi = jax.jvp(ffi, (x,), (jnp.ones_like(x),))
    ok = np.asarray(ref.formula_status) <= 2
    jvp_du = float(np.nanmax(np.abs(np.asarray(t_ffi.u) - np.asarray(t_ref.u))[ok]))
    jv_x = jax.jit(lambda s: jax.jvp(lambda z: filt.step_fn(z).u, (s,), (jnp.ones_like(s),)))
    jv_f = jax.jit(lambda s: jax.jvp(lambda z: ffi(z).u, (s,), (jnp.ones_like(s),)))
    jvp_us = {"xla": one_call_us(jv_x, one, calls), "ffi": one_call_us(jv_f, one, calls)}

    solvers = {}
    try:
        import daqp

        da, _ = qp_rows(filt, states[:64])
        solvers["daqp"] = one_call_us(lambda a: daqp.solve(*a), da, calls)
    except ImportError:
        pass
    try:
        import quadprog

        _, qa = qp_rows(filt, states[:64])

        def quad(a):
            try:
                return quadprog.solve_qp(*a, 0)[0]
            except ValueError:  # inconsistent rows (the filter relaxes its CBFs there)
                return None

        solvers["quadprog"] = one_call_us(quad, qa, calls)
    except ImportError:
        pass
    base = rows["xla"]
    print(f"\n| {name} | one call (us) | x XLA | vmap {BATCH:,} (/s) | x XLA | first call (s) "
          "| max abs du vs XLA | same statuses |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for key, r in rows.items():
        print(
            f"| {key} | {r['one_us']:.1f} | {base['one_us'] / r['one_us']:.1f}x | "
            f"{r['per_s']:.3g} | {r['per_s'] / base['per_s']:.1f}x | {r['first_s']:.1f} | "
            f"{r['max_du']:.1e} | {100 * r['same_status']:.0f} % |"
        )
    for key, us in solvers.items():
        print(f"| {key} (rows prebuilt, from Python) | {us:.1f} | "
              f"{base['one_us'] / us:.1f}x | | | | | |")  # fmt: skip
    print(
        f"\njvp of u, one state in a user's jit: xla {jvp_us['xla']:.1f} us, ffi "
        f"{jvp_us['ffi']:.1f} us; max |du tangent - XLA's| {jvp_du:.1e} (solved states)"
    )
    if "daqp" in solvers:
        print(f"ffi / daqp = {rows['ffi']['one_us'] / solvers['daqp']:.2f} (target <= 2)")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--calls", type=int, default=500)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"JAX {jax.__version__}, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.2f} at the start")  # fmt: skip
    obstacles = rng.uniform(-6, 6, (8, 2))
    run_problem("point robot, 8 discs", robot_filter(obstacles),
                robot_states(rng, obstacles, BATCH), args.calls)  # fmt: skip
    run_problem("ACC (CBF-CLF-Helper)", acc_filter(), acc_states(rng, BATCH), args.calls)
    print(f"\nload average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
