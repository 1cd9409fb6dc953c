"""Float exports that stay safe: the controller to export in float, and states to test it on.

A float step errs on every term; :func:`float_safe_controller` widens a GP cache's band for
float rounding and adds a CBF margin of twice the float step's error on the condition, so a
float step whose flag says satisfied keeps the exact condition (docs/export.md, "Float that
stays safe").
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import ParameterError
from .harness import DEFAULT_RTOL, cbf_condition_scale

__all__ = [
    "FLOAT_WIDENING_LIMIT",
    "box_test_states",
    "float_check_states",
    "float_refusal",
    "float_safe_controller",
]


def _corners(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The ``2^n`` corners of the box ``low <= x <= high``, shape (2^n, n)."""
    return np.array(np.meshgrid(*zip(low, high, strict=True))).reshape(len(low), -1).T


def box_test_states(low: Any, high: Any, n: int = 4000, seed: int = 5) -> np.ndarray:
    """States to test a float step on: uniform in a box, its corners and its faces.

    ``n`` uniform states, the ``2^n_states`` corners and ``n`` states with one coordinate on
    a face, rounded to float (what a float step is given); shape (2 n + 2^n_states, n_states).
    """
    low, high = np.asarray(low, float), np.asarray(high, float)
    rng = np.random.default_rng(seed)
    inside = rng.uniform(low, high, (n, len(low)))
    corners = _corners(low, high)
    faces = rng.uniform(low, high, (n, len(low)))
    k = rng.integers(0, len(low), n)
    faces[np.arange(n), k] = np.where(rng.random(n) < 0.5, low[k], high[k])
    return np.concatenate([inside, corners, faces]).astype(np.float32).astype(np.float64)


#: The float export of a GP cache is refused when float rounding widens its std by more
#: than this factor somewhere in the box (:func:`float_safe_controller`).
FLOAT_WIDENING_LIMIT = 10.0


def float_check_states(
    low: Any, high: Any, *, extra_states: Any = None, n_states: int = 4096, seed: int = 0
) -> np.ndarray:
    """The states a float export is checked at, shape (N, n).

    ``n_states`` uniform states of the box ``low <= x <= high``, its corners and
    ``extra_states``, rounded to float (what a float step is given).
    """
    low, high = np.asarray(low, float), np.asarray(high, float)
    rng = np.random.default_rng(seed)
    parts = [rng.uniform(low, high, size=(n_states, len(low))), _corners(low, high)]
    if extra_states is not None:
        parts.append(np.asarray(extra_states, float))
    return np.concatenate(parts).astype(np.float32).astype(np.float64)


def float_refusal(controller: Any, x: Any) -> str | None:
    """Why a float step cannot carry the controller's GP cache at states ``x``, or None.

    The reason (the message :func:`float_safe_controller` raises) when float rounding alone
    widens the cache's std by more than :data:`FLOAT_WIDENING_LIMIT` at some state of ``x``
    (N, n): the posterior variance is so far below the prior's that ``amp^2 - |a|^2`` cancels
    more digits than float has. None for a controller without such a cache.
    """
    unc = controller.uncertainty
    if unc is None or not hasattr(unc, "for_precision"):
        return None
    x = np.asarray(x, float)
    _, std = unc.predict(x, return_std=True)
    _, std_f = unc.for_precision("float").predict(x, return_std=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(std > 0, std_f / std, 1.0).max(0)
    worst = int(np.argmax(ratio))
    if ratio[worst] <= FLOAT_WIDENING_LIMIT:
        return None
    return (
        "precision='float' cannot evaluate this GP cache: for state component "
        f"{worst}, float rounding alone widens the std up to {ratio[worst]:.3g} times "
        f"the float64 cache's (to {std_f[:, worst].max():.3g} where the float64 "
        f"cache's is at most {std[:, worst].max():.3g}): the posterior variance is far "
        "below the prior one there, and amp^2 - |a|^2 cancels more digits than float "
        "has. Export in double (a Cortex-M7 with a double-precision FPU), or use a "
        "GP whose posterior std is closer to its prior (docs/export.md)"
    )


def filter_condition_scale(filt: Any, out: Any, states: Any) -> np.ndarray:
    """Per state and barrier, the magnitude a filter's CBF condition is rounded relative to.

    Shape (N, k). As :func:`~safestab.export.harness.cbf_condition_scale` for each of the
    filter's rows: ``|c_i| + sum_j |dh_i/dx_j| |f_j| + |alpha_i(h_i)| + rho Gamma_i +
    sum_l (|d_il| + sum_j |dh_i/dx_j| |g_jl|) |u_l|`` at the step's own ``u``, with the GP's
    ``|dh_i/dx| (|mean| + beta std)`` where the filter has an uncertainty model.
    """
    import jax
    import jax.numpy as jnp

    from ..sampled import sampled_shift

    x = jnp.asarray(np.asarray(states, float))
    sys_ = filt.system

    def one(s):
        f, g = sys_.f(s), sys_.g(s)
        grads = jnp.stack([cb.gradient(s) for cb in filt.cbfs])  # (k, n)
        alphas = jnp.stack([cb.rate_term(cb.value(s)) for cb in filt.cbfs])
        _, _, c, d, _ = filt.rows(s)
        spread = jnp.zeros_like(s)
        if filt.uncertainty is not None:
            mean, std = filt.uncertainty.mean_std(s)
            spread = jnp.abs(mean) + jnp.asarray(filt.gp_beta) * std
        c_sum = jnp.abs(grads) @ (jnp.abs(f) + spread) + jnp.abs(alphas)
        if filt.sample_time is not None:  # the sampled-data shift, which c may cancel
            hs = jnp.stack([cb.value(s) for cb in filt.cbfs])
            c_sum = c_sum + jnp.abs(sampled_shift(hs, alphas, filt.sample_time, filt.ddh_bound))
        d_mag = jnp.abs(d) + jnp.abs(grads) @ jnp.abs(g)
        return jnp.abs(c) + c_sum, d_mag, c, d

    c_mag, d_mag, c, d = (np.asarray(v) for v in jax.vmap(one)(x))
    u = np.abs(np.nan_to_num(np.asarray(out.u)))[:, None, :]
    varphi = float(filt.params["varphi"])
    gamma = np.sqrt(c * c + varphi * np.sum(d * d, -1) ** 2)
    rho = float(filt.params["rho"])
    return c_mag + rho * gamma + np.sum(d_mag * u, -1)


def float_safe_controller(
    controller: Any,
    low: Any,
    high: Any,
    *,
    extra_states: Any = None,
    n_states: int = 4096,
    seed: int = 0,
) -> tuple[Any, float]:
    """The controller to export in float, and its CBF margin.

    A float step errs on every term; two changes keep its CBF condition on the safe side of
    the exact one over the box ``low <= x <= high``:

    * a :class:`~safestab.learning.FastGP` uncertainty is replaced by
      ``FastGP.for_precision("float")``, whose band still contains the exact band when
      evaluated in float (where float cannot resolve the posterior variance, the band is
      as wide as float can vouch for);
    * ``cbf_margin = 2 E`` with ``E = DEFAULT_RTOL["float"] * max cbf_condition_scale``
      over ``n_states`` uniform states of the box, its corners and ``extra_states``: the
      float step's error on the condition, ``rtol`` times its magnitude, as the harness
      certifies for every term. The formula then enforces the condition with margin ``2 E``
      and ``cbf_satisfied`` reports it with margin ``E``, so a float step whose flag says
      satisfied satisfies the exact condition (tested in tests/test_embedded.py).

    For a :class:`~safestab.SafetyFilter` it also sets ``precision="float"`` (the solver's
    tolerances and the flags' at float's rounding) and measures ``E`` on every barrier's
    row (:func:`filter_condition_scale`), with the flags' own tolerance at that precision
    added to the float step's error.

    Outside the box the margin is not checked: export with the box the controller will see.

    Raises
    ------
    ParameterError
        If float rounding widens the GP cache's std by more than
        :data:`FLOAT_WIDENING_LIMIT` somewhere in the box: float cannot resolve that GP's
        posterior (the stress preset's drag: 3000 times); export it in double. For a
        :class:`~safestab.PolicyController` (it enforces nothing a margin could keep), and
        for a filter with run-time parameters.

    Returns
    -------
    (controller, margin)
    """
    from ..filters import SafetyFilter
    from ..formulas._dual_active_set import UNIT_FLOAT
    from ..formulas._kernels import satisfied_rtol
    from ..policy import PolicyController

    # what cannot be made float-safe is refused before any evaluation
    if isinstance(controller, PolicyController):
        raise ParameterError(
            "float_safe_controller takes a UniversalController or a SafetyFilter, got a "
            "PolicyController: it monitors a user's law and enforces no condition that a "
            "margin could keep; export it as it is"
        )
    is_filter = isinstance(controller, SafetyFilter)
    if is_filter and controller.params_spec is not None:
        raise ParameterError(
            "float_safe_controller needs a filter without run-time parameters (params=): "
            "its margin is measured over the box's states alone"
        )
    x = float_check_states(low, high, extra_states=extra_states, n_states=n_states, seed=seed)
    reason = float_refusal(controller, x)
    if reason is not None:
        raise ParameterError(reason)
    unc = controller.uncertainty
    if unc is not None and hasattr(unc, "for_precision"):
        unc_f = unc.for_precision("float")
        controller = controller.replace(uncertainty=unc_f)
    # the error the margin covers: the float step's (the harness's rtol) and, for a filter,
    # the tolerance its flags and its certificate accept at float's rounding
    rtol = DEFAULT_RTOL["float"]
    if is_filter:  # the solver's tolerances and the flags' to float's rounding
        rtol += satisfied_rtol(UNIT_FLOAT)
        controller = controller.replace(precision="float")
    margin = 0.0
    for _ in range(3):  # the margin moves u a little: recompute the scale at the new u
        ctrl = controller.replace(cbf_margin=margin)
        out = ctrl.step_fn(x)
        scale = (
            filter_condition_scale(ctrl, out, x) if is_filter else cbf_condition_scale(ctrl, out, x)
        )
        need = 2.0 * rtol * float(np.nanmax(scale))
        if need <= margin:
            break
        margin = 1.25 * need
    return controller.replace(cbf_margin=margin), margin
