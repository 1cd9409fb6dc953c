"""Figures. Functions take ``ax=None`` (or ``axes=None``) and return the figure or axes."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["plot_acc_study", "plot_trajectory_h"]

_STYLES = {
    "true model": {"color": "black", "ls": "-"},
    "mismatched model": {"color": "tab:red", "ls": "--"},
    "GP-corrected": {"color": "tab:blue", "ls": "-."},
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
    ref = result.trajectories["true model"]
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
