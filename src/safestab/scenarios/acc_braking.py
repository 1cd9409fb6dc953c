"""The ACC's braking-distance barrier: a barrier the limited brake can always keep.

With the follower's braking limited to ``a_f = input_limit g`` (the wheel force at least
``-input_limit M g``; the drag only adds to it) and the lead's deceleration bounded by
``a_l = lead_decel g`` (a lead stops, it does not reverse), the barrier

    h(x) = D - tau v_f - v_f^2 / (2 a_f) + v_l^2 / (2 a_l)

says: after both vehicles brake as hard as they may, the gap left (the lead's stopping
distance added, the follower's taken off) still covers ``tau v_f``. Its gradient is
``(-(tau + v_f / a_f), v_l / a_l, 1)``: the lead's acceleration ``a_L`` moves ``h`` by
``(v_l / a_l) a_L >= -v_l`` (for ``v_l >= 0``, ``a_L >= -a_l``), so the controllers act on
a model whose lead brakes at ``a_l`` (:func:`worst_lead`): their condition then holds for
every admissible lead. Under full braking, at every state with ``v_f, v_l >= 0``,

    h' >= L_{f_w} h + L_g h (-u_lim) = tau a_f + (tau + v_f / a_f) F_r(v_f) / M >= tau a_f

(``f_w``: the model with the worst lead), so the braking limit meets the CBF condition
everywhere ``h >= 0`` with ``tau a_f`` to spare; docs/acc.md derives it. The relative-speed
form ``D - tau v_f - max(0, v_f - v_l)^2 / (2 (a_f - a_l))`` needs ``a_f > a_l``, which the
presets' equal limits (0.3 g each, the paper's Table I) do not give; this one needs
nothing between the two.

The sampled-data margin (:mod:`safestab.sampled`) needs ``M >= -d/dt h'_w`` along the held
flow, where ``h'_w = -v_f - (tau + v_f / a_f) phi``, ``phi = (k u - F_r(v_f)) / M``, is the
worst-lead rate the controllers bound (the true ``h'`` is at least it). It depends on
``v_f`` and ``u`` only, and :func:`braking_ddh_bound` bounds it in closed form.
"""

from __future__ import annotations

import math
from typing import Any

import jax.numpy as jnp

from ..errors import ParameterError

__all__ = [
    "BARRIERS", "braking_barrier", "braking_ddh_bound", "braking_lie_terms", "check_lead_bound",
    "worst_lead",
]  # fmt: skip

#: The ACC's barriers: the paper's headway ``D - tau v_f`` and the braking distance.
BARRIERS = ("headway", "braking")


def braking_barrier(tau: float, a_follow: float, a_lead: float) -> Any:
    """``h = D - tau v_f - v_f^2 / (2 a_follow) + v_l^2 / (2 a_lead)`` (m), ``x = (v_f, v_l, D)``.

    ``a_follow``, ``a_lead``: the follower's braking limit and the lead's largest
    deceleration, m/s^2, both > 0.
    """
    for name, value in (("a_follow", a_follow), ("a_lead", a_lead)):
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ParameterError(f"{name} must be a finite number > 0 (m/s^2), got {value!r}")

    def h(x: Any) -> Any:
        return x[2] - tau * x[0] - x[0] ** 2 / (2 * a_follow) + x[1] ** 2 / (2 * a_lead)

    return h


def worst_lead(a_lead: float) -> Any:
    """``w(x) = (0, -a_lead, 0)``: the lead braking as hard as it may, added to the model."""

    def w(x: Any) -> Any:
        return jnp.array([0.0, -a_lead, 0.0]) + 0.0 * x

    return w


def braking_ddh_bound(drag: Any, mass: float, tau: float, a_follow: float, v_max: float) -> float:
    """A sound bound ``M >= -d/dt h'_w`` for ``0 <= v_f <= v_max`` and every input in the limits.

    ``-d/dt h'_w = q(phi) = phi + phi^2 / a_f - (tau + v_f / a_f) r'(v_f) phi`` with
    ``r = F_r / M``: convex in ``phi``, so its largest value over
    ``phi in [-a_f - r, a_f - r]`` is at an end. At the upper end ``q <= 2 a_f`` when
    ``phi >= 0`` (the last term is then <= 0), and ``q <= max(q(phi_lo), 0)`` when
    ``phi < 0`` (convexity on ``[phi_lo, 0]``, ``q(0) = 0``); at the lower end
    ``q = (a_f + r) r / a_f + (tau + v_f / a_f) r' (a_f + r)``, increasing in ``v_f`` for
    drag coefficients >= 0. Hence ``M = max(2 a_f, q_lo(v_max))``.

    Parameters
    ----------
    drag : Drag
        The true plant's resistance (``f0``, ``f1``, ``f2`` >= 0; upper bounds where unknown).
    mass, tau, a_follow, v_max : float
        kg, s, m/s^2 (the braking limit), m/s (the largest follower speed the loop visits).

    Raises
    ------
    ParameterError
        If a number is not finite and > 0 (``tau``, ``v_max`` may be 0).
    """
    for name, value, low in (("mass", mass, 0.0), ("a_follow", a_follow, 0.0),
                             ("tau", tau, None), ("v_max", v_max, None)):  # fmt: skip
        ok = isinstance(value, int | float) and math.isfinite(value)
        if not ok or (value <= 0 if low is not None else value < 0):
            expected = "> 0" if low is not None else ">= 0"
            raise ParameterError(f"{name} must be a finite number {expected}, got {value!r}")
    r = (drag.f0 + drag.f1 * v_max + drag.f2 * v_max**2) / mass
    dr = (drag.f1 + 2 * drag.f2 * v_max) / mass
    q_lo = (a_follow + r) * r / a_follow + (tau + v_max / a_follow) * dr * (a_follow + r)
    return float(max(2 * a_follow, q_lo))


def braking_lie_terms(sc: Any, x: Any, drag: Any) -> tuple[Any, Any]:
    """``(c, d)`` of the braking barrier on the worst-lead model, written out by hand.

    ``c = (tau + v_f / a_f) F_r / M - v_f + beta h``, ``d = -(tau + v_f / a_f) k / M``.
    """
    a_f, a_l = sc.input_limit * sc.gravity, sc.lead_decel * sc.gravity
    vf, vl, D = x[..., 0], x[..., 1], x[..., 2]
    fr = drag.f0 + drag.f1 * vf + drag.f2 * vf**2
    slope = sc.tau + vf / a_f
    h = D - sc.tau * vf - vf**2 / (2 * a_f) + vl**2 / (2 * a_l)
    c = slope * fr / sc.mass - vf + sc.beta * h
    d = -slope * sc.input_scale / sc.mass
    return c, d


def check_lead_bound(sc: Any, spec: Any, source: str, error: type[Exception]) -> None:
    """Refuse a Monte Carlo lead that brakes harder than the braking barrier assumes."""
    if getattr(sc, "barrier", "headway") != "braking" or spec is None:
        return
    if spec.lead_kind == "random" and spec.lead_decel_max > sc.lead_decel:
        raise error(
            f"{source}: montecarlo.lead.decel_max must be <= certificates.lead_decel = "
            f"{sc.lead_decel!r} (the lead's largest deceleration the braking barrier is valid "
            f"for, fraction of g), got {spec.lead_decel_max!r}"
        )
