"""The Monte Carlo study's trial: the package's closed loop with running statistics.

One trial runs every compared controller on its own copy of the plant (the closed loop of
:func:`~safestab.closed_loop`, ``lax.scan`` over time, ``vmap``-ed over trials), from the same
initial state and under the same exogenous input, and keeps only running statistics (no
history), so memory grows with the number of trials in a chunk, not with the horizon. The
exogenous input is per-trial *data* (``params``), not a Python constant, so a batch of random
lead profiles is one ``vmap``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from ..certificates import CBF, CLF
from ..controllers import Controller, StepStatus, has_input
from ..errors import DimensionError, InputTypeError, ParameterError
from ..formulas import SATISFIED_RTOL
from ..simulation import closed_loop
from ..systems import ControlAffineSystem

__all__ = ["RECORD_FIELDS", "StatisticsRecorder", "trial_function"]

#: The per-trial, per-controller records, with their meaning (docs/montecarlo.md).
RECORD_FIELDS: dict[str, str] = {
    "min_h": "smallest h over the visited states t_0 .. t_K (m for the ACC)",
    "min_h_between": "smallest h over every hold interval, at its start and after each of "
    "the spec's substeps (equal to min_h with one substep: the samples alone)",
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
    "first_bad_status": "the first StepStatus that gave no input (statuses 1 to 7: a "
    "non-finite state, model or input; 0 if none)",
    "first_bad_step": "the step of first_bad_status (-1 if none)",
    "mean_input_gap": "mean over steps of max_j |u_j - u_ref,j(x)|, u_ref the reference "
    "(true-model) controller's input at the same state; -1 when not measured "
    "(MonteCarloSpec.price_metrics)",
    "barrier_unmet_steps": "steps whose input broke a CBF condition the controller enforces "
    "and said so (StepStatus CBF_UNACTUATED, CBF_INFEASIBLE, CBF_UNMET or UNCERTIFIED: the "
    "limits and the barrier conflicted, say)",
    "limit_steps": "steps whose applied input lies on a limit (some u_j at u_min,j or u_max,j, "
    "within SATISFIED_RTOL of the bound); 0 without limits",
    "settle_time": "time (s) from which V stays at or below SETTLE_FRACTION V(x_0) to the end; "
    "the horizon if it never settles; -1 when not measured",
}

#: ``settle_time``: V at or below this fraction of its initial value counts as converged.
SETTLE_FRACTION = 0.01

#: ``e(t, x, params) -> (n,)``: a known term of the true dynamics, from per-trial data.
Exogenous = Callable[[jax.Array, jax.Array, Any], jax.Array]
#: ``omega(x, params) -> (n,)``: the true model error the GP learns.
Omega = Callable[[jax.Array, Any], jax.Array]


def _violated(value: jax.Array, scale: jax.Array, sign: float) -> jax.Array:
    """``sign * value < 0`` beyond a rounding allowance relative to the terms' magnitude."""
    return sign * value < -SATISFIED_RTOL * scale


class StatisticsRecorder:
    """The running statistics of one controller's trial (:data:`RECORD_FIELDS`), no history.

    The step's output it reads is a dict: ``u``, ``incompatible``, ``status`` and, for a
    Lemma-2 check, the uncertainty model's ``mean`` and ``std`` at the state.

    ``cbfs``: the barriers recorded (one or more): ``h`` is their least value, a step breaks
    the CBF condition where one of them does, the margin is the least over them. ``clf``:
    the CLF recorded, or None (``clf_true_fraction``, ``final_V`` and ``settle_time`` are
    then -1).
    """

    def __init__(self, plant, clf, cbfs, exo, omega, beta, n_steps, dt, price=False) -> None:
        self.plant, self.clf, self.cbfs, self.exo = plant, clf, tuple(cbfs), exo
        self.omega, self.beta, self.n_steps, self.dt = omega, beta, n_steps, dt
        self.price = price  # the step's output then has "u_ref"

    def h(self, x: jax.Array) -> jax.Array:
        """The least barrier value at ``x`` (the one barrier's value for one)."""
        values = [cbf.fn(x) for cbf in self.cbfs]
        return values[0] if len(values) == 1 else jnp.min(jnp.stack(values))

    def init(self, x0: jax.Array, data: Any) -> dict[str, jax.Array]:
        """The statistics before the first step (minima at inf, counts at 0)."""
        zero_i = jnp.asarray(0, jnp.int64)
        return {
            "min_h": jnp.asarray(jnp.inf),
            "min_h_between": jnp.asarray(jnp.inf),
            "h_negative_steps": zero_i,
            "cbf_true_violations": zero_i,
            "min_cbf_true_margin": jnp.asarray(jnp.inf),
            "clf_true_steps": zero_i,
            "incompatible_steps": zero_i,
            "lemma2_violations": zero_i,
            "first_bad_status": zero_i,
            "first_bad_step": jnp.asarray(-1, jnp.int64),
            "barrier_unmet_steps": zero_i,
            "limit_steps": zero_i,
            **(self._price_init(x0) if self.price else {}),
        }

    def _price_init(self, x0: jax.Array) -> dict[str, jax.Array]:
        """The running sums of ``mean_input_gap`` and ``settle_time`` (``price`` only)."""
        return {
            "input_gap_sum": jnp.asarray(0.0),
            "v_settled": SETTLE_FRACTION * self.clf.fn(x0),
            "last_unsettled": jnp.asarray(-1, jnp.int64),
        }

    def _lemma2_bad(self, x: jax.Array, data: Any, ev: dict) -> jax.Array:
        if self.beta is None or self.omega is None:
            return jnp.asarray(False)
        return jnp.any(jnp.abs(self.omega(x, data) - ev["mean"]) > self.beta * ev["std"])

    def update(self, s, k, t, x, ev, data, between=None):
        """The statistics after step ``k`` (the true dynamics' conditions at ``x``).

        ``between``: the least ``h`` over the hold interval after ``x`` (substeps), if any.
        """
        plant, clf = self.plant, self.clf
        u = ev["u"]
        e = self.exo(t, x, data)
        cbf_bad, c_true = jnp.asarray(False), jnp.asarray(jnp.inf)
        for cbf in self.cbfs:  # each barrier's condition on the true dynamics
            c, d = cbf.lie_point(plant, x)
            gh = cbf.grad(x)
            c_i = c + gh @ e + d @ u
            scale = jnp.abs(c) + jnp.abs(gh @ e) + jnp.abs(d) @ jnp.abs(u)
            cbf_bad = cbf_bad | _violated(c_i, scale, 1.0)
            c_true = jnp.minimum(c_true, c_i)
        clf_ok = jnp.asarray(False)
        if clf is not None:
            a, b = clf.lie_point(plant, x)
            gv = clf.grad(x)
            a_true = a + gv @ e + b @ u
            scale = jnp.abs(a) + jnp.abs(gv @ e) + jnp.abs(b) @ jnp.abs(u)
            clf_ok = ~_violated(a_true, scale, -1.0)
        h, status = self.h(x), ev["status"]
        bad = ~has_input(status)
        first = (s["first_bad_status"] == 0) & bad
        least = h if between is None else jnp.minimum(h, between)
        new = {
            "min_h": jnp.minimum(s["min_h"], h),
            "min_h_between": jnp.minimum(s["min_h_between"], least),
            "h_negative_steps": s["h_negative_steps"] + (h < 0),
            "cbf_true_violations": s["cbf_true_violations"] + cbf_bad,
            "min_cbf_true_margin": jnp.minimum(s["min_cbf_true_margin"], c_true),
            "clf_true_steps": s["clf_true_steps"] + clf_ok,
            "incompatible_steps": s["incompatible_steps"] + ev["incompatible"],
            "lemma2_violations": s["lemma2_violations"] + self._lemma2_bad(x, data, ev),
            "first_bad_status": jnp.where(first, status, s["first_bad_status"]),
            "first_bad_step": jnp.where(first, k, s["first_bad_step"]),
            "barrier_unmet_steps": s["barrier_unmet_steps"] + (status >= StepStatus.CBF_UNACTUATED),
            "limit_steps": s["limit_steps"] + ev["at_limit"],
        }
        if self.price:
            unsettled = self.clf.fn(x) > s["v_settled"]
            new |= {
                "input_gap_sum": s["input_gap_sum"] + jnp.max(jnp.abs(u - ev["u_ref"])),
                "v_settled": s["v_settled"],
                "last_unsettled": jnp.where(unsettled, k, s["last_unsettled"]),
            }
        return new, None

    def finish(self, s, ys, x_final, ev_final, t_final, data) -> dict[str, jax.Array]:
        """The records of :data:`RECORD_FIELDS`, with the final state's values."""
        n_steps = self.n_steps
        final_bad = ~jnp.all(jnp.isfinite(x_final)) & (s["first_bad_status"] == 0)
        l2 = s["lemma2_violations"] + self._lemma2_bad(x_final, data, ev_final)
        no_clf = jnp.asarray(-1.0)
        v_final = no_clf if self.clf is None else self.clf.fn(x_final)
        h_final = self.h(x_final)
        return {
            "min_h": jnp.minimum(s["min_h"], h_final),
            "min_h_between": jnp.minimum(s["min_h_between"], h_final),
            "time_h_negative": s["h_negative_steps"] * self.dt,
            "cbf_true_violations": s["cbf_true_violations"],
            "min_cbf_true_margin": s["min_cbf_true_margin"],
            "clf_true_fraction": no_clf if self.clf is None else s["clf_true_steps"] / n_steps,
            "final_V": v_final,
            "incompatible_steps": s["incompatible_steps"],
            "lemma2_violations": l2 if self.beta is not None else jnp.asarray(-1),
            "first_bad_status": jnp.where(
                final_bad, int(StepStatus.NONFINITE_STATE), s["first_bad_status"]
            ),
            "first_bad_step": jnp.where(final_bad, n_steps, s["first_bad_step"]),
            "barrier_unmet_steps": s["barrier_unmet_steps"],
            "limit_steps": s["limit_steps"],
            **(self._price_finish(s, v_final) if self.price else
               {"mean_input_gap": jnp.asarray(-1.0), "settle_time": jnp.asarray(-1.0)}),
        }  # fmt: skip

    def _price_finish(self, s: dict, v_final: jax.Array) -> dict[str, jax.Array]:
        # settled from step last_unsettled + 1 on; with the final state unsettled (V(x_K)
        # above the threshold), never: the horizon
        last = jnp.where(v_final > s["v_settled"], self.n_steps,
                         s["last_unsettled"] + 1)  # fmt: skip
        return {"mean_input_gap": s["input_gap_sum"] / self.n_steps,
                "settle_time": last * self.dt}  # fmt: skip


def _at_limit(ctrl: Any, u: jax.Array) -> jax.Array:
    """Whether some input component lies on its limit (within SATISFIED_RTOL of the bound)."""
    if getattr(ctrl, "u_min", None) is None:
        return jnp.asarray(False)
    lo, hi = jnp.asarray(ctrl.u_min), jnp.asarray(ctrl.u_max)
    # an infinite side is never reached (and its tolerance would be inf - inf)
    on_lo = jnp.isfinite(lo) & (u <= lo + SATISFIED_RTOL * jnp.abs(lo))
    on_hi = jnp.isfinite(hi) & (u >= hi - SATISFIED_RTOL * jnp.abs(hi))
    return jnp.any(on_lo | on_hi)


def trial_function(
    controllers: Sequence[Controller],
    *,
    plant: ControlAffineSystem,
    clf: CLF | None = None,
    cbfs: CBF | Sequence[CBF] | None = None,
    n_steps: int,
    dt: float,
    exogenous: Exogenous | None = None,
    omega: Omega | None = None,
    lemma2: Sequence[tuple[Any, jax.Array] | None] | None = None,
    reference: Controller | None = None,
    substeps: int = 1,
) -> Callable[[jax.Array, Any], dict[str, jax.Array]]:
    """Build ``run(x0, params) -> records`` for one trial and every controller.

    Each controller runs the package's one closed loop (:func:`~safestab.closed_loop`) with
    a :class:`StatisticsRecorder`.

    Parameters
    ----------
    controllers : Controller or sequence of Controller
        ``C`` controllers of any kind: :class:`~safestab.UniversalController` (with or
        without a CLF or a CBF), :class:`~safestab.SafetyFilter` (any formula, any number of
        rows), :class:`~safestab.PolicyController` (a user's own law); each drives its own
        copy of ``plant``, and all are scored on the same certificates (``clf``, ``cbfs``).
        The ``incompatible`` record counts the steps whose conditions were incompatible
        (a filter: whose problem was not solved whole, ``formula_status`` other than
        ``SOLVED``; never for a PolicyController).
    plant : ControlAffineSystem
        The true dynamics.
    clf : CLF, optional
        The CLF the records use (``clf_true_fraction``, ``final_V``, ``settle_time``);
        default the first controller's first CLF; where there is none, those records are
        -1.
    cbfs : CBF or sequence of CBF, optional
        The barriers the records use: ``min_h`` and ``min_h_between`` are the least value
        over them, a step breaks the CBF condition where one of them does. Default: the
        first controller's CBFs.
    n_steps : int
        Steps ``K``; ``K + 1`` states are visited (``t_0 .. t_K``).
    dt : float
        Step, s (zero-order hold, one RK4 step per ``dt``, as :func:`~safestab.simulate`).
    exogenous : callable, optional
        ``e(t, x, params)`` of shape (n,), added to the true dynamics.
    omega : callable, optional
        ``omega(x, params)`` of shape (n,), the true model error; needed with ``lemma2``.
    lemma2 : sequence of (uncertainty, beta) or None, optional
        Per controller, an uncertainty model and ``beta`` (n,) whose band
        ``|omega_i - m_i| <= beta_i sigma_i`` is checked at every visited state (with the true
        ``omega``), or ``None`` (no check; recorded as -1). When the model is the
        controller's own, it is evaluated once per step for both
        (:meth:`~safestab.UniversalController.step_with_uncertainty`; XLA does not merge two
        evaluations: measured, the check doubled the cost of a GP-robust step).
    reference : UniversalController, optional
        With it, every controller's trial also records ``mean_input_gap`` (its input against
        this controller's input at the same state, one more step per step) and
        ``settle_time``; without, both are -1.
    substeps : int
        RK4 steps per hold interval (default 1); with more, ``min_h_between`` records the
        least ``h`` at every substep (what the samples alone can miss).

    Returns
    -------
    callable
        ``run(x0, params)`` with ``x0`` of shape (n,) and ``params`` a pytree of per-trial
        data; returns a dict of arrays of shape (C,), keys :data:`RECORD_FIELDS`. Jittable and
        meant to be ``vmap``-ed over trials.

    Raises
    ------
    ValueError
        If ``lemma2`` has not one entry per controller, or checks are asked without
        ``omega``.
    InputTypeError
        If a controller is not a :class:`~safestab.Controller`, or ``clf``/``cbfs`` are not
        certificates.
    ParameterError
        If no CBF is given or found (the records are about safety), if a ``reference`` is
        given without a CLF (``settle_time`` needs one), or if a controller takes run-time
        parameters.
    """
    ctrls = (controllers,) if isinstance(controllers, Controller) else tuple(controllers)
    bad = [type(c).__name__ for c in ctrls if not isinstance(c, Controller)]
    if bad or not ctrls:
        raise InputTypeError(
            "controllers must be a non-empty sequence of safestab controllers "
            f"(UniversalController, SafetyFilter, PolicyController), got {bad or 'none'}"
        )
    for c in ctrls:
        dims = (c.system.n_states, c.system.n_inputs)
        if dims != (plant.n_states, plant.n_inputs):
            raise DimensionError(
                f"plant dimensions (n={plant.n_states}, m={plant.n_inputs}) differ from the "
                f"controller's model (n={dims[0]}, m={dims[1]}): {c!r}"
            )
    takes = [repr(c) for c in ctrls if c.params_spec is not None]
    if takes:
        raise ParameterError(
            f"the trial loop passes no run-time parameters, but {takes[0]} takes them; bind "
            "their values in its functions (per-trial data reaches exogenous and omega)"
        )
    checks = tuple(lemma2) if lemma2 is not None else (None,) * len(ctrls)
    if len(checks) != len(ctrls):
        raise ValueError("lemma2 must have one entry per controller")
    if omega is None and any(c is not None for c in checks):
        raise ValueError("lemma2 checks need omega")
    clf, cbfs = _record_certificates(ctrls[0], clf, cbfs, reference)
    cbf = cbfs[0] if len(cbfs) == 1 else None
    n = plant.n_states

    def exo(t, x, p):
        return jnp.zeros(n) if exogenous is None else exogenous(t, x, p)

    def rhs(t, x, ev, p):
        return plant.f(x) + plant.g(x) @ ev["u"] + exo(t, x, p)

    def stepper(ctrl, check):
        def step(t, x, p):
            mean = std = jnp.zeros(n)
            if check is not None:
                mean, std = check[0].mean_std(x)
            if check is not None and check[0] is ctrl.uncertainty:
                out = ctrl.step_with_uncertainty(x, mean, std)  # the model evaluated once
            else:
                out = ctrl.step_fn(x)
            # a filter: a CBF relaxed against the box, or the solver stopped uncertified (the
            # problem was not solved whole); a universal formula: Lemma 1's incompatibility
            ev = {"u": out.u, "incompatible": out.incompatible, "status": out.status,
                  "mean": mean, "std": std, "at_limit": _at_limit(ctrl, out.u)}  # fmt: skip
            if reference is not None:
                ev["u_ref"] = reference.step_fn(x).u
            return ev

        return step

    def watch(t, x, p):  # the least barrier value inside each hold interval
        return cbf.fn(x) if cbf is not None else jnp.min(jnp.stack([c.fn(x) for c in cbfs]))

    loops = [
        closed_loop(
            stepper(ctrl, check),
            rhs,
            StatisticsRecorder(
                plant,
                clf,
                cbfs,
                exo,
                omega,
                None if check is None else check[1],
                n_steps,
                dt,
                price=reference is not None,
            ),
            n_steps=n_steps,
            dt=dt,
            substeps=substeps,
            watch=None if substeps == 1 else watch,
        )
        for ctrl, check in zip(ctrls, checks, strict=True)
    ]

    def run(x0: jax.Array, params: Any) -> dict[str, jax.Array]:
        per = [loop(x0, params) for loop in loops]
        return {key: jnp.stack([jnp.asarray(r[key]) for r in per]) for key in RECORD_FIELDS}

    return run


def _record_certificates(
    first: Controller, clf: Any, cbfs: Any, reference: Any
) -> tuple[CLF | None, tuple[CBF, ...]]:
    """The records' CLF and CBFs: as given, else the first controller's; checked."""
    if clf is None:
        clf = first.clfs[0] if first.clfs else None
    elif not isinstance(clf, CLF):
        raise InputTypeError(f"clf must be a CLF or None, got {type(clf).__name__}")
    if cbfs is None:
        cbfs = first.cbfs
    cbfs = (cbfs,) if isinstance(cbfs, CBF) else tuple(cbfs)
    if not all(isinstance(c, CBF) for c in cbfs):
        raise InputTypeError(
            f"cbfs must be a CBF or a sequence of CBFs, got {[type(c).__name__ for c in cbfs]}"
        )
    if not cbfs:
        raise ParameterError(
            "the trial records are about safety: give cbfs= (the first controller has no CBF)"
        )
    if reference is not None and clf is None:
        raise ParameterError(
            "settle_time (with a reference) needs a CLF: give clf= (the first controller has none)"
        )
    return clf, cbfs
