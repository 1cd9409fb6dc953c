"""Closed-loop simulation: fixed-step RK4 with zero-order hold, compiled with ``lax.scan``."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from ._numerics import tied
from ._params import ParamSpec, merge_specs, resolve
from ._validation import check_real, check_scalar_range, traced_results
from .controllers import (
    Controller,
    StepStatus,
    UniversalController,
    controller_step,
    has_input,
)
from .errors import (
    DimensionError,
    InfeasibleError,
    InputTypeError,
    ModelError,
    NonFiniteError,
    ParameterError,
)
from .formulas import MultiStatus, Region
from .systems import ControlAffineSystem

__all__ = [
    "MAX_STEPS",
    "Recorder",
    "Trajectory",
    "TrajectoryRecorder",
    "closed_loop",
    "rk4_step",
    "simulate",
]

#: The most steps one call of :func:`simulate` takes (``t_final / dt``); beyond it the request is
#: almost certainly a unit mistake, and the history would not fit in memory with a batch.
MAX_STEPS = 10_000_000
#: The largest history :func:`simulate` allocates (states, inputs and diagnostics), bytes.
MAX_HISTORY_BYTES = 8 * 2**30

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
        CLF and CBF values at ``x`` (NaN where a controller has no CLF, or no CBF); for a
        :class:`~safestab.SafetyFilter` (any formula) or a
        :class:`~safestab.PolicyController`, shapes (..., T, p) and (..., T, k): one value per
        CLF and per CBF.
    region : int array of shape (..., T)
        :class:`~safestab.formulas.Region` per step; for a filter its
        :class:`~safestab.formulas.MultiStatus` (``SOLVED`` or the fallback used).
    compatible : bool array of shape (..., T)
        Compatibility of the conditions the controller used, per step (for a filter: the
        whole problem was solved, ``SOLVED``).
    cbf_satisfied : bool array of shape (..., T)
        Whether the applied input met the controller's CBF condition (for a filter: every
        barrier's).
    status : int array of shape (..., T)
        :class:`~safestab.controllers.StepStatus` per step: ``NONFINITE_STATE`` from the first
        step whose state is not finite (a diverging plant), or the controller's own status.
    h_between : array of shape (..., T) or (..., T, k), or None
        With ``simulate(..., substeps=N)``, ``N > 1``: the least ``h`` over each hold
        interval ``[t_k, t_k + dt]``, at its start and after each of the ``N`` RK4
        substeps (NaN at the final sample, which starts no interval); ``None`` otherwise.
        The samples alone (``h``) can miss a dip between them.
    multi : bool
        True for a filter's trajectory (static: not a pytree leaf).
    """

    t: jax.Array
    x: jax.Array
    u: jax.Array
    V: jax.Array
    h: jax.Array
    region: jax.Array
    compatible: jax.Array
    cbf_satisfied: jax.Array
    status: jax.Array
    h_between: jax.Array | None = None
    multi: bool = False

    @property
    def infeasible_steps(self) -> int:
        """Number of steps where the formula met no compatible conditions (all batches).

        For a filter: the steps that used a fallback or stopped uncertified (its
        :class:`~safestab.formulas.MultiStatus` is not ``SOLVED``).
        """
        if self.multi:
            return int(np.sum(np.asarray(self.region) != MultiStatus.SOLVED))
        return int(np.sum(np.asarray(self.region) == Region.INCOMPATIBLE))

    @property
    def ok(self) -> bool:
        """True when every step of every trajectory has status ``OK``.

        So every step produced an input and that input met every CBF condition the controller
        enforces, at the samples (docs/deployed.md says what holds between them).
        """
        return bool(np.all(np.asarray(self.status) == StepStatus.OK))

    @property
    def barrier_unmet_steps(self) -> int:
        """Steps (all batches) whose applied input broke a CBF condition the controller used.

        Counted where the step produced an input (``cbf_satisfied`` False there): the
        statuses ``CBF_UNACTUATED``, ``CBF_INFEASIBLE`` and ``CBF_UNMET``, and, for Sontag's
        CLF formula, which does not enforce the CBF, the steps whose input happened to break
        it.
        """
        with_input = np.asarray(has_input(np.asarray(self.status)))
        return int(np.sum(with_input & ~np.asarray(self.cbf_satisfied, dtype=bool)))

    @property
    def first_failure_index(self) -> np.ndarray:
        """Index of the first step whose status is not OK, per trajectory (-1 if none).

        An int array of the batch shape (a 0-d array for a single trajectory).
        """
        bad = np.asarray(self.status) != StepStatus.OK
        first = np.argmax(bad, axis=-1)
        return np.where(np.any(bad, axis=-1), first, -1)

    def failure_summary(self) -> str:
        """One line naming the first step that was not OK (status and time), or ``"ok"``.

        Where inputs broke a barrier's condition, the line also counts those steps
        (:attr:`barrier_unmet_steps`).
        """
        status = np.asarray(self.status)
        if not np.any(status != StepStatus.OK):
            return "ok"
        unmet = self.barrier_unmet_steps
        count = f"; {unmet} of {status.size} steps missed a CBF condition" if unmet else ""
        return self._first_where(status != StepStatus.OK) + count

    def _first_where(self, bad: np.ndarray) -> str:
        """``"NAME first at [trajectory i, ]step k (t = ... s)"``: the earliest step in ``bad``."""
        status = np.asarray(self.status)
        flat = status.reshape(-1, status.shape[-1])
        badf = bad.reshape(-1, status.shape[-1])
        # the earliest over the batch
        firsts = np.where(badf.any(-1), badf.argmax(-1), status.shape[-1])
        traj = int(np.argmin(firsts))
        k = int(firsts[traj])
        t = float(np.asarray(self.t)[k])
        where = f"trajectory {traj}, " if status.ndim > 1 else ""
        return f"{StepStatus(int(flat[traj, k])).name} first at {where}step {k} (t = {t:g} s)"


jax.tree_util.register_dataclass(
    Trajectory,
    data_fields=[f.name for f in dataclasses.fields(Trajectory) if f.name != "multi"],
    meta_fields=["multi"],
)


class Recorder(Protocol):
    """What a closed loop keeps of its run: a full history, or running statistics.

    :func:`closed_loop` calls ``init`` once, ``update`` at every step ``k = 0 .. K-1`` with
    the state ``x_k`` and the controller's output there, and ``finish`` with the final state
    ``x_K`` and its output. ``update`` returns the new running state and a per-step output
    (stacked by ``lax.scan`` along a leading time axis; ``None`` to keep nothing per step).
    ``update`` is traced, wrapped in ``jax.jit``, for the shape of its output and inside the
    loop: it must be a pure function of its arguments (no Python side effects).
    """

    def init(self, x0: jax.Array, data: Any) -> Any:
        """The running state before the first step (a pytree; ``None`` for none)."""
        ...

    def update(
        self, state: Any, k: jax.Array, t: jax.Array, x: jax.Array, out: Any, data: Any
    ) -> tuple[Any, Any]:
        """Step ``k`` at time ``t``: the new running state and this step's output."""
        ...

    def finish(
        self, state: Any, ys: Any, x_final: jax.Array, out_final: Any, t_final: Any, data: Any
    ) -> Any:
        """The run's result from the running state, the stacked outputs and the final state."""
        ...


def _zeros_of(shapes: Any) -> Any:
    """Zero arrays of the shapes and dtypes of a pytree of ``ShapeDtypeStruct`` (``eval_shape``)."""
    return jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)


def closed_loop(
    step: Callable[[jax.Array, jax.Array, Any], Any],
    rhs: Callable[[jax.Array, jax.Array, Any, Any], jax.Array],
    recorder: Recorder,
    *,
    n_steps: int,
    dt: float,
    substeps: int = 1,
    watch: Callable[[jax.Array, jax.Array, Any], jax.Array] | None = None,
) -> Callable[[jax.Array, Any], Any]:
    """The closed loop, one ``lax.scan``, as a function ``run(x0, data) -> recorded``.

    The one loop of the package: :func:`simulate` runs it with a full-history recorder, the
    Monte Carlo study (:func:`~safestab.montecarlo.trial_function`) with running statistics.

    Parameters
    ----------
    step : callable
        ``step(t, x, data) -> out``: the controller at state ``x`` (n,) and time ``t``;
        ``out`` is any pytree that ``rhs`` and the recorder read (a
        :class:`~safestab.ControlOutput`, say). ``data`` is the run's data (run-time
        parameters, a trial's exogenous profile), passed through unchanged.
    rhs : callable
        ``rhs(t, x, out, data) -> xdot`` of shape (n,): the plant under the held output.
    recorder : Recorder
    n_steps : int
        Steps ``K``: the states ``x_0 .. x_K`` at ``t_k = k dt`` are visited.
    dt : float
        Step, s: zero-order hold of ``out`` over ``[t_k, t_k + dt)``, one RK4 step.
    substeps : int
        RK4 steps per hold interval (default 1), each of ``dt / substeps``: the input is
        still held over the whole interval.
    watch : callable, optional
        ``watch(t, x, data)``, an array (a barrier's value, say): its elementwise least value
        over each hold interval, at the start and after every substep, reaches the recorder
        as ``update(..., between=least)`` (a recorder given a ``watch`` accepts the keyword).

    Returns
    -------
    callable
        ``run(x0, data)``, jittable and ``vmap``-able over ``x0`` and ``data``.

    Notes
    -----
    The scan runs ``K + 1`` iterations. Iteration ``k`` evaluates the controller at ``x_k``;
    for ``k < K`` a conditional, whose branch is fixed by the step counter, then records the
    step and integrates to ``x_{k+1}``; at ``k = K`` it does neither, and the output at
    ``x_K`` leaves the loop in the carry. So the controller appears once in the program.
    (Computing the output at ``x_0`` before the loop puts a second copy of the controller
    in the program once XLA inlines it: measured, an obstacle closed loop then compiled in
    5.6 to 8.6 s, against 3.1 to 5.0 s with one copy, without a compilation cache.)

    The conditional also makes XLA compute the held output and the next state once, into
    buffers: nothing fuses across a conditional (and XLA's CPU pipeline removes
    ``optimization_barrier`` before fusion). Without it, XLA fused cheap producers into each
    consumer, per element: the tail of the controller into the four RK4 stages, and the RK4
    update into the GP's ``(M_c, B)`` kernel values and every small fusion of the next
    controller call (measured: a third of the Monte Carlo loop's time).
    """
    # the shapes of the output and of a recorded row come from tracing the step and the
    # recorder's update once: as jitted functions, the loop's calls reuse those traces
    step_once = jax.jit(step)
    update_once = jax.jit(recorder.update)
    if int(substeps) != substeps or substeps < 1:
        raise ParameterError(f"substeps must be an integer >= 1, got {substeps!r}")
    substeps = int(substeps)
    h_sub = dt / substeps

    def held(t, x, out, data):
        """The state after the hold interval in substeps, and the least ``watch`` value."""

        def sub(carry, i):
            z, least = carry
            ts = t + i * h_sub
            z = rk4_step(lambda s, q: rhs(s, q, out, data), ts, z, h_sub)
            if watch is not None:
                least = jnp.minimum(least, watch(ts + h_sub, z, data))
            return (z, least), None

        least0 = watch(t, x, data) if watch is not None else jnp.zeros(())
        (z, least), _ = jax.lax.scan(sub, (x, least0), jnp.arange(substeps, dtype=jnp.float64))
        return z, (least if watch is not None else None)

    def update_with(state, k, t, x, out, data, least):
        if least is None:
            return update_once(state, k, t, x, out, data)
        return update_once(state, k, t, x, out, data, between=least)

    def run(x0: jax.Array, data: Any) -> Any:
        k0, t0 = jnp.asarray(0, jnp.int64), jnp.asarray(0.0, jnp.float64)
        state0 = recorder.init(x0, data)
        # placeholders, never read (the body replaces the output, the last row is dropped),
        # tied to x0: under vmap they are then batched like the values that replace them,
        # and the scan's batching rule passes over the body once instead of twice
        tie = x0.reshape(-1)[0]
        out0 = tied(_zeros_of(jax.eval_shape(step_once, t0, x0, data)), tie)
        least0 = None if watch is None else jax.eval_shape(watch, t0, x0, data)
        if least0 is not None:
            least0 = _zeros_of(least0)
        shapes = jax.eval_shape(update_with, state0, k0, t0, x0, out0, data, least0)
        y0 = tied(_zeros_of(shapes[1]), tie)

        def body(carry, k):
            x, _, state = carry
            t = jnp.asarray(k * dt, jnp.float64)
            out = step_once(t, x, data)

            def advance(state):
                if substeps == 1 and watch is None:  # the plain loop, as it always was
                    state, y = update_once(state, k, t, x, out, data)
                    return rk4_step(lambda s, z: rhs(s, z, out, data), t, x, dt), state, y
                x_next, least = held(t, x, out, data)
                state, y = update_with(state, k, t, x, out, data, least)
                return x_next, state, y

            # at k = K only the output at x_K is wanted: no row, no step (a branch fixed by
            # the counter: the held output and the next state are buffers, see the notes)
            x_next, state, y = jax.lax.cond(k == n_steps, lambda st: (x, st, y0), advance, state)
            return (x_next, out, state), y

        carry0 = (x0, out0, state0)
        (x_final, out_final, state), ys = jax.lax.scan(
            body, carry0, jnp.arange(n_steps + 1, dtype=jnp.int64)
        )
        ys = jax.tree_util.tree_map(lambda a: a[:-1], ys)
        return recorder.finish(state, ys, x_final, out_final, n_steps * dt, data)

    return run


def _records_rows(controller: Any) -> bool:
    """Whether a trajectory of ``controller`` records a value per certificate (several rows).

    Every controller but a :class:`~safestab.UniversalController` (one CLF and one CBF at
    most): a :class:`~safestab.SafetyFilter` with any formula, a
    :class:`~safestab.PolicyController`.
    """
    return not isinstance(controller, UniversalController)


def _values(certificates: tuple, x: jax.Array, p: Any) -> jax.Array:
    """Each certificate's value at ``x``, shape (len,) (``(0,)`` for none)."""
    return jnp.stack([c.fn_of(x, p) for c in certificates]) if certificates else jnp.zeros(0)


class TrajectoryRecorder:
    """The full history of :func:`simulate`: states, inputs, certificate values and flags.

    For a :class:`~safestab.UniversalController` ``V`` and ``h`` are scalars per step; for a
    :class:`~safestab.SafetyFilter` one value per CLF and per CBF, ``region`` is the
    :class:`~safestab.formulas.MultiStatus`, ``compatible`` says the whole problem was solved
    (``SOLVED``) and ``cbf_satisfied`` that every barrier's condition held.
    """

    def __init__(self, controller: Any, params_at: Callable[[Any, Any], Any]) -> None:
        self.controller, self.params_at = controller, params_at
        self.multi = _records_rows(controller)
        # one program for the rows of the steps and of the final state (traced once)
        self._row_once = jax.jit(self._row)

    def init(self, x0: jax.Array, data: Any) -> None:
        """No running state: everything is per step."""
        return None

    def _row(self, x: jax.Array, t: Any, out: Any, data: Any) -> tuple:
        p = self.params_at(t, data)
        ctrl = self.controller
        if self.multi:
            V, h = _values(ctrl.clfs, x, p), _values(ctrl.cbfs, x, p)
            ok = out.status == StepStatus.OK
            region = out.formula_status
            compatible = ok & ~out.incompatible
            sat = jnp.all(out.cbf_satisfied)
        else:  # NaN for a certificate the controller has not
            V, h = (jnp.nan if c is None else c.fn_of(x, p) for c in (ctrl.clf, ctrl.cbf))
            V, h = jnp.asarray(V, float), jnp.asarray(h, float)
            region, compatible, sat = out.region, out.compatible, out.cbf_satisfied
        return (x, out.u, V, h, region, compatible, sat, out.status)

    def update(self, state, k, t, x, out, data, between=None):
        """The step's row: the state, the input, ``V``, ``h``, the flags (and ``between``)."""
        row = self._row_once(x, jnp.asarray(t, jnp.float64), out, data)
        return None, row if between is None else (*row, between)

    def finish(self, state, ys, x_final, out_final, t_final, data):
        """The rows of every step and the final state's, stacked along time (``K + 1``).

        With a watched value per hold interval (``between``), the final state's is NaN: no
        interval follows it.
        """
        last = self._row_once(x_final, jnp.asarray(t_final, jnp.float64), out_final, data)
        if len(ys) > len(last):
            last = (*last, jnp.full_like(ys[-1][0], jnp.nan))
        return tuple(jnp.concatenate([a, b[None]], 0) for a, b in zip(ys, last, strict=True))


def _params_of_time(spec: ParamSpec | None, params: Any) -> Any:
    """Check ``params`` (a pytree or a function of time); the pytree (``None`` for a function).

    A function's output is checked symbolically against the declared example;
    :func:`_params_at` evaluates it in the loop.
    """
    owner = "the closed loop (controller and plant)"
    if not callable(params):
        return resolve(spec, params, owner)
    if spec is None:
        resolve(spec, params, owner)  # raises: given where none is declared
    assert spec is not None
    try:
        out = jax.eval_shape(params, jax.ShapeDtypeStruct((), jnp.float64))
    except TypeError as err:
        raise InputTypeError(
            f"params must be a pytree or a function params(t) of the time; calling it failed: {err}"
        ) from None
    # check the structure and leaf shapes of params(t) against the example, symbolically
    spec.check(_zeros_of(out), "params(t)")
    return None


def _params_at(params_fn: Callable | None) -> Callable[[Any, Any], Any]:
    """``params_at(t, data)``: the run's constant pytree, or ``params_fn(t)`` (a function)."""
    if params_fn is None:
        return lambda t, params: params

    def params_at(t: Any, _: Any) -> Any:
        return jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), params_fn(t))

    return params_at


@functools.partial(
    jax.jit,
    static_argnames=("plant", "exogenous", "params_fn", "n_steps", "dt", "batched", "substeps"),
)
def _simulation(
    controller, x0, params, *, plant, exogenous, params_fn, n_steps, dt, batched, substeps
) -> tuple:
    """The closed loop of :func:`simulate`, the controller an argument of the program.

    One jitted function: a controller of a tree structure seen before (built alike, or
    :meth:`~safestab.Controller.replace` with new numbers, a new fitted GP of the same
    shapes) runs the program compiled for the first, with the same plant, ``exogenous`` and
    ``params(t)`` objects (compared as static arguments: a bound method by its object and
    function), horizon, step, batching and substeps.
    """
    params_at = _params_at(params_fn)

    def rhs(t, x, out, data):
        p = params_at(t, data)
        xdot = plant.f_of(x, p) + plant.g_of(x, p) @ out.u
        return xdot if exogenous is None else xdot + exogenous(t)

    def step(t, x, data):
        # through the controller's own jitted step: its trace (by step_fn, eval_shape or an
        # earlier loop of the same structure) is reused
        return controller_step(controller, x, params_at(t, data))

    watch = None
    if substeps > 1:  # the barriers' least value over each hold interval

        def watch(t, x, data):
            p = params_at(t, data)
            if _records_rows(controller):
                return _values(controller.cbfs, x, p)
            return jnp.asarray(jnp.nan if controller.cbf is None else controller.cbf.fn_of(x, p))

    recorder = TrajectoryRecorder(controller, params_at)
    run = closed_loop(step, rhs, recorder, n_steps=n_steps, dt=dt, substeps=substeps, watch=watch)
    return jax.vmap(run, in_axes=(0, None))(x0, params) if batched else run(x0, params)


def simulate(
    controller: Controller,
    x0: Any,
    *,
    t_final: float,
    dt: float = 0.01,
    plant: ControlAffineSystem | None = None,
    exogenous: Exogenous | None = None,
    strict: bool = False,
    params: Any = None,
    substeps: int = 1,
) -> Trajectory:
    """Simulate ``controller`` in closed loop from ``x0`` (one state or a batch).

    The input is computed at each ``t_k = k dt`` and held constant over the step (zero-order
    hold); the plant is integrated with one RK4 step per ``dt``. The whole loop is one
    ``lax.scan``, and a batch of initial states is one ``vmap``.

    Parameters
    ----------
    controller : Controller
        A :class:`~safestab.UniversalController` or a :class:`~safestab.SafetyFilter`; a
        filter's trajectory records every CLF's and CBF's value (see :class:`Trajectory`).
    x0 : array of shape (n,) or (batch, n)
    t_final : float
        Horizon, s, at least ``dt``; ``round(t_final / dt)`` steps, at most :data:`MAX_STEPS`.
    dt : float
        Step, s (default 0.01).
    plant : ControlAffineSystem, optional
        The true system to integrate; defaults to the controller's own model.
    exogenous : callable, optional
        A known time-dependent term ``e(t)`` of shape (n,) added to the plant's dynamics (for
        example the lead vehicle's acceleration in the ACC study); ``t`` is a scalar, s.
    strict : bool
        Raise if some step was not finite (:class:`~safestab.errors.NonFiniteError`, naming
        the status and the time it first occurred), infeasible or lost the CBF condition
        (:class:`~safestab.errors.InfeasibleError`), instead of only recording it.
    params : pytree or callable, optional
        The run-time parameters, required when the controller (its system, certificates or
        itself) or the plant declared ``params=example``: a constant pytree, or a function
        ``params(t)`` of the time (a scalar, s) returning one (a moving obstacle). The
        controller sees ``params(t_k)`` at each sampling instant (held with the input); the
        plant sees ``params(t)`` at every RK4 stage; ``V`` and ``h`` are recorded with
        ``params(t_k)``. The same ``p`` for every trajectory of a batch.
    substeps : int
        RK4 steps per hold interval, each of ``dt / substeps`` (default 1), the input held
        over the whole interval. With ``substeps > 1`` the trajectory also records the least
        ``h`` over each interval (:attr:`Trajectory.h_between`), which the samples alone can
        miss.

    Returns
    -------
    Trajectory

    Raises
    ------
    ParameterError
        If ``t_final`` or ``dt`` is not positive, ``t_final < dt``, or the step count or the
        history's size is absurd; if ``params`` (or what ``params(t)`` returns) is missing
        where declared, given where not, or has another structure than the declared example
        (a wrong leaf shape is a ``DimensionError``).
    DimensionError, NonFiniteError
        If ``x0`` has the wrong shape or is not finite, or ``exogenous`` does not return
        shape (n,).
    ModelError
        If the uncertainty model returned a negative standard deviation during the run.
    InputTypeError
        If ``controller`` is neither a :class:`~safestab.UniversalController` nor a
        :class:`~safestab.SafetyFilter`.
    NonFiniteError, InfeasibleError
        With ``strict=True``, as above.

    Notes
    -----
    A state that stops being finite (a diverging plant) is not an error: the trajectory
    records status ``NONFINITE_STATE`` from that step on, and :meth:`Trajectory.failure_summary`
    names the first one.

    The loop is one jitted function with the controller as its argument: a later call with
    a controller of the same tree structure (class, options, and the same system and
    certificate objects; any parameter values, any fitted GP of the same shapes) and the same
    ``plant``, ``exogenous`` and ``params(t)`` objects, horizon, step, batching and substeps
    runs the compiled program (20 controllers that differ in their numbers: one
    compilation). As with ``jax.jit``, a reused program does not see a change made since to
    those objects in place (an attribute of the object behind a bound method ``exogenous``,
    say) or to a global variable their functions read: pass new objects.
    """
    if not isinstance(controller, Controller):
        raise InputTypeError(
            "controller must be a UniversalController, a SafetyFilter or a PolicyController, got "
            f"{type(controller).__name__}"
        )
    for name, value in (("t_final", t_final), ("dt", dt)):
        check_real(name, value)
        if np.ndim(value) != 0:
            raise DimensionError(f"{name} must be a scalar, got shape {np.shape(value)}")
    check_scalar_range("t_final", t_final, lower=0.0, strict_lower=True)
    check_scalar_range("dt", dt, lower=0.0, strict_lower=True)
    if t_final < dt:
        raise ParameterError(
            f"t_final must be >= dt (at least one step), got t_final={t_final!r} and dt={dt!r}"
        )
    n_steps_float = float(t_final) / float(dt)
    if n_steps_float > MAX_STEPS:
        raise ParameterError(
            f"t_final / dt must be <= {MAX_STEPS} steps, got {n_steps_float:.3g} "
            f"(t_final={t_final!r} s, dt={dt!r} s); check the units"
        )
    plant = plant or controller.system
    if plant.n_states != controller.system.n_states or plant.n_inputs != controller.system.n_inputs:
        raise DimensionError(
            f"plant dimensions (n={plant.n_states}, m={plant.n_inputs}) differ from the "
            f"controller's model (n={controller.system.n_states}, m={controller.system.n_inputs})"
        )
    check_real("x0", x0)
    x0 = controller.system.check_state(x0, "x0")
    if x0.ndim > 2:
        raise DimensionError(f"x0 must have shape (n,) or (batch, n), got shape {x0.shape}")
    n = controller.system.n_states
    if exogenous is not None:
        if not callable(exogenous):
            raise TypeError("exogenous must be a callable e(t) returning shape (n,)")
        probe = jax.ShapeDtypeStruct((), jnp.float64)
        shape = getattr(jax.eval_shape(exogenous, probe), "shape", None)
        if shape != (n,):
            raise DimensionError(f"exogenous(t) must return shape ({n},), got {shape}")
    if isinstance(substeps, bool) or not isinstance(substeps, int | np.integer) or substeps < 1:
        raise ParameterError(f"substeps must be an integer >= 1, got {substeps!r}")
    n_steps = int(round(n_steps_float))
    batch = x0.shape[0] if x0.ndim == 2 else 1
    n_values = len(controller.cbfs) + len(controller.clfs)
    n_values += len(controller.cbfs) if substeps > 1 else 0
    history = (n_steps + 1) * batch * (2 * n + 2 * controller.system.n_inputs + 6 + n_values) * 8
    if history > MAX_HISTORY_BYTES:
        raise ParameterError(
            f"the history would take {history / 2**30:.1f} GiB (> {MAX_HISTORY_BYTES / 2**30:.0f}"
            f" GiB): {n_steps} steps x {batch} trajectories; use fewer steps or a smaller batch"
        )
    spec = merge_specs([getattr(controller, "params_spec", None), plant.params_spec])
    params_fn = params if callable(params) else None
    params = _params_of_time(spec, params)
    xs, us, Vs, hs, regions, comps, sats, stats, *between = _simulation(
        controller, x0, params, plant=plant, exogenous=exogenous, params_fn=params_fn,
        n_steps=n_steps, dt=float(dt), batched=x0.ndim == 2, substeps=int(substeps),
    )  # fmt: skip
    traj = Trajectory(
        t=jnp.asarray(np.arange(n_steps + 1) * dt),
        x=xs,
        u=us,
        V=Vs,
        h=hs,
        region=regions,
        compatible=comps,
        cbf_satisfied=sats,
        status=stats,
        h_between=between[0] if between else None,
        multi=_records_rows(controller),
    )
    if traced_results((xs, us, stats), strict, "simulate"):  # the statuses are the record
        return traj
    if np.any(np.asarray(stats) == StepStatus.NEGATIVE_STD):
        raise ModelError(
            "the uncertainty model returned a negative standard deviation during the run: "
            f"{traj.failure_summary()}"
        )
    no_input = ~np.asarray(has_input(np.asarray(stats)))
    if strict and np.any(no_input):
        raise NonFiniteError(f"the closed loop stopped being finite: {traj._first_where(no_input)}")
    if strict and (traj.infeasible_steps or not traj.ok or not bool(np.all(np.asarray(sats)))):
        raise InfeasibleError(
            f"{traj.infeasible_steps} infeasible steps and "
            f"{int(np.sum(~np.asarray(sats)))} steps where the applied input broke the CBF "
            f"condition ({traj.failure_summary()})"
        )
    return traj
