"""The exporter's intermediate form: values, statements, and the jaxpr walker.

A jaxpr is walked once, equation by equation. Calls (``jit``, ``custom_jvp_call``, ...) are
inlined; an equation whose inputs are all known at export time is evaluated at once with JAX
(constant folding, so parameters, GP caches and index arithmetic become ``static const``
tables or literals); every other equation is handed to its translation rule in
:data:`~safestab.export._primitives.RULES`, which returns the output values and registers a
:class:`Stmt` whose ``gen`` writes the C lines later. After the walk, statements that no
output depends on are dropped (dead-code elimination), so the C has no unused variables.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jcore
from jax.extend import source_info_util

from ..errors import UnsupportedPrimitiveError

#: dtypes the C code can hold (bool as int 0/1).
SUPPORTED_DTYPES = frozenset(
    np.dtype(d) for d in ("float64", "float32", "int32", "int64", "bool", "uint8", "uint32")
)

#: Primitives whose only job is to call a sub-jaxpr; they are inlined.
CALL_PARAMS = {
    "jit": "jaxpr",
    "pjit": "jaxpr",
    "closed_call": "call_jaxpr",
    "core_call": "call_jaxpr",
    "custom_jvp_call": "call_jaxpr",
    "custom_vjp_call": "call_jaxpr",
    "custom_vjp_call_jaxpr": "fun_jaxpr",
    "checkpoint": "jaxpr",
    "remat": "jaxpr",
}


class Val:
    """One array of the program: known at export time (``const``) or computed at run time.

    ``base`` makes the value an alias of another one with the same elements in the same
    (row-major) order, e.g. after a reshape: no C code, no copy.
    """

    __slots__ = ("shape", "dtype", "const", "base", "producer", "param")

    def __init__(
        self,
        shape: Sequence[int],
        dtype: Any,
        *,
        const: np.ndarray | None = None,
        base: Val | None = None,
        param: str | None = None,
    ) -> None:
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        self.const = None if const is None else np.asarray(const, dtype=self.dtype)
        self.base = base
        self.producer: Stmt | None = None
        self.param = param  # name of a pointer parameter (the state x)

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    def root(self) -> Val:
        v = self
        while v.base is not None:
            v = v.base
        return v

    def splat(self) -> Any:
        """The single value of a constant whose elements are all equal (bitwise), else None."""
        c = self.const
        if c is None or c.size == 0:
            return None
        raw = np.ascontiguousarray(c).reshape(c.size).view(np.uint8).reshape(c.size, -1)
        return c.reshape(-1)[0] if bool(np.all(raw == raw[0])) else None


class Stmt:
    """Run-time code for one equation: ``gen(emitter)`` returns its C lines."""

    __slots__ = ("prim", "where", "outs", "ins", "gen", "blocks", "scratch", "results")

    def __init__(
        self, prim: str, where: str, outs, ins, gen, blocks=(), scratch=(), results=()
    ) -> None:
        self.prim = prim
        self.where = where
        self.outs: list[Val] = list(outs)
        self.ins: list[Val] = list(ins)
        self.gen: Callable[[Any], list[str]] = gen
        #: Nested statement lists (a loop's body, a branch), written by ``gen`` itself.
        self.blocks: tuple[list[Stmt], ...] = tuple(blocks)
        #: Values the C code may hold besides the outputs (staged copies, work arrays), at
        #: most these sizes: counted in the stack bound.
        self.scratch: tuple[Val, ...] = tuple(scratch)
        #: Values of the blocks that ``gen`` itself reads after them (a branch's or a loop
        #: body's results, a loop condition): they live to the end of the blocks.
        self.results: tuple[Val, ...] = tuple(results)


def where_from(eqn: Any) -> str:
    """``file:line (function)`` of the user code that produced an equation."""
    try:
        return source_info_util.summarize(eqn.source_info).strip()
    except Exception:  # pragma: no cover - depends on JAX internals
        return ""


def check_dtype(dtype: Any, prim: str, where: str) -> None:
    """Raise :class:`UnsupportedPrimitiveError` for a dtype the C code cannot hold."""
    if np.dtype(dtype) not in SUPPORTED_DTYPES:
        raise UnsupportedPrimitiveError(
            f"primitive '{prim}' at {where} produces dtype {np.dtype(dtype).name}, which the C "
            f"export does not support (supported: "
            f"{', '.join(sorted(d.name for d in SUPPORTED_DTYPES))})"
        )


class Program:
    """The result of walking a jaxpr: statements in order, inputs and outputs."""

    def __init__(self) -> None:
        self.stmts: list[Stmt] = []
        self._prim = "?"
        self._where = "?"
        self.rules: dict[str, Callable] = {}
        #: ``(primitive name, NumPy arguments, params) -> outputs`` for the primitives folded
        #: exactly without XLA (data movement), None for the others (export_function)
        self.exact_fold: Callable[..., list[np.ndarray] | None] = lambda name, args, params: None
        #: "host" or "embedded": how rules lay out loops and constants (export_function)
        self.layout = "host"
        # common subexpressions: key -> (outputs, inputs); holding the inputs keeps the ids
        # in the keys from being reused by new objects
        self._seen: dict[Any, tuple[list[Val], list[Val]]] = {}

    # -- building blocks used by the translation rules -----------------------------------

    def const(self, value: Any, dtype: Any = None) -> Val:
        arr = np.asarray(value, dtype=dtype)
        return Val(arr.shape, arr.dtype, const=arr)

    def new(self, aval: Any) -> Val:
        check_dtype(aval.dtype, self._prim, self._where)
        return Val(aval.shape, aval.dtype)

    def alias(self, src: Val, shape: Sequence[int], dtype: Any = None) -> Val:
        dtype = src.dtype if dtype is None else dtype
        if src.const is not None:
            return Val(shape, dtype, const=src.const.reshape(shape))
        return Val(shape, dtype, base=src)

    def stmt(
        self,
        outs: Sequence[Val],
        ins: Sequence[Val],
        gen: Callable,
        blocks: Sequence = (),
        scratch: Sequence[Val] = (),
        results: Sequence[Val] = (),
    ) -> None:
        st = Stmt(self._prim, self._where, outs, ins, gen, blocks, scratch, results)
        for v in outs:
            v.producer = st
        self.stmts.append(st)

    def unsupported(self, detail: str) -> UnsupportedPrimitiveError:
        return UnsupportedPrimitiveError(
            f"cannot export primitive '{self._prim}' (from {self._where}): {detail}"
        )

    def block(
        self, jaxpr: Any, consts: Sequence[Any], args: Sequence[Val]
    ) -> tuple[list[Stmt], list[Val]]:
        """Walk a nested jaxpr (a loop body, a branch) into its own statement list.

        Returns the live statements of the block and its outputs. Nothing is shared with the
        enclosing code by common-subexpression merging, in either direction: a value computed
        inside is out of scope after the block, and a value the block uses from outside must
        reach it as an argument (so the enclosing statement lists it as an input).
        """
        saved = self.stmts, self._seen
        self.stmts, self._seen = [], {}
        try:
            outs = self.run(jaxpr, consts, args)
            return live_statements(self.stmts, outs), outs
        finally:
            self.stmts, self._seen = saved

    # -- the walk --------------------------------------------------------------------

    def run(self, jaxpr: Any, consts: Sequence[Any], args: Sequence[Val]) -> list[Val]:
        """Walk ``jaxpr`` (a core Jaxpr) with ``consts`` and argument values; return outputs."""
        env: dict[Any, Val] = {}

        def read(atom: Any) -> Val:
            if isinstance(atom, jcore.Literal):
                return self.const(atom.val, atom.aval.dtype)  # type: ignore[attr-defined]
            return env[atom]

        for var, c in zip(jaxpr.constvars, consts, strict=True):
            env[var] = c if isinstance(c, Val) else self.const(np.asarray(c))
        for var, a in zip(jaxpr.invars, args, strict=True):
            env[var] = a
        for eqn in jaxpr.eqns:
            outs = self.equation(eqn, [read(a) for a in eqn.invars])
            for var, val in zip(eqn.outvars, outs, strict=True):
                if not isinstance(var, jcore.DropVar):
                    env[var] = val
        return [read(a) for a in jaxpr.outvars]

    def equation(self, eqn: Any, ins: list[Val]) -> list[Val]:
        name = eqn.primitive.name
        prev = self._prim, self._where
        # equations inside JAX's own functions (jnp.hypot, ...) have no user frame: keep the
        # location of the call that led there
        self._prim, self._where = name, (where_from(eqn) or prev[1])
        try:
            if name in CALL_PARAMS:
                sub = eqn.params[CALL_PARAMS[name]]
                if isinstance(sub, jcore.ClosedJaxpr):
                    return self.run(sub.jaxpr, sub.consts, ins)
                return self.run(sub, [], ins)
            if eqn.effects:
                raise self.unsupported("it has side effects (callbacks, prints, RNG state)")
            if all(v.const is not None for v in ins) and name not in NO_FOLD:
                return self.fold(eqn, ins)
            avals = [var.aval for var in eqn.outvars]
            if all(math.prod(a.shape) == 0 for a in avals):  # no elements: nothing to compute
                return [self.const(np.zeros(a.shape, a.dtype)) for a in avals]
            key = _cse_key(eqn, ins)
            if key is not None and key in self._seen:
                return self._seen[key][0]
            rule = self.rules.get(name)
            if rule is None:
                raise self.unsupported(
                    "no C translation is registered for it; supported primitives are listed "
                    "in safestab.export.PRIMITIVES (see docs/export.md to add one)"
                )
            outs = rule(self, eqn, ins)
            for var, val in zip(eqn.outvars, outs, strict=True):
                if tuple(var.aval.shape) != val.shape:  # pragma: no cover - a rule's bug
                    raise AssertionError(f"{name}: rule gave shape {val.shape}, not {var.aval}")
            if key is not None:
                self._seen[key] = (outs, ins)
            return outs
        finally:
            self._prim, self._where = prev

    def fold(self, eqn: Any, ins: list[Val]) -> list[Val]:
        """Evaluate an equation whose inputs are all known, with JAX itself.

        Data movement (a copy of elements, exact in any arithmetic) is evaluated by
        :attr:`exact_fold` without compiling an XLA program for it.
        """
        moved = self.exact_fold(eqn.primitive.name, [v.const for v in ins], eqn.params)
        if moved is not None:
            return [self.const(r) for r in moved]
        res = eqn.primitive.bind(*[jnp.asarray(v.const) for v in ins], **eqn.params)
        res = res if eqn.primitive.multiple_results else [res]
        return [self.const(np.asarray(jax.device_get(r))) for r in res]


def _cse_key(eqn: Any, ins: list[Val]) -> Any:
    """A key equal for two equations that compute the same thing (None: do not merge)."""
    parts: list[Any] = []
    for v in ins:
        if v.const is None:
            parts.append(id(v))
        else:
            parts.append((v.dtype.str, v.shape, v.const.tobytes()))
    for p in eqn.params.values():  # a nested jaxpr's closed-over constants are not in repr
        for sub in p if isinstance(p, tuple | list) else (p,):
            if getattr(sub, "consts", None):
                return None
    try:
        params = tuple(sorted((k, repr(p)) for k, p in eqn.params.items()))
    except Exception:  # pragma: no cover - an unprintable parameter
        return None
    return (eqn.primitive.name, params, tuple(parts))


#: Primitives never folded: a loop is written as a loop (folding it would run it at export
#: time, and hide an unsupported primitive inside behind the particular constants);
#: ``platform_index`` is resolved by its rule (the C code is one platform: the default).
NO_FOLD = frozenset({"while", "scan", "platform_index"})


def live_statements(program: Program | list[Stmt], outputs: Sequence[Val]) -> list[Stmt]:
    """The statements (of a program or a list) some output depends on, in their order."""
    stmts = program.stmts if isinstance(program, Program) else program
    live: set[int] = set()
    stack = [v for v in outputs]
    seen: set[int] = set()
    while stack:
        v = stack.pop()
        if id(v) in seen:
            continue
        seen.add(id(v))
        if v.base is not None:
            stack.append(v.base)
        st = v.producer
        if st is not None and id(st) not in live:
            live.add(id(st))
            stack.extend(st.ins)
    return [st for st in stmts if id(st) in live]
