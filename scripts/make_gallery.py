"""Make the figures of docs/gallery/ from real runs of safestab.

Usage (from the repository root, with safestab installed or ``PYTHONPATH=src``)::

    python scripts/make_gallery.py                    # every figure (about 3 minutes on 2 cores)
    python scripts/make_gallery.py --only regions     # some of them
    bash scripts/make-gallery.sh                      # the same, in a fresh .venv

Every figure is computed here by the package's public API; the two ACC figures are the
output of the ``safestab acc`` command itself. The script also writes
``docs/gallery/manifest.json``: for each figure, its file, the command that made it, the
seconds it took and the package version, which docs/gallery.md and the tests rely on.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import safestab as ss  # noqa: E402
from safestab.controller_names import NameMap  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
GALLERY = ROOT / "docs" / "gallery"
DPI = 120
REGION_COLOURS = {
    ss.Region.INCOMPATIBLE: "#d62728",
    ss.Region.P1: "#9ecae1",
    ss.Region.P2: "#fdae6b",
    ss.Region.P3: "#a1d99b",
    ss.Region.P4: "#f0f0f0",
}


def _save(fig, path: Path) -> None:
    fig.savefig(path, dpi=DPI, metadata={"Software": None})  # no version stamp: stable files
    plt.close(fig)


# -- the ACC study, through the command line --------------------------------------------------


#: Where the ACC runs keep their result files (``--results``); a temporary folder if None.
RESULTS: Path | None = None


def _acc(scenario: str, out: Path) -> dict:
    """Run ``safestab acc --scenario SCENARIO`` and keep its PNG and headline metrics."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = RESULTS or Path(tmp)
        cmd = [sys.executable, "-m", "safestab.cli", "acc", "--scenario", scenario, "--out",
               str(folder)]  # fmt: skip
        env = dict(os.environ, COLUMNS="120")
        subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
        shutil.copyfile(folder / f"acc_{scenario}.png", out / f"acc_{scenario}.png")
        metrics = json.loads((folder / f"acc_{scenario}_metrics.json").read_text())
    controllers = NameMap(metrics["controllers"], where="acc metrics")  # old names renamed
    mins = {name: round(m["min_h_m"], 3) for name, m in controllers.items()}
    return {"command": f"safestab acc --scenario {scenario} --out DIR", "min_h_m": mins}


def acc_paper(out: Path) -> dict:
    """Fig. 4 with the paper's printed parameters."""
    return _acc("paper", out)


def acc_stress(out: Path) -> dict:
    """Fig. 4 for the stress preset, where the three controllers differ."""
    return _acc("stress", out)


# -- the formulas on raw Lie terms ------------------------------------------------------------


def formulas(out: Path) -> dict:
    """Sontag's CLF formula against the QP's least-norm input, and the CBF formula."""
    s = np.linspace(-3.0, 3.0, 601)
    one = np.ones((s.size, 1))
    fig, (ax_v, ax_h) = plt.subplots(1, 2, figsize=(9, 3.4), constrained_layout=True)
    for kappa, colour in ((0.2, "tab:blue"), (1.0, "tab:orange"), (2.0, "tab:green")):
        u = ss.clf_sontag(s, one, kappa=kappa, phi=1.0).u[:, 0]
        # The CLF-only QP: a CBF condition that every input meets (c = 10 >= rho Gamma, d = 0).
        qp = ss.clf_cbf(
            s, one, np.full(s.size, 10.0), 0 * one, kappa=kappa, rho=0.0, phi=1.0, varphi=1.0
        ).u[:, 0]
        ax_v.plot(s, u, color=colour, label=f"Sontag, kappa = {kappa}")
        ax_v.plot(s, qp, color=colour, ls="--", lw=1, label=f"QP optimum, kappa = {kappa}")
    ax_v.set(
        xlabel="a = L_f V + lambda V",
        ylabel="u  (b = 1)",
        title="CLF: eq. (3) and the least-norm input",
    )
    ax_v.legend(fontsize=7)
    for rho, colour in ((0.0, "tab:blue"), (0.5, "tab:orange"), (1.0, "tab:green")):
        u = ss.cbf_universal(s, one, rho=rho, varphi=1.0).u[:, 0]
        ax_h.plot(s, u, color=colour, label=f"rho = {rho}")
    ax_h.axhline(0, color="0.6", lw=0.8)
    ax_h.set(xlabel="c = L_f h + beta h", ylabel="u  (d = 1)", title="CBF: eq. (6)")
    ax_h.legend(fontsize=7)
    _save(fig, out / "formulas.png")
    return {"command": "ss.clf_sontag, ss.clf_cbf, ss.cbf_universal on a line of terms"}


def qp_geometry(out: Path) -> dict:
    """The combined formula as the least-norm point of two half-planes, one case per panel."""
    cases = {  # (a, b, c, d) with two inputs, chosen to land in each region
        "P1": (1.0, [1.0, 0.5], 2.0, [0.0, 1.0]),
        "P2": (-3.0, [1.0, 0.0], -1.0, [0.3, 1.0]),
        "P3": (1.0, [1.0, 0.2], -1.0, [0.5, 1.0]),
        "P4": (-3.0, [1.0, 0.0], 2.0, [0.0, 1.0]),
    }
    params = dict(kappa=0.5, rho=0.2, phi=0.1, varphi=0.1)
    grid = np.linspace(-3.0, 3.0, 301)
    u1, u2 = np.meshgrid(grid, grid)
    fig, axes = plt.subplots(1, 4, figsize=(12, 3.3), constrained_layout=True)
    for ax, (name, (a, b, c, d)) in zip(axes, cases.items(), strict=True):
        b, d = np.asarray(b), np.asarray(d)
        res = ss.clf_cbf(a, b, c, d, **params)
        zeta = np.sqrt(a**2 + params["phi"] * (b @ b) ** 2)
        gamma = np.sqrt(c**2 + params["varphi"] * (d @ d) ** 2)
        clf_ok = a + b[0] * u1 + b[1] * u2 <= -params["kappa"] * zeta
        cbf_ok = c + d[0] * u1 + d[1] * u2 >= params["rho"] * gamma
        ax.contourf(u1, u2, clf_ok.astype(float), levels=[0.5, 1.5], colors=["tab:blue"], alpha=0.2)
        ax.contourf(
            u1, u2, cbf_ok.astype(float), levels=[0.5, 1.5], colors=["tab:orange"], alpha=0.2
        )
        ax.contour(
            u1, u2, (clf_ok & cbf_ok).astype(float), levels=[0.5], colors="k", linewidths=0.8
        )
        u = np.asarray(res.u)
        ax.plot(*u, "ko", ms=5)
        ax.plot(0, 0, "k+", ms=8)
        ax.set_title(f"{ss.Region(int(res.region)).name}: u = ({u[0]:.2f}, {u[1]:.2f})", fontsize=9)
        ax.set(xlabel="$u_1$", aspect="equal", xlim=(-3, 3), ylim=(-3, 3))
    axes[0].set_ylabel("$u_2$")
    fig.suptitle(
        "clf_cbf: least-norm input (dot) in CLF half-plane (blue) and CBF half-plane "
        "(orange); black outline: both",
        fontsize=9,
    )
    _save(fig, out / "qp_geometry.png")
    return {"command": "ss.clf_cbf on four hand-picked (a, b, c, d)"}


# -- a system: regions over the state space, closed loops -------------------------------------


def _pendulum():
    system = ss.ControlAffineSystem(
        f=lambda x: jnp.array([x[1], -jnp.sin(x[0])]),
        g=lambda x: jnp.array([[0.0], [1.0]]),
        n_states=2,
        name="pendulum",
    )
    clf = ss.CLF(lambda x: x @ x, lam=1.0)
    cbf = ss.CBF(lambda x: 1.0 - x[0] ** 2 - 0.5 * x[1] ** 2, beta=2.0)
    return system, clf, cbf


def regions(out: Path) -> dict:
    """Regions of the combined and the relaxed formula over a grid of pendulum states."""
    system, clf, cbf = _pendulum()
    params = dict(kappa=0.5, rho=0.2, phi=1.0, varphi=0.5)
    axis = np.linspace(-1.6, 1.6, 241)
    x0, x1 = np.meshgrid(axis, axis)
    terms = ss.lie_terms(system, clf, cbf, np.stack([x0, x1], -1))  # batch shape (241, 241)
    hard = np.asarray(ss.clf_cbf(*terms, **params).region)
    relaxed = np.asarray(ss.clf_cbf_relaxed(*terms, slack_weight=10.0, **params).region)
    h = np.asarray(cbf.value(np.stack([x0, x1], -1)))

    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.patches import Patch

    fig, axes = plt.subplots(1, 2, figsize=(9.5, 4.4), constrained_layout=True)
    cmap = ListedColormap([REGION_COLOURS[r] for r in ss.Region])
    norm = BoundaryNorm(np.arange(len(ss.Region) + 1) - 0.5, len(ss.Region))
    for ax, reg, title in (
        (axes[0], hard, "clf_cbf (Theorem 1)"),
        (axes[1], relaxed, "clf_cbf_relaxed, m = 10 (Theorem 3)"),
    ):
        ax.pcolormesh(x0, x1, reg, cmap=cmap, norm=norm, shading="auto")
        ax.set_title(title, fontsize=10)
    axes[1].legend(
        handles=[Patch(color=REGION_COLOURS[r], label=r.name) for r in ss.Region],
        fontsize=7,
        loc="lower right",
    )
    for ax in axes:
        ax.contour(x0, x1, h, levels=[0.0], colors="k", linewidths=1.2)
        ax.set(xlabel="angle x_0 (rad)", aspect="equal")
    axes[0].set_ylabel("angular velocity x_1 (rad/s)")
    fig.suptitle("Pendulum, V = |x|^2, h = 1 - x_0^2 - x_1^2/2 (black: h = 0)", fontsize=10)
    _save(fig, out / "regions.png")
    fractions = {r.name: round(float(np.mean(hard == r)), 4) for r in ss.Region}
    return {
        "command": "ss.lie_terms, ss.clf_cbf, ss.clf_cbf_relaxed on a 241 x 241 grid",
        "hard_region_fractions": fractions,
    }


def compatibility_acc(out: Path) -> dict:
    """Lemma 1's cases over (v_f, D) for the ACC stress preset's nominal model."""
    from matplotlib.patches import Patch

    from safestab.scenarios import load_scenario

    sc = load_scenario("stress")
    system = sc.system("nominal")
    clf, cbf = sc.certificates()
    vf, gap = np.meshgrid(np.linspace(5.0, 35.0, 301), np.linspace(0.0, 80.0, 321))
    x = np.stack([vf, np.full_like(vf, sc.v_l0), gap], -1)  # lead speed fixed at v_l0
    terms = ss.lie_terms(system, clf, cbf, x)
    case = np.asarray(
        ss.compatibility(*terms, kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi).case
    )
    cases = sorted(set(case.ravel().tolist()))
    colours = {
        -1: "#d62728",
        1: "#bdbdbd",
        2: "#9ecae1",
        3: "#fdae6b",
        4: "#a1d99b",
        5: "#c7e9c0",
        -2: "#67000d",
        -3: "#7f2704",
    }
    index = np.searchsorted(cases, case)
    from matplotlib.colors import ListedColormap

    fig, ax = plt.subplots(figsize=(6.5, 4.2), constrained_layout=True)
    ax.pcolormesh(
        vf,
        gap,
        index,
        cmap=ListedColormap([colours[c] for c in cases]),
        vmin=-0.5,
        vmax=len(cases) - 0.5,
        shading="auto",
    )
    ax.plot(vf[0], sc.tau * vf[0], "k-", lw=1.2, label="h = 0 (D = tau v_f)")
    ax.axvline(sc.v_d, color="k", ls=":", lw=1, label="v_f = v_d")
    handles = [Patch(color=colours[c], label=ss.CompatibilityCase(c).name) for c in cases]
    ax.legend(handles=handles + ax.get_legend_handles_labels()[0], fontsize=7, loc="upper left")
    ax.set(
        xlabel="follower speed v_f (m/s)",
        ylabel="gap D (m)",
        ylim=(0, 80),
        title=f"ACC stress preset: compatibility of the hard conditions (v_l = {sc.v_l0} m/s)",
    )
    ax.title.set_fontsize(9)
    _save(fig, out / "compatibility_acc.png")
    incompatible = float(np.mean(case < 0))
    return {
        "command": "ss.lie_terms, ss.compatibility on a 301 x 321 grid of the stress "
        "preset's nominal model",
        "incompatible_fraction": round(incompatible, 4),
    }


def robot(out: Path) -> dict:
    """Closed loops of the getting-started robot from a fan of initial states (one vmap)."""
    robot_sys = ss.ControlAffineSystem(
        f=lambda x: jnp.zeros(2), g=lambda x: jnp.eye(2), n_states=2, name="robot"
    )
    centre, radius = np.array([-1.5, 0.0]), 0.5
    clf = ss.CLF(lambda x: x @ x, lam=1.0)
    cbf = ss.CBF(lambda x: (x - centre) @ (x - centre) - radius**2, beta=1.0)
    ctrl = ss.UniversalController(
        robot_sys, clf, cbf, kappa=0.2, rho=0.1, phi=0.01, varphi=0.01, slack_weight=10.0
    )
    angles = np.linspace(-0.6, 0.6, 13)
    x0 = np.stack([-3.0 * np.cos(angles), 3.0 * np.sin(angles)], -1)  # (13, 2)
    traj = ss.simulate(ctrl, x0, t_final=10.0, dt=0.01)
    x, h = np.asarray(traj.x), np.asarray(traj.h)
    fig, (ax, ax_h) = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    ax.add_patch(plt.Circle(centre, radius, color="0.7"))
    for k in range(len(x0)):
        ax.plot(x[k, :, 0], x[k, :, 1], lw=1)
        ax_h.plot(np.asarray(traj.t), h[k], lw=1)
    ax.plot(0, 0, "k*", ms=10)
    ax.set(xlabel="x_0", ylabel="x_1", aspect="equal", title="13 closed loops (one vmap)")
    ax_h.axhline(0, color="0.5", lw=0.8)
    ax_h.set(xlabel="time (s)", ylabel="h = |x - c|^2 - r^2", title="barrier value")
    _save(fig, out / "robot.png")
    return {
        "command": "ss.simulate(ctrl, x0) with x0 of shape (13, 2)",
        "min_h": round(float(h.min()), 4),
    }


def gp_band(out: Path) -> dict:
    """A GP's band around the true model error, from the learning tutorial's cart."""
    from safestab.learning import GaussianProcessModel, collect_data

    k_model, k_true = 0.5, 0.05

    def omega(x):
        return jnp.array([0.0, (k_model - k_true) * x[1] - 0.2 * jnp.sin(2.0 * x[0])])

    model = ss.ControlAffineSystem(
        lambda x: jnp.array([x[1], -k_model * x[1]]),
        lambda x: jnp.array([[0.0], [1.0]]),
        n_states=2,
    )
    true_cart = model.with_disturbance(omega)
    data = collect_data(
        true_cart,
        model,
        x0=([-3.0, -1.0], [0.5, 3.0]),
        u_low=-1.0,
        u_high=1.0,
        n_samples=240,
        horizon=3.0,
        noise_std=0.01,
        seed=0,
    )
    gp = GaussianProcessModel(kernel="se").fit(data.x, data.y, components=[1])
    lo, hi = data.x.min(0), data.x.max(0)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4), constrained_layout=True)
    slices = (
        (0, np.linspace(lo[0] - 3, hi[0] + 3, 400), 1.0, "position p (m)", "v = 1 m/s"),
        (1, np.linspace(lo[1] - 3, hi[1] + 3, 400), -1.0, "velocity v (m/s)", "p = -1 m"),
    )
    for ax, (axis, s, fixed, label, where) in zip(axes, slices, strict=True):
        xs = np.stack([s, np.full_like(s, fixed)] if axis == 0 else [np.full_like(s, fixed), s], -1)
        mean, sd = (a[:, 1] for a in gp.predict(xs, return_std=True))
        truth = np.asarray(jax.vmap(omega)(jnp.asarray(xs)))[:, 1]
        ax.fill_between(
            s, mean - 2 * sd, mean + 2 * sd, color="tab:blue", alpha=0.25, label="mean +- 2 sigma"
        )
        ax.plot(s, mean, color="tab:blue", label="GP mean")
        ax.plot(s, truth, "k--", lw=1, label="true omega_1")
        ax.axvspan(lo[axis], hi[axis], color="0.92", zorder=0, label="range of the data")
        ax.set(xlabel=label, ylabel="omega_1 (m/s^2)", title=f"slice at {where}")
        ax.legend(fontsize=7)
    _save(fig, out / "gp_band.png")
    return {
        "command": "collect_data(..., n_samples=240, horizon=3.0), GaussianProcessModel().fit, "
        "gp.predict on two slices"
    }


FIGURES: dict[str, tuple[str, Callable[[Path], dict]]] = {
    "formulas": ("formulas.png", formulas),
    "qp_geometry": ("qp_geometry.png", qp_geometry),
    "regions": ("regions.png", regions),
    "compatibility_acc": ("compatibility_acc.png", compatibility_acc),
    "robot": ("robot.png", robot),
    "gp_band": ("gp_band.png", gp_band),
    "acc_paper": ("acc_paper.png", acc_paper),
    "acc_stress": ("acc_stress.png", acc_stress),
}


def main(argv: list[str] | None = None) -> int:
    """Make the figures named by ``--only`` (default: all) and update the manifest."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", choices=list(FIGURES), default=list(FIGURES))
    parser.add_argument("--out", type=Path, default=GALLERY)
    parser.add_argument(
        "--results", type=Path, default=None,
        help="keep the ACC runs' result files here (default: a temporary folder)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    global RESULTS
    RESULTS = args.results
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    manifest_path = out / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.exists() else {}
    total = time.perf_counter()
    for name in args.only:
        filename, make = FIGURES[name]
        t0 = time.perf_counter()
        info = make(out)
        seconds = round(time.perf_counter() - t0, 1)
        manifest[name] = {"file": filename, **info, "seconds": seconds, "safestab": ss.__version__}
        print(f"{filename}: {seconds} s")
        # written after each figure (atomically), so a failure later keeps what was made
        tmp = manifest_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(dict(sorted(manifest.items())), indent=2) + "\n")
        tmp.replace(manifest_path)
    print(f"total: {time.perf_counter() - total:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
