"""The exported steps on microcontrollers (QEMU), and the float variant's safety.

    python benchmarks/embedded.py          # about 5 minutes on 2 cores

writes docs/embedded.json and the table block of docs/export.md ("On a microcontroller").
Needs arm-none-eabi-gcc, libnewlib-arm-none-eabi and qemu-system-arm (installed with apt-get
where this process may; else the error names them).

Rows: the GP-robust ACC controller (presets paper and stress) and the obstacle scenario's
GP-robust controller on a Cortex-M4F (float) and a Cortex-M7 (double), the stress preset's
nominal controller in float, and a safety filter (a point robot among 8 discs, a CLF, input
limits) on the M7 in double and on the M4F in double and in float (``float_safe_controller``:
float's tolerances and the CBF margin). Each row: the harness under QEMU against the JAX step,
bit agreement with the host build of the same C, flash, RAM, stack (static call graph and
measured), instructions per step. Then the float variant: its error against the float64
step (relative to the harness's scales) on the recorded and on extreme states, and how often
its cbf_satisfied flag says 1 where the exact condition is violated, with and without the
margin.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _page import machine, put_block  # noqa: E402

BEGIN, END = "<!-- embedded:begin -->", "<!-- embedded:end -->"
BUDGET = 168_000  # instructions in 1 ms at 168 MHz (one instruction per cycle at best)


def robot_filter(n_obstacles: int = 8, seed: int = 0):
    """A point robot among discs with a CLF to the origin and |u_i| <= 1 (SafetyFilter)."""
    import jax.numpy as jnp

    import safestab as ss

    rng = np.random.default_rng(seed)
    obstacles = rng.uniform(-6, 6, (n_obstacles, 2))
    system = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2, name="robot")
    cbfs = [ss.CBF(lambda x, o=o: jnp.sum((x - o) ** 2) - 1.0, beta=1.0) for o in obstacles]
    clf = ss.CLF(lambda x: jnp.sum(x**2), lam=0.5)
    filt = ss.SafetyFilter(system, cbfs, clfs=clf, u_nom=lambda x: -x, u_min=-1.0, u_max=1.0)
    return filt, rng.uniform(-6, 6, (256, 2))


def scenario_row(scenario, controller, target, out):
    from safestab.scenarios.export_study import export_scenario

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rep = export_scenario(scenario, out, controller=controller, target=target)
    row = {"problem": f"{scenario} preset, {controller} controller", **rep.embedded.row()}
    row["host_harness_passed"] = bool(rep.passed)
    row["notes"] = list(rep.notes)  # the build in double where float cannot carry the GP
    row["seconds"] = time.perf_counter() - t0
    return row


def filter_row(target, out, precision=None):
    from safestab.export.embedded import export_for_target

    filt, states = robot_filter()
    t0 = time.perf_counter()
    if precision == "float":  # float's tolerances and the CBF margin, over the scene's box
        from safestab.export.float_safety import float_safe_controller

        filt, _ = float_safe_controller(filt, [-6.0, -6.0], [6.0, 6.0], extra_states=states)
    rep = export_for_target(filt, "robot", out, states, target, precision=precision)
    row = {"problem": "safety filter: robot, 8 discs, CLF, limits", **rep.row()}
    row["seconds"] = time.perf_counter() - t0
    return row


def float_safety(scenario, which):
    """Float step against float64: errors on the recorded and extreme states, false flags."""
    import safestab as ss
    from safestab.export import NativeController
    from safestab.export.float_safety import box_test_states, float_safe_controller
    from safestab.export.harness import comparison_scales
    from safestab.scenarios.export_study import scenario_controller
    from safestab.scenarios.loading import load

    sc = load(scenario)
    exact, *_ = scenario_controller(sc, which)
    rng = np.random.default_rng(sc.seed)
    recorded = rng.uniform(sc.x0_low, sc.x0_high, (256, len(sc.x0_low)))
    recorded = recorded.astype(np.float32).astype(np.float64)
    ctrl_f, margin = float_safe_controller(exact, sc.x0_low, sc.x0_high, extra_states=recorded)
    p = {k: float(exact.params[k]) for k in ("kappa", "rho", "phi", "varphi")}
    row = {"scenario": scenario, "controller": which, "cbf_margin": margin}
    for label, ctrl in (("without_margin", exact), ("with_margin", ctrl_f)):
        native = NativeController(ctrl, name=f"fs_{label}", precision="float")
        extreme = box_test_states(sc.x0_low, sc.x0_high)
        for states_label, x in (("recorded", recorded), ("extreme", extreme)):
            got = native.step(x)
            u_f = np.asarray(got.u, np.float64)
            ok = np.asarray(got.status) == 0
            terms = exact.step_fn(x).terms
            flags = ss.conditions_satisfied(*terms, np.where(ok[:, None], u_f, 0.0), **p)
            lies = np.asarray(got.cbf_satisfied) & ok & ~np.asarray(flags.cbf_satisfied)
            row[f"false_flags_{label}_{states_label}"] = int(lies.sum())
            row[f"states_{states_label}"] = len(x)
            if label == "with_margin":
                ref = ctrl.step_fn(x)
                scale = comparison_scales(ctrl, ref, x)[0]
                err = np.abs(u_f - np.asarray(ref.u)) / (np.abs(np.asarray(ref.u)) + scale)
                row[f"u_error_{states_label}"] = float(np.nanmax(err))
    return row


def cache_accuracy(n: int = 48) -> dict:
    """The stress GP cache's std at n states: XLA (batched, single state) and the exported C
    against a 60-digit evaluation of the same cache arrays (mpmath), for the drag component."""
    import mpmath as mp

    from safestab.export import compile_native, export_function
    from safestab.learning import FastGP
    from safestab.scenarios import load_scenario
    from safestab.scenarios.acc_study import collect_study_data, fit_study_gp

    sc = load_scenario("stress")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        train, _ = collect_study_data(sc, seed=sc.seed)
        fast = FastGP(fit_study_gp(sc, train, seed=sc.seed), 32)
    p = fast.arrays()
    x = np.random.default_rng(sc.seed).uniform(sc.x0_low, sc.x0_high, (n, 3))
    mp.mp.dps = 60
    j, m = 0, int(fast.n_inducing_[0])

    def exact(xs):  # learning._posterior.band_component's proven std, in 60 digits
        f = lambda key, *i: mp.mpf(float(p[key][(j, *i)]))  # noqa: E731
        z0 = [(mp.mpf(xs[i]) - mp.mpf(p["offset"][i])) / mp.mpf(p["scale"][i]) for i in range(3)]
        a, mm, u = f("amp"), p["z"].shape[1], mp.mpf(2) ** -53
        amp2, ek = a * a, f("ek")
        k = [amp2 * mp.exp(-sum(((z0[i] - f("z", c, i)) / f("ls", i)) ** 2
                                for i in range(3)) / 2) for c in range(m)]  # fmt: skip

        def mat(key, v):
            return [mp.fsum(f(key, r, c) * v[c] for c in range(m)) for r in range(m)]

        def dot(v, w):
            return mp.fsum(x_ * y_ for x_, y_ in zip(v, w, strict=True))

        lt = [[f("li", c, r) for c in range(m)] for r in range(m)]  # Lj^-T, row by row
        c = [mp.fsum(lt[r][i] * t for i, t in enumerate(mat("li", k))) for r in range(m)]
        kc = mat("kzz", c)
        c1, c2 = mp.fsum(abs(t) for t in c), mp.sqrt(dot(c, c))
        dot_u = (mm + 3) * u
        q = amp2 - 2 * dot(c, k) + dot(c, kc)
        r = mp.sqrt(max(q, 0) + amp2 * (1 + c1) ** 2 * (2 * dot_u + 2 * ek * u + 3 * u))
        gc = mat("g", c)
        pp = mp.sqrt(dot(gc, gc)) + (dot_u + u) * f("gnorm") * c2
        res = [k[i] - kc[i] for i in range(m)]
        res_n = mp.sqrt(dot(res, res)) + mp.sqrt(mm) * amp2 * (1 + c1) * (dot_u + (ek + 1) * u)
        cmc = mat("cm", c)
        gam = mp.sqrt(dot(cmc, cmc)) + (dot_u + u) * f("cnorm") * c2
        cross = 2 * (c2 * res_n + gam * (f("rho") * r + f("wnorm") * res_n))
        sd = mp.sqrt(pp * pp + r * r + min(2 * pp * r, cross)) * (1 + 4 * u)
        abs_b_k = mp.fsum(abs(f("b", i)) * k[i] for i in range(m))
        abs_c_rho = mp.fsum(abs(c[i]) * abs(f("rho_b", i)) for i in range(m))
        bn = f("bnorm")
        mround = (
            dot_u * (abs(f("mu")) + abs_b_k + abs_c_rho)
            + u * (ek * amp2 * bn + abs_c_rho + amp2 * c1 * bn)
            + c1 * f("rho_err")
        )
        e_w = f("err") + u * a * bn
        return float(sd + (e_w * r + mround) / fast.min_beta)

    ref = np.array([exact(s) for s in x])
    _, batched = fast.predict(x, return_std=True)
    single = np.stack([np.asarray(fast.mean_std(s)[1]) for s in x])
    native = compile_native(export_function(fast.mean_std, 3, "cache"))
    (_, c_std), _ = native.columns(np.ascontiguousarray(x))
    rel = lambda v: float(np.max(np.abs(np.asarray(v)[:, 0] - ref) / ref))  # noqa: E731
    return {"states": n, "xla_batched": rel(batched), "xla_single": rel(single),
            "c": rel(c_std)}  # fmt: skip


def markdown(res: dict) -> str:
    lines = [
        BEGIN,
        "",
        f"Measured by `python benchmarks/embedded.py` ({res['when']}; QEMU "
        f"{res['qemu']}, {res['gcc']}). Sizes in bytes; instructions per step are QEMU's "
        "count (`-icount`), max and median over the 256 recorded states; headroom is "
        f"{BUDGET:,} (1 ms at 168 MHz) over the max.",
        "",
        "| step | core | precision | harness vs JAX | bits = host | step code | firmware "
        "flash | static RAM | stack (static / measured) | instructions (max / median) | "
        "headroom at 168 MHz, 1 kHz |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        if "refused" in r:
            lines.append(f"| {r['problem']} | {r['target']} | {r['precision']} | refused: "
                         f"{r['refused']} | | | | | | | |")  # fmt: skip
            continue
        precision = r["precision"] + (
            " (float cannot carry its GP cache)" if r.get("notes") else ""
        )
        lines.append(
            f"| {r['problem']} | {r['target']} | {precision} | "
            f"{r['harness_mismatches']} mismatches / {r['states']} | "
            f"{r['bit_identical_to_host']} / {r['states']} | {r['step_text']:,} | "
            f"{r['firmware_flash']:,} | {r['firmware_ram']:,} | "
            f"{r['stack_static']:,} / {r['stack_measured']:,} | "
            f"{r['instructions_max']:,} / {r['instructions_median']:,} | "
            f"{BUDGET / r['instructions_max']:.1f}x |"
        )
    lines += [
        "",
        "The float variant against the float64 step (largest `|u_f - u| / (|u| + scale)`, the "
        "harness's measure; its tolerance is 1e-5) and its `cbf_satisfied` flags that claim a "
        "condition the exact step finds violated, without and with the CBF margin "
        "(recorded states / extreme states: the box, its corners and faces):",
        "",
        "| scenario | controller | CBF margin | u error (recorded / extreme) | false flags "
        "without margin | false flags with margin |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["float_safety"]:
        lines.append(
            f"| {r['scenario']} | {r['controller']} | {r['cbf_margin']:.3g} | "
            f"{r['u_error_recorded']:.2g} / {r['u_error_extreme']:.2g} | "
            f"{r['false_flags_without_margin_recorded']} / "
            f"{r['false_flags_without_margin_extreme']} of {r['states_recorded']} / "
            f"{r['states_extreme']} | {r['false_flags_with_margin_recorded']} / "
            f"{r['false_flags_with_margin_extreme']} |"
        )
    acc = res["cache_accuracy"]
    lines += [
        "",
        f"Cache accuracy (stress preset's GP cache, drag component, {acc['states']} states): "
        "largest relative error of the std against a 60-digit evaluation of the same cache: "
        f"XLA batched {acc['xla_batched']:.2g}, XLA single state {acc['xla_single']:.2g}, "
        f"exported C {acc['c']:.2g}.",
        "",
        END,
    ]
    return "\n".join(lines)


def main() -> None:
    import subprocess

    from safestab.errors import ParameterError
    from safestab.export.embedded import find_toolchain

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    parser.add_argument("--build", type=Path, default=ROOT / "build" / "embedded")
    args = parser.parse_args()
    tools = find_toolchain()
    qemu = subprocess.run([tools["qemu"], "--version"], capture_output=True, text=True)
    gcc = subprocess.run([tools["gcc"], "--version"], capture_output=True, text=True)
    res: dict = {
        "when": time.strftime("%Y-%m-%d"),
        "qemu": qemu.stdout.split("\n")[0].split("version")[-1].strip(),
        "gcc": gcc.stdout.split("\n")[0],
        "machine": machine(),
        "rows": [],
        "float_safety": [],
    }
    for scenario, controller, target in [
        ("paper", "gp", "cortex-m4"),
        ("paper", "gp", "cortex-m7"),
        ("stress", "gp", "cortex-m4"),
        ("stress", "gp", "cortex-m7"),
        ("stress", "nominal", "cortex-m4"),
        ("obstacle", "gp", "cortex-m4"),
        ("obstacle", "gp", "cortex-m7"),
    ]:
        out = args.build / f"{scenario}_{controller}_{target}"
        try:
            row = scenario_row(scenario, controller, target, out)
        except ParameterError as exc:
            row = {"problem": f"{scenario} preset, {controller} controller", "target": target,
                   "precision": "float", "refused": str(exc).split(":")[0]}  # fmt: skip
        print(json.dumps({k: v for k, v in row.items() if k != "flags"}), flush=True)
        res["rows"].append(row)
    for target, precision in (("cortex-m7", None), ("cortex-m4", "double"), ("cortex-m4", "float")):
        row = filter_row(target, args.build / f"filter_{target}", precision)
        print(json.dumps({k: v for k, v in row.items() if k != "flags"}), flush=True)
        res["rows"].append(row)
    for scenario in ("paper", "stress", "obstacle"):
        for which in ("nominal", "true"):
            row = float_safety(scenario, which)
            print(json.dumps(row), flush=True)
            res["float_safety"].append(row)
    res["cache_accuracy"] = cache_accuracy()
    print(json.dumps(res["cache_accuracy"]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "embedded.json"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(res, indent=2, allow_nan=False))
    tmp.replace(path)
    put_block(args.out / "export.md", markdown(res), BEGIN, END)
    print(markdown(res))


if __name__ == "__main__":
    main()
