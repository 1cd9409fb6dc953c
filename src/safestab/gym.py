"""A Gymnasium wrapper that passes every action through a safety filter (optional extra).

    pip install "safestab[gym]"

Safe reinforcement learning and any other policy on a Gymnasium environment: the policy's
action is the filter's nominal input (``SafetyFilter.step(x, u_nom=...)``), the filtered
input is what the environment receives, and ``info["safestab"]`` reports what the filter did.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .controllers import StepStatus
from .errors import DimensionError, InputTypeError, ParameterError
from .filters import SafetyFilter

try:
    import gymnasium
except ImportError as exc:  # pragma: no cover - the optional extra is missing
    raise ImportError(
        'safestab.gym needs gymnasium: pip install "safestab[gym]" (or pip install gymnasium)'
    ) from exc

__all__ = ["SafetyWrapper"]


class SafetyWrapper(gymnasium.Wrapper):
    """Filter every action of an environment through a :class:`~safestab.SafetyFilter`.

    At each ``step(action)``: the filter's state ``x = state(env, obs)`` from the last
    observation (or the environment itself), the policy's action mapped to the filter's
    input (``u_nom``), the filtered input ``u`` mapped back to an action, and that action
    sent to the environment.

    Parameters
    ----------
    env : gymnasium.Env
        With a ``Box`` action space of shape (m,), ``m`` the filter's inputs.
    safety_filter : SafetyFilter
        The filter (its ``u_nom`` is replaced by the policy's action at every step).
    state : callable
        ``state(env, obs) -> x`` of shape (n,): the filter's state from the wrapped
        environment (``env.unwrapped`` reaches the simulator) and its last observation.
    params : callable, optional
        ``params(env, obs) -> p``: the filter's run-time parameters, when it declares them.
    input_low, input_high : array of shape (m,), optional
        The filter's inputs that the action space's ``low`` and ``high`` stand for: the
        action ``a`` is the input ``low_u + (a - low_a) (high_u - low_u) / (high_a - low_a)``,
        and back. Default: the filter's ``u_min`` and ``u_max`` (where a side is unbounded,
        the action space's bound there), or the action space itself (the action is the
        input) when the filter has no limits.

    Notes
    -----
    ``info["safestab"]`` after each step: ``h`` (each barrier's value at ``x``, shape (k,)),
    ``status`` (the :class:`~safestab.StepStatus` name: ``"OK"`` where the filtered input
    meets every barrier condition), ``action`` (the policy's), ``filtered_action`` (what the
    environment received), ``intervention`` (``|filtered_action - action|``, the largest
    component) and ``x``. Where the step gives no input (a non-finite state), the policy's
    action is sent unchanged, clipped to the action space, and the status says so.
    """

    def __init__(
        self,
        env: Any,
        safety_filter: SafetyFilter,
        state: Callable[[Any, Any], Any],
        *,
        params: Callable[[Any, Any], Any] | None = None,
        input_low: Any = None,
        input_high: Any = None,
    ) -> None:
        super().__init__(env)
        if not isinstance(safety_filter, SafetyFilter):
            raise InputTypeError(
                f"safety_filter must be a SafetyFilter, got {type(safety_filter).__name__}"
            )
        if not callable(state):
            raise InputTypeError(f"state must be a callable state(env, obs), got {state!r}")
        space = env.action_space
        m = safety_filter.system.n_inputs
        if not isinstance(space, gymnasium.spaces.Box) or space.shape != (m,):
            raise DimensionError(
                f"env.action_space must be a Box of shape ({m},) (the filter's inputs), got "
                f"{space!r}"
            )
        low_a = np.asarray(space.low, dtype=float)
        high_a = np.asarray(space.high, dtype=float)
        if not (np.all(np.isfinite(low_a)) and np.all(np.isfinite(high_a))):
            raise ParameterError(f"env.action_space must be bounded, got {space!r}")
        if input_low is None and input_high is None:
            if safety_filter.u_min is not None:
                # an unbounded side of the filter's box: the action space's bound there
                lo = np.broadcast_to(np.asarray(safety_filter.u_min, dtype=float), (m,))
                hi = np.broadcast_to(np.asarray(safety_filter.u_max, dtype=float), (m,))
                input_low = np.where(np.isfinite(lo), lo, low_a)
                input_high = np.where(np.isfinite(hi), hi, high_a)
            else:
                input_low, input_high = low_a, high_a
        elif input_low is None or input_high is None:
            raise ParameterError("give input_low and input_high together, or neither")
        for name, value in (("input_low", input_low), ("input_high", input_high)):
            if not np.all(np.isfinite(np.asarray(value, dtype=float))):
                raise ParameterError(
                    f"{name} must be finite (the inputs the action space's bounds stand for), "
                    f"got {np.asarray(value).tolist()}"
                )
        self.safety_filter = safety_filter
        self.state = state
        self.params = params
        self._low_a, self._span_a = low_a, high_a - low_a
        self._low_u = np.broadcast_to(np.asarray(input_low, dtype=float), (m,))
        self._span_u = np.broadcast_to(np.asarray(input_high, dtype=float), (m,)) - self._low_u
        if np.any(self._span_a <= 0) or np.any(self._span_u <= 0):
            raise ParameterError(
                "the action space and the filter's input range must have low < high in every "
                f"component, got actions {low_a.tolist()} to {high_a.tolist()} and inputs "
                f"{self._low_u.tolist()} to {(self._low_u + self._span_u).tolist()}"
            )
        self._obs: Any = None
        cbfs = safety_filter.cbfs
        #: every barrier's value at one state, compiled once (an eager evaluation per step
        #: cost milliseconds)
        self._barriers = jax.jit(lambda x, p: jnp.stack([c.fn_of(x, p) for c in cbfs]))

    def action_to_input(self, action: Any) -> np.ndarray:
        """The filter's input (m,) that an action stands for."""
        a = np.asarray(action, dtype=float)
        return self._low_u + (a - self._low_a) * self._span_u / self._span_a

    def input_to_action(self, u: Any) -> np.ndarray:
        """The action (m,) that stands for the filter's input ``u``."""
        return (
            self._low_a + (np.asarray(u, dtype=float) - self._low_u) * self._span_a / self._span_u
        )

    def reset(self, **kwargs: Any) -> tuple[Any, dict]:
        """Reset the environment and keep its first observation (the filter's next state)."""
        obs, info = self.env.reset(**kwargs)
        self._obs = obs
        return obs, info

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict]:
        """Filter ``action``, step the environment with the result, report in ``info``."""
        if self._obs is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        flt = self.safety_filter
        x = np.asarray(self.state(self.env, self._obs), dtype=float)
        p = None if self.params is None else self.params(self.env, self._obs)
        action = np.asarray(action, dtype=float)
        u_nom = self.action_to_input(action)
        out = flt.step(x, params=p, u_nom=u_nom)
        status = int(out.status)
        u = np.asarray(out.u)
        space = self.env.action_space
        if np.all(np.isfinite(u)):
            filtered = self.input_to_action(u)
        else:  # no input (statuses 1 to 7): the policy's action, inside the space
            filtered = action
        filtered = np.clip(filtered, space.low, space.high).astype(space.dtype)
        obs, reward, terminated, truncated, info = self.env.step(filtered)
        self._obs = obs
        info = dict(info)
        info["safestab"] = {
            "x": x,
            "h": np.asarray(self._barriers(x, p), dtype=float),
            "status": StepStatus(status).name,
            "action": action,
            "filtered_action": np.asarray(filtered, dtype=float),
            "intervention": float(np.max(np.abs(np.asarray(filtered, float) - action))),
        }
        return obs, reward, terminated, truncated, info
