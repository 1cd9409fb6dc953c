"""Data collection for learning ``omega(x)`` (Assumption 1, eq. (11), and Section IV).

Trajectories of the true system start from states drawn from ``X0`` and are excited by inputs
that span the admissible range: random constants, steps, sinusoids, and (if a controller is
given) the controller plus noise. States and inputs are sampled at a fixed rate and the
targets are ``y = xdot - f(x) - g(x) u - e(t) + noise`` with the nominal ``f, g`` and the known
exogenous term ``e(t)``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np

from .._validation import check_finite, check_scalar_range
from ..errors import DimensionError, NonFiniteError, ParameterError
from ..simulation import rk4_step
from ..systems import ControlAffineSystem
from ._checks import check_count, check_seed

__all__ = ["Dataset", "collect_data", "EXCITATIONS"]

EXCITATIONS = ("constant", "step", "sine", "controller")


@dataclasses.dataclass(frozen=True)
class Dataset:
    """Samples ``(x, u, xdot, y)`` of the unknown dynamics; ``Q`` rows.

    Attributes
    ----------
    x : array of shape (Q, n)
    u : array of shape (Q, m)
    xdot : array of shape (Q, n)
        Measured (or finite-difference) derivatives.
    y : array of shape (Q, n)
        Targets ``xdot - f(x) - g(x) u - e(t)`` plus measurement noise.
    t : array of shape (Q,)
        Sample times within each trajectory, s.
    trajectory : array of shape (Q,) or None
        Index of the trajectory each row comes from (for per-trajectory splits and the
        per-trajectory conformal beta).
    """

    x: np.ndarray
    u: np.ndarray
    xdot: np.ndarray
    y: np.ndarray
    t: np.ndarray
    trajectory: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def split(self, test_fraction: float, *, seed: int = 0) -> tuple[Dataset, Dataset]:
        """Random train/test split (rows shuffled with ``seed``, an integer in [0, 2**32 - 1])."""
        seed = check_seed("seed", seed)
        check_scalar_range(
            "test_fraction",
            test_fraction,
            lower=0.0,
            strict_lower=True,
            upper=1.0,
            strict_upper=True,
        )
        perm = np.random.default_rng(seed).permutation(len(self))
        n_test = max(1, int(round(test_fraction * len(self))))
        te, tr = perm[:n_test], perm[n_test:]
        return self.take(tr), self.take(te)

    def take(self, idx: Any) -> Dataset:
        """The rows ``idx`` (an int array or a boolean mask of shape (N,)) as a new data set."""
        idx = np.asarray(idx)
        traj = None if self.trajectory is None else self.trajectory[idx]
        return Dataset(self.x[idx], self.u[idx], self.xdot[idx], self.y[idx], self.t[idx], traj)

    def thin(self, stride: int) -> Dataset:
        """Every ``stride``-th row of each trajectory, counted from the trajectory's first row.

        The rows of one trajectory must be contiguous (as :func:`collect_data` returns them);
        every trajectory then keeps the same sample times, also when its length is not a
        multiple of ``stride`` (thinning the concatenated rows would not: what keeps
        per-trajectory calibration units exchangeable).

        Raises
        ------
        ParameterError
            If ``stride`` is not an integer >= 1, or the data set has no trajectory labels.
        """
        stride = check_count("stride", stride)
        if self.trajectory is None:
            raise ParameterError("thin needs trajectory labels; this data set has none")
        n = len(self)
        starts = np.r_[0, np.flatnonzero(np.diff(self.trajectory)) + 1]
        first = np.repeat(starts, np.diff(np.r_[starts, n]))  # each row's block start
        return self.take(np.flatnonzero((np.arange(n) - first) % stride == 0))


def _x0_sampler(x0: Any, n_states: int) -> Callable[[jax.Array, int], jax.Array]:
    if callable(x0):
        return x0
    try:
        pair = [np.asarray(v, float) for v in x0]
    except (TypeError, ValueError):
        pair = []
    if len(pair) != 2 or any(v.shape not in ((), (n_states,)) for v in pair):
        got = [v.shape for v in pair] if len(pair) == 2 else repr(x0)
        raise DimensionError(
            f"x0 must be a sampler (key, count) -> (count, {n_states}) or a pair (low, high) "
            f"of scalars or arrays of shape ({n_states},), got {got}"
        )
    low, high = (np.broadcast_to(v, (n_states,)) for v in pair)
    check_finite("x0 low", low)
    check_finite("x0 high", high)
    if np.any(low > high):
        raise ParameterError(
            f"x0 low must be <= high, got low={low.tolist()}, high={high.tolist()}"
        )
    return lambda key, count: jax.random.uniform(key, (count, n_states), minval=low, maxval=high)


def collect_data(
    true_system: ControlAffineSystem,
    nominal: ControlAffineSystem,
    *,
    x0: Any,
    u_low: Any,
    u_high: Any,
    n_samples: int = 2000,
    rate: float = 10.0,
    horizon: float = 10.0,
    noise_std: Any = 0.0,
    excitations: tuple[str, ...] = ("constant", "step", "sine"),
    controller: Callable[[jax.Array], jax.Array] | None = None,
    controller_noise: float = 0.1,
    derivative: Literal["exact", "finite_difference"] = "exact",
    exogenous: Callable[[jax.Array], jax.Array] | None = None,
    substeps: int = 10,
    seed: int = 0,
) -> Dataset:
    """Simulate the true system under exciting inputs and return ``Q = n_samples`` samples.

    Parameters
    ----------
    true_system : ControlAffineSystem
        The real dynamics (a simulator), ``f + omega`` and ``g``.
    nominal : ControlAffineSystem
        The model ``f, g`` whose error ``omega`` is to be learned.
    x0 : (low, high) or callable
        The distribution ``X0`` of initial states: bounds of a uniform box, or a function
        ``(key, count) -> (count, n)``.
    u_low, u_high : arrays broadcastable to (m,)
        The input range the excitation spans, in the system's input units.
    n_samples : int
        ``Q``, the number of samples returned.
    rate : float
        Sampling rate, Hz; the input is held between samples (zero-order hold).
    horizon : float
        Length of each trajectory, s; ``ceil(Q / (horizon * rate))`` trajectories are run.
    noise_std : float or array of shape (n,)
        Standard deviation ``sigma_epsilon`` of the Gaussian noise added to ``y``.
    excitations : tuple of str
        Input families drawn uniformly per trajectory, from ``"constant"``, ``"step"``
        (two levels, random switch time), ``"sine"`` (random frequency 0.05-1 Hz and phase)
        and ``"controller"`` (``controller(x)`` plus Gaussian noise of
        ``controller_noise * (u_high - u_low)``, saturated to the range; needs ``controller``).
    controller : callable, optional
        A jittable map from one state (n,) to an input (m,).
    controller_noise : float
        Relative noise level of the controller excitation.
    derivative : {"exact", "finite_difference"}
        ``"exact"``: ``xdot`` from the simulator (Assumption 1). ``"finite_difference"``:
        ``(x_{k+1} - x_k) * rate``, a forward difference within the interval where ``u_k`` is
        held; its error is ``(1/(2 rate)) xddot + O(rate^-2)``, first order in the sampling
        period (a central difference would straddle input jumps and err by O(1)).
    exogenous : callable, optional
        Known time-dependent term ``e(t)`` of shape (n,) in the true dynamics; subtracted from
        ``y``.
    substeps : int
        RK4 steps per sampling period.
    seed : int
        Seeds everything (initial states, excitation parameters, noise); an integer in
        ``[0, 2**32 - 1]``.

    Returns
    -------
    Dataset

    Raises
    ------
    ParameterError
        For non-positive ``n_samples``, ``rate``, ``horizon`` or ``substeps``, negative noise,
        an unknown excitation, ``"controller"`` without a controller, or a ``seed`` that is not
        an integer in ``[0, 2**32 - 1]``.
    DimensionError
        If the two systems' dimensions differ, or ``x0``'s bounds or ``u_low``/``u_high`` are
        neither scalars nor of the state's (input's) shape.
    NonFiniteError
        If a bound is not finite, or the true system diverged (a recorded state or
        derivative is NaN or inf): no data set with non-finite entries is returned.
    """
    seed = check_seed("seed", seed)
    n, m = nominal.n_states, nominal.n_inputs
    if (true_system.n_states, true_system.n_inputs) != (n, m):
        raise DimensionError(
            f"true_system has (n, m) = ({true_system.n_states}, {true_system.n_inputs}), "
            f"nominal has ({n}, {m})"
        )
    n_samples = check_count("n_samples", n_samples)
    check_scalar_range("rate", rate, lower=0.0, strict_lower=True)
    check_scalar_range("horizon", horizon, lower=0.0, strict_lower=True)
    check_scalar_range("noise_std", noise_std, lower=0.0)
    check_scalar_range("controller_noise", controller_noise, lower=0.0)
    substeps = check_count("substeps", substeps)
    unknown = [e for e in excitations if e not in EXCITATIONS]
    if unknown or not excitations:
        raise ParameterError(
            f"excitations must be a non-empty subset of {EXCITATIONS}, got {excitations!r}"
        )
    if "controller" in excitations and controller is None:
        raise ParameterError("the 'controller' excitation needs controller=")
    if derivative not in ("exact", "finite_difference"):
        raise ParameterError(
            f"derivative must be 'exact' or 'finite_difference', got {derivative!r}"
        )
    for name, v in (("u_low", u_low), ("u_high", u_high)):
        if np.shape(v) not in ((), (m,)):
            raise DimensionError(f"{name} must be a scalar or have shape ({m},), got {np.shape(v)}")
    low = np.broadcast_to(np.asarray(u_low, float), (m,))
    high = np.broadcast_to(np.asarray(u_high, float), (m,))
    check_finite("u_low", low)
    check_finite("u_high", high)
    if np.any(low > high):
        raise ParameterError(f"u_low must be <= u_high, got {low.tolist()} and {high.tolist()}")

    per_traj = max(1, int(round(horizon * rate)))
    n_traj = -(-int(n_samples) // per_traj)
    period = 1.0 / rate
    h = period / substeps
    sampler = _x0_sampler(x0, n)
    kinds = jnp.array([EXCITATIONS.index(e) for e in excitations])
    key = jax.random.PRNGKey(seed)
    k_x0, *keys = jax.random.split(key, 8)
    x0s = jnp.asarray(sampler(k_x0, n_traj), dtype=float)
    if x0s.shape != (n_traj, n):
        raise DimensionError(f"the x0 sampler must return shape ({n_traj}, {n}), got {x0s.shape}")
    params, y_noise = _draws(
        jnp.stack(keys), kinds, jnp.asarray(low), jnp.asarray(high), jnp.asarray(float(horizon)),
        shape=(n_traj, per_traj, m, int(n_samples), n),
    )  # fmt: skip
    xs, us, xdots, ts, x_next = _trajectories(
        x0s, params, true_system=true_system, exogenous=exogenous, controller=controller,
        m=m, per_traj=per_traj, substeps=substeps, period=period, h=h,
        controller_noise=float(controller_noise), low=tuple(low.tolist()),
        high=tuple(high.tolist()),
    )  # fmt: skip
    if derivative == "finite_difference":
        xdots = (x_next - xs) / period
    flat = [
        np.asarray(a).reshape((n_traj * per_traj,) + a.shape[2:])[:n_samples]
        for a in (xs, us, xdots, ts)
    ]
    x, u, xdot, t = flat
    traj = np.repeat(np.arange(n_traj), per_traj)[:n_samples]
    bad = ~(np.isfinite(x).all(1) & np.isfinite(xdot).all(1))
    if bad.any():
        first = int(np.argmax(bad))
        raise NonFiniteError(
            f"collect_data: {int(bad.sum())} of {len(x)} samples are not finite (the first in "
            f"trajectory {int(traj[first])} at t = {float(t[first]):g} s): the true system "
            "diverged under the excitation; shorten horizon, narrow x0 or the input range"
        )
    f_nom = np.asarray(nominal.drift(jnp.asarray(x)))
    g_nom = np.asarray(nominal.input_matrix(jnp.asarray(x)))
    e = np.zeros_like(x) if exogenous is None else np.asarray(jax.vmap(exogenous)(jnp.asarray(t)))
    y = xdot - f_nom - np.einsum("qij,qj->qi", g_nom, u) - e
    noise = np.asarray(y_noise) * np.broadcast_to(np.asarray(noise_std, float), (n,))
    return Dataset(x=x, u=u, xdot=xdot, y=y + noise, t=t, trajectory=traj)


@functools.partial(jax.jit, static_argnames=("shape",))
def _draws(keys, kinds, low, high, horizon, *, shape):
    """The random excitation parameters of :func:`collect_data` and the measurement noise.

    One compiled program for the seven draws: drawn one by one, each was compiled on its own
    on a first run (the same numbers, bit for bit). ``shape`` is ``(trajectories, samples
    per trajectory, m, n_samples, n)``.
    """
    n_traj, per_traj, m, n_samples, n = shape
    k_kind, k_lv, k_sw, k_fr, k_ph, k_noise, k_y = keys
    params = {
        "kind": kinds[jax.random.randint(k_kind, (n_traj,), 0, kinds.shape[0])],
        "levels": jax.random.uniform(k_lv, (n_traj, 2, m), minval=low, maxval=high),
        "switch": jax.random.uniform(k_sw, (n_traj,), minval=0.1, maxval=0.9) * horizon,
        "freq": jax.random.uniform(k_fr, (n_traj, m), minval=0.05, maxval=1.0),
        "phase": jax.random.uniform(k_ph, (n_traj, m), maxval=2 * np.pi),
        "noise": jax.random.normal(k_noise, (n_traj, per_traj, m)),
    }
    return params, jax.random.normal(k_y, (n_samples, n))


_STATIC = ("true_system", "exogenous", "controller", "m", "per_traj", "substeps", "period", "h",
           "controller_noise", "low", "high")  # fmt: skip


@functools.partial(jax.jit, static_argnames=_STATIC)
def _trajectories(
    x0s, params, *, true_system, exogenous, controller, m, per_traj, substeps, period, h,
    controller_noise, low, high,
):  # fmt: skip
    """The excitation trajectories of :func:`collect_data` from ``x0s`` (B, n), vmapped.

    One jitted function: the system, the callables (by identity), the excitation settings
    and the input range are its static arguments, so a study that collects many data sets
    with the same objects traces and compiles once instead of once per data set.
    """
    low, high = np.asarray(low, float), np.asarray(high, float)
    mid, half = jnp.asarray((low + high) / 2), jnp.asarray((high - low) / 2)
    ctrl = controller if controller is not None else (lambda x: jnp.zeros(m))

    def u_of(p, k, t, x):
        constant = p["levels"][0]
        step = jnp.where(t < p["switch"], p["levels"][0], p["levels"][1])
        sine = mid + half * jnp.sin(2 * jnp.pi * p["freq"] * t + p["phase"])
        fb = jnp.clip(ctrl(x) + controller_noise * 2 * half * p["noise"][k], low, high)
        return jnp.stack([constant, step, sine, fb])[p["kind"]]

    def xdot_true(t, x, u):
        out = true_system.f(x) + true_system.g(x) @ u
        return out if exogenous is None else out + exogenous(t)

    def trajectory(x0_, p):
        def sample(x, k):
            t = k * period
            u = u_of(p, k, t, x)

            def sub(y, j):
                return rk4_step(lambda s, z: xdot_true(s, z, u), t + j * h, y, h), None

            x_next, _ = jax.lax.scan(sub, x, jnp.arange(substeps))
            return x_next, (x, u, xdot_true(t, x, u), t, x_next)

        _, rec = jax.lax.scan(sample, x0_, jnp.arange(per_traj))
        return rec

    return jax.vmap(trajectory)(x0s, params)
