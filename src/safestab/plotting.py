"""Figures. Functions take ``ax=None`` (or ``axes=None``) and return the figure or axes."""

from __future__ import annotations

from typing import Any

import numpy as np

from .controller_names import GP_ROBUST, MISMATCHED_MODEL, TRUE_MODEL

__all__ = [
    "OUTCOME_COLORS",
    "plot_acc_study",
    "plot_compatibility_maps",
    "plot_obstacle_plane",
    "plot_swarm",
    "plot_trajectory_h",
]

_STYLES = {
    TRUE_MODEL: {"color": "black", "ls": "-"},
    MISMATCHED_MODEL: {"color": "tab:red", "ls": "--"},
    GP_ROBUST: {"color": "tab:blue", "ls": "-."},
}


def plot_trajectory_h(trajectories: dict[str, Any], ax: Any = None) -> Any:
    """Plot ``h(t)`` of several runs on one axes, with the safe-set boundary ``h = 0``."""
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(4, 3))
    for name, tr in trajectories.items():
        ax.plot(np.asarray(tr.t), np.asarray(tr.h), label=name, lw=1.4, **_STYLES.get(name, {}))
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(r"$h = D - \tau_d v_f$ (m)")
    return ax


def plot_acc_study(result: Any, axes: Any = None) -> Any:
    """Three-panel figure like the paper's Fig. 4.

    Left: follower speed of each controller, the lead speed and the desired speed (m/s), with
    the gap distance on a second axis (m). Middle: ``h`` for the three controllers (m). Right:
    the input ``u / (M g)``.

    Parameters
    ----------
    result : StudyResult
    axes : sequence of 3 matplotlib axes, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    sc = result.scenario
    if axes is None:
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), constrained_layout=True)
    else:
        fig = axes[0].figure
    ax_v, ax_h, ax_u = axes
    ref = result.trajectories[TRUE_MODEL]
    t = np.asarray(ref.t)
    ax_v.plot(t, np.asarray(ref.x)[:, 1], color="tab:green", lw=1.2, label="lead $v_l$")
    ax_v.axhline(sc.v_d, color="0.6", lw=0.8, ls=":", label="$v_d$")
    ax_d = ax_v.twinx()
    for name, tr in result.trajectories.items():
        st = _STYLES.get(name, {})
        x = np.asarray(tr.x)
        ax_v.plot(t, x[:, 0], lw=1.4, label=f"$v_f$, {name}", **st)
        ax_d.plot(t, x[:, 2], lw=0.8, alpha=0.5, color=st.get("color"), ls=st.get("ls"))
        u = np.asarray(tr.u)[:, 0] * sc.input_scale / (sc.mass * sc.gravity)
        ax_u.plot(t, u, lw=1.2, label=name, **st)
    ax_v.set_xlabel("time (s)")
    ax_v.set_ylabel("speed (m/s)")
    ax_d.set_ylabel("gap $D$ (m), thin lines")
    ax_v.legend(fontsize=7, loc="best")
    plot_trajectory_h(result.trajectories, ax=ax_h)
    ax_h.legend(fontsize=7, loc="best")
    ax_u.set_xlabel("time (s)")
    ax_u.set_ylabel("$u / (M g)$")
    ax_u.legend(fontsize=7, loc="best")
    fig.suptitle(f"ACC study: scenario '{sc.name}'", fontsize=10)
    return fig


# -- the obstacle scenario (the paper's Fig. 2) -----------------------------------------

#: Colours of the trajectory outcomes of the obstacle study.
OUTCOME_COLORS = {
    "converged": "tab:blue",
    "stuck": "goldenrod",
    "unsafe": "tab:red",
    "moving": "0.45",
}


def _run_keys(result: Any) -> tuple[list[str], list[str]]:
    """The controllers and the limit settings of a study's runs, in the study's order."""
    names = list(dict.fromkeys(name for name, _ in result.runs))
    settings = list(dict.fromkeys(limits for _, limits in result.runs))
    return names, settings


def _plane(ax: Any, sc: Any, level: float | None) -> None:
    """Safe set (green), obstacle (red disc), level sets of V (grey), ``{V <= level}`` (black)."""
    from matplotlib.patches import Circle

    lo, hi = sc.map_x1
    hw = sc.map_x2_half_width
    x1, x2 = np.linspace(lo, hi, 241), np.linspace(-hw, hw, 161)
    X1, X2 = np.meshgrid(x1, x2)
    V = np.asarray(sc.V(np.stack([X1, X2], -1)))
    ax.set_facecolor("#e3f2e1")  # the safe set C = {h >= 0}
    ax.add_patch(Circle(tuple(sc.obstacle_center), sc.radius, color="tab:red", alpha=0.3, lw=0))
    ax.add_patch(Circle(tuple(sc.obstacle_center), sc.radius, fill=False, color="tab:red", lw=1))
    levels = np.geomspace(0.5, max(float(V.max()), 1.0), 8)
    ax.contour(X1, X2, V, levels=levels, colors="0.65", linewidths=0.5)
    if level is not None and np.isfinite(level):
        ax.contour(X1, X2, V, levels=[level], colors="black", linewidths=1.3)
    ax.plot(0, 0, marker="*", color="black", ms=9, zorder=5)
    ax.set_xlim(lo, hi)
    ax.set_ylim(-hw, hw)
    ax.set_aspect("equal")
    ax.set_xlabel("$x_1$ (m)")
    ax.set_ylabel("$x_2$ (m)")


def plot_obstacle_plane(result: Any, axes: Any = None) -> Any:
    """The paper's Fig. 2 for each controller and limit setting.

    Each panel shows the safe set (green), the obstacle (red), level sets of ``V`` (grey),
    the certified domain of attraction ``{V <= doa_fraction c*}`` of that controller (black
    ellipse), and the closed-loop trajectories from every start coloured by outcome
    (:data:`OUTCOME_COLORS`); the end points of stuck and unsafe runs are marked ``x``.

    Parameters
    ----------
    result : ObstacleStudyResult
    axes : array of matplotlib axes of shape (2, 3), optional
        Rows: no limits, input limits; columns: true model, mismatched model, GP-robust.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    sc = result.scenario
    names, settings = _run_keys(result)
    if axes is None:
        fig, axes = plt.subplots(
            len(settings), len(names), figsize=(15, 7.2), constrained_layout=True, squeeze=False
        )
    else:
        fig = axes[0][0].figure
    for i, limits in enumerate(settings):
        for j, name in enumerate(names):
            ax = axes[i][j]
            run = result.runs[(name, limits)]
            _plane(ax, sc, sc.doa_fraction * result.doa[name])
            # every path of the panel as one collection, and the marks as one artist each:
            # the same picture as a line per start, at a fraction of the drawing time
            # (72 starts x 6 panels made 900 artists, most of the main job's figure time)
            colors = [OUTCOME_COLORS[str(o)] for o in run.outcome]
            ax.add_collection(
                LineCollection(
                    list(np.asarray(run.x[..., :2])), colors=colors, linewidths=0.8, alpha=0.85
                )
            )
            ax.scatter(run.x0[:, 0], run.x0[:, 1], s=2.5**2, c=colors, marker="o", lw=0)
            ends = run.x[np.isin(run.outcome, ("stuck", "unsafe")), -1]
            ax.plot(ends[:, 0], ends[:, 1], ls="", marker="x", ms=7, mew=1.8, color="black",
                    zorder=6)  # fmt: skip
            counts = ", ".join(
                f"{int(np.sum(run.outcome == o))} {o}"
                for o in OUTCOME_COLORS
                if np.any(run.outcome == o)
            )
            ax.set_title(
                f"{name}, {limits}\n{counts}; min h = {np.min(run.h):.3g} m$^2$", fontsize=8
            )
    handles = [Line2D([], [], color=c, label=o) for o, c in OUTCOME_COLORS.items()]
    handles += [
        Line2D([], [], color="black", lw=1.3, label=r"$\{V \leq c\}$ certified"),
        Line2D([], [], color="black", marker="x", ls="", label="end of stuck/unsafe run"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=6, fontsize=8)
    fig.suptitle(
        f"Obstacle scenario '{sc.name}': closed loops under the current "
        f"(gain {sc.gain_true:g} vs {sc.gain_nominal:g} nominal)",
        fontsize=10,
    )
    return fig


def plot_compatibility_maps(result: Any, axes: Any = None) -> Any:
    """Compatibility over the plane: Lemma 1 (nominal model) and eq. (20) (GP-robust terms).

    Left: the region of the compatible formula on the nominal terms (P1 to P4; black where
    Lemma 1 says incompatible). Right: the probabilistic verdict for the GP-robust terms
    (black: incompatible; orange: compatible by eq. (20) only; light blue: also by Lemma 4's
    sufficient condition), with the stated probability. Both panels mark the incompatible
    points of the parallel set (thick black) and the end points of the runs of the matching
    controller that came to rest outside the goal ball (``x``; stuck, or unsafe and at rest).

    Parameters
    ----------
    result : ObstacleStudyResult
    axes : sequence of 2 matplotlib axes, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    sc, maps = result.scenario, result.maps
    _, settings = _run_keys(result)
    if axes is None:
        # 5.4 in high: two equal-aspect panels of the 12 m x 8 m plane, their titles and
        # x labels (at 4.6 in the layout could not fit them and cut the x label off)
        fig, axes = plt.subplots(1, 2, figsize=(13, 5.4), constrained_layout=True)
    else:
        fig = axes[0].figure
    region_colors = ["black", "#9ecae1", "#fdae6b", "#c7a0d8", "#d9d9d9"]  # INCOMPATIBLE, P1..P4
    robust_class = np.where(~maps.robust_updated, 0, np.where(maps.robust_lemma4, 2, 1))
    panels = [
        (maps.nominal_region, region_colors, MISMATCHED_MODEL,
         "Lemma 1, nominal model: regions of the compatible formula",
         ["incompatible", "P1", "P2", "P3", "P4"]),
        (robust_class, ["black", "#fdae6b", "#9ecae1"], GP_ROBUST,
         f"eq. (20), GP-robust terms ($\\beta$ = {sc.gp_beta:.3g}"
         + (", conformal), stated probability $1-\\delta$"
            if result.coverage.get("beta_method") == "conformal"
            else "), stated probability $(1-\\delta)^2$")
         + f" = {maps.probability:.4f}",
         ["incompatible", "compatible (eq. 20)", "compatible (eq. 20 and Lemma 4)"]),
    ]  # fmt: skip
    for ax, (z, colors, name, title, labels) in zip(axes, panels, strict=True):
        # rasterized in a PDF (an image at the save's dpi, as in the PNG): the grid's cells as
        # vector quads made the PDF's writing five times slower than the PNG's
        ax.pcolormesh(
            maps.x1, maps.x2, np.asarray(z).T, shading="nearest",
            cmap=ListedColormap(colors), vmin=-0.5, vmax=len(colors) - 0.5, rasterized=True,
        )  # fmt: skip
        ax.add_artist(
            plt.Circle(tuple(sc.obstacle_center), sc.radius, fill=False, color="tab:red", lw=1.2)
        )
        bad = ~result.parallel_verdicts[name]
        pts = result.parallel_set[bad]
        ax.plot(pts[:, 0], pts[:, 1], ".", color="black", ms=3)
        for limits in settings:
            run = result.runs[(name, limits)]
            ends = run.x[run.stopped(sc.ball_radius, sc.rest_speed), -1]
            ax.plot(ends[:, 0], ends[:, 1], "x", color="tab:red", ms=8, mew=2)
        ax.plot(0, 0, marker="*", color="black", ms=9)
        ax.set_aspect("equal")
        ax.set_xlabel("$x_1$ (m)")
        ax.set_ylabel("$x_2$ (m)")
        ax.set_title(title, fontsize=9)
        handles: list[Any] = [
            Patch(facecolor=c, edgecolor="0.3", label=lab)
            for c, lab in zip(colors, labels, strict=True)
        ]
        handles.append(
            plt.Line2D([], [], color="tab:red", marker="x", ls="", label=f"rest points, {name}")
        )
        ax.legend(handles=handles, fontsize=7, loc="upper right", framealpha=0.9)
    fig.suptitle(
        f"Obstacle scenario '{sc.name}': where the CLF and CBF are compatible", fontsize=10
    )
    return fig


def plot_swarm(result: Any, axes: Any = None) -> Any:
    """The swarm study: paths per filter, least pair distance and the filter's input change.

    ``result`` is a :class:`~safestab.scenarios.swarm_study.SwarmStudy`. Returns the figure.
    """
    import matplotlib.pyplot as plt

    sc, runs = result.scenario, result.runs
    if axes is None:
        fig, axes = plt.subplots(1, 4, figsize=(15, 3.8), constrained_layout=True)
    else:
        fig = axes[0].figure
    colors = plt.get_cmap("hsv")(np.linspace(0, 1, sc.n_robots, endpoint=False))
    for ax, mode in zip(axes[:2], ("centralized", "decentralized"), strict=True):
        run = runs[mode]
        for i in range(sc.n_robots):
            ax.plot(run.p[:, i, 0], run.p[:, i, 1], color=colors[i], lw=1.0)
            ax.plot(*run.p[0, i], "o", color=colors[i], ms=3)
            ax.add_patch(
                plt.Circle(run.p[-1, i], sc.safety_distance / 2, color=colors[i], alpha=0.3)
            )
        ax.set_aspect("equal")
        ax.set_title(f"{mode} filter")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    styles = {"centralized": "-", "decentralized": "--", "unfiltered": ":"}
    for mode, run in runs.items():
        axes[2].plot(run.t, run.min_distance(), styles[mode], label=mode)
        nominal = np.clip(run.u_nom, -sc.speed_limit, sc.speed_limit)
        change = np.linalg.norm(run.u - nominal, axis=-1).mean(-1)
        if mode != "unfiltered":
            axes[3].plot(run.t[:-1], change, styles[mode], label=mode)
    axes[2].axhline(sc.safety_distance, color="0.4", lw=0.8)
    axes[2].set_xlabel("time (s)")
    axes[2].set_ylabel("least pair distance (m)")
    axes[2].set_yscale("log")
    axes[2].legend(fontsize=8)
    axes[2].set_title(f"safety distance {sc.safety_distance} m (grey)")
    axes[3].set_xlabel("time (s)")
    axes[3].set_ylabel(r"mean $|u - \mathrm{clip}(u_{nom})|$ per robot (m/s)")
    axes[3].legend(fontsize=8)
    axes[3].set_title("the filter's change to the input")
    return fig
