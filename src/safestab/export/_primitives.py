"""The primitive table: one small translation rule per JAX primitive.

A rule has the signature ``rule(program, eqn, ins) -> outs``: ``ins`` are the input
:class:`~safestab.export._ir.Val` objects, the rule creates the outputs (``program.new``),
registers a statement whose ``gen(emitter)`` returns C lines, and returns the outputs. Inputs
known at export time never reach a rule (they are folded), and calls are inlined before.
To support a new primitive, add a rule to :data:`RULES` (docs/export.md shows an example).

Semantics follow XLA, not C, where they differ: ``max``/``min`` propagate NaN and order
``-0 < +0``; ``sign`` keeps NaN and signed zeros; float-to-int conversion truncates, maps NaN
to 0 and saturates; ``argmax``/``argmin`` pick the first NaN.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
import numpy as np

from ._assemble import render
from ._cgen import Emitter
from ._dual_qp import int_work_size, work_size
from ._ir import Program, Val

Rule = Callable[[Program, Any, list[Val]], list[Val]]
RULES: dict[str, Rule] = {}


def _register(*names: str) -> Callable[[Rule], Rule]:
    def deco(rule: Rule) -> Rule:
        for name in names:
            RULES[name] = rule
        return rule

    return deco


# --------------------------------------------------------------------------------------
# loops and indices


def _strides(shape: tuple[int, ...]) -> list[int]:
    out, acc = [], 1
    for s in reversed(shape):
        out.append(acc)
        acc *= s
    return out[::-1]


def _index(terms: list[tuple[str, int]]) -> str:
    """Flat index ``var0 * stride0 + ...`` (``"0"`` when empty)."""
    parts = [v if st == 1 else f"{v} * {st}" for v, st in terms if st != 0]
    return " + ".join(parts) or "0"


def _affine(start: int, step: int, var: str = "i") -> str:
    if step == 0:
        return str(start)
    term = var if abs(step) == 1 else f"{abs(step)} * {var}"
    if start == 0 and step > 0:
        return term
    return f"{start} {'+' if step > 0 else '-'} {term}"


def _nest(loops: list[tuple[str, int]], body: list[str]) -> list[str]:
    """Nested ``for`` loops (outermost first) around ``body``; extents of 1 are skipped."""
    lines = list(body)
    for var, n in reversed([lp for lp in loops if lp[1] > 1]):
        head = f"for (int {var} = 0; {var} < {n}; ++{var})"
        if len(lines) == 1 and not lines[0].startswith("for"):
            lines = [f"{head} {lines[0]}"]
        else:
            lines = [head + " {"] + ["    " + ln for ln in lines] + ["}"]
    return lines


# --------------------------------------------------------------------------------------
# elementwise


def elementwise(p: Program, eqn: Any, ins: list[Val], expr: Callable[..., str]) -> list[Val]:
    """One output element from the same element of each input (scalars broadcast)."""
    out = p.new(eqn.outvars[0].aval)

    # operands are scalars, of the output's shape, or (JAX >= 0.9) of the same rank with
    # size-1 axes broadcast
    broadcast = any(v.size != 1 and v.shape != out.shape for v in ins)
    for v in ins:
        if v.size != 1 and (
            len(v.shape) != len(out.shape)
            or any(s not in (1, o) for s, o in zip(v.shape, out.shape, strict=True))
        ):  # pragma: no cover - JAX does not produce this
            raise p.unsupported(f"operand of shape {v.shape} for an output of shape {out.shape}")

    def gen(e: Emitter) -> list[str]:
        if out.size == 1:
            return [e.declare(out, expr(e, *[e.ref(v, 0) for v in ins]))]
        if not broadcast:
            refs = [e.ref(v, 0 if v.size == 1 else "i") for v in ins]
            loop = f"for (int i = 0; i < {out.size}; ++i) {e.name(out)}[i] = {expr(e, *refs)};"
            return [e.declare(out), loop]
        loops = [(f"i{d}", s) for d, s in enumerate(out.shape)]

        def idx(shape: tuple[int, ...]) -> str:
            st = _strides(shape)
            return _index([(f"i{d}", st[d]) for d, s in enumerate(shape) if s > 1])

        refs = [e.ref(v, 0 if v.size == 1 else idx(v.shape)) for v in ins]
        body = [f"{e.target(out, idx(out.shape))} = {expr(e, *refs)};"]
        return [e.declare(out)] + _nest(loops, body)

    p.stmt([out], ins, gen)
    return [out]


def _unary(fmt: Callable[[Emitter, Any, str], str]) -> Rule:
    def rule(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
        dt = ins[0].dtype
        return elementwise(p, eqn, ins, lambda e, a: fmt(e, dt, a))

    return rule


def _binary(fmt: Callable[[Emitter, Any, str, str], str]) -> Rule:
    def rule(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
        dt = ins[0].dtype
        return elementwise(p, eqn, ins, lambda e, a, b: fmt(e, dt, a, b))

    return rule


def _math(fn: str) -> Rule:
    return _unary(lambda e, dt, a: f"{e.math(fn, dt)}({a})")


for _name in (
    "exp2 log log1p expm1 sin cos tan tanh asin acos atan sinh cosh asinh acosh atanh "
    "sqrt cbrt erf erfc lgamma floor ceil"
).split():
    RULES[_name] = _math(_name)
RULES["exp"] = _unary(lambda e, dt, a: f"{e.helper('exp', dt)}({a})")
RULES["atan2"] = _binary(lambda e, dt, a, b: f"{e.math('atan2', dt)}({a}, {b})")
RULES["nextafter"] = _binary(lambda e, dt, a, b: f"{e.math('nextafter', dt)}({a}, {b})")
RULES["pow"] = _binary(lambda e, dt, a, b: f"{e.math('pow', dt)}({a}, {b})")
RULES["rsqrt"] = _unary(lambda e, dt, a: f"{e.lit(1, dt)} / {e.math('sqrt', dt)}({a})")
RULES["logistic"] = _unary(
    lambda e, dt, a: f"{e.lit(1, dt)} / ({e.lit(1, dt)} + {e.math('exp', dt)}(-{a}))"
)
RULES["square"] = _unary(lambda e, dt, a: f"{a} * {a}")
RULES["neg"] = _unary(lambda e, dt, a: f"-{a}")
RULES["sign"] = _unary(lambda e, dt, a: f"{e.helper('sign', dt)}({a})")
RULES["abs"] = _unary(
    lambda e, dt, a: f"{e.math('fabs', dt)}({a})" if e.is_float(dt) else f"({a} < 0 ? -{a} : {a})"
)
RULES["is_finite"] = _unary(lambda e, dt, a: f"(isfinite({a}) ? 1 : 0)")
RULES["not"] = _unary(lambda e, dt, a: f"!{a}" if dt == np.bool_ else f"~{a}")
RULES["add"] = RULES["add_any"] = _binary(lambda e, dt, a, b: f"{a} + {b}")
RULES["sub"] = _binary(lambda e, dt, a, b: f"{a} - {b}")
RULES["mul"] = _binary(lambda e, dt, a, b: f"{a} * {b}")
RULES["div"] = _binary(lambda e, dt, a, b: f"{a} / {b}")
RULES["rem"] = _binary(
    lambda e, dt, a, b: f"{e.math('fmod', dt)}({a}, {b})" if e.is_float(dt) else f"{a} % {b}"
)
RULES["max"] = _binary(lambda e, dt, a, b: f"{e.helper('max', dt)}({a}, {b})")
RULES["min"] = _binary(lambda e, dt, a, b: f"{e.helper('min', dt)}({a}, {b})")
RULES["and"] = _binary(lambda e, dt, a, b: f"{a} & {b}")
RULES["or"] = _binary(lambda e, dt, a, b: f"{a} | {b}")
RULES["xor"] = _binary(lambda e, dt, a, b: f"{a} ^ {b}")
for _name, _op in (
    ("eq", "=="),
    ("ne", "!="),
    ("lt", "<"),
    ("le", "<="),
    ("gt", ">"),
    ("ge", ">="),
):
    RULES[_name] = _binary(lambda e, dt, a, b, op=_op: f"{a} {op} {b}")  # type: ignore[misc]


@_register("round")
def _round(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    # rounding_method 0: half away from zero (C round); 1: half to even (nearbyint)
    fn = "round" if int(eqn.params["rounding_method"]) == 0 else "nearbyint"
    return _math(fn)(p, eqn, ins)


@_register("integer_pow")
def _integer_pow(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    y, dt = int(eqn.params["y"]), ins[0].dtype
    if y == 0:
        return elementwise(p, eqn, ins, lambda e, a: e.lit(1, dt))
    if y == 1:
        return elementwise(p, eqn, ins, lambda e, a: a)
    if y == 2:
        return elementwise(p, eqn, ins, lambda e, a: f"{a} * {a}")
    return elementwise(p, eqn, ins, lambda e, a: f"{e.helper('ipow', dt)}({a}, {y})")


@_register("clamp")
def _clamp(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    dt = ins[1].dtype  # clamp(lo, x, hi) = min(max(x, lo), hi), as XLA
    return elementwise(
        p,
        eqn,
        ins,
        lambda e, lo, x, hi: f"{e.helper('min', dt)}({e.helper('max', dt)}({x}, {lo}), {hi})",
    )


@_register("select_n")
def _select_n(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    pred, cases = ins[0], ins[1:]
    s = pred.splat()
    if s is not None and pred.size in (1, cases[0].size):
        chosen = cases[int(s)]
        if chosen.shape == tuple(eqn.outvars[0].aval.shape):
            return [chosen]
    boolean = pred.dtype == np.bool_

    def expr(e: Emitter, c: str, *refs: str) -> str:
        if boolean:
            return f"{c} ? {refs[1]} : {refs[0]}"
        text = refs[-1]
        for k in range(len(refs) - 2, -1, -1):
            text = f"{c} == {k} ? {refs[k]} : ({text})"
        return text

    return elementwise(p, eqn, ins, expr)


@_register("convert_element_type")
def _convert(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    src, dst = ins[0].dtype, np.dtype(eqn.params["new_dtype"])
    if src == dst:
        return [ins[0]]

    def expr(e: Emitter, a: str) -> str:
        if dst == np.bool_:
            return f"{a} != {e.zero(src)}"
        if dst.kind in "iu" and src.kind == "f":
            return f"{e.helper('f2i', src, dst)}({a})"
        if e.ctype(src) == e.ctype(dst):
            return a
        return f"({e.ctype(dst)}){a}"

    return elementwise(p, eqn, ins, expr)


@_register("copy", "copy_p", "optimization_barrier")
def _identity(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    return list(ins)


@_register("reduce_precision")
def _reduce_precision(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    info = np.finfo(ins[0].dtype)
    if (eqn.params["exponent_bits"], eqn.params["mantissa_bits"]) == (info.nexp, info.nmant):
        return list(ins)
    raise p.unsupported("rounding to a narrower float format is not exported")


# --------------------------------------------------------------------------------------
# data movement: the index map is found by running the primitive on element labels


_DATA_OPERANDS: dict[str, Callable[[int], list[int]]] = {
    "broadcast_in_dim": lambda n: [0],
    "reshape": lambda n: [0],
    "squeeze": lambda n: [0],
    "expand_dims": lambda n: [0],
    "transpose": lambda n: [0],
    "rev": lambda n: [0],
    "slice": lambda n: [0],
    "split": lambda n: [0],
    "concatenate": lambda n: list(range(n)),
    "stack": lambda n: list(range(n)),
    "pad": lambda n: [0, 1],
    "gather": lambda n: [0],
    "scatter": lambda n: [0, 2],
    "dynamic_slice": lambda n: [0],
    "dynamic_update_slice": lambda n: [0, 1],
}


def _clamped_starts(x: np.ndarray, sizes: tuple[int, ...], starts: list[Any]) -> tuple[slice, ...]:
    """The slices of a dynamic slice or update at ``starts``, clamped into range as in XLA."""
    out = []
    for dim, size, s in zip(x.shape, sizes, starts, strict=True):
        lo = min(max(int(np.asarray(s)), 0), dim - size)
        out.append(slice(lo, lo + size))
    return tuple(out)


def _pad(x: np.ndarray, fill: np.ndarray, config: Any) -> np.ndarray:
    """``lax.pad``: ``(low, high, interior)`` per axis, negative low or high crops."""
    shape = [
        lo + hi + n + max(n - 1, 0) * inner
        for n, (lo, hi, inner) in zip(x.shape, config, strict=True)
    ]
    out = np.full(shape, fill, dtype=x.dtype)
    index, keep = [], []
    for n, size, (lo, _, inner) in zip(x.shape, shape, config, strict=True):
        pos = lo + np.arange(n) * (inner + 1)
        inside = (pos >= 0) & (pos < size)
        index.append(pos[inside])
        keep.append(np.flatnonzero(inside))
    out[np.ix_(*index)] = x[np.ix_(*keep)]
    return out


#: NumPy versions of the movement primitives: finding where each output element comes from
#: needs no XLA program (``bind`` compiled one per primitive and shape: half the time of
#: exporting a filter). Each is the primitive's documented semantics, checked against ``bind``
#: in the tests; the others (gather, scatter) run through JAX.
_NUMPY_MOVEMENT: dict[str, Callable[..., list[np.ndarray]]] = {
    "broadcast_in_dim": lambda x, *, shape, broadcast_dimensions, **_: [
        np.broadcast_to(
            x.reshape(
                [
                    x.shape[broadcast_dimensions.index(d)] if d in broadcast_dimensions else 1
                    for d in range(len(shape))
                ]
            ),
            shape,
        )
    ],
    "reshape": lambda x, *, new_sizes, dimensions, **_: [
        (x if dimensions is None else np.transpose(x, dimensions)).reshape(new_sizes)
    ],
    "squeeze": lambda x, *, dimensions: [np.squeeze(x, axis=tuple(dimensions))],
    "transpose": lambda x, *, permutation: [np.transpose(x, permutation)],
    "rev": lambda x, *, dimensions: [np.flip(x, axis=tuple(dimensions))],
    "slice": lambda x, *, start_indices, limit_indices, strides: [
        x[
            tuple(
                slice(s, e, 1 if strides is None else st)
                for s, e, st in zip(start_indices, limit_indices, strides or start_indices)
            )
        ]
    ],
    "concatenate": lambda *xs, dimension: [np.concatenate(xs, axis=dimension)],
    "split": lambda x, *, sizes, axis: np.split(
        x, np.cumsum([int(s) for s in sizes])[:-1], axis=axis
    ),
    "pad": lambda x, fill, *, padding_config: [_pad(x, fill, padding_config)],
    "dynamic_slice": lambda x, *starts, slice_sizes: [
        x[_clamped_starts(x, tuple(slice_sizes), list(starts))]
    ],
    "dynamic_update_slice": lambda x, upd, *starts: [
        _updated(x, upd, _clamped_starts(x, upd.shape, list(starts)))
    ],
}


def _updated(x: np.ndarray, upd: np.ndarray, where: tuple[slice, ...]) -> np.ndarray:
    out = np.array(x)
    out[where] = upd
    return out


#: Elementwise primitives whose every result is exactly determined by IEEE 754 (a correctly
#: rounded operation, a comparison or a logical one): NumPy gives XLA's bits. Left to XLA:
#: ``max``/``min`` (the sign of a zero result), ``exp`` and the other transcendental ones,
#: reductions with rounding (their order), integer division and ``integer_pow``.
_NUMPY_EXACT: dict[str, Callable[..., Any]] = {
    "add": np.add, "sub": np.subtract, "mul": np.multiply, "neg": np.negative,
    "abs": np.abs, "sqrt": np.sqrt, "square": np.square,
    "eq": np.equal, "ne": np.not_equal, "lt": np.less, "le": np.less_equal,
    "gt": np.greater, "ge": np.greater_equal,
    "and": np.bitwise_and, "or": np.bitwise_or, "xor": np.bitwise_xor, "not": np.invert,
    "is_finite": np.isfinite,
}  # fmt: skip
_FLOATS = (np.dtype(np.float64), np.dtype(np.float32))


def _subnormal(x: np.ndarray) -> bool:
    """Whether a float array holds a subnormal number (XLA on the CPU flushes them to 0)."""
    if x.dtype not in _FLOATS:
        return False
    return bool(np.any((x != 0) & (np.abs(x) < np.finfo(x.dtype).tiny)))


def _exact(name: str, args: list[np.ndarray], params: dict[str, Any]) -> np.ndarray | None:
    """``name`` on NumPy arrays where IEEE 754 fixes its bits (None: left to XLA).

    Where an input or the result is subnormal, XLA's CPU code (which flushes subnormals to
    zero) and IEEE arithmetic differ: those are left to XLA.
    """
    if any(_subnormal(a) for a in args):
        return None
    out = _exact_normal(name, args, params)
    return None if out is None or _subnormal(np.asarray(out)) else out


def _exact_normal(name: str, args: list[np.ndarray], params: dict[str, Any]) -> Any:
    dtypes = {np.asarray(a).dtype for a in args}
    if name == "div":
        return np.true_divide(*args) if len(dtypes) == 1 and dtypes <= set(_FLOATS) else None
    if name in ("sqrt", "is_finite") and not dtypes <= set(_FLOATS):
        return None
    if name == "select_n":
        which, *cases = (np.asarray(a) for a in args)
        if len({c.dtype for c in cases}) != 1:
            return None
        return np.choose(which.astype(np.int64), cases) if cases else None
    if name == "convert_element_type":
        (x,) = (np.asarray(a) for a in args)
        new = np.dtype(params["new_dtype"])
        # widening or a float's rounding to float32: exact in both; to an integer or a bool
        # (truncation, out-of-range values, NaN) is left to XLA
        small_int = x.dtype.kind == "i" and x.dtype.itemsize <= 4
        exact = (x.dtype == new or (x.dtype in _FLOATS and new in _FLOATS)
                 or (x.dtype == np.bool_ and new != np.bool_)
                 or (small_int and new == np.float64))  # fmt: skip
        return x.astype(new) if exact else None
    fn = _NUMPY_EXACT.get(name)
    if fn is None or len(dtypes) != 1:
        return None
    return fn(*args)


def move(name: str, args: list[np.ndarray], params: dict[str, Any]) -> list[np.ndarray] | None:
    """The movement primitive ``name`` on NumPy arrays (None: not one done in NumPy)."""
    fn = _NUMPY_MOVEMENT.get(name)
    if fn is None:
        return None
    return [np.array(r, order="C") for r in fn(*args, **params)]


def fold_exact(
    name: str, args: list[np.ndarray], params: dict[str, Any]
) -> list[np.ndarray] | None:
    """An equation on known values in NumPy, where that gives XLA's bits without compiling.

    Data movement (:func:`move`) and the elementwise operations whose results IEEE 754 fixes;
    None for the rest, which JAX evaluates.
    """
    moved = move(name, args, params)
    if moved is not None:
        return moved
    with np.errstate(all="ignore"):  # IEEE results (inf, NaN) as XLA gives them, silently
        out = _exact(name, [np.asarray(a) for a in args], params)
    return None if out is None else [np.array(out, order="C")]


def _movement(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    """Copy elements: every output element is one input element or a fill value."""
    data = _DATA_OPERANDS[eqn.primitive.name](len(ins))
    args, starts, owners = [], [], []
    base = 0
    for k, v in enumerate(ins):
        if k in data:
            labels = np.arange(base, base + v.size, dtype=np.float64).reshape(v.shape)
            args.append(labels)
            starts.append(base)
            owners.append(v)
            base += v.size
        elif v.const is None:
            raise p.unsupported(
                "an index operand depends on the state; only indices known at export time "
                "are supported"
            )
        else:
            args.append(np.asarray(v.const))
    res = move(eqn.primitive.name, args, eqn.params)
    if res is None:
        res = eqn.primitive.bind(*[jnp.asarray(a) for a in args], **eqn.params)
        res = res if eqn.primitive.multiple_results else [res]
    return [
        _copy_from(p, var.aval, np.asarray(r).reshape(-1), np.array(starts), owners)
        for r, var in zip(res, eqn.outvars, strict=True)
    ]


for _name in _DATA_OPERANDS:
    RULES[_name] = _movement


@_register("dynamic_slice")
def _dynamic_slice(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    """A slice at start indices computed at run time (clamped into range, as in XLA)."""
    x, starts = ins[0], ins[1:]
    if all(v.const is not None for v in starts):
        return _movement(p, eqn, ins)
    sizes = tuple(int(s) for s in eqn.params["slice_sizes"])
    out = p.new(eqn.outvars[0].aval)

    def gen(e: Emitter) -> list[str]:
        xs, os_ = _strides(x.shape), _strides(sizes)
        lines = [e.declare(out), "{"]
        terms = []
        for d, (dim, size) in enumerate(zip(x.shape, sizes, strict=True)):
            start = f"(long long){e.ref(starts[d], 0)}"  # signed, whatever its type
            hi = dim - size
            lines.append(
                f"    const long long dsl_{d} = ({start}) < 0 ? 0 : (({start}) > {hi} ? {hi} : "
                f"({start}));"
            )
            if size > 1:
                terms.append(f"(dsl_{d} + i{d}) * {xs[d]}" if xs[d] != 1 else f"dsl_{d} + i{d}")
            else:
                terms.append(f"dsl_{d} * {xs[d]}" if xs[d] != 1 else f"dsl_{d}")
        loops = [(f"i{d}", size) for d, size in enumerate(sizes)]
        tgt = e.target(out, _index([(f"i{d}", os_[d]) for d, s in enumerate(sizes) if s > 1]))
        body = [f"{tgt} = {e.ref(x, ' + '.join(terms) or '0')};"]
        return lines + _indent(_nest(loops, body)) + ["}"]

    p.stmt([out], ins, gen)
    return [out]


def _copy_from(p: Program, aval: Any, lab: np.ndarray, starts: np.ndarray, owners) -> Val:
    n = lab.size
    if n == 0:
        return p.const(np.zeros(aval.shape, aval.dtype))
    fill = np.isnan(lab)
    if fill.any() and np.dtype(aval.dtype).kind != "f":
        raise p.unsupported("out-of-bounds indices with a non-float fill value")
    li = np.where(fill, 0, lab).astype(np.int64)
    owner = np.where(fill, -1, np.searchsorted(starts, li, side="right") - 1)
    src = np.where(fill, 0, li - starts[np.maximum(owner, 0)])
    if (owner == owner[0]).all() and owner[0] >= 0:
        v = owners[owner[0]]
        if v.size == n and (src == np.arange(n)).all():
            return p.alias(v, aval.shape, aval.dtype)
    if all(o < 0 or owners[o].const is not None for o in owner):
        flat = np.array(
            [np.nan if o < 0 else owners[o].const.reshape(-1)[s] for o, s in zip(owner, src)]
        )
        return p.const(flat.astype(aval.dtype).reshape(aval.shape))
    out = p.new(aval)
    runs = []  # (out start, length, owner, src start, src step)
    j = 0
    while j < n:
        o, s = int(owner[j]), int(src[j])
        length, step = 1, 0
        if j + 1 < n and owner[j + 1] == o:
            step = 0 if o < 0 else int(src[j + 1] - s)
            while (
                j + length < n and owner[j + length] == o and src[j + length] == s + step * length
            ):
                length += 1
        runs.append((j, length, o, s, step))
        j += length
    used = sorted({o for o in owner.tolist() if o >= 0})
    table = None
    if len(runs) > 8 and n > 16 and len(used) == 1 and not fill.any():
        table = p.const(src.astype(np.int32))
    ins = [owners[o] for o in used] + ([table] if table is not None else [])

    def gen(e: Emitter) -> list[str]:
        def src_ref(o: int, idx: int | str) -> str:
            return e.lit(np.nan, aval.dtype) if o < 0 else e.ref(owners[o], idx)

        if out.size == 1:
            return [e.declare(out, src_ref(runs[0][2], runs[0][3]))]
        lines = [e.declare(out)]
        name = e.name(out)
        if table is not None:
            ref = e.ref(owners[used[0]], e.ref(table, "i"))
            return lines + [f"for (int i = 0; i < {n}; ++i) {name}[i] = {ref};"]
        for start, length, o, s, step in runs:
            if length == 1:
                lines.append(f"{name}[{start}] = {src_ref(o, s)};")
            else:
                lines.append(
                    f"for (int i = 0; i < {length}; ++i) {name}[{_affine(start, 1)}] = "
                    f"{src_ref(o, _affine(s, step))};"
                )
        return lines

    p.stmt([out], ins, gen)
    return out


# --------------------------------------------------------------------------------------
# reductions


def _reduce_ops(kind: str, e: Emitter, dt: Any) -> tuple[str, Callable[[str, str], str]]:
    """Initial value and combination of a reduction, as XLA defines them."""
    flt = e.is_float(dt)
    if kind == "sum":
        return e.zero(dt), lambda acc, v: f"{acc} + {v}"
    if kind == "prod":
        return e.lit(1, dt), lambda acc, v: f"{acc} * {v}"
    if kind in ("max", "min"):
        if flt:
            init = e.lit(-np.inf if kind == "max" else np.inf, dt)
        elif dt == np.bool_:
            init = "0" if kind == "max" else "1"
        else:
            info = np.iinfo(dt)
            init = e.lit(info.min if kind == "max" else info.max, dt)
        fn = e.helper(kind, dt)
        return init, lambda acc, v: f"{fn}({acc}, {v})"
    op = {"and": "&", "or": "|", "xor": "^"}[kind]
    return ("1" if kind == "and" else "0"), lambda acc, v: f"{acc} {op} {v}"


def _reduction(kind: str) -> Rule:
    def rule(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
        x = ins[0]
        axes = sorted(int(a) for a in eqn.params["axes"])
        out = p.new(eqn.outvars[0].aval)
        kept = [d for d in range(len(x.shape)) if d not in axes]

        def gen(e: Emitter) -> list[str]:
            xs, os_ = _strides(x.shape), _strides(out.shape)
            kept_loops = [(f"i{d}", x.shape[d]) for d in kept]
            red_loops = [(f"r{d}", x.shape[d]) for d in axes]
            out_idx = _index([(f"i{d}", os_[j]) for j, d in enumerate(kept) if x.shape[d] > 1])
            in_idx = _index(
                [
                    (f"{'r' if d in axes else 'i'}{d}", xs[d])
                    for d in range(len(x.shape))
                    if x.shape[d] > 1
                ]
            )
            tgt = e.target(out, out_idx)
            init, combine = _reduce_ops(kind, e, x.dtype)
            body = [f"{tgt} = {init};"] + _nest(
                red_loops, [f"{tgt} = {combine(tgt, e.ref(x, in_idx))};"]
            )
            return [e.declare(out)] + _nest(kept_loops, body)

        p.stmt([out], [x], gen)
        return [out]

    return rule


for _kind in ("sum", "prod", "max", "min", "and", "or", "xor"):
    RULES[f"reduce_{_kind}"] = _reduction(_kind)


def _arg_extremum(kind: str) -> Rule:
    def rule(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
        x = ins[0]
        (axis,) = (int(a) for a in eqn.params["axes"])
        out = p.new(eqn.outvars[0].aval)
        kept = [d for d in range(len(x.shape)) if d != axis]

        def gen(e: Emitter) -> list[str]:
            xs, os_ = _strides(x.shape), _strides(out.shape)
            out_idx = _index([(f"i{d}", os_[j]) for j, d in enumerate(kept) if x.shape[d] > 1])
            terms = [(f"i{d}", xs[d]) for d in kept if x.shape[d] > 1]
            tgt = e.target(out, out_idx)
            if x.shape[axis] == 1:
                body = [f"{tgt} = 0;"]
            else:
                first = e.ref(x, _index(terms))
                cur = e.ref(x, _index(terms + [("r", xs[axis])]))
                op = ">" if kind == "max" else "<"
                better = f"v {op} best"
                if e.is_float(x.dtype):  # XLA: the first NaN wins
                    better = f"{better} || (v != v && best == best)"
                ct = e.ctype(x.dtype)
                body = [
                    "{",
                    f"    {ct} best = {first};",
                    f"    {tgt} = 0;",
                    f"    for (int r = 1; r < {x.shape[axis]}; ++r) {{",
                    f"        const {ct} v = {cur};",
                    f"        if ({better}) {{ best = v; {tgt} = r; }}",
                    "    }",
                    "}",
                ]
            return [e.declare(out)] + _nest([(f"i{d}", x.shape[d]) for d in kept], body)

        p.stmt([out], [x], gen)
        return [out]

    return rule


RULES["argmax"] = _arg_extremum("max")
RULES["argmin"] = _arg_extremum("min")


# --------------------------------------------------------------------------------------
# dot_general


@_register("dot_general")
def _dot_general(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    lhs, rhs = ins
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    lc, rc, lb, rb = (tuple(int(d) for d in t) for t in (lc, rc, lb, rb))
    out = p.new(eqn.outvars[0].aval)
    lfree = [d for d in range(len(lhs.shape)) if d not in lc and d not in lb]
    rfree = [d for d in range(len(rhs.shape)) if d not in rc and d not in rb]
    lvar: dict[int, str] = {}
    rvar: dict[int, str] = {}
    for j, (a, b) in enumerate(zip(lb, rb, strict=True)):
        lvar[a] = rvar[b] = f"i{j}"
    for j, d in enumerate(lfree):
        lvar[d] = f"i{len(lb) + j}"
    for j, d in enumerate(rfree):
        rvar[d] = f"i{len(lb) + len(lfree) + j}"
    for t, (a, b) in enumerate(zip(lc, rc, strict=True)):
        lvar[a] = rvar[b] = f"k{t}"
    # Host layout: the innermost loop runs over the last output axis; a constant operand is
    # stored with that axis last so the loop reads contiguous memory (and the compiler can
    # vectorise it). Embedded layout (cores without SIMD): each output element is summed in
    # a register over the contraction axes, stored last in a constant operand. Both sum the
    # products in the same order (the contraction index ascending), so they give the same
    # bits.
    embedded = getattr(p, "layout", "host") == "embedded"
    last = f"i{len(out.shape) - 1}" if out.shape else None
    k_names = [f"k{t}" for t in range(len(lc))]
    operands = []
    for v, var in ((lhs, lvar), (rhs, rvar)):
        dims = list(range(len(v.shape)))
        if v.const is not None and v.splat() is None:
            if embedded:
                tail = [next(d for d in dims if var[d] == k) for k in k_names]
                perm = [d for d in dims if d not in tail] + tail
            elif last in var.values():
                d_last = next(d for d in dims if var[d] == last)
                perm = [d for d in dims if d != d_last] + [d_last]
            else:
                perm = dims
            if perm != dims:
                v = p.const(np.transpose(v.const, perm))
                var = {j: var[d] for j, d in enumerate(perm)}
        operands.append((v, var))

    def gen(e: Emitter) -> list[str]:
        ct = e.ctype(out.dtype)

        def term(v: Val, var: dict[int, str]) -> str:
            st = _strides(v.shape)
            ref = e.ref(v, _index([(var[d], st[d]) for d in range(len(v.shape)) if v.shape[d] > 1]))
            return ref if e.ctype(v.dtype) == ct else f"({ct}){ref}"

        out_loops = [(f"i{j}", s) for j, s in enumerate(out.shape)]
        k_loops = [(f"k{t}", lhs.shape[a]) for t, a in enumerate(lc)]
        ost = _strides(out.shape)
        tgt = e.target(out, _index([(v, ost[j]) for j, (v, s) in enumerate(out_loops) if s > 1]))
        prod = f"{term(*operands[0])} * {term(*operands[1])}"
        if embedded:
            body = ["{", f"    {ct} acc = {e.zero(out.dtype)};"]
            body += ["    " + ln for ln in _nest(k_loops, [f"acc += {prod};"])]
            body += [f"    {tgt} = acc;", "}"]
            return [e.declare(out)] + _nest(out_loops, body)
        inner = out_loops[-1:] if out_loops else []
        body = _nest(inner, [f"{tgt} = {e.zero(out.dtype)};"])
        body += _nest(k_loops + inner, [f"{tgt} += {prod};"])
        return [e.declare(out)] + _nest(out_loops[:-1], body)

    p.stmt([out], [operands[0][0], operands[1][0]], gen)
    return [out]


# --------------------------------------------------------------------------------------
# control flow


def _copy_into(e: Emitter, dst: Val, src: Val) -> list[str]:
    """Assign every element of ``src`` to the (mutable) run-time value ``dst``."""
    if dst.size == 0 or src.root() is dst.root():
        return []
    if dst.size == 1:
        return [f"{e.target(dst, 0)} = {e.ref(src, 0)};"]
    return [f"for (int i = 0; i < {dst.size}; ++i) {e.name(dst)}[i] = {e.ref(src, 'i')};"]


def _assign_all(e: Emitter, dsts: list[Val], srcs: list[Val]) -> list[str]:
    """``dsts = srcs`` as one simultaneous assignment (a source may be another destination)."""
    roots = {id(d.root()): k for k, d in enumerate(dsts)}
    lines: list[str] = []
    staged: list[tuple[Val, Val]] = []
    for k, (dst, src) in enumerate(zip(dsts, srcs, strict=True)):
        j = roots.get(id(src.root()))
        if j is not None and j != k and dst.size:  # read before it is overwritten: stage it
            tmp = Val(src.shape, src.dtype)
            lines += [e.declare(tmp)] + _copy_into(e, tmp, src)
            staged.append((dst, tmp))
        else:
            staged.append((dst, src))
    for dst, src in staged:
        lines += _copy_into(e, dst, src)
    return lines


def _declare_mutable(e: Emitter, vals: list[Val]) -> list[str]:
    # "(void)": a result that nothing after the statement reads is not a warning (the
    # statement is kept whole for the results that are read)
    return [f"{e.declare(v)} (void){e.name(v)};" for v in vals if v.size]


def _indent(lines: list[str]) -> list[str]:
    return ["    " + ln for ln in lines]


@_register("cond")
def _cond(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    branches = eqn.params["branches"]
    index, args = ins[0], ins[1:]
    if index.const is not None:
        k = int(np.clip(int(index.const), 0, len(branches) - 1))
        return p.run(branches[k].jaxpr, branches[k].consts, args)
    # only the branch taken runs: if / else if / else (an index out of range is clamped, as
    # lax.switch does before it binds cond, and as the constant index above)
    outs = [p.new(var.aval) for var in eqn.outvars]
    blocks = [p.block(b.jaxpr, b.consts, args) for b in branches]

    def gen(e: Emitter) -> list[str]:
        c = e.ref(index, 0)
        lines = _declare_mutable(e, outs)
        last = len(blocks) - 1
        if last == 0:  # one branch: it always runs
            stmts, res = blocks[0]
            return lines + ["{"] + _indent(render(e, stmts) + _assign_all(e, outs, res)) + ["}"]
        for k, (stmts, res) in enumerate(blocks):
            head = (
                f"if ({c} <= 0) {{" if k == 0
                else ("} else {" if k == last else f"}} else if ({c} == {k}) {{")
            )  # fmt: skip
            lines += [head] + _indent(render(e, stmts) + _assign_all(e, outs, res))
        return lines + ["}"]

    results = [v for b in blocks for v in b[1]]
    p.stmt(outs, ins, gen, blocks=[b[0] for b in blocks], scratch=outs, results=results)
    return outs


@_register("while")
def _while(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    """``lax.while_loop`` (and ``fori_loop`` with bounds known only at run time).

    The carried values are mutable variables declared before the loop; each pass evaluates
    the condition, leaves the loop when it is false, runs the body and assigns its results to
    the carried variables (simultaneously). The iteration bound is the program's own: the
    loop runs exactly as many passes as the JAX loop.
    """
    cj, bj = eqn.params["cond_jaxpr"], eqn.params["body_jaxpr"]
    nc, nb = eqn.params["cond_nconsts"], eqn.params["body_nconsts"]
    cconsts, bconsts, init = ins[:nc], ins[nc : nc + nb], ins[nc + nb :]
    carried = [p.new(var.aval) for var in eqn.outvars]
    cond_stmts, (pred,) = p.block(cj.jaxpr, cj.consts, cconsts + carried)
    body_stmts, res = p.block(bj.jaxpr, bj.consts, bconsts + carried)

    def gen(e: Emitter) -> list[str]:
        lines = _declare_mutable(e, carried) + _assign_all(e, carried, init)
        inner = render(e, cond_stmts) + [f"if (!({e.ref(pred, 0)})) break;"]
        inner += render(e, body_stmts) + _assign_all(e, carried, res)
        return lines + ["for (;;) {"] + _indent(inner) + ["}"]

    p.stmt(
        carried, ins, gen, blocks=[cond_stmts, body_stmts], scratch=carried, results=[pred, *res]
    )
    return carried


@_register("platform_index")
def _platform_index(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    # the C code is one platform, the default one (None), as on CPU
    platforms = eqn.params["platforms"]
    for k, names in enumerate(platforms):
        if names is None or "cpu" in names:
            return [p.const(k, eqn.outvars[0].aval.dtype)]
    raise p.unsupported(f"no default branch among the platforms {platforms}")


@_register("stop_gradient")
def _stop_gradient(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    return list(ins)


# --------------------------------------------------------------------------------------
# linear algebra (small dense matrices; loops in C)


@_register("triangular_solve")
def _triangular_solve(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    a, b = ins
    prm = eqn.params
    if not prm["left_side"]:
        raise p.unsupported("right-side triangular solves (x A = b) are not exported")
    out = p.new(eqn.outvars[0].aval)
    m, n = b.shape[-2], b.shape[-1]
    batch = math.prod(b.shape[:-2])
    a_batched = math.prod(a.shape[:-2]) > 1
    trans, unit = bool(prm["transpose_a"]), bool(prm["unit_diagonal"])
    forward = bool(prm["lower"]) != trans  # op(A) lower triangular: forward substitution

    def gen(e: Emitter) -> list[str]:
        ct = e.ctype(out.dtype)
        ab = f"tri_b * {m * m} + " if a_batched else ""

        def A(r: str, c: str) -> str:  # element (r, c) of op(A)
            return e.ref(a, f"{ab}({c}) * {m} + ({r})" if trans else f"{ab}({r}) * {m} + ({c})")

        X = lambda r: e.target(out, f"tri_b * {m * n} + ({r}) * {n} + tri_j")  # noqa: E731
        rng = "tri_c = 0; tri_c < tri_r; ++tri_c" if forward else (
            f"tri_c = tri_r + 1; tri_c < {m}; ++tri_c"
        )  # fmt: skip
        row = "tri_r0" if forward else f"{m - 1} - tri_r0"
        div = "" if unit else f" / {A('tri_r', 'tri_r')}"
        return [
            e.declare(out),
            f"for (int tri_b = 0; tri_b < {batch}; ++tri_b)",
            f"for (int tri_j = 0; tri_j < {n}; ++tri_j)",
            f"for (int tri_r0 = 0; tri_r0 < {m}; ++tri_r0) {{",
            f"    const int tri_r = {row};",
            f"    {ct} tri_s = {e.ref(b, f'tri_b * {m * n} + tri_r * {n} + tri_j')};",
            f"    for (int {rng}) tri_s -= {A('tri_r', 'tri_c')} * {X('tri_c')};",
            f"    {X('tri_r')} = tri_s{div};",
            "}",
        ]

    p.stmt([out], [a, b], gen)
    return [out]


@_register("qr")
def _qr(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    """Householder QR with LAPACK's conventions (``geqrf`` + ``orgqr``: same signs)."""
    (a,) = ins
    if eqn.params.get("pivoting") or eqn.params.get("full_matrices"):
        raise p.unsupported("only the reduced QR without pivoting is exported")
    q, r = (p.new(var.aval) for var in eqn.outvars)
    M, N = a.shape[-2:]
    K = min(M, N)
    batch = math.prod(a.shape[:-2])
    if q.size == 1 or r.size == 1:
        raise p.unsupported("a 1 x 1 QR")
    work = Val((M * N,), a.dtype)
    tau = Val((K,), a.dtype)

    def gen(e: Emitter) -> list[str]:
        fn = e.helper("qr", a.dtype)
        return [
            e.declare(q), e.declare(r),
            f"for (int qr_b = 0; qr_b < {batch}; ++qr_b) {{",
            f"    {e.ctype(a.dtype)} {e.name(work)}[{M * N}], {e.name(tau)}[{K}];",
            f"    for (int i = 0; i < {M * N}; ++i) "
            f"{e.name(work)}[i] = {e.ref(a, f'qr_b * {M * N} + i')};",
            f"    {fn}({M}, {N}, {e.name(work)}, {e.name(tau)}, {e.name(q)} + qr_b * {M * K}, "
            f"{e.name(r)} + qr_b * {K * N});",
            "}",
        ]  # fmt: skip

    p.stmt([q, r], [a], gen, scratch=[work, tau])
    return [q, r]


@_register("safestab_dual_qp")
def _dual_qp(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    """The filter's QP solver as one call of its C function per problem.

    :data:`~safestab.formulas._dual_active_set.dual_qp_p`, written by
    :mod:`safestab.export._dual_qp` (which lays the rows out for the solver itself).
    """
    G, r, w0, use, max_iter, slack = ins
    outs = [p.new(var.aval) for var in eqn.outvars]
    w, mult, active, status, iters, cond, certified = outs
    n_rows, cols = G.shape[-2:]
    dim = w0.shape[-1]  # cols + the slacks' coordinates
    k = dim - cols
    batch = math.prod(G.shape[:-2])
    tols = eqn.params["tols"]
    real, i32 = G.dtype, np.dtype(np.int32)
    # one problem's inputs and outputs, staged; the work arrays
    arr = lambda size, dtype=real: Val((size,), dtype)  # noqa: E731
    gs, rs, w0s, ss = arr(n_rows * cols), arr(n_rows), arr(dim), arr(max(k, 1))
    us, ws, ms, acts = arr(n_rows, i32), arr(dim), arr(n_rows), arr(n_rows, i32)
    work, iwork = arr(work_size(n_rows, dim)), arr(int_work_size(n_rows, dim), i32)
    # the rows are read in place where they are a run-time array, else staged
    in_place = G.const is None and G.root().size > 1 and G.root().param is None
    staged = [rs, w0s, ss, us, ws, ms, acts, work, iwork] + ([] if in_place else [gs])

    def gen(e: Emitter) -> list[str]:
        fn = e.helper("dual_qp", real)
        n = e.name
        lit = lambda x: e.lit(x, real)  # noqa: E731
        copy = lambda dst, src, size: (  # noqa: E731
            f"    for (int i = 0; i < {size}; ++i) {n(dst)}[i] = "
            f"{e.ref(src, f'dq_b * {size} + i')};"
        )
        put = lambda dst, src, size: (  # noqa: E731
            f"    for (int i = 0; i < {size}; ++i) "
            f"{e.target(dst, f'dq_b * {size} + i')} = {n(src)}[i];"
        )
        rows = f"{n(G)} + dq_b * {n_rows * cols}" if in_place else n(gs)
        decl = [f"    {e.ctype(v.dtype)} {n(v)}[{v.size}];" for v in staged]
        return [
            *(e.declare(v) for v in outs),
            f"for (int dq_b = 0; dq_b < {batch}; ++dq_b) {{",
            *decl,
            "    int dq_status, dq_iters, dq_cert;",
            f"    {e.ctype(real)} dq_cond;",
            *([] if in_place else [copy(gs, G, n_rows * cols)]),
            copy(rs, r, n_rows), copy(w0s, w0, dim),
            copy(us, use, n_rows),
            copy(ss, slack, k) if k else f"    {n(ss)}[0] = {lit(0)};  /* no slacks */",
            f"    {fn}({n_rows}, {cols}, {dim}, {rows}, {n(rs)}, {n(w0s)}, {n(us)}, "
            f"{e.ref(max_iter, 'dq_b')}, {n(ss)}, {int(eqn.params['slack_row'])}, "
            f"{lit(tols.add)}, {lit(tols.dep)}, {lit(tols.cert)}, {lit(tols.eps)}, {n(work)}, "
            f"{n(iwork)}, {n(ws)}, {n(ms)}, {n(acts)}, &dq_status, &dq_iters, &dq_cond, "
            "&dq_cert);",
            put(w, ws, dim), put(mult, ms, n_rows), put(active, acts, n_rows),
            f"    {e.target(status, 'dq_b')} = dq_status;",
            f"    {e.target(iters, 'dq_b')} = dq_iters;",
            f"    {e.target(cond, 'dq_b')} = dq_cond;",
            f"    {e.target(certified, 'dq_b')} = dq_cert;",
            "}",
        ]  # fmt: skip

    p.stmt(outs, ins, gen, scratch=staged)
    return outs


@_register("scan")
def _scan(p: Program, eqn: Any, ins: list[Val]) -> list[Val]:
    """A counted ``for`` loop: ``lax.fori_loop`` with bounds known when traced.

    JAX writes such a loop as a scan without scanned inputs or stacked outputs; the loop runs
    ``length`` passes over the carry. Any other scan is reported as unsupported.
    """
    prm = eqn.params
    nc, ncarry = prm["num_consts"], prm["num_carry"]
    if len(ins) != nc + ncarry or len(eqn.outvars) != ncarry:
        raise p.unsupported(
            "lax.scan over arrays (scanned inputs or stacked outputs) is not exported; "
            "lax.fori_loop and lax.while_loop are, and a Python for loop is unrolled"
        )
    consts, init = ins[:nc], ins[nc:]
    carried = [p.new(var.aval) for var in eqn.outvars]
    body_stmts, res = p.block(prm["jaxpr"].jaxpr, prm["jaxpr"].consts, consts + carried)

    def gen(e: Emitter) -> list[str]:
        lines = _declare_mutable(e, carried) + _assign_all(e, carried, init)
        inner = render(e, body_stmts) + _assign_all(e, carried, res)
        head = f"for (int scan_s = 0; scan_s < {int(prm['length'])}; ++scan_s) {{"
        return lines + [head] + _indent(inner) + ["}"]

    p.stmt(carried, ins, gen, blocks=[body_stmts], scratch=carried, results=res)
    return carried
