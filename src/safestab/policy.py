"""A user's own control law in the package's loops: :class:`PolicyController`.

Any state-feedback law a user brings (a learned policy, an MPC's explicit approximation, a
hand-written law, another library's controller written in JAX) becomes a controller that
:func:`~safestab.simulate`, :func:`~safestab.controller_step`, the Monte Carlo trial loop
(:func:`~safestab.montecarlo.trial_function`), :func:`~safestab.export_c` and
:class:`~safestab.export.NativeController` take like the package's own. It changes nothing in
the law's input (beyond the projection onto the limits, where given): it *monitors* it, and
its status says, at every step, whether the input meets each barrier's condition, with the
same statuses and flags as a :class:`~safestab.SafetyFilter` (docs/getting-started.md, "Your
own controller").

The protocol a law follows: a pure JAX function of one state ``x`` of shape (n,) returning
the input, shape (m,), that ``jax.jit`` and ``jax.vmap`` can trace: ``policy(x)``;
``policy(x, weights)`` when the controller is given ``weights`` (any pytree of arrays: a
network's parameters, gains), which are then the controller's data, so new weights run the
compiled program of the old ones; and a last argument ``p`` where run-time parameters are
declared (``params=example``, or by the system or a certificate).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from ._params import trace_shape
from ._validation import check_real
from .certificates import CBF, CLF
from .errors import DimensionError, InputTypeError
from .filters import SafetyFilter
from .formulas.passthrough import PassThrough
from .systems import ControlAffineSystem

__all__ = ["PolicyController"]


class PolicyController(SafetyFilter):
    """A user's control law, run and monitored as a controller (nothing enforced).

    At each state the step computes ``u = policy(x)`` (projected onto ``[u_min, u_max]``
    where limits are given: the exact projection, one-sided and infinite bounds allowed) and
    evaluates every CBF condition ``L_f h + L_g h u + alpha(h) >= 0`` and every CLF condition
    ``L_f V + L_g V u + gamma(V) <= 0`` at that input on the controller's model, each judged
    against its own magnitudes. The output is a :class:`~safestab.FilterOutput`: ``status``
    is ``OK`` only where an input was computed and it meets every barrier's condition;
    where it does not, ``CBF_UNACTUATED`` (the violated barrier's ``L_g h`` is zero: no input
    moves it), ``CBF_INFEASIBLE`` (with limits: no input within them meets that barrier
    alone) or ``CBF_UNMET`` (an input within the limits meets each violated barrier alone:
    the law chose another; a :class:`~safestab.SafetyFilter` around it enforces them where
    they can be met together);
    statuses 1 to 7 where the state, the model or the law's input is not finite (``u`` NaN).
    ``formula_status`` is always ``SOLVED`` (nothing is relaxed), ``active`` marks the limit
    rows the projection hit, the multipliers and slacks are zero. ``CBF_UNMET`` judges each
    violated barrier alone: whether an input meets several barriers at once is not
    checked (a filter's solver decides that).

    ``step(x, u_nom=a)`` (and ``controller_step(ctrl, x, p, a)``) monitors the given input
    ``a`` instead of the law's: an action from elsewhere (a policy outside JAX), checked
    against the same barriers and limits.

    Parameters
    ----------
    system : ControlAffineSystem
        The model the conditions are evaluated on (the plant a loop integrates may differ).
    policy : callable
        The law: ``policy(x)``, ``policy(x, weights)`` with ``weights``, and a last argument
        ``p`` with run-time parameters; one state (n,) in, the input (m,) out; jittable.
    weights : pytree of arrays, optional
        The law's numbers (a network's parameters, gains): leaves of the controller, so a
        controller with new weights (:meth:`replace` ``(weights=...)``) runs the program
        compiled for the old ones, and ``jax.grad`` reaches them.
    cbfs : CBF or sequence of CBF, optional
        The barriers to monitor (``k >= 0``; each must be moved by the input somewhere,
        as for a filter: a barrier with ``L_g h = 0`` everywhere is refused, see
        :func:`~safestab.certificates.high_order_cbf`).
    clfs : CLF or sequence of CLF, optional
        The Lyapunov functions to monitor (``clf_satisfied``).
    u_min, u_max : float or array of shape (m,), optional
        Limits the law's input is projected onto; one alone is a one-sided box.
    params : pytree, optional
        An example of the run-time parameters the law takes as its last argument.
    sample_time, ddh_bound : optional
        The sampled-data margin (docs/deployed.md): the barriers' conditions are judged
        shifted by ``M T / 2 + max(0, alpha(h) - h / T)``, so ``OK`` also says that ``h``
        stays ``>= 0`` over the hold interval (under the margin's assumptions). Needs a CBF.

    Raises
    ------
    InputTypeError
        If ``policy`` is not callable, or a leaf of ``weights`` is not a real array.
    DimensionError
        If the law does not return shape (m,) for a state of shape (n,).
    ParameterError, RelativeDegreeError
        For invalid limits, certificates or margins, named.

    Examples
    --------
    >>> import jax.numpy as jnp
    >>> import safestab as ss
    >>> system = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)
    >>> disc = ss.CBF(lambda x: 1.0 - x @ x, beta=1.0)
    >>> law = ss.PolicyController(system, lambda x, K: -K @ x, weights=jnp.eye(2), cbfs=disc)
    >>> out = law.step(jnp.array([0.5, 0.0]))
    >>> out.u.tolist(), ss.StepStatus(int(out.status)).name
    ([-0.5, 0.0], 'OK')
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        policy: Callable[..., Any],
        *,
        weights: Any = None,
        cbfs: CBF | Sequence[CBF] = (),
        clfs: CLF | Sequence[CLF] = (),
        u_min: Any = None,
        u_max: Any = None,
        params: Any = None,
        sample_time: float | None = None,
        ddh_bound: Any = None,
    ) -> None:
        init_args = {k: v for k, v in locals().items() if k not in ("self", "__class__")}
        if not callable(policy):
            raise InputTypeError(
                f"policy must be a function of the state (a JAX-traceable law x -> u), got "
                f"{type(policy).__name__}"
            )
        if weights is not None:
            for path, leaf in jax.tree_util.tree_leaves_with_path(weights):
                check_real(f"weights{jax.tree_util.keystr(path)}", leaf)
            weights = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), weights)
        if not isinstance(system, ControlAffineSystem):
            raise InputTypeError(
                f"system must be a ControlAffineSystem, got {type(system).__name__}"
            )
        try:
            cbf_list = (cbfs,) if isinstance(cbfs, CBF) else tuple(cbfs)
        except TypeError:
            raise InputTypeError(
                f"cbfs must be a CBF or a sequence of them, got {type(cbfs).__name__}"
            ) from None
        self.policy, self.weights = policy, weights
        SafetyFilter.__init__(
            self,
            system,
            cbf_list,
            clfs=clfs,
            u_min=u_min,
            u_max=u_max,
            params=params,
            sample_time=sample_time,
            ddh_bound=ddh_bound,
            formula=PassThrough(),
        )
        spec = self.params_spec
        self._takes_params = spec is not None
        m = system.n_inputs
        if weights is None:
            law = policy
        else:
            w = weights
            law = lambda x, *p: policy(x, w, *p)  # noqa: E731
        shape = getattr(_trace_law(law, system.n_states, spec, weights is not None), "shape", None)
        if shape != (m,):
            raise DimensionError(
                f"policy must return the input of shape ({m},) for one state of shape "
                f"({system.n_states},), got {shape}"
            )
        self._remember(PolicyController, init_args)

    _DATA_KWARGS = ("uncertainty", "weights")

    def _children(self) -> tuple[str, ...]:
        return super()._children() + (("weights",) if self.weights is not None else ())

    def _leaf_names(self) -> tuple[str, ...]:
        names = ["u_min", "u_max"] if self.u_min is not None else []
        names += ["sample_time", "ddh_bound"] if self.sample_time is not None else []
        return tuple(names)

    def nominal_input(self, x: jax.Array, p: Any = None) -> jax.Array:
        """The law's input at one state ``x`` (n,), before the limits: shape (m,)."""
        args = (x,) if self.weights is None else (x, self.weights)
        return jnp.asarray(self.policy(*args, *((p,) if self._takes_params else ())), float)

    def __repr__(self) -> str:
        name = getattr(self.policy, "__name__", type(self.policy).__name__)
        limits = "" if self.u_min is None else ", limits"
        return (
            f"PolicyController({self.system.name}, policy={name}, {len(self.cbfs)} CBF(s), "
            f"{len(self.clfs)} CLF(s){limits})"
        )

    _owner = "policy controller"


def _trace_law(law: Callable[..., Any], n: int, spec: Any, with_weights: bool) -> Any:
    """The law's output shape for one state; errors that name the protocol.

    Raises
    ------
    InputTypeError
        Where the law cannot be called with the protocol's arguments, or is not a JAX
        function (NumPy or Python branching on the state under tracing).
    """
    args = "x, weights" if with_weights else "x"
    args += ", p" if spec is not None else ""
    given = "weights= given" if with_weights else "no weights="
    given += ", run-time params declared" if spec is not None else ""
    try:
        return trace_shape("policy", law, n, spec)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError) as err:
        raise InputTypeError(
            "policy must be a JAX function of the state (jax.numpy, no NumPy calls or Python "
            f"branches on x) to be traced; {type(err).__name__}. A law outside JAX: give its "
            "action per call, SafetyFilter.step(x, u_nom=action) or safestab.gym.SafetyWrapper"
        ) from None
    except TypeError as err:  # InputTypeError included: the protocol's call, named
        raise InputTypeError(
            f"policy is called as policy({args}) ({given}); calling it failed: {err}"
        ) from None
