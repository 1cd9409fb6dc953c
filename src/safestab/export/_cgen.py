"""C text: types, literals, helper functions, names and references of values.

The :class:`Emitter` is handed to every statement's ``gen``: it names values (``t12``), writes
references to one element (``t12[i]``, a scalar ``t12``, a literal, or an element of a
``static const`` table), and collects the helper functions and tables that the live code uses,
so the file declares nothing unused (the code compiles with ``-Wall -Wextra -Werror``).
"""

from __future__ import annotations

import keyword
import math
import re
from typing import Any

import numpy as np

from ._dual_qp import source as dual_qp_source
from ._ir import Val

#: C99 keywords and names the generated functions use themselves.
RESERVED = frozenset(
    """auto break case char const continue default do double else enum extern float for goto if
    inline int long register restrict return short signed sizeof static struct switch typedef
    union unsigned void volatile while _Bool _Complex _Imaginary x info status count k i best
    v scratch""".split()
) | frozenset(keyword.kwlist)

_INTERNAL_NAME = re.compile(r"^(t|c|i|k|r)\d+$")


def c_identifier(text: str) -> str:
    """A valid, non-reserved C identifier made from ``text``."""
    s = re.sub(r"[^0-9A-Za-z_]", "_", text).strip("_") or "y"
    if s[0].isdigit():
        s = "y" + s
    if s in RESERVED or _INTERNAL_NAME.match(s):
        s += "_"
    return s


class Emitter:
    """Writes C for one exported function.

    Parameters
    ----------
    real : {"double", "float"}
        The C type of float64 values.
    """

    def __init__(self, real: str) -> None:
        self.real = real
        self._names: dict[int, str] = {}
        self._tables: dict[int, tuple[str, Val]] = {}
        self._splats: dict[int, Any] = {}
        self.helpers: dict[str, str] = {}
        #: headers the helpers need besides <math.h> (freestanding headers only)
        self.includes: set[str] = set()
        self._count = 0
        #: Work array and offset of run-time arrays (by root id), set by
        #: ``_assemble.plan_work`` from the values' lifetimes; others are declared alone.
        self.work: dict[int, tuple[str, int]] = {}

    # -- types and literals ----------------------------------------------------------

    def ctype(self, dtype: Any) -> str:
        """C type of a value of ``dtype`` inside the function (bool is an int 0/1)."""
        dt = np.dtype(dtype)
        if dt == np.float64:
            return self.real
        return {
            "float32": "float",
            "int32": "int",
            "int64": "long long",
            "bool": "int",
            "uint8": "unsigned char",
            "uint32": "unsigned int",
        }[dt.name]

    def io_ctype(self, dtype: Any) -> str:
        """C type of an output field (bool as ``unsigned char``, NumPy's layout)."""
        return "unsigned char" if np.dtype(dtype) == np.bool_ else self.ctype(dtype)

    def is_float(self, dtype: Any) -> bool:
        return np.dtype(dtype).kind == "f"

    def math(self, fn: str, dtype: Any) -> str:
        """Name of a <math.h> function for ``dtype`` (``expf`` for float)."""
        return fn + ("f" if self.ctype(dtype) == "float" else "")

    def zero(self, dtype: Any) -> str:
        return self.lit(0, dtype)

    def lit(self, value: Any, dtype: Any) -> str:
        """A C literal for one value of ``dtype``, parenthesised when negative."""
        dt = np.dtype(dtype)
        if dt == np.bool_:
            return "1" if bool(value) else "0"
        if dt.kind in "iu":
            v = int(value)
            if dt == np.int64:
                if v == -(2**63):
                    return "(-9223372036854775807LL - 1)"
                s = f"{v}LL"
            elif dt == np.int32 and v == -(2**31):
                return "(-2147483647 - 1)"
            else:
                s = f"{v}u" if dt.kind == "u" else str(v)
            return f"({s})" if v < 0 else s
        ctype = self.ctype(dt)
        f = float(value)
        if np.isnan(f):
            return "NAN"
        if np.isinf(f):
            return "INFINITY" if f > 0 else "(-INFINITY)"
        if ctype == "float":
            s = str(np.float32(f))
            if not any(ch in s for ch in ".e"):
                s += ".0"
            s += "f"
        else:
            s = repr(f)
            if not any(ch in s for ch in ".e"):
                s += ".0"
        return f"({s})" if s.startswith("-") else s

    # -- names and references ---------------------------------------------------------

    def name(self, v: Val) -> str:
        """The C name of a run-time value (its root, for aliases)."""
        r = v.root()
        if r.param is not None:
            return r.param
        key = id(r)
        if key not in self._names:
            self._count += 1
            self._names[key] = f"t{self._count}"
        return self._names[key]

    def splat(self, v: Val) -> Any:
        key = id(v)
        if key not in self._splats:
            self._splats[key] = v.splat()
        return self._splats[key]

    def table(self, v: Val) -> str:
        """Name of the ``static const`` table holding a constant (declared once)."""
        key = id(v)
        if key not in self._tables:
            self._tables[key] = (f"c{len(self._tables) + 1}", v)
        return self._tables[key][0]

    def ref(self, v: Val, idx: int | str) -> str:
        """Expression for element ``idx`` (row-major flat index, int or C expression) of ``v``."""
        if v.const is not None:
            s = self.splat(v)
            if s is not None:
                return self.lit(s, v.dtype)
            if isinstance(idx, int):
                return self.lit(v.const.reshape(-1)[idx], v.dtype)
            return f"{self.table(v)}[{idx}]"
        r = v.root()
        if r.param is not None:
            return f"{r.param}[{idx}]"
        if r.size == 1:
            return self.name(r)
        return f"{self.name(r)}[{idx}]"

    def target(self, v: Val, idx: int | str) -> str:
        """Assignable element ``idx`` of a run-time value."""
        return self.name(v) if v.size == 1 else f"{self.name(v)}[{idx}]"

    def declare(self, v: Val, init: str | None = None) -> str:
        """Declaration of a run-time value: ``double t5[96];`` or ``const double t5 = init;``."""
        ct = self.ctype(v.dtype)
        if v.size == 1:
            return f"const {ct} {self.name(v)} = {init};" if init else f"{ct} {self.name(v)};"
        slot = self.work.get(id(v.root()))
        if slot is not None:  # a slice of a shared work array, reused once the value is dead
            array, off = slot
            return f"{ct} *const {self.name(v)} = {array} + {off};  /* [{v.size}] */"
        return f"{ct} {self.name(v)}[{v.size}];"

    def tables(self) -> list[str]:
        """Definitions of every table referenced so far."""
        lines: list[str] = []
        for name, v in self._tables.values():
            assert v.const is not None
            flat = v.const.reshape(-1)
            items = [self.lit(x, v.dtype) for x in flat]
            lines.append(
                f"/* {v.dtype.name}{list(v.shape)} */".replace(" ", "")
                + f"\nstatic const {self.ctype(v.dtype)} {name}[{v.size}] = {{"
            )
            row: list[str] = []
            width = 4
            for item in items:
                row.append(item)
                if sum(len(s) + 2 for s in row) > 92:
                    lines.append(" " * width + ", ".join(row) + ",")
                    row = []
            if row:
                lines.append(" " * width + ", ".join(row) + ",")
            lines[-1] = lines[-1].rstrip(",")
            lines.append("};")
        return lines

    # -- helper functions ---------------------------------------------------------------

    def helper(self, kind: str, dtype: Any, dst: Any = None) -> str:
        """Name of a small static helper (registered for emission on first use)."""
        ct = self.ctype(dtype)
        suffix = {
            "double": "",
            "float": "f",
            "int": "i",
            "long long": "ll",
            "unsigned char": "u8",
            "unsigned int": "u32",
        }[ct]
        if kind == "f2i":
            dct = self.ctype(dst)
            name = f"ss_{suffix or 'd'}_to_{dct.replace(' ', '')}"
            key = name
            if key not in self.helpers:
                self.helpers[key] = _float_to_int(name, ct, dct, np.dtype(dst))
            return name
        name = f"ss_{kind}{suffix}"
        if name not in self.helpers:
            self.helpers[name] = _HELPERS[kind](name, ct, self.is_float(dtype), self)
        return name


def _max(name: str, ct: str, flt: bool, e: Emitter) -> str:
    if not flt:
        return f"static {ct} {name}({ct} a, {ct} b) {{ return a > b ? a : b; }}"
    # XLA: NaN propagates; -0 < +0
    return (
        f"static {ct} {name}({ct} a, {ct} b)\n{{\n"
        "    if (a != a) return a;\n    if (b != b) return b;\n"
        "    if (a > b) return a;\n    if (b > a) return b;\n"
        "    return signbit(a) ? b : a; /* equal: prefer +0 over -0 */\n}"
    )


def _min(name: str, ct: str, flt: bool, e: Emitter) -> str:
    if not flt:
        return f"static {ct} {name}({ct} a, {ct} b) {{ return a < b ? a : b; }}"
    return (
        f"static {ct} {name}({ct} a, {ct} b)\n{{\n"
        "    if (a != a) return a;\n    if (b != b) return b;\n"
        "    if (a < b) return a;\n    if (b < a) return b;\n"
        "    return signbit(a) ? a : b; /* equal: prefer -0 over +0 */\n}"
    )


def _sign(name: str, ct: str, flt: bool, e: Emitter) -> str:
    if not flt:
        return f"static {ct} {name}({ct} a) {{ return (a > 0) - (a < 0); }}"
    one = "1.0f" if ct == "float" else "1.0"
    # XLA: sign(NaN) = NaN, sign(+-0) = +-0
    return f"static {ct} {name}({ct} a) {{ return a > 0 ? {one} : (a < 0 ? -{one} : a); }}"


def _ipow(name: str, ct: str, flt: bool, e: Emitter) -> str:
    one = "1.0f" if ct == "float" else ("1.0" if flt else "1")
    # binary exponentiation in the order of JAX's integer_pow lowering
    return (
        f"static {ct} {name}({ct} x, int y)\n{{\n"
        f"    int recip = y < 0;\n    {ct} acc = {one};\n    int first = 1;\n"
        "    if (recip) y = -y;\n"
        "    while (y > 0) {\n"
        "        if (y & 1) { acc = first ? x : acc * x; first = 0; }\n"
        "        y >>= 1;\n        if (y > 0) x = x * x;\n    }\n"
        f"    return recip ? {one} / acc : acc;\n}}"
    )


def _exp(name: str, ct: str, flt: bool, e: Emitter) -> str:
    # exp without a library call, so that loops over arrays (the GP cache's kernel values)
    # vectorise: a = k ln2 + r with |r| <= ln2 / 2 (k rounded to nearest by adding 1.5 * 2^52,
    # or 2^23 for float), exp(r) by its Taylor polynomial (degree 13 for double, 7 for float:
    # truncation below a quarter of an ulp), 2^k as two powers of two built from their bits
    # (k split in halves so that each is a normal number; the products then round like one,
    # down to subnormal results and up to +inf). Within 1 ulp of a correctly rounded exp
    # (tests/test_export.py measures it against mpmath); NaN in, NaN out; exp(-inf) = +0.
    e.includes.add("<stdint.h>")
    single = ct == "float"
    dt = np.float32 if single else np.float64
    # mantissa bits, exponent bias and mask, unsigned type of the same width, the clamps
    # (above: the result overflows; below: it rounds to +0), the polynomial's degree and
    # ln 2 in two parts whose high part has few enough bits that kd * it is exact here
    mant, bias, mask, uint, hi, lo, deg, ln2_hi, ln2_lo = (
        (23, 127, "0xffu", "uint32_t", 89.0, -104.0, 7, 0.693145752, 1.42860677e-06)
        if single
        else (52, 1023, "0x7ffu", "uint64_t", 710.0, -746.0, 13, 0.6931471803691238,
              1.9082149292705877e-10)
    )  # fmt: skip

    def lit(v: float) -> str:
        return e.lit(v, dt)

    coeffs = [1.0 / math.factorial(i) for i in range(deg, -1, -1)]
    poly = "\n".join(f"    p = p * r + {lit(c)};" for c in coeffs[1:])
    return (
        f"static {ct} {name}({ct} a)\n{{\n"
        f"    const {ct} shift = {lit(1.5 * 2.0**mant)}; /* 1.5 * 2^{mant} */\n"
        f"    {ct} x = a > {lit(hi)} ? {lit(hi)} : a;\n"
        f"    x = x < {lit(lo)} ? {lit(lo)} : x; /* exp(a) rounds to +0 below {lo:g} */\n"
        f"    const {ct} kd = (x * {lit(1.0 / math.log(2.0))} + shift) - shift;\n"
        f"    /* ln 2 in two parts: kd * {lit(ln2_hi)} is exact for every kd here */\n"
        f"    const {ct} r = (x - kd * {lit(ln2_hi)}) - kd * {lit(ln2_lo)};\n"
        f"    {ct} p = {lit(coeffs[0])};\n{poly}\n"
        f"    const {ct} k1 = (kd * {lit(0.5)} + shift) - shift, k2 = kd - k1;\n"
        f"    union {{ {ct} v; {uint} u; }} s1, s2;\n"
        f"    s1.v = k1 + (shift + {lit(bias)});\n"
        f"    s2.v = k2 + (shift + {lit(bias)});\n"
        f"    s1.u = (s1.u & {mask}) << {mant};\n"
        f"    s2.u = (s2.u & {mask}) << {mant};\n"
        f"    return a < {lit(lo)} ? {lit(0.0)} : p * s1.v * s2.v;\n}}"
    )


def _qr(name: str, ct: str, flt: bool, e: Emitter) -> str:
    # Householder QR of the M x N matrix a (row-major, overwritten), K = min(M, N): q (M x K),
    # r (K x N). LAPACK's conventions (dgeqr2 with dlarfg, then dorg2r), so the signs of r's
    # diagonal and q's columns are those of jnp.linalg.qr: beta = -sign(alpha) |(alpha, x)|,
    # tau = (beta - alpha) / beta, v = x / (alpha - beta); a column with x = 0 is left as it is.
    # Literals of the real type throughout (GCC 12 stops with an internal error on the float
    # version inlined into a step when the norm's update mixes an int literal in).
    f = "f" if ct == "float" else ""
    one, zero = ("1.0f", "0.0f") if f else ("1.0", "0.0")
    return (
        f"static void {name}(int M, int N, {ct} *a, {ct} *tau, {ct} *q, {ct} *r)\n{{\n"
        "    const int K = M < N ? M : N;\n"
        "    for (int j = 0; j < K; ++j) {\n"
        f"        {ct} scale = {zero}, ssq = {one}, xnorm;\n"
        "        for (int i = j + 1; i < M; ++i) {\n"
        f"            const {ct} v = fabs{f}(a[i * N + j]);\n"
        f"            if (v > scale) {{ ssq = {one} + ssq * (scale / v) * (scale / v);"
        " scale = v; }\n"
        f"            else if (v > {zero}) ssq += (v / scale) * (v / scale);\n"
        "        }\n"
        f"        xnorm = scale * sqrt{f}(ssq);\n"
        f"        if (xnorm == {zero}) {{ tau[j] = {zero}; continue; }}\n"
        f"        const {ct} alpha = a[j * N + j];\n"
        f"        const {ct} beta = -copysign{f}(hypot{f}(alpha, xnorm), alpha);\n"
        "        tau[j] = (beta - alpha) / beta;\n"
        f"        const {ct} s = {one} / (alpha - beta);\n"
        "        for (int i = j + 1; i < M; ++i) a[i * N + j] *= s;\n"
        "        a[j * N + j] = beta;\n"
        "        for (int c = j + 1; c < N; ++c) {\n"
        f"            {ct} w = a[j * N + c];\n"
        "            for (int i = j + 1; i < M; ++i) w += a[i * N + j] * a[i * N + c];\n"
        "            w *= tau[j];\n"
        "            a[j * N + c] -= w;\n"
        "            for (int i = j + 1; i < M; ++i) a[i * N + c] -= w * a[i * N + j];\n"
        "        }\n"
        "    }\n"
        "    for (int i = 0; i < K; ++i)\n"
        f"        for (int c = 0; c < N; ++c) r[i * N + c] = c >= i ? a[i * N + c] : {zero};\n"
        "    for (int i = 0; i < M; ++i)\n"
        f"        for (int c = 0; c < K; ++c) q[i * K + c] = i == c ? {one} : {zero};\n"
        "    for (int j = K - 1; j >= 0; --j) {\n"
        f"        if (tau[j] == {zero}) continue;\n"
        "        for (int c = j; c < K; ++c) {\n"
        f"            {ct} w = q[j * K + c];\n"
        "            for (int i = j + 1; i < M; ++i) w += a[i * N + j] * q[i * K + c];\n"
        "            w *= tau[j];\n"
        "            q[j * K + c] -= w;\n"
        "            for (int i = j + 1; i < M; ++i) q[i * K + c] -= w * a[i * N + j];\n"
        "        }\n"
        "    }\n"
        "}"
    )


_HELPERS = {
    "max": _max, "min": _min, "sign": _sign, "ipow": _ipow, "exp": _exp, "qr": _qr,
    "dual_qp": dual_qp_source,
}  # fmt: skip


def _float_to_int(name: str, ct: str, dct: str, dst: np.dtype) -> str:
    info = np.iinfo(dst)
    lo, hi = int(info.min), int(info.max)
    suffix = "LL" if dst == np.int64 else ("u" if dst.kind == "u" else "")
    lo_lit = (
        "(-9223372036854775807LL - 1)"
        if lo == -(2**63)
        else ("(-2147483647 - 1)" if lo == -(2**31) else f"{lo}{suffix}")
    )
    hi_lit = f"{hi}{suffix}"
    # XLA: truncation toward zero, NaN -> 0, saturation at the type's range
    return (
        f"static {dct} {name}({ct} a)\n{{\n"
        "    if (a != a) return 0;\n"
        f"    if (a <= ({ct}){lo_lit}) return {lo_lit};\n"
        f"    if (a >= ({ct}){hi_lit}) return {hi_lit};\n"
        f"    return ({dct})a;\n}}"
    )
