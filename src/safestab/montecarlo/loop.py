"""The batched closed loop of a Monte Carlo study: ``lax.scan`` over time inside ``vmap``.

One trial runs every compared controller on its own copy of the plant, from the same initial
state and under the same exogenous input, and keeps only running statistics (no history), so
memory grows with the number of trials in a chunk, not with the horizon. The exogenous input
is per-trial *data* passed through the scan (``params``), not a Python closure, so a batch of
random lead profiles is one ``vmap``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from ..certificates import lie_terms_point
from ..controllers import StepStatus, UniversalController
from ..formulas import SATISFIED_RTOL, Region
from ..simulation import rk4_step
from ..systems import ControlAffineSystem

__all__ = ["RECORD_FIELDS", "trial_function"]

#: The per-trial, per-controller records, with their meaning (docs/montecarlo.md).
RECORD_FIELDS: dict[str, str] = {
    "min_h": "smallest h over the visited states t_0 .. t_K (m for the ACC)",
    "time_h_negative": "time with h < 0 (s): steps k < K with h(x_k) < 0, times dt",
    "cbf_true_violations": "steps where the applied u broke the CBF condition on the TRUE "
    "dynamics, L_f h + L_g h u + dh/dx e(t) + beta h >= 0 (relative tolerance SATISFIED_RTOL)",
    "min_cbf_true_margin": "smallest L_f h + L_g h u + dh/dx e + beta h (true dynamics)",
    "clf_true_fraction": "fraction of steps where the applied u met the CLF condition on the true "
    "dynamics, L_f V + L_g V u + dV/dx e + lambda V <= 0",
    "final_V": "V at the final state",
    "incompatible_steps": "steps where the conditions the controller used were incompatible",
    "lemma2_violations": "visited states where |omega_i - m_i| <= beta_i sigma_i failed for "
    "some i, with the simulator's true omega; -1 for controllers without a GP",
    "first_bad_status": "the first StepStatus other than OK (0 if none)",
    "first_bad_step": "the step of first_bad_status (-1 if none)",
}

#: ``e(t, x, params) -> (n,)``: a known term of the true dynamics, from per-trial data.
Exogenous = Callable[[jax.Array, jax.Array, Any], jax.Array]
#: ``omega(x, params) -> (n,)``: the true model error the GP learns.
Omega = Callable[[jax.Array, Any], jax.Array]


def _violated(value: jax.Array, scale: jax.Array, sign: float) -> jax.Array:
    """``sign * value < 0`` beyond a rounding allowance relative to the terms' magnitude."""
    return sign * value < -SATISFIED_RTOL * scale


def _materialized(value: jax.Array, k: jax.Array) -> jax.Array:
    """``value``, computed once into a buffer: its consumers read it instead of recomputing it.

    XLA's CPU fusion copies cheap producers (the RK4 combination of the step's next state)
    into every consumer, per element of the consumer's output: the GP's kernel values at the
    next state, ``(M_c, B)`` per component, and every small fusion of the controller recomputed
    the whole RK4 update (measured: a third of the loop's time after the GP's padding was
    dropped). ``optimization_barrier`` is removed by XLA's CPU pipeline before fusion; a
    conditional is not, and nothing fuses across it. ``k`` (the step, never negative, not known
    to XLA) picks the identity branch; the other is never taken.
    """
    return jax.lax.cond(k >= 0, lambda v: v, lambda v: -v, value)


class _Given:
    """An uncertainty model returning a mean and std computed already (for one state)."""

    def __init__(self, mean: jax.Array, std: jax.Array, n_states: int) -> None:
        self._mean, self._std, self.n_states = mean, std, n_states

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        return self._mean, self._std


def trial_function(
    controllers: Sequence[UniversalController],
    *,
    plant: ControlAffineSystem,
    n_steps: int,
    dt: float,
    exogenous: Exogenous | None = None,
    omega: Omega | None = None,
    lemma2: Sequence[tuple[Any, jax.Array] | None] | None = None,
    rebuild: Sequence[Callable[[Any], UniversalController] | None] | None = None,
) -> Callable[[jax.Array, Any], dict[str, jax.Array]]:
    """Build ``run(x0, params) -> records`` for one trial and every controller.

    Parameters
    ----------
    controllers : sequence of UniversalController
        ``C`` controllers (the same CLF and CBF); each drives its own copy of ``plant``.
    plant : ControlAffineSystem
        The true dynamics.
    n_steps : int
        Steps ``K``; ``K + 1`` states are visited (``t_0 .. t_K``).
    dt : float
        Step, s (zero-order hold, one RK4 step per ``dt``, as :func:`~safestab.simulate`).
    exogenous : callable, optional
        ``e(t, x, params)`` of shape (n,), added to the true dynamics.
    omega : callable, optional
        ``omega(x, params)`` of shape (n,), the true model error; needed with ``lemma2``.
    lemma2 : sequence of (uncertainty, beta) or None, optional
        Per controller, the uncertainty model and ``beta`` (n,) whose band
        ``|omega_i - m_i| <= beta_i sigma_i`` is checked at every visited state (with the true
        ``omega``), or ``None`` (no GP; recorded as -1).
    rebuild : sequence of callable or None, optional
        Per controller with a ``lemma2`` check, ``rebuild(uncertainty)`` returns the same
        controller with another uncertainty model. The GP is then evaluated once per step:
        its mean and std at the state feed both the controller (through a model returning
        them) and the check, instead of once in each (XLA did not merge the two evaluations:
        measured, the check doubled the cost of a GP-robust step).

    Returns
    -------
    callable
        ``run(x0, params)`` with ``x0`` of shape (n,) and ``params`` a pytree of per-trial
        data; returns a dict of arrays of shape (C,), keys :data:`RECORD_FIELDS`. Jittable and
        meant to be ``vmap``-ed over trials.
    """
    ctrls = tuple(controllers)
    checks = tuple(lemma2) if lemma2 is not None else (None,) * len(ctrls)
    builders = tuple(rebuild) if rebuild is not None else (None,) * len(ctrls)
    if len(checks) != len(ctrls) or len(builders) != len(ctrls):
        raise ValueError("lemma2 and rebuild must have one entry per controller")
    if omega is None and any(c is not None for c in checks):
        raise ValueError("lemma2 checks need omega")
    clf, cbf = ctrls[0].clf, ctrls[0].cbf
    n = plant.n_states

    def exo(t, x, p):
        return jnp.zeros(n) if exogenous is None else exogenous(t, x, p)

    def evaluate(i, x):
        """Controller ``i`` at ``x``: what the step's records and the integration need."""
        ctrl, check, build = ctrls[i], checks[i], builders[i]
        mean = std = jnp.zeros(n)
        if check is not None and build is not None:
            mean, std = check[0].mean_std(x)  # once: for the controller and the check
            ctrl = build(_Given(mean, std, n))
        out = ctrl.step_fn(x)
        incompatible = (~out.compatible) | (out.region == Region.INCOMPATIBLE)
        return {"u": out.u, "incompatible": incompatible, "status": out.status,
                "mean": mean, "std": std}  # fmt: skip

    def lemma2_bad(i, x, p, ev):
        check = checks[i]
        if check is None or omega is None:
            return jnp.asarray(False)
        model, beta = check
        mean, std = (ev["mean"], ev["std"]) if builders[i] is not None else model.mean_std(x)
        return jnp.any(jnp.abs(omega(x, p) - mean) > beta * std)

    def record(i, x, t, p, ev):
        """The step's quantities at ``x`` with the controller's output ``ev`` there."""
        u = ev["u"]
        a, b, c, d = lie_terms_point(plant, clf, cbf, x)
        e = exo(t, x, p)
        gv, gh = clf.grad(x), cbf.grad(x)
        c_true = c + gh @ e + d @ u
        a_true = a + gv @ e + b @ u
        cbf_bad = _violated(c_true, jnp.abs(c) + jnp.abs(gh @ e) + jnp.abs(d) @ jnp.abs(u), 1.0)
        clf_ok = ~_violated(a_true, jnp.abs(a) + jnp.abs(gv @ e) + jnp.abs(b) @ jnp.abs(u), -1.0)
        return (cbf.fn(x), c_true, cbf_bad, clf_ok, ev["incompatible"],
                lemma2_bad(i, x, p, ev), ev["status"])  # fmt: skip

    def body(carry, k):
        # The controller's output at x_k comes in the carry: computed at the end of the
        # previous iteration (before the loop for k = 0). Had it been computed here, XLA
        # would have fused the tail of the closed form into each of its consumers (the four
        # RK4 stages, per state component), evaluating it a dozen times per step (measured:
        # a third of the loop's time). The same operations; XLA's other fusion can round the
        # last bits of the records differently (measured: 4e-15 relative at most).
        xs, evs, stats = carry
        t = k * dt
        p = stats["params"]
        new_x, new_evs, new_stats = [], [], []
        for i in range(len(ctrls)):
            x, ev = xs[i], evs[i]
            h, c_true, cbf_bad, clf_ok, incomp, l2_bad, status = record(i, x, t, p, ev)
            u = ev["u"]
            x_next = rk4_step(lambda s, y, u=u: plant.f(y) + plant.g(y) @ u + exo(s, y, p),
                              t, x, dt)  # fmt: skip
            x_next = _materialized(x_next, k)
            s = stats["per"][i]
            bad = status != StepStatus.OK
            first = (s["first_bad_status"] == 0) & bad
            new_stats.append(
                {
                    "min_h": jnp.minimum(s["min_h"], h),
                    "h_negative_steps": s["h_negative_steps"] + (h < 0),
                    "cbf_true_violations": s["cbf_true_violations"] + cbf_bad,
                    "min_cbf_true_margin": jnp.minimum(s["min_cbf_true_margin"], c_true),
                    "clf_true_steps": s["clf_true_steps"] + clf_ok,
                    "incompatible_steps": s["incompatible_steps"] + incomp,
                    "lemma2_violations": s["lemma2_violations"] + l2_bad,
                    "first_bad_status": jnp.where(first, status, s["first_bad_status"]),
                    "first_bad_step": jnp.where(first, k, s["first_bad_step"]),
                }
            )
            new_x.append(x_next)
            new_evs.append(evaluate(i, x_next))  # for step k + 1 (at k = K - 1: the final state)
        return (jnp.stack(new_x), new_evs, {"params": p, "per": new_stats}), None

    def run(x0: jax.Array, params: Any) -> dict[str, jax.Array]:
        zero_i = jnp.asarray(0, jnp.int64)
        init = {
            "min_h": jnp.asarray(jnp.inf),
            "h_negative_steps": zero_i,
            "cbf_true_violations": zero_i,
            "min_cbf_true_margin": jnp.asarray(jnp.inf),
            "clf_true_steps": zero_i,
            "incompatible_steps": zero_i,
            "lemma2_violations": zero_i,
            "first_bad_status": zero_i,
            "first_bad_step": jnp.asarray(-1, jnp.int64),
        }
        xs0 = jnp.broadcast_to(x0, (len(ctrls), n))
        evs0 = [evaluate(i, x0) for i in range(len(ctrls))]
        carry0 = (xs0, evs0, {"params": params, "per": [dict(init) for _ in ctrls]})
        (xs_final, evs_final, stats), _ = jax.lax.scan(body, carry0, jnp.arange(n_steps))
        records: dict[str, list[jax.Array]] = {key: [] for key in RECORD_FIELDS}
        for i, s in enumerate(stats["per"]):
            x_final = xs_final[i]
            h_final = cbf.fn(x_final)
            final_bad = ~jnp.all(jnp.isfinite(x_final)) & (s["first_bad_status"] == 0)
            l2_final = lemma2_bad(i, x_final, params, evs_final[i])
            records["min_h"].append(jnp.minimum(s["min_h"], h_final))
            records["time_h_negative"].append(s["h_negative_steps"] * dt)
            records["cbf_true_violations"].append(s["cbf_true_violations"])
            records["min_cbf_true_margin"].append(s["min_cbf_true_margin"])
            records["clf_true_fraction"].append(s["clf_true_steps"] / n_steps)
            records["final_V"].append(clf.fn(x_final))
            records["incompatible_steps"].append(s["incompatible_steps"])
            records["lemma2_violations"].append(
                s["lemma2_violations"] + l2_final if checks[i] is not None else jnp.asarray(-1)
            )
            records["first_bad_status"].append(
                jnp.where(final_bad, int(StepStatus.NONFINITE_STATE), s["first_bad_status"])
            )
            records["first_bad_step"].append(jnp.where(final_bad, n_steps, s["first_bad_step"]))
        return {key: jnp.stack([jnp.asarray(v) for v in vals]) for key, vals in records.items()}

    return run
