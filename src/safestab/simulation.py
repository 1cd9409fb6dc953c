"""Closed-loop simulation: fixed-step RK4 with zero-order hold, compiled with ``lax.scan``."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._validation import check_scalar_range
from .controllers import UniversalController
from .errors import DimensionError, InfeasibleError
from .formulas import Region
from .systems import ControlAffineSystem

__all__ = ["Trajectory", "rk4_step", "simulate"]

Exogenous = Callable[[jax.Array], jax.Array]


def rk4_step(
    rhs: Callable[[jax.Array, jax.Array], jax.Array], t: jax.Array, x: jax.Array, dt: float
) -> jax.Array:
    """One classical Runge-Kutta step of ``xdot = rhs(t, x)``; global error O(dt^4)."""
    k1 = rhs(t, x)
    k2 = rhs(t + dt / 2, x + dt / 2 * k1)
    k3 = rhs(t + dt / 2, x + dt / 2 * k2)
    k4 = rhs(t + dt, x + dt * k3)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """A simulated closed loop; arrays have a time axis after any batch axes.

    Attributes
    ----------
    t : array of shape (T,)
        Times of the samples, s.
    x : array of shape (..., T, n)
        States at ``t``.
    u : array of shape (..., T, m)
        Inputs held on ``[t_k, t_k + dt)`` (the last one is the input the controller would
        apply at the final state).
    V, h : arrays of shape (..., T)
        CLF and CBF values at ``x``.
    region : int array of shape (..., T)
        :class:`~safestab.formulas.Region` per step.
    compatible : bool array of shape (..., T)
        Compatibility of the conditions the controller used, per step.
    cbf_satisfied : bool array of shape (..., T)
        Whether the applied input met the controller's CBF condition.
    """

    t: jax.Array
    x: jax.Array
    u: jax.Array
    V: jax.Array
    h: jax.Array
    region: jax.Array
    compatible: jax.Array
    cbf_satisfied: jax.Array

    @property
    def infeasible_steps(self) -> int:
        """Number of steps where the formula met no compatible conditions (all batches)."""
        return int(np.sum(np.asarray(self.region) == Region.INCOMPATIBLE))


jax.tree_util.register_dataclass(
    Trajectory, data_fields=[f.name for f in dataclasses.fields(Trajectory)], meta_fields=[]
)


def _closed_loop(controller, plant, exogenous, n_steps, dt):
    clf, cbf = controller.clf, controller.cbf

    def rhs(t, x, u):
        xdot = plant.f(x) + plant.g(x) @ u
        return xdot if exogenous is None else xdot + exogenous(t)

    def record(x):
        out = controller._step(x)
        return out, (clf.fn(x), cbf.fn(x))

    def body(x, k):
        t = k * dt
        out, vals = record(x)
        x_next = rk4_step(lambda s, y: rhs(s, y, out.u), t, x, dt)
        return x_next, (x, out.u, vals, out.region, out.compatible, out.cbf_satisfied)

    def run(x0):
        x_final, hist = jax.lax.scan(body, x0, jnp.arange(n_steps))
        out, vals = record(x_final)
        xs, us, (Vs, hs), regions, comps, sats = hist

        def cat(a, b):
            return jnp.concatenate([a, b[None]], 0)

        return (
            cat(xs, x_final),
            cat(us, out.u),
            cat(Vs, vals[0]),
            cat(hs, vals[1]),
            cat(regions, out.region),
            cat(comps, out.compatible),
            cat(sats, out.cbf_satisfied),
        )

    return run


def simulate(
    controller: UniversalController,
    x0: Any,
    *,
    t_final: float,
    dt: float = 0.01,
    plant: ControlAffineSystem | None = None,
    exogenous: Exogenous | None = None,
    strict: bool = False,
) -> Trajectory:
    """Simulate ``controller`` in closed loop from ``x0`` (one state or a batch).

    The input is computed at each ``t_k = k dt`` and held constant over the step (zero-order
    hold); the plant is integrated with one RK4 step per ``dt``. The whole loop is one
    ``lax.scan``, and a batch of initial states is one ``vmap``.

    Parameters
    ----------
    controller : UniversalController
    x0 : array of shape (n,) or (batch, n)
    t_final : float
        Horizon, s; ``round(t_final / dt)`` steps.
    dt : float
        Step, s (default 0.01).
    plant : ControlAffineSystem, optional
        The true system to integrate; defaults to the controller's own model.
    exogenous : callable, optional
        A known time-dependent term ``e(t)`` of shape (n,) added to the plant's dynamics (for
        example the lead vehicle's acceleration in the ACC study).
    strict : bool
        Raise :class:`~safestab.errors.InfeasibleError` if some step was infeasible or lost
        the CBF condition, instead of only recording it.

    Returns
    -------
    Trajectory

    Raises
    ------
    ParameterError
        If ``t_final`` or ``dt`` is not positive.
    DimensionError, NonFiniteError
        If ``x0`` has the wrong shape or is not finite.
    InfeasibleError
        With ``strict=True``, as above.
    """
    check_scalar_range("t_final", t_final, lower=0.0, strict_lower=True)
    check_scalar_range("dt", dt, lower=0.0, strict_lower=True)
    plant = plant or controller.system
    if plant.n_states != controller.system.n_states or plant.n_inputs != controller.system.n_inputs:
        raise DimensionError(
            f"plant dimensions (n={plant.n_states}, m={plant.n_inputs}) differ from the "
            f"controller's model (n={controller.system.n_states}, m={controller.system.n_inputs})"
        )
    x0 = controller.system.check_state(x0, "x0")
    if x0.ndim > 2:
        raise DimensionError(f"x0 must have shape (n,) or (batch, n), got shape {x0.shape}")
    n_steps = int(round(t_final / dt))
    run = _closed_loop(controller, plant, exogenous, n_steps, float(dt))
    fn = jax.jit(jax.vmap(run) if x0.ndim == 2 else run)
    xs, us, Vs, hs, regions, comps, sats = fn(x0)
    traj = Trajectory(
        t=jnp.arange(n_steps + 1) * dt,
        x=xs,
        u=us,
        V=Vs,
        h=hs,
        region=regions,
        compatible=comps,
        cbf_satisfied=sats,
    )
    if strict and (traj.infeasible_steps or not bool(np.all(np.asarray(sats)))):
        raise InfeasibleError(
            f"{traj.infeasible_steps} infeasible steps and "
            f"{int(np.sum(~np.asarray(sats)))} steps where the applied input broke the CBF "
            "condition"
        )
    return traj
