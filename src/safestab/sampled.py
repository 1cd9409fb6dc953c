"""The sampled-data margin: a CBF condition at the samples that keeps ``h >= 0`` between them.

A deployed controller computes its input at the samples ``t_k = k T`` and holds it until the
next one (zero-order hold); the CBF conditions of the paper are proven for an input that acts
continuously. This module shifts each CBF condition so that, with the input held, ``h`` stays
non-negative over the whole hold interval, not only at the samples (docs/deployed.md).

The method: a second-order Taylor bound along the flow
-------------------------------------------------------
Let ``x(t_k + s)``, ``0 <= s <= T``, be the true plant's flow under the held input ``u_k``,
and ``M >= 0`` a bound on ``-d^2 h / dt^2`` along it: ``h''(s) >= -M`` for every state the hold
interval visits (inside an operating region ``X``) and every input the controller applies
(inside the limits ``U``). Then ``h(s) >= h_k + s h'(0) - M s^2 / 2``. At the sample the
shifted condition ``c + d.u >= rho Gamma + shift``, with ``c = L_f h + alpha(h)`` and

    shift = M T / 2 + max(0, alpha(h_k) - h_k / T)      (h_k >= 0; the second term 0 else)

gives ``h'(0) >= -min(alpha(h_k), h_k / T) + M T / 2`` (``rho Gamma >= 0``), so

    h(s) >= h_k (1 - s / T) + s M (T - s) / 2 >= 0   for  0 <= s <= T.

The second term caps the class-K rate at ``1 / T``: a rate ``beta > 1 / T`` would let ``h``
fall from ``h_k`` to below 0 within one hold even with ``M = 0``. The shift is a function of
the state only (a shift of ``c``), so every formula stays closed-form, exact derivatives and
the C export are kept. It composes with the GP-robust terms (Lemma 3): ``c`` is then the
robust ``c~``, and the guarantee holds on the event that the GP band holds at the samples
(Lemma 2) and ``M`` bounds the true ``-h''``.

Related methods: Breeden, Garg and Panagou, "Control barrier functions in sampled-data
systems", IEEE Control Systems Letters 6, 2021 (a margin from a one-step reachable set), and
Cortez, Oetomo, Manzie and Choong, "Control barrier functions for mechanical systems", CDC 2019
(a Lipschitz margin). Both are first order in ``T`` with a Lipschitz constant of ``h'``; the
bound here is the same order with the constant ``M / 2`` of the Taylor remainder, and asks
for one number per barrier.

Where ``M`` comes from
----------------------
The user gives it (a bound from an analysis of the plant, which makes the guarantee a proof),
or :func:`ddh_bound` estimates it by evaluating ``h''`` exactly (automatic differentiation) on
a dense set of states of a box, inputs of the limits and, optionally, disturbances of a box,
times a safety factor: an estimate, not a proof (a maximum between the sampled points is
missed by at most what the safety factor covers).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._validation import check_finite, check_real, is_concrete
from .certificates import CBF
from .errors import DimensionError, NonFiniteError, ParameterError
from .systems import ControlAffineSystem

__all__ = ["sampled_shift", "check_sampled", "ddh_bound", "hold_second_derivative"]


def sampled_shift(h: Any, alpha_h: Any, sample_time: Any, ddh_bound: Any) -> jax.Array:
    """The shift of the CBF condition at a sample, ``M T / 2 + max(0, alpha(h) - h / T)``.

    Unchecked and jittable; batched over leading axes.

    Parameters
    ----------
    h : array of shape (...,)
        The barrier's value at the sample.
    alpha_h : array of shape (...,)
        Its class-K term ``alpha(h)`` (``beta h`` for a linear rate).
    sample_time : float
        ``T > 0``, s.
    ddh_bound : float or array of shape (...,)
        ``M >= 0``: a bound on ``-h''`` along the held flow, in the units of ``h`` per s^2.

    Returns
    -------
    array of shape (...,)
        ``>= 0``, in the units of ``dh/dt``; the second term only where ``h >= 0``.
    """
    h = jnp.asarray(h, dtype=float)
    cap = jnp.where(h >= 0, jnp.maximum(alpha_h - h / sample_time, 0.0), 0.0)
    return 0.5 * ddh_bound * sample_time + cap


def check_sampled(sample_time: Any, ddh_bound: Any, n_barriers: int | None = None) -> tuple:
    """Check the ``sample_time`` and ``ddh_bound`` arguments of a controller or filter.

    Both or neither; ``sample_time`` a finite scalar > 0 (s); ``ddh_bound`` finite and >= 0,
    a scalar, or (a filter, ``n_barriers`` given) of shape (k,), one per barrier. Traced
    values are checked on their shapes only.

    Returns
    -------
    tuple
        ``(sample_time, ddh_bound)`` as floats or arrays (``(None, None)`` for neither).

    Raises
    ------
    ParameterError
        If only one is given, or a value is out of range.
    DimensionError
        If a value has the wrong shape.
    """
    if (sample_time is None) != (ddh_bound is None):
        raise ParameterError(
            "give sample_time and ddh_bound together (the hold time, s, and a bound M on "
            f"-d^2h/dt^2 along the held flow; safestab.sampled.ddh_bound estimates one), got "
            f"sample_time={sample_time!r}, ddh_bound={ddh_bound!r}"
        )
    if sample_time is None:
        return None, None
    check_real("sample_time", sample_time)
    if np.ndim(sample_time) != 0:
        raise DimensionError(f"sample_time must be a scalar, got shape {np.shape(sample_time)}")
    if is_concrete(sample_time) and not (
        np.isfinite(float(sample_time)) and float(sample_time) > 0
    ):
        raise ParameterError(f"sample_time must be a finite number > 0 (s), got {sample_time!r}")
    check_real("ddh_bound", ddh_bound)
    allowed = ((),) if n_barriers is None else ((), (n_barriers,))
    if np.shape(ddh_bound) not in allowed:
        what = "a scalar" if n_barriers is None else f"a scalar or shape ({n_barriers},)"
        raise DimensionError(f"ddh_bound must be {what}, got shape {np.shape(ddh_bound)}")
    if is_concrete(ddh_bound):
        check_finite("ddh_bound", ddh_bound)
        if np.any(np.asarray(ddh_bound, dtype=float) < 0):
            raise ParameterError(f"ddh_bound must be >= 0, got {np.asarray(ddh_bound).tolist()}")
        ddh_bound = (
            float(ddh_bound) if np.ndim(ddh_bound) == 0 else np.asarray(ddh_bound, dtype=float)
        )
    if is_concrete(sample_time):
        sample_time = float(sample_time)
    return sample_time, ddh_bound


def hold_second_derivative(
    plant: ControlAffineSystem, cbf: CBF, x: Any, u: Any, w: Any = None, params: Any = None
) -> jax.Array:
    """``d^2 h / dt^2`` along the plant's flow with the input held, by autodiff.

    ``h'' = grad(grad h . F)(x) . F`` with ``F(x) = f(x) + g(x) u + w`` (``u`` and the
    disturbance ``w`` constant). Batched: ``x`` (..., n), ``u`` (..., m), ``w`` (..., n)
    broadcast together.

    Parameters
    ----------
    plant : ControlAffineSystem
        The dynamics to differentiate (the true plant where known, say
        ``model.with_disturbance(omega)``).
    cbf : CBF
        The barrier; for :func:`~safestab.high_order_cbf`, the bound concerns its ``psi1``
        (the function whose condition the controller imposes).
    x, u : arrays of shape (..., n) and (..., m)
    w : array of shape (..., n), optional
        A constant additive term (an exogenous input, an unmodelled term's value).
    params : pytree, optional
        The run-time parameters, when the plant or the barrier take them.

    Returns
    -------
    array of shape (...,)
    """
    n, m = plant.n_states, plant.n_inputs
    x = jnp.asarray(x, dtype=float)
    u = jnp.asarray(u, dtype=float)
    w = jnp.zeros(n) if w is None else jnp.asarray(w, dtype=float)
    batch = jnp.broadcast_shapes(x.shape[:-1], u.shape[:-1], w.shape[:-1])
    x = jnp.broadcast_to(x, batch + (n,)).reshape(-1, n)
    u = jnp.broadcast_to(u, batch + (m,)).reshape(-1, m)
    w = jnp.broadcast_to(w, batch + (n,)).reshape(-1, n)

    def one(xs: jax.Array, us: jax.Array, ws: jax.Array) -> jax.Array:
        def flow(z: jax.Array) -> jax.Array:
            return plant.f_of(z, params) + plant.g_of(z, params) @ us + ws

        def hdot(z: jax.Array) -> jax.Array:
            return cbf.grad_of(z, params) @ flow(z)

        return jax.jvp(hdot, (xs,), (flow(xs),))[1]

    return jax.jit(jax.vmap(one))(x, u, w).reshape(batch)


def _box(name: str, lower: Any, upper: Any, size: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.broadcast_to(np.asarray(lower, dtype=float), (size,)).copy()
    hi = np.broadcast_to(np.asarray(upper, dtype=float), (size,)).copy()
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ParameterError(f"{name} must be a finite box, got {lo.tolist()} to {hi.tolist()}")
    if np.any(lo > hi):
        raise ParameterError(f"{name}: lower must be <= upper, got {lo.tolist()} > {hi.tolist()}")
    return lo, hi


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The box's corners and its centre, shape (2^k + 1, k) (a degenerate side counted once)."""
    axes = [np.unique([a, b]) for a, b in zip(lo, hi, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(lo))
    return np.vstack([grid, 0.5 * (lo + hi)])


def ddh_bound(
    plant: ControlAffineSystem,
    cbfs: CBF | Sequence[CBF],
    lower: Any,
    upper: Any,
    *,
    u_min: Any,
    u_max: Any,
    disturbance: tuple[Any, Any] | None = None,
    grid: int = 9,
    n_random: int = 4096,
    safety_factor: float = 1.5,
    seed: int = 0,
    params: Any = None,
) -> np.ndarray:
    """Estimate ``M``, a bound on ``-d^2 h/dt^2`` along the held flow, for each barrier.

    Evaluates :func:`hold_second_derivative` exactly at a grid of ``grid^n`` states of the box
    ``[lower, upper]`` (capped at 20,000 states) and ``n_random`` seeded uniform ones, each
    with the input box's corners and centre and 16 seeded uniform inputs (and the
    disturbance box's corners and centre, when given), and returns ``safety_factor`` times the
    largest ``-h''`` found (0 if ``h'' >= 0`` everywhere). An estimate, not a proof: the
    largest value between the sampled points is missed by at most what ``safety_factor``
    covers; for a guarantee, give the controller a bound from an analysis of the plant
    (docs/deployed.md).

    Parameters
    ----------
    plant : ControlAffineSystem
        The dynamics the bound concerns (the true plant where known).
    cbfs : CBF or sequence of CBF
    lower, upper : arrays of shape (n,) or scalars
        The operating region: a box that holds every state the hold intervals visit.
    u_min, u_max : arrays of shape (m,) or scalars
        The inputs the controller may apply (its limits).
    disturbance : (lower, upper), optional
        A box of constant additive terms ``w`` of shape (n,) (an exogenous input's range).
    grid, n_random : int
        Grid points per state axis (>= 2) and random states (>= 0).
    safety_factor : float
        >= 1: the estimate's factor over the largest sampled value.
    seed : int
    params : pytree, optional
        The run-time parameters, when the plant or a barrier takes them.

    Returns
    -------
    ndarray of shape (k,)
        One bound per barrier, in the units of ``h`` per s^2.

    Raises
    ------
    ParameterError
        If a box is not finite or has ``lower > upper``, ``grid < 2``, ``n_random < 0`` or
        ``safety_factor < 1``.
    NonFiniteError
        If ``h''`` is not finite at a sampled point (named).
    """
    items = (cbfs,) if isinstance(cbfs, CBF) else tuple(cbfs)
    if not items or not all(isinstance(c, CBF) for c in items):
        raise TypeError("cbfs must be a CBF or a non-empty sequence of them")
    n, m = plant.n_states, plant.n_inputs
    if int(grid) != grid or grid < 2:
        raise ParameterError(f"grid must be an integer >= 2, got {grid!r}")
    if int(n_random) != n_random or n_random < 0:
        raise ParameterError(f"n_random must be an integer >= 0, got {n_random!r}")
    if not safety_factor >= 1:
        raise ParameterError(f"safety_factor must be >= 1, got {safety_factor!r}")
    xlo, xhi = _box("the state box", lower, upper, n)
    ulo, uhi = _box("the input limits", u_min, u_max, m)
    rng = np.random.default_rng(seed)
    per_axis = max(2, min(int(grid), int(20_000 ** (1.0 / n))))
    axes = [np.linspace(a, b, per_axis) for a, b in zip(xlo, xhi, strict=True)]
    states = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, n)
    states = np.vstack([states, rng.uniform(xlo, xhi, size=(int(n_random), n))])
    inputs = np.vstack([_corners(ulo, uhi), rng.uniform(ulo, uhi, size=(16, m))])
    if disturbance is None:
        dist = np.zeros((1, n))
    else:
        wlo, whi = _box("disturbance", disturbance[0], disturbance[1], n)
        dist = _corners(wlo, whi)
    x = states[:, None, None, :]
    u = inputs[None, :, None, :]
    w = dist[None, None, :, :]
    out = []
    for i, cbf in enumerate(items):
        hdd = np.asarray(hold_second_derivative(plant, cbf, x, u, w, params))
        bad = ~np.isfinite(hdd)
        if np.any(bad):
            j, k, el = np.unravel_index(int(np.argmax(bad)), hdd.shape)
            raise NonFiniteError(
                f"d^2h/dt^2 of cbfs[{i}] is not finite at x = {states[j].tolist()}, "
                f"u = {inputs[k].tolist()}, w = {dist[el].tolist()}: the plant or the barrier "
                "overflows there; shrink the box"
            )
        out.append(safety_factor * max(float(np.max(-hdd)), 0.0))
    return np.asarray(out)
