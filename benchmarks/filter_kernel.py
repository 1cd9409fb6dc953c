"""Candidates for the filter's CPU kernel inside JAX, measured side by side in one run.

Problems: the point robot of ``benchmarks/filter.py`` among 8 discs (2 inputs, |u_i| <= 1,
12 rows) and an adaptive cruise control filter with CBF-CLF-Helper's parameters (one soft
CLF, one CBF, force limits: 4 rows). Candidates, each called inside a user's ``jax.jit``:

* ``xla_loop``: the filter's JAX step (``step_fn``) with the solver's loop run by XLA
  (``SAFESTAB_NATIVE_SOLVER=off`` while it is compiled), the baseline;
* ``xla``: the filter's JAX step as it runs by default on the CPU: the rows and the phases in
  XLA, the solver one custom call into its written C (``safestab.export._dual_qp_ffi``);
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
compare with the baseline on the 1,000 states. daqp and quadprog solve the same rows
prebuilt (their Python call, not inside JAX) where installed.

The 100-disc problem (104 rows) is measured under vmap only; where ``native_step`` refuses it
(its step needing more stack than :data:`safestab.export.jax_kernel.MAX_STACK_BYTES`), the
block says so. *Build from the disk cache* is the first call of ``native_step`` at 8 discs in
a fresh process whose cache folder another fresh process has just filled (the built object is
loaded, no compiler runs; the rest is the export's trace of the filter).

    python benchmarks/filter_kernel.py --json docs/performance_filter_kernel.json [--calls 500]
    python benchmarks/run.py --only filter-kernel          # the same, into docs/

``--json PATH`` writes the results as strict JSON (atomically) and, where PATH's folder holds
``performance.md``, puts their block between ``<!-- filter-kernel:begin -->`` and
``<!-- filter-kernel:end -->``; ``python benchmarks/run.py --page`` rewrites the block from the
saved JSON. Without ``--json`` the block is printed only.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("SAFESTAB_COMPILATION_CACHE", "off")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import safestab as ss  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _page import states_per_second  # noqa: E402
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


def robot_states(rng, obstacles, n, oversample=4):
    x = rng.uniform(-5, 5, (oversample * n, 2))
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


#: Candidates' names in the block.
LABELS = {
    "xla_loop": "JAX step, the solver's loop in XLA (`SAFESTAB_NATIVE_SOLVER=off`)",
    "xla": "JAX step (`step_fn`; the solver one custom call, the default on the CPU)",
    "pure_callback": "`jax.pure_callback` into the C step",
    "ffi": "XLA custom call (`native_step`)",
}
BEGIN, END = "<!-- filter-kernel:begin -->", "<!-- filter-kernel:end -->"
#: Discs of the problem measured under vmap only, and its target (states per second).
LARGE_DISCS, LARGE_TARGET = 100, 2e5


@contextlib.contextmanager
def solver_loop_in_xla(on: bool = True):
    """While compiling inside it (``on``), the filter's solver runs as XLA's loop on the CPU."""
    from safestab.export._dual_qp_ffi import ENV

    old = os.environ.get(ENV)
    if on:
        os.environ[ENV] = "off"
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = old


def measure(fn, r, x, ref, one, calls):
    """A candidate's differences to the baseline ``ref``, its one call and its vmap rate."""
    got = jax.jit(jax.vmap(fn))(x)
    r["max_abs_du_vs_xla"] = float(np.nanmax(np.abs(np.asarray(got.u) - np.asarray(ref.u))))
    r["same_status"] = float(
        np.mean((np.asarray(got.status) == np.asarray(ref.status))
                & (np.asarray(got.formula_status) == np.asarray(ref.formula_status)))
    )  # fmt: skip
    r["one_call_us"] = one_call_us(jax.jit(lambda s: fn(s).u), one, calls)
    r["vmap_per_s"] = states_per_second(jax.jit(jax.vmap(lambda s: fn(s).u)), x)


def run_problem(name, filt, states, calls):
    """One problem's candidates and solvers; a JSON-ready dict."""
    from safestab.export import NativeController, native_step

    print(f"\n== {name}: {len(filt.cbfs)} CBF(s), {len(filt.clfs)} CLF(s); load "
          f"{os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip
    load_start = os.getloadavg()[0]
    x = jnp.asarray(states)
    one = [jnp.asarray(s) for s in states[:64]]
    rows, fns = {}, {}

    # each candidate is a step function (x -> FilterOutput) that a user's jit traces; the
    # first call builds it and runs the user's jitted function returning u once
    with solver_loop_in_xla():
        t = time.perf_counter()
        fns["xla_loop"] = filt.step_fn
        jax.block_until_ready(jax.jit(lambda s: fns["xla_loop"](s).u)(one[0]))
        rows["xla_loop"] = {"first_call_s": time.perf_counter() - t}
        ref = jax.jit(fns["xla_loop"])(x)

    t = time.perf_counter()
    fns["xla"] = filt.step_fn
    jax.block_until_ready(jax.jit(lambda s: fns["xla"](s).u)(one[0]))
    rows["xla"] = {"first_call_s": time.perf_counter() - t}

    t = time.perf_counter()
    fns["pure_callback"] = callback_step(NativeController(filt, name="kcb"), filt)
    jax.block_until_ready(jax.jit(lambda s: fns["pure_callback"](s).u)(one[0]))
    rows["pure_callback"] = {"first_call_s": time.perf_counter() - t}

    t = time.perf_counter()
    fns["ffi"] = ffi = native_step(filt, name="kffi")
    jax.block_until_ready(jax.jit(lambda s: ffi(s).u)(one[0]))
    rows["ffi"] = {"first_call_s": time.perf_counter() - t}

    for key, r in rows.items():
        with solver_loop_in_xla(key == "xla_loop"):
            measure(fns[key], r, x, ref, one, calls)
        print(f"  {key}: one call {r['one_call_us']:.1f} us, vmap {r['vmap_per_s']:.3g}/s, "
              f"first call {r['first_call_s']:.1f} s", flush=True)  # fmt: skip
    # the eager call a user makes from Python (its argument checks, the dispatch, the
    # output's checks) against the jitted step on the same host (NumPy) states
    host = [np.asarray(s) for s in states[:64]]
    eager = {
        "eager_step_us": one_call_us(lambda s: filt.step(s).u, host, calls),
        "jitted_step_us": one_call_us(lambda s: filt.step_fn(s).u, host, calls),
    }
    eager["ratio"] = eager["eager_step_us"] / eager["jitted_step_us"]
    print(f"  eager step {eager['eager_step_us']:.1f} us, jitted {eager['jitted_step_us']:.1f}"
          f" us: {eager['ratio']:.2f}x", flush=True)  # fmt: skip
    # the derivative: jvp of u inside a user's jit, one state
    with solver_loop_in_xla():
        _, t_ref = jax.jit(lambda x: jax.jvp(filt.step_fn, (x,), (jnp.ones_like(x),)))(x)
    _, t_ffi = jax.jvp(ffi, (x,), (jnp.ones_like(x),))
    ok = np.asarray(ref.formula_status) <= 2
    jvp_du = float(np.nanmax(np.abs(np.asarray(t_ffi.u) - np.asarray(t_ref.u))[ok]))
    jv_f = jax.jit(lambda s: jax.jvp(lambda z: ffi(z).u, (s,), (jnp.ones_like(s),)))
    jvp_us = {"ffi": one_call_us(jv_f, one, calls)}
    for key in ("xla_loop", "xla"):
        with solver_loop_in_xla(key == "xla_loop"):
            jv_x = jax.jit(
                lambda s: jax.jvp(lambda z: filt.step_fn(z).u, (s,), (jnp.ones_like(s),))
            )
            jvp_us[key] = one_call_us(jv_x, one, calls)

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
    result = {
        "name": name, "n_cbfs": len(filt.cbfs), "n_clfs": len(filt.clfs),
        "n_states_compared": len(states), "candidates": rows, "solvers_us": solvers,
        "jvp_one_call_us": jvp_us, "jvp_max_abs_du_vs_xla": jvp_du, "eager": eager,
        "load_average": [load_start, os.getloadavg()[0]],
    }  # fmt: skip
    print(problem_table(result))
    return result


def large_problem(rng):
    """The 100-disc robot under vmap: XLA's rate, and the custom call's or why it refuses."""
    from safestab.errors import ParameterError
    from safestab.export import native_step

    print(f"\n== point robot, {LARGE_DISCS} discs (vmap only)", flush=True)
    obstacles = rng.uniform(-6, 6, (LARGE_DISCS, 2))
    filt = robot_filter(obstacles)
    x = jnp.asarray(robot_states(rng, obstacles, BATCH, oversample=40))
    out = {"discs": LARGE_DISCS, "rows": LARGE_DISCS + 4, "batch": int(x.shape[0]),
           "target_per_s": LARGE_TARGET}  # fmt: skip
    with solver_loop_in_xla():
        out["xla_loop_vmap_per_s"] = states_per_second(
            jax.jit(jax.vmap(lambda s: filt.step_fn(s).u)), x
        )
    out["xla_vmap_per_s"] = states_per_second(jax.jit(jax.vmap(lambda s: filt.step_fn(s).u)), x)
    fs = np.asarray(jax.jit(jax.vmap(filt.step_fn))(x).formula_status)
    out["formula_status_shares"] = {
        ss.formulas.MultiStatus(int(v)).name: float(np.mean(fs == v)) for v in np.unique(fs)
    }
    try:
        ffi = native_step(filt, name="kffi_large")
    except ParameterError as exc:
        out["ffi_vmap_per_s"] = None
        out["ffi_refused"] = str(exc)
    else:
        out["ffi_vmap_per_s"] = states_per_second(jax.jit(jax.vmap(lambda s: ffi(s).u)), x)
        out["ffi_refused"] = None
    print(f"  xla loop vmap {out['xla_loop_vmap_per_s']:.3g}/s, xla vmap "
          f"{out['xla_vmap_per_s']:.3g}/s; ffi "
          f"{out['ffi_vmap_per_s'] or out['ffi_refused']}", flush=True)  # fmt: skip
    return out


def cached_build_s():
    """First ``native_step`` at 8 discs in a fresh process: with an empty cache, then a full one."""
    import subprocess
    import tempfile

    times = []
    with tempfile.TemporaryDirectory(prefix="safestab-kernel-cache-") as tmp:
        env = {**os.environ, "SAFESTAB_COMPILATION_CACHE": tmp}
        for _ in range(2):
            proc = subprocess.run(
                [sys.executable, __file__, "--build-child"], env=env, capture_output=True,
                text=True, check=True,
            )  # fmt: skip
            times.append(float(proc.stdout.strip().splitlines()[-1]))
        stored = len(list(Path(tmp, "native").glob("*.so")))
    return {"empty_cache_s": times[0], "from_disk_cache_s": times[1], "objects_stored": stored}


def build_child() -> None:
    """Print the seconds from nothing to the first answer of ``native_step`` at 8 discs."""
    from safestab.export import native_step

    obstacles = np.random.default_rng(0).uniform(-6, 6, (8, 2))
    t = time.perf_counter()
    step = native_step(robot_filter(obstacles), name="kffi")
    jax.block_until_ready(jax.jit(lambda s: step(s).u)(jnp.ones(2)))
    print(time.perf_counter() - t)


def bench(calls: int) -> dict:
    """Every measurement of the block, as a JSON-ready dict."""
    from _page import machine

    # first calls compile (also when run.py imported safestab, which turns the caches on;
    # the native object cache is off with the compilation cache)
    ss.disable_compilation_cache()
    rng = np.random.default_rng(0)
    results = {
        "date": time.strftime("%Y-%m-%d"), "machine": machine(),
        "settings": {"calls": calls, "rounds": 3, "batch": BATCH, "seed": 0,
                     "compilation_cache": "off (first calls compile)",
                     "one_call": "jax.jit(lambda x: step(x).u) on one state, median of the "
                                 "calls, median of the rounds",
                     "vmap": f"jax.jit(jax.vmap(lambda x: step(x).u)) over {BATCH} states, "
                             "median of 5"},
    }  # fmt: skip
    print(f"JAX {jax.__version__}, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.2f} at the start", flush=True)  # fmt: skip
    obstacles = rng.uniform(-6, 6, (8, 2))
    results["problems"] = [
        run_problem("point robot, 8 discs", robot_filter(obstacles),
                    robot_states(rng, obstacles, BATCH), calls),
        run_problem("ACC (CBF-CLF-Helper)", acc_filter(), acc_states(rng, BATCH), calls),
    ]  # fmt: skip
    results["large"] = large_problem(rng)
    results["cached_build"] = cached_build_s()
    results["load_average_at_end"] = os.getloadavg()[0]
    print(f"\nload average {results['load_average_at_end']:.2f} at the end")
    return results


def _x(a, b):
    return f"{a / b:.1f}x" if a and b else ""


def problem_table(p: dict) -> str:
    rows = p["candidates"]
    base = rows["xla_loop"]
    lines = [
        f"| {p['name']} ({p['n_cbfs']} CBF, {p['n_clfs']} CLF) | one call (us) | x loop "
        f"| vmap (/s) | x loop | first call (s) | max abs du vs loop | same statuses |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key, r in rows.items():
        lines.append(
            f"| {LABELS[key]} | {r['one_call_us']:.1f} | {_x(base['one_call_us'], r['one_call_us'])} "
            f"| {r['vmap_per_s']:.3g} | {_x(r['vmap_per_s'], base['vmap_per_s'])} "
            f"| {r['first_call_s']:.1f} | {r['max_abs_du_vs_xla']:.1e} "
            f"| {100 * r['same_status']:.0f} % |"
        )
    for key, us in p["solvers_us"].items():
        lines.append(f"| {key} (rows prebuilt, from Python) | {us:.1f} "
                     f"| {_x(base['one_call_us'], us)} | | | | | |")  # fmt: skip
    return "\n".join(lines)


def markdown(r: dict) -> str:
    """The block of docs/performance.md made of the saved results."""
    m = r["machine"]
    robot, acc = r["problems"]
    ffi, daqp = robot["candidates"]["ffi"], robot["solvers_us"].get("daqp")
    lines = [
        BEGIN,
        "## The filter inside a user's jit: the native kernel",
        "",
        "On the CPU, the filter's JAX step (`step_fn`, `filter.step`, `simulate`) runs its "
        "solver as one XLA custom call into the solver written in C (the function the C export "
        "writes, `safestab/export/_dual_qp.py`; built with the system compilers on first use "
        "and kept in the compilation cache's folder); the rows, the phases and the flags stay "
        "XLA operations. `SAFESTAB_NATIVE_SOLVER=off` runs the solver's loop in XLA instead, "
        "the baseline here, and the only path on other backends. "
        "`safestab.export.native_step(filter)` goes further: the whole exported step (rows "
        "from the state, solver, statuses) as one custom call, composing with `jax.jit` and "
        "`jax.vmap` (a batch is one loop in C), with the derivative of the optimum on the "
        "final active set (`custom_jvp`). "
        "Regenerate with `python benchmarks/run.py --only filter-kernel` (or "
        "`python benchmarks/filter_kernel.py --json docs/performance_filter_kernel.json`); "
        f"results in `docs/performance_filter_kernel.json`. Measured {r['date']} on "
        f"{m['platform']}, {m['cpus']} CPUs, JAX {m['jax']}, load average "
        f"{m['load_average_at_start']:.1f} at the start and {r['load_average_at_end']:.1f} at "
        "the end (a shared machine: ratios are within one run). *One call*: "
        f"{r['settings']['one_call']} ({r['settings']['calls']} calls, "
        f"{r['settings']['rounds']} rounds); *vmap*: {r['settings']['vmap']}; *first call*: "
        "from nothing to the first answer (export and C/C++ compilation for the native "
        "candidates, tracing and XLA compilation for each; the compilation cache off). daqp "
        "and quadprog solve the same rows, prebuilt, from Python.",
        "",
        problem_table(robot),
        "",
        problem_table(acc),
        "",
    ]
    jr, ja = robot["jvp_one_call_us"], acc["jvp_one_call_us"]
    lines.append(
        f"A `jvp` of `u` on one state costs {jr['ffi']:.0f} us with `native_step` at 8 discs "
        f"({jr['xla']:.0f} us for the JAX step, {jr['xla_loop']:.0f} us with the solver's loop "
        f"in XLA) and {ja['ffi']:.0f} us on ACC ({ja['xla']:.0f} and {ja['xla_loop']:.0f} "
        "us): the tangent (the rows' derivatives and a dense KKT solve) runs as XLA "
        "operations. Largest difference of `native_step`'s tangent of `u` to the baseline's, "
        f"solved states: {robot['jvp_max_abs_du_vs_xla']:.1e} (8 discs), "
        f"{acc['jvp_max_abs_du_vs_xla']:.1e} (ACC)."
    )
    lines.append("")
    big = r["large"]
    shares = ", ".join(f"{100 * v:.0f} % {k}" for k, v in big["formula_status_shares"].items())
    steps = (f"the JAX step {big['xla_vmap_per_s']:.3g} states/s, with the solver's loop in "
             f"XLA {big['xla_loop_vmap_per_s']:.3g}/s ({shares})")  # fmt: skip
    if big["ffi_vmap_per_s"] is not None:
        big_line = (f"`native_step` {big['ffi_vmap_per_s']:.3g} states/s (target "
                    f"{big['target_per_s']:.0e}), {steps}.")  # fmt: skip
    else:
        big_line = (
            f"{steps}; target {big['target_per_s']:.0e}; no `native_step` row: it refuses "
            f"the filter ({big['ffi_refused']}). The exported step keeps its temporaries on "
            "the stack, and the custom call runs on a thread of XLA's, whose stack safestab "
            "cannot size."
        )
    lines.append(f"Point robot, {big['discs']} discs ({big['rows']} rows), vmap over "
                 f"{big['batch']:,} states of the whole step (rows from the state by autodiff; "
                 "the filter block's *batched* column times the solver alone, on prebuilt "
                 f"rows): {big_line}")  # fmt: skip
    lines.append("")
    cb = r["cached_build"]
    lines.append(
        f"Build from the disk cache: the first call of `native_step` at 8 discs in a fresh "
        f"process took {cb['empty_cache_s']:.1f} s with an empty cache and "
        f"{cb['from_disk_cache_s']:.1f} s when an earlier process had stored the built object "
        "(loaded, no compiler run; the rest is the export's trace of the filter and XLA's "
        "compilation of the user's function)."
    )
    lines.append("")
    jx = robot["candidates"]["xla"]
    targets = []
    for label, c in (("`native_step`", ffi), ("the JAX step", jx)):
        line = f"one call at 8 discs, {label}, {c['one_call_us']:.1f} us"
        if daqp:
            line += f", {c['one_call_us'] / daqp:.2f}x daqp's {daqp:.1f} us (target at most 2x)"
        targets.append(line)
    for label, c in (("`native_step`", ffi), ("the JAX step", jx)):
        targets.append(f"vmap at 8 discs, {label}, {c['vmap_per_s']:.3g} states/s (target 1e6)")
    for p in r["problems"]:
        if "eager" in p:
            e = p["eager"]
            inside = p["candidates"]["xla"]["one_call_us"]
            targets.append(
                f"{p['name']}: `filter.step(x)` from Python (checks included) "
                f"{e['eager_step_us']:.1f} us, {e['eager_step_us'] / inside:.2f}x the call "
                f"inside a user's jit ({inside:.1f} us) and {e['ratio']:.2f}x `step_fn(x)` on "
                f"the same NumPy state ({e['jitted_step_us']:.1f} us; target at most 2x)"
            )
    lines.append("Read against the targets: " + "; ".join(targets) + ".")
    lines += ["", END]
    return "\n".join(lines)


def write_results(path: Path, results: dict) -> None:
    """``results`` as strict JSON at ``path`` (atomically); the block into a performance.md beside it."""
    import json

    from _page import update_block

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(results, indent=2, allow_nan=False) + "\n")
    tmp.replace(path)
    page = path.parent / "performance.md"
    if page.exists():
        update_block(page, path, markdown, BEGIN, END)


def update_markdown(md_path: Path, json_path: Path) -> None:
    """Rewrite the block from the saved results (``benchmarks/run.py --page``)."""
    from _page import update_block

    update_block(md_path, json_path, markdown, BEGIN, END)


def main(out: Path | None = None, calls: int = 500) -> None:
    """``benchmarks/run.py --only filter-kernel``: measure, write ``out``'s JSON and block."""
    results = bench(calls)
    if out is not None:
        write_results(out / "performance_filter_kernel.json", results)
    print(markdown(results))


def cli() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--calls", type=int, default=500)
    parser.add_argument("--json", type=Path, help="write the results here (strict JSON)")
    parser.add_argument("--build-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.build_child:
        build_child()
        return
    results = bench(args.calls)
    if args.json is not None:
        write_results(args.json, results)
    print(markdown(results))


if __name__ == "__main__":
    cli()
