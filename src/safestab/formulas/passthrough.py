"""The formula that enforces nothing: the nominal input, projected onto the limits.

A :class:`~safestab.PolicyController` runs a user's own control law (a learned policy, an
MPC's approximation, a hand-written law) through the package's loops: its step evaluates
every CBF and CLF condition at the law's input and names in its status where a barrier's
condition fails, but it changes nothing. This formula is what it solves: ``u = u_nom``, or
``clip(u_nom, u_min, u_max)`` with limits (the projection onto the box, exact, one-sided and
infinite bounds included). Its result has the shape of the several-row solver's
(:class:`~safestab.formulas.MultiResult`), so the step's outputs are a filter's: the rows'
multipliers are zero, the limit rows active where the projection moved the input, and the
status ``SOLVED`` (nothing was relaxed or dropped; the barriers' flags say whether the
input meets them).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax.numpy as jnp

from ..errors import ParameterError
from .multi import MultiResult, MultiStatus
from .problem import Formula, Problem, register_formula

__all__ = ["PassThrough"]


@register_formula
@dataclasses.dataclass(frozen=True)
class PassThrough(Formula):
    """``u = u_nom`` projected onto the limits (where given); no condition is enforced.

    Rows as the several-row solver orders them: the ``p`` CLFs, the ``k`` CBFs, then
    ``u <= u_max`` and ``u >= u_min`` per input; a limit row is active where the projection
    put the input on it.
    """

    uses: ClassVar[tuple[str, ...]] = ("u_min", "u_max", "u_nom")

    def solve(self, problem: Problem) -> MultiResult:
        """The nominal input of ``problem``, projected onto its box."""
        self._check_fields(problem)
        if problem.u_nom is None:
            raise ParameterError("PassThrough needs the problem's u_nom (the input to pass)")
        u = problem.u_nom
        batch = u.shape[:-1]
        n_rows = problem.b.shape[-2] + problem.d.shape[-2]
        active = [jnp.zeros(batch + (n_rows,), bool)]
        if problem.u_min is not None or problem.u_max is not None:
            lo = -jnp.inf if problem.u_min is None else problem.u_min
            hi = jnp.inf if problem.u_max is None else problem.u_max
            u = jnp.minimum(jnp.maximum(u, lo), hi)
            active += [u >= hi, u <= lo]
        rows = jnp.concatenate(active, -1)
        return MultiResult(
            u=u,
            status=jnp.full(batch, MultiStatus.SOLVED, jnp.int32),
            active=rows,
            multipliers=jnp.zeros(rows.shape),
            slack=jnp.zeros(batch + (problem.b.shape[-2],)),
        )
