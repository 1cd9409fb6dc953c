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
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import safestab as ss
from safestab.learning import FastGP, GaussianProcessModel, calibration, collect_data
from safestab.reference import solve_formula_qp
from safestab.scenarios import load_scenario
from safestab.simulation import _closed_loop

ROOT = Path(__file__).resolve().parent.parent


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
    train = data._take(np.arange(q))
    test = data._take(np.arange(q, q + n_test))
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


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--q", type=int, default=2000)
    parser.add_argument("--repeat", type=int, default=3000)
    parser.add_argument("--no-full-fit", action="store_true", help="skip the slow full-data GP fit")
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    # Monte Carlo rows (issue 13): benchmarks/mc_rows.py, also runnable on their own
    parser.add_argument("--only-mc", action="store_true", help="run only the Monte Carlo rows")
    parser.add_argument("--mc-trials", type=int, default=10_000)
    parser.add_argument("--mc-ray-trials", type=int, default=10_000, help="0 skips the Ray row")
    args = parser.parse_args()
    if args.only_mc:
        import mc_rows

        mc_rows.main(args.out, args.mc_trials, args.mc_ray_trials)
        return
    rng = np.random.default_rng(0)
    results: dict = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpus": os.cpu_count(),
            "jax": jax.__version__,
            "device": str(jax.devices()[0]),
        }
    }

    print("collecting data and fitting the GP ...", flush=True)
    sc, train, test = setup(args.q, seed=0)
    results["gp_fit"], gp = bench_fit(sc, train, test, full=not args.no_full_fit)
    fast = FastGP(gp, n_inducing=32)
    widening = fast.calibrate(test.x[:300], sc.gp_beta)
    results["fast_cache"] = {
        "n_inducing": fast.n_inducing_.tolist(),
        "widening": widening.tolist(),
        "coverage_of_exact_band_on_unseen_states": fast.coverage_of_exact_band(
            test.x[300:], sc.gp_beta
        ).tolist(),
    }

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
    fast1.calibrate(test.x[:300], sc.gp_beta)
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
    formula = jax.jit(
        lambda t: (
            ss.formulas._clf_cbf_relaxed(
                *t, sc.kappa, sc.rho, sc.phi, sc.varphi, sc.slack_weight, 1e-12
            ).u
        )
    )
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

    print("closed loop ...", flush=True)
    loop = {}
    for name, ctrl in [("fast GP controller", c_fast), ("nominal controller", c_nom)]:
        n_steps = int(round(80.0 / 0.001))
        run = jax.jit(_closed_loop(ctrl, true_sys, sc.exogenous, n_steps, 0.001))
        x0 = jnp.asarray(sc.x0)
        t0 = time.perf_counter()
        jax.block_until_ready(run(x0))
        first = time.perf_counter() - t0
        reps = []
        for _ in range(3):
            t0 = time.perf_counter()
            jax.block_until_ready(run(x0))
            reps.append(time.perf_counter() - t0)
        loop[name] = {
            "seconds_after_compile": float(np.median(reps)),
            "first_call_with_compile": first,
            "steps": n_steps,
        }
    results["closed_loop_80s_1kHz"] = loop

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "performance.json").write_text(json.dumps(results, indent=2, default=float))
    write_markdown(results, args.out / "performance.md")
    import mc_rows  # the Monte Carlo block of the last --only-mc run, kept in the page

    mc_rows.update_markdown(args.out / "performance.md", args.out / "performance_mc.json")
    print(f"wrote {args.out / 'performance.json'} and performance.md")


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
    fc = r["fast_cache"]
    lines += [
        "",
        "## Fast cache",
        "",
        f"Inducing inputs per component: {fc['n_inducing']}; measured widening factors of sigma: "
        f"{[round(w, 3) for w in fc['widening']]}; fraction of unseen held-out states where the widened "
        f"band contains the exact band: {fc['coverage_of_exact_band_on_unseen_states']}.",
        "",
    ]
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
    lines += ["## Targets", "", "| target | met | measured |", "|---|---|---:|"]
    lines += [f"| {t} | {'yes' if ok else 'NO'} | {m} |" for t, ok, m in targets]
    lines.append("")
    notes = ROOT / "benchmarks" / "NOTES.md"
    if notes.exists():
        lines += [notes.read_text()]
    path.write_text("\n".join(lines))


if __name__ == "__main__":
    main()
