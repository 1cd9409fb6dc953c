"""Speed benchmarks: closed forms vs QP solvers, exact vs cached GP, closed loop, GP fit.

Run ``bash scripts/run-benchmarks.sh`` (or ``python benchmarks/run.py``). Writes
``docs/performance.json`` and ``docs/performance.md``. Every ratio compares two numbers
measured in the same run on the same machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import safestab as ss
from safestab.learning import FastGP, GaussianProcessModel, calibration, collect_data
from safestab.reference import solve_formula_qp
from safestab.scenarios import load_scenario
from safestab.simulation import TrajectoryRecorder, closed_loop

ROOT = Path(__file__).resolve().parent.parent
#: The markers of this run's block of performance.md (the page's head, to its targets and
#: benchmarks/NOTES.md); the other blocks are their benchmarks' own.
BEGIN, END = "<!-- benchmarks:begin -->", "<!-- benchmarks:end -->"


def latency(fn, args_list, repeat):
    """Median and quartiles (microseconds) of single calls, cycling through ``args_list``."""
    for a in args_list[:5]:
        fn(a)  # warm up / compile
    times = np.empty(repeat)
    k = len(args_list)
    for i in range(repeat):
        a = args_list[i % k]
        t0 = time.perf_counter()
        fn(a)
        times[i] = time.perf_counter() - t0
    q1, med, q3 = np.percentile(times * 1e6, [25, 50, 75])
    return {"median_us": med, "q1_us": q1, "q3_us": q3, "n": repeat}


def latency_blocks(fn, args_list, repeat, block=50):
    """Like :func:`latency`, but each sample is the mean over ``block`` consecutive calls.

    Timing every call with two ``perf_counter`` reads adds 0.1 to 0.3 us on this machine,
    which is most of a microsecond-scale row; over a block it is amortised. Median and
    quartiles are over the blocks (``repeat // block`` of them, at least 20).
    """
    for a in args_list[:5]:
        fn(a)  # warm up / compile
    k = len(args_list)
    n_blocks = max(repeat // block, 20)
    times = np.empty(n_blocks)
    for b in range(n_blocks):
        args = [args_list[(b * block + j) % k] for j in range(block)]
        t0 = time.perf_counter()
        for a in args:
            fn(a)
        times[b] = (time.perf_counter() - t0) / block
    q1, med, q3 = np.percentile(times * 1e6, [25, 50, 75])
    return {"median_us": med, "q1_us": q1, "q3_us": q3, "n": n_blocks * block, "block": block}


def block(f):
    return lambda x: jax.block_until_ready(f(x))


def setup(q, seed):
    sc = load_scenario("stress")
    n_test = 600
    data = collect_data(
        sc.system("true"), sc.system("nominal"), x0=(sc.x0_low, sc.x0_high),
        u_low=-0.3, u_high=0.3, n_samples=q + n_test, rate=sc.sample_rate,
        horizon=sc.sample_horizon, noise_std=sc.noise_std, seed=seed,
    )  # fmt: skip
    train = data.take(np.arange(q))
    test = data.take(np.arange(q, q + n_test))
    return sc, train, test


def bench_fit(sc, train, test, full):
    out = {}
    omega = np.asarray(sc.omega(test.x))
    variants = [("subset 500 + condition on all", 500)] + ([("full", None)] if full else [])
    models = {}
    for name, subset in variants:
        t0 = time.perf_counter()
        gp = GaussianProcessModel(kernel=sc.kernel).fit(
            train.x, train.y, hyper_subset=subset, seed=0
        )
        dt = time.perf_counter() - t0
        cal = calibration(gp, test.x, omega, 2.0)
        out[name] = {
            "seconds": dt,
            "coverage_beta2": cal.per_component.tolist(),
            "rmse": cal.rmse.tolist(),
            "log_marginal_likelihood": gp.log_marginal_likelihood_.tolist(),
        }
        models[name] = gp
    return out, models["subset 500 + condition on all"]


C_TIMER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <time.h>
#include "NAME.h"
#include "states.h"
int main(void)
{
    double u[NAME_UPPER_N_OUT], sink = 0.0, best = 1e300;
    NAME_info info;
    for (int rep = 0; rep < 7; ++rep) {
        struct timespec a, b;
        const long n = STEPS;
        clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &a);
        for (long k = 0; k < n; ++k) {
            NAME_step(states + (k % N_REC) * NAME_UPPER_N_STATES, u, &info);
            sink += u[0];
        }
        clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &b);
        const double ns = ((double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec)) / n;
        printf("%.2f\n", ns);
        if (ns < best) best = ns;
    }
    return sink == 0.123456789 && best < 0.0;
}
"""


def c_loop_ns(ctrl, states, native_flags, steps=200_000):
    """CPU ns per step of <name>_step called in a C loop over recorded states (7 repetitions).

    Process CPU time, not wall time: on a shared machine the wall clock also counts the time
    other processes hold the CPU. ``native_flags``: the flags NativeController uses
    (``safestab.export.native.native_flags``), else the portable -O2 of the harness.
    """
    import subprocess
    import tempfile

    from safestab.export import export_c
    from safestab.export.native import find_compiler
    from safestab.export.native import native_flags as native_flags_of

    with tempfile.TemporaryDirectory() as tmp:
        ex = export_c(ctrl, "bench", tmp)
        flat = ", ".join(repr(float(v)) for v in np.asarray(states).ravel())
        Path(tmp, "states.h").write_text(
            f"#define N_REC {len(states)}\nstatic const double states[] = {{{flat}}};\n"
        )
        src = C_TIMER.replace("NAME_UPPER", "BENCH").replace("NAME", "bench")
        Path(tmp, "timer.c").write_text(src.replace("STEPS", str(steps)))
        cc = find_compiler()
        flags = (
            list(native_flags_of(cc)) if native_flags else ["-std=c99", "-O2", "-ffp-contract=off"]
        )
        exe = str(Path(tmp, "timer"))
        subprocess.run([cc, *flags, "bench.c", "timer.c", "-lm", "-o", exe], cwd=tmp, check=True)
        out = subprocess.run([exe], capture_output=True, text=True, check=False).stdout.split()
    reps = [float(v) for v in out]
    return {
        "median_ns": float(np.median(reps)),
        "min_ns": float(np.min(reps)),
        "steps": steps,
        "repetitions": len(reps),
        "flags": " ".join(flags),
        "stack_bytes": ex.stack_bytes,
    }


def bench_export(c_fast, c_nom, states_1, xb, repeat):
    """Native (exported C) controller rows: Python call, C loop, batched throughput."""
    from safestab.export import NativeController

    out = {}
    t0 = time.perf_counter()
    n_fast = NativeController(c_fast, name="acc_gp")
    out["build_seconds_gp"] = time.perf_counter() - t0
    n_nom = NativeController(c_nom, name="acc_nominal")
    out["cffi_mode"] = n_fast.function.mode
    states_np = [np.asarray(x) for x in states_1]
    lat = {}
    lat["JAX fused step (controller.input_fn), GP-robust"] = latency_blocks(
        block(c_fast.input_fn), states_1, repeat
    )
    lat["native GP-robust step from Python (NativeController.input_fn)"] = latency_blocks(
        n_fast.input_fn, states_np, repeat
    )
    lat["native GP-robust step from Python (NativeController(x))"] = latency_blocks(
        n_fast, states_np, repeat
    )
    lat["native GP-robust step() with all diagnostics"] = latency_blocks(
        n_fast.step, states_np, repeat
    )
    lat["JAX fused step (controller.input_fn), nominal"] = latency_blocks(
        block(c_nom.input_fn), states_1, repeat
    )
    lat["native nominal step from Python (NativeController.input_fn)"] = latency_blocks(
        n_nom.input_fn, states_np, repeat
    )
    out["latency"] = lat
    out["c_loop"] = {
        "GP-robust, flags of NativeController": c_loop_ns(c_fast, states_np[:200], True),
        "GP-robust, portable flags of the harness": c_loop_ns(c_fast, states_np[:200], False),
        "nominal, flags of NativeController": c_loop_ns(c_nom, states_np[:200], True),
    }
    from _page import states_per_second

    thr = {}
    xb_np = np.asarray(xb)
    for name, fn, arg in [
        ("JAX batched GP-robust step (input_fn)", c_fast.input_fn, xb),
        ("native batched GP-robust step (NativeController(x), C loop)", n_fast, xb_np),
        ("JAX batched nominal step (input_fn)", c_nom.input_fn, xb),
        ("native batched nominal step", n_nom, xb_np),
    ]:
        thr[name] = {"states_per_second": states_per_second(fn, arg), "batch": len(arg)}
    out["throughput"] = thr
    return out


GP_SCALING_Q = (2000, 6000, 10000)


def gp_scaling_worker(q):
    """One row of the fit-scaling table, run in a fresh process so its peak RSS is its own."""
    sc, train, test = setup(q, seed=0)
    t0 = time.perf_counter()
    gp = GaussianProcessModel(kernel=sc.kernel).fit(train.x, train.y, hyper_subset=500, seed=0)
    fit_s = time.perf_counter() - t0
    rss_fit = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB
    t0 = time.perf_counter()
    jax.block_until_ready(gp.predict(test.x, return_std=True))  # first call: compilation included
    first_predict_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(gp.predict(test.x, return_std=True))
    predict_s = time.perf_counter() - t0
    cal = calibration(gp, test.x, np.asarray(sc.omega(test.x)), sc.gp_beta)
    return {
        "q": q,
        "hyper_subset": 500,
        "fit_seconds": fit_s,
        "peak_rss_gib_after_fit": rss_fit,
        "first_predict_600_states_seconds": first_predict_s,
        "predict_600_states_seconds": predict_s,
        "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "n_starts": gp.n_starts_,
        "converged": gp.converged_.tolist(),
        "coverage_beta2": cal.per_component.tolist(),
        "rmse": cal.rmse.tolist(),
    }


def bench_gp_scaling(qs):
    rows = []
    for q in qs:
        print(f"  GP fit at Q = {q} (fresh process) ...", flush=True)
        out = subprocess.run(
            [sys.executable, __file__, "--gp-scaling-worker", str(q)],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return rows


def machine():
    return {
        "platform": platform.platform(),
        "processor": platform.processor(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "device": str(jax.devices()[0]),
        "load_average_at_start": os.getloadavg()[0],
    }


def main_gp_only(args):
    """Rerun only the GP fit-scaling section and merge it into the existing performance.json."""
    path = args.out / "performance.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    print("GP fit scaling ...", flush=True)
    results["gp_scaling"] = bench_gp_scaling(GP_SCALING_Q)
    results["gp_scaling_machine"] = machine()
    args.out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=2, default=float))
    write_page(results, args.out)
    print(f"wrote {path} and performance.md")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--q", type=int, default=2000)
    parser.add_argument("--repeat", type=int, default=3000)
    parser.add_argument("--no-full-fit", action="store_true", help="skip the slow full-data GP fit")
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    parser.add_argument(
        "--only", choices=("all", "gp", "export", "multi", "filter", "filter-kernel", "jax"),
        default="all",
        help="'gp': rerun only the GP fit-scaling section; 'export': only the "
        "native controller rows; each merged into the existing performance.json; 'multi': only "
        "the several-CBF rows (benchmarks/multi.py, saved to performance_multi.json); 'filter': "
        "only the safety filter's solver against daqp, quadprog, Clarabel and qpax "
        "(benchmarks/filter.py, saved to performance_filter.json); 'filter-kernel': the filter "
        "inside a user's jit, XLA against the native kernel (benchmarks/filter_kernel.py, "
        "saved to performance_filter_kernel.json); 'jax': the formulas in a "
        "user's jit and their gradients against qpax (benchmarks/jax_native.py, saved to "
        "performance_jax.json)",
    )  # fmt: skip
    parser.add_argument("--page", action="store_true",
                        help="measure nothing: rewrite performance.md from the saved results")  # fmt: skip
    parser.add_argument("--gp-scaling-worker", type=int, help=argparse.SUPPRESS)
    # Monte Carlo rows (issue 13): benchmarks/mc_rows.py, also runnable on their own
    parser.add_argument("--only-mc", action="store_true", help="run only the Monte Carlo rows")
    parser.add_argument("--mc-trials", type=int, default=10_000)
    parser.add_argument("--mc-ray-trials", type=int, default=10_000, help="0 skips the Ray row")
    args = parser.parse_args()
    if args.gp_scaling_worker is not None:
        print(json.dumps(gp_scaling_worker(args.gp_scaling_worker), default=float))
        return
    if args.page:
        write_page(json.loads((args.out / "performance.json").read_text()), args.out)
        return
    if args.only_mc:
        import mc_rows

        mc_rows.main(args.out, args.mc_trials, args.mc_ray_trials)
        return
    if args.only == "gp":
        main_gp_only(args)
        return
    if args.only == "multi":
        import multi

        multi.main(args.out)
        return
    if args.only == "filter":
        import filter as filter_rows

        filter_rows.main(args.out)
        return
    if args.only == "filter-kernel":
        import filter_kernel

        filter_kernel.main(args.out)
        return
    if args.only == "jax":
        import jax_native

        jax_native.main(args.out)
        return
    rng = np.random.default_rng(0)
    results: dict = {"machine": machine()}

    print("collecting data and fitting the GP ...", flush=True)
    sc, train, test = setup(args.q, seed=0)
    if args.only == "export":
        return run_export_only(args, sc, train, test, rng, results["machine"])
    results["gp_fit"], gp = bench_fit(sc, train, test, full=not args.no_full_fit)
    fast = FastGP(gp, n_inducing=32)

    nominal, true_sys = sc.system("nominal"), sc.system("true")
    clf, cbf = sc.certificates()
    p = dict(kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi, slack_weight=sc.slack_weight)
    c_nom = ss.UniversalController(nominal, clf, cbf, **p)
    c_exact = ss.UniversalController(nominal, clf, cbf, uncertainty=gp, gp_beta=sc.gp_beta, **p)
    c_fast = ss.UniversalController(nominal, clf, cbf, uncertainty=fast, gp_beta=sc.gp_beta, **p)
    # the ACC kinematics (v_l' = a_L, D' = v_l - v_f) are exact: learning only omega_1 is the
    # practical set-up, measured as a second configuration of the same cache
    gp1 = GaussianProcessModel(kernel=sc.kernel).fit(
        train.x, train.y, components=[0], hyper_subset=500
    )
    fast1 = FastGP(gp1, n_inducing=32)
    c_fast1 = ss.UniversalController(nominal, clf, cbf, uncertainty=fast1, gp_beta=sc.gp_beta, **p)
    states = [jnp.asarray(x) for x in test.x[:200]]

    print("single-step latency ...", flush=True)
    lat = {}
    lat["closed form, nominal terms"] = latency(block(c_nom.input_fn), states, args.repeat)
    lat["GP controller, fast cache"] = latency(block(c_fast.input_fn), states, args.repeat)
    lat["GP controller, fast cache, omega_1 only"] = latency(
        block(c_fast1.input_fn), states, args.repeat
    )
    # profile of the fast step: the dispatch floor and the cache on its own
    lat["profile: empty jitted call (dispatch floor)"] = latency(
        block(jax.jit(lambda x: 2.0 * x)), states, args.repeat
    )
    lat["profile: fast cache mean_std alone (3 GPs)"] = latency(
        block(jax.jit(fast.mean_std)), states, args.repeat
    )
    lat["GP controller, exact posterior"] = latency(
        block(c_exact.input_fn), states, max(200, args.repeat // 10)
    )
    terms_fast = jax.jit(c_fast.terms_point)

    def qp_step(solver):
        def step(x):
            a, b, c, d = (np.asarray(t) for t in terms_fast(x))
            return solve_formula_qp(float(a), b, float(c), d, solver=solver, tight=False, **p).u

        return step

    agreement = {}
    solvers = ["clarabel", "osqp"]
    try:
        import quadprog  # noqa: F401

        solvers.append("quadprog")
    except ImportError:
        pass
    for solver in solvers:
        lat[f"QP via qpsolvers: {solver}"] = latency(
            qp_step(solver), states, max(300, args.repeat // 5)
        )
        diffs = [
            np.max(np.abs(qp_step(solver)(x) - np.asarray(c_fast.input_fn(x))))
            for x in states[:100]
        ]
        agreement[solver] = float(np.max(diffs))
    try:
        import cvxpy as cp

        u_var, chi = cp.Variable(1), cp.Variable()
        pa, pb, pc, pd = cp.Parameter(), cp.Parameter(1), cp.Parameter(), cp.Parameter(1)
        prob = cp.Problem(
            cp.Minimize(0.5 * cp.sum_squares(u_var) + 0.5 * sc.slack_weight * cp.square(chi)),
            [pb @ u_var - chi <= -pa, pd @ u_var >= pc],
        )

        def cvx_step(x):
            a, b, c, d = (np.asarray(t) for t in terms_fast(x))
            A, B = ss.reference.margins_numpy(
                float(a), b, float(c), d, kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi
            )
            pa.value, pb.value, pc.value, pd.value = A, b, B, d
            prob.solve(solver=cp.CLARABEL)
            return u_var.value

        lat["QP via cvxpy (Clarabel, parametrised)"] = latency(
            cvx_step, states, max(200, args.repeat // 10)
        )
        agreement["cvxpy"] = float(
            max(np.max(np.abs(cvx_step(x) - np.asarray(c_fast.input_fn(x)))) for x in states[:50])
        )
    except Exception as exc:  # pragma: no cover - optional dependency
        lat["QP via cvxpy"] = {"error": repr(exc)}
    results["latency"] = lat
    results["qp_agreement_max_abs_u"] = agreement

    print("batched throughput ...", flush=True)
    n_batch = 1_000_000
    xb = jnp.asarray(rng.uniform(sc.x0_low, sc.x0_high, size=(n_batch, 3)))
    terms = ss.lie_terms(nominal, clf, cbf, xb)
    formula = jax.jit(  # the public formula inside the user's jit (JAX-native, issue 24)
        lambda t: ss.clf_cbf_relaxed(
            *t, kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi,
            slack_weight=sc.slack_weight,
        ).u
    )  # fmt: skip
    thr = {}
    for name, fn, arg in [
        ("closed form on precomputed nominal Lie terms", formula, terms),
        ("full nominal step (autodiff terms + formula)", c_nom.input_fn, xb),
        ("full GP step, fast cache", c_fast.input_fn, xb[:100_000]),
    ]:
        jax.block_until_ready(fn(arg))
        reps = []
        for _ in range(5):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(arg))
            reps.append(time.perf_counter() - t0)
        count = (arg[0] if isinstance(arg, tuple) else arg).shape[0]
        thr[name] = {"states_per_second": count / float(np.median(reps)), "batch": count}
    results["throughput"] = thr

    print("native (exported C) controller ...", flush=True)
    results["export"] = bench_export(c_fast, c_nom, states, xb[:100_000], args.repeat)

    print("closed loop ...", flush=True)
    loop = {}
    for name, ctrl in [("fast GP controller", c_fast), ("nominal controller", c_nom)]:
        n_steps = int(round(80.0 / 0.001))
        # simulate's loop (the full history) without its argument checks
        run = jax.jit(
            closed_loop(
                lambda t, x, data, ctrl=ctrl: ctrl.step_fn(x),
                lambda t, x, out, data: true_sys.f(x) + true_sys.g(x) @ out.u + sc.exogenous(t),
                TrajectoryRecorder(ctrl, lambda t, data: None),
                n_steps=n_steps,
                dt=0.001,
            )
        )
        x0 = jnp.asarray(sc.x0)
        t0 = time.perf_counter()
        jax.block_until_ready(run(x0, None))
        first = time.perf_counter() - t0
        reps = []
        for _ in range(3):
            t0 = time.perf_counter()
            jax.block_until_ready(run(x0, None))
            reps.append(time.perf_counter() - t0)
        loop[name] = {
            "seconds_after_compile": float(np.median(reps)),
            "first_call_with_compile": first,
            "steps": n_steps,
        }
    results["closed_loop_80s_1kHz"] = loop
    print("GP fit scaling ...", flush=True)
    results["gp_scaling"] = bench_gp_scaling(GP_SCALING_Q)
    results["gp_scaling_machine"] = results["machine"]

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "performance.json").write_text(json.dumps(results, indent=2, default=float))
    write_page(results, args.out)
    import multi  # the several-CBF rows (issue 10): cheap, so rerun with every full run

    multi.main(args.out)
    import filter as filter_rows  # the safety filter's solver against small-QP solvers

    filter_rows.main(args.out)
    print(f"wrote {args.out / 'performance.json'} and performance.md")


def run_export_only(args, sc, train, test, rng, machine):
    """``--only export``: the native rows alone, merged into the existing results."""
    gp = GaussianProcessModel(kernel=sc.kernel).fit(train.x, train.y, hyper_subset=500, seed=0)
    fast = FastGP(gp, n_inducing=32)
    nominal = sc.system("nominal")
    clf, cbf = sc.certificates()
    p = dict(kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi, slack_weight=sc.slack_weight)
    c_nom = ss.UniversalController(nominal, clf, cbf, **p)
    c_fast = ss.UniversalController(nominal, clf, cbf, uncertainty=fast, gp_beta=sc.gp_beta, **p)
    states = [jnp.asarray(x) for x in test.x[:200]]
    xb = jnp.asarray(rng.uniform(sc.x0_low, sc.x0_high, size=(100_000, 3)))
    print("native (exported C) controller ...", flush=True)
    path = args.out / "performance.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    results["export"] = bench_export(c_fast, c_nom, states, xb, args.repeat)
    results["export"]["machine"] = machine
    args.out.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(results, indent=2, default=float))
    tmp.replace(path)
    if "latency" in results:
        write_page(results, args.out)
    print(json.dumps(results["export"], indent=2, default=float))


def export_markdown(e):
    """The rows of the native (exported C) controller."""
    lat, loop, thr = e["latency"], e["c_loop"], e["throughput"]
    jax_gp = lat["JAX fused step (controller.input_fn), GP-robust"]["median_us"]
    # the target's row: input_fn, the plain function, as the JAX baseline's controller.input_fn
    nat_row = next(
        k
        for k in (
            "native GP-robust step from Python (NativeController.input_fn)",
            "native GP-robust step from Python (NativeController(x))",
        )
        if k in lat
    )
    nat_gp = lat[nat_row]["median_us"]
    lines = [
        "## Native controller (exported C, `safestab.export`)",
        "",
        "`NativeController` compiles the C99 export of the fused step (cffi "
        f"{e['cffi_mode']} mode) and calls it per state; same GP-robust ACC controller as above "
        "(fast cache, Q = 2000). Each latency sample is the mean over 50 consecutive calls "
        "(cycling over 200 held-out states; timing single calls adds the timer's 0.1 to 0.3 us), "
        "median and quartiles over the samples. Rerun these rows alone with "
        "`python benchmarks/run.py --only export`.",
    ]
    if "machine" in e:
        load = e["machine"].get("load_average_at_start", float("nan"))
        lines += [
            "",
            f"Measured on {e['machine']['platform']}, {e['machine']['cpus']} CPUs, "
            f"load average {load:.1f} at the start.",
        ]
    lines += [
        "",
        "| step | median (us) | quartiles (us) | JAX fused step / this |",
        "|---|---:|---:|---:|",
    ]
    for name, v in lat.items():
        base = (
            jax_gp
            if "GP" in name
            else lat["JAX fused step (controller.input_fn), nominal"]["median_us"]
        )
        lines.append(
            f"| {name} | {v['median_us']:.2f} | {v['q1_us']:.2f} - {v['q3_us']:.2f} | {base / v['median_us']:.1f}x |"
        )
    lines += [
        "",
        "| C function alone, in a C loop (process CPU time) | ns per step (median of 7) | best | flags |",
        "|---|---:|---:|---|",
    ]
    for name, v in loop.items():
        lines.append(f"| {name} | {v['median_ns']:.0f} | {v['min_ns']:.0f} | `{v['flags']}` |")
    lines += ["", "| batched (100,000 states) | states per second |", "|---|---:|"]
    for name, v in thr.items():
        lines.append(f"| {name} | {v['states_per_second']:.3g} |")
    loop_gp = loop["GP-robust, flags of NativeController"]["median_ns"]
    thr_nat = thr["native batched GP-robust step (NativeController(x), C loop)"][
        "states_per_second"
    ]
    thr_jax = thr["JAX batched GP-robust step (input_fn)"]["states_per_second"]
    targets = [
        (
            f"native GP-robust step from Python, median <= 2 us (`{nat_row.split('(')[-1][:-1]}`)",
            nat_gp <= 2.0,
            f"{nat_gp:.2f} us",
        ),
        (
            "native >= 10x faster than the JAX fused step",
            jax_gp / nat_gp >= 10,
            f"{jax_gp / nat_gp:.1f}x",
        ),
        ("C loop <= 1 us per GP-robust step", loop_gp <= 1000, f"{loop_gp:.0f} ns"),
        (
            "native batched throughput >= JAX batched",
            thr_nat >= thr_jax,
            f"{thr_nat / thr_jax:.2f}x",
        ),
    ]
    lines += ["", "| target (issue 9) | met | measured |", "|---|---|---:|"]
    lines += [f"| {t} | {'yes' if ok else 'NO'} | {m} |" for t, ok, m in targets]
    nom_nat = thr["native batched nominal step"]["states_per_second"]
    nom_jax = thr["JAX batched nominal step (input_fn)"]["states_per_second"]
    lines += [
        "",
        "The batched-throughput target is read for the GP-robust step, the product's "
        "controller. For the nominal step the C loop reaches "
        f"{nom_nat / nom_jax:.2f}x JAX's batched throughput: XLA evaluates that short "
        "formula for several states at once (SIMD across the batch), while the C loop "
        "goes state after state (SIMD only within a state's GP kernel rows).",
    ]
    return lines + [""]


def write_page(results, out):
    """Rewrite performance.md from ``results``, keeping the blocks that other runs measured.

    The Monte Carlo, several-CBF, filter and first-run blocks come from their own runs
    (performance_mc.json, performance_multi.json, performance_filter.json,
    performance_filter_kernel.json, performance_first_run.json, performance_sparse.json, performance_gp_step.json,
    performance_xla_flags.json) and are put back, so a partial rerun loses none.
    """
    import filter as filter_rows
    import filter_kernel
    import first_run
    import gp_step
    import mc_rows
    import multi
    import sparse_gp
    import xla_flags
    from _page import update_block

    write_markdown(results, out / "performance.md")
    mc_rows.update_markdown(out / "performance.md", out / "performance_mc.json")
    multi.update_markdown(out / "performance.md", out / "performance_multi.json")
    filter_rows.update_markdown(out / "performance.md", out / "performance_filter.json")
    filter_kernel.update_markdown(
        out / "performance.md", out / "performance_filter_kernel.json"
    )  # fmt: skip
    update_block(
        out / "performance.md", out / "performance_first_run.json", first_run.markdown,
        first_run.BEGIN, first_run.END,
    )  # fmt: skip
    update_block(
        out / "performance.md", out / "performance_sparse.json", sparse_gp.markdown,
        sparse_gp.BEGIN, sparse_gp.END,
    )  # fmt: skip
    update_block(
        out / "performance.md", out / "performance_gp_step.json", gp_step.markdown,
        gp_step.BEGIN, gp_step.END,
    )  # fmt: skip
    update_block(
        out / "performance.md", out / "performance_xla_flags.json", xla_flags.markdown,
        xla_flags.BEGIN, xla_flags.END,
    )  # fmt: skip


def write_markdown(r, path):
    lat, thr, loop, fit = r["latency"], r["throughput"], r["closed_loop_80s_1kHz"], r["gp_fit"]
    fast_med = lat["GP controller, fast cache"]["median_us"]
    lines = [
        "# Performance",
        "",
        "Measured by `bash scripts/run-benchmarks.sh` (which runs `benchmarks/run.py`); the numbers",
        "below are copied from `docs/performance.json` of the last run. Every ratio compares two",
        "figures from the same run. Single-step latencies are wall-clock times of one Python call",
        "of the jitted function, JAX dispatch included, cycling over 200 held-out ACC states.",
        "",
        f"Machine: {r['machine']['platform']}, {r['machine']['cpus']} CPUs, JAX {r['machine']['jax']} "
        f"on {r['machine']['device']}.",
        "",
        "## One control step (ACC `stress` preset, relaxed formula, GP with Q = 2000)",
        "",
        "| step | median (us) | quartiles (us) | fast cache is faster by |",
        "|---|---:|---:|---:|",
    ]
    for name, v in lat.items():
        if "error" in v:
            lines.append(f"| {name} | error: {v['error']} | | |")
            continue
        ratio = v["median_us"] / fast_med
        lines.append(
            f"| {name} | {v['median_us']:.1f} | {v['q1_us']:.1f} - {v['q3_us']:.1f} | {ratio:.1f}x |"
        )
    lines += [
        "",
        "Inputs of the QP solvers against the closed form (max |u difference|, input in units of M g): "
        + ", ".join(f"{k}: {v:.1e}" for k, v in r["qp_agreement_max_abs_u"].items())
        + " (default solver tolerances).",
        "",
        "## Batched throughput",
        "",
        "| computation | batch | states per second |",
        "|---|---:|---:|",
    ]
    for name, v in thr.items():
        lines.append(f"| {name} | {v['batch']:,} | {v['states_per_second']:.3g} |")
    lines += ["", "## 80 s ACC closed loop at 1 kHz (80,000 RK4 steps, one `lax.scan`)", "",
              "| controller | after compilation (s) | first call incl. compilation (s) |", "|---|---:|---:|"]  # fmt: skip
    for name, v in loop.items():
        lines.append(
            f"| {name} | {v['seconds_after_compile']:.3f} | {v['first_call_with_compile']:.2f} |"
        )
    lines += ["", "## GP fit, Q = 2000, n = 3 (ACC `stress` data)", "",
              "| fit | seconds | held-out coverage at beta = 2 | RMSE of omega_1 (m/s^2) |", "|---|---:|---|---:|"]  # fmt: skip
    for name, v in fit.items():
        cov = ", ".join(f"{c:.3f}" for c in v["coverage_beta2"])
        lines.append(f"| {name} | {v['seconds']:.1f} | {cov} | {v['rmse'][0]:.2e} |")
    if "gp_scaling" in r:
        gm = r["gp_scaling_machine"]
        lines += [
            "",
            "## GP fit scaling: hyperparameters from 500 rows, then conditioning on all Q",
            "",
            f"Each row runs in a fresh process (`python benchmarks/run.py --only gp` reruns this "
            f"table alone). Machine: {gm['cpus']} CPUs, load average "
            f"{gm.get('load_average_at_start', float('nan')):.1f} at the start (the machine is "
            "shared: wall times are upper bounds). Peak RSS is the process's maximum resident "
            "memory, data collection and JAX included.",
            "",
            "| Q | fit (s) | peak RSS after fit (GiB) | first predict, 600 states, incl. compile (s) "
            "| again (s) | peak RSS (GiB) | held-out coverage at beta = 2 |",
            "|---:|---:|---:|---:|---:|---:|---|",
        ]
        for row in r["gp_scaling"]:
            cov = ", ".join(f"{c:.3f}" for c in row["coverage_beta2"])
            lines.append(
                f"| {row['q']:,} | {row['fit_seconds']:.1f} | {row['peak_rss_gib_after_fit']:.2f} "
                f"| {row['first_predict_600_states_seconds']:.2f} "
                f"| {row['predict_600_states_seconds']:.2f} | {row['peak_rss_gib']:.2f} | {cov} |"
            )
    lines += [
        "",
        "## Fast cache: its band against the exact one",
        "",
        "How much wider the fast cache's proven band is than the exact GP's, and that it "
        "contains it, is measured once and shown in one place: "
        "[the learning page's tables](learning.md#how-wide-the-band-is) "
        "(every preset's own data, and the stress and obstacle Monte Carlo's first 20 data "
        "sets, near the data and ten times outside its box), which `bash "
        "scripts/reproduce-docs.sh` regenerates (steps `fast-band` and `mc-band`). This page "
        "times the cache; it does not repeat its widths.",
    ]
    lines.append("")
    fast1_med = lat["GP controller, fast cache, omega_1 only"]["median_us"]
    targets = [
        ("fast GP step median < 20 us", fast_med < 20, f"{fast_med:.1f} us"),
        ("(same, learning omega_1 only) < 20 us", fast1_med < 20, f"{fast1_med:.1f} us"),
        ("fast GP step >= 20x faster than OSQP", lat["QP via qpsolvers: osqp"]["median_us"] / fast_med >= 20,
         f"{lat['QP via qpsolvers: osqp']['median_us'] / fast_med:.0f}x"),
        ("fast GP step >= 50x faster than exact posterior", lat["GP controller, exact posterior"]["median_us"] / fast_med >= 50,
         f"{lat['GP controller, exact posterior']['median_us'] / fast_med:.0f}x"),
        ("nominal closed form batched >= 1e7 states/s",
         thr["closed form on precomputed nominal Lie terms"]["states_per_second"] >= 1e7,
         f"{thr['closed form on precomputed nominal Lie terms']['states_per_second']:.3g} /s"),
        ("80 s loop at 1 kHz with fast GP < 1 s", loop["fast GP controller"]["seconds_after_compile"] < 1.0,
         f"{loop['fast GP controller']['seconds_after_compile']:.3f} s"),
        ("GP fit at Q = 2000 < 10 s", fit["subset 500 + condition on all"]["seconds"] < 10.0,
         f"{fit['subset 500 + condition on all']['seconds']:.1f} s"),
    ]  # fmt: skip
    if "export" in r:
        lines += export_markdown(r["export"])
    lines += ["## Targets", "", "| target | met | measured |", "|---|---|---:|"]
    lines += [f"| {t} | {'yes' if ok else 'NO'} | {m} |" for t, ok, m in targets]
    lines.append("")
    notes = ROOT / "benchmarks" / "NOTES.md"
    if notes.exists():
        lines += [notes.read_text()]
    # only this run's block: the page's other blocks and the prose around them stay (the
    # whole page was rewritten, and the paragraphs written beside the other blocks lost)
    from _page import put_block

    body = "\n".join(lines).rstrip("\n")
    put_block(path, f"{BEGIN}\n{body}\n{END}", BEGIN, END)


if __name__ == "__main__":
    main()
