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
    if ct == "float":
        coeffs = [1.0 / math.factorial(i) for i in range(7, -1, -1)]
        lit = [_float_lit(c) for c in coeffs]
        poly = "\n".join(f"    p = p * r + {c};" for c in lit[1:])
        return (
            f"static float {name}(float a)\n{{\n"
            "    const float shift = 12582912.0f; /* 1.5 * 2^23 */\n"
            "    float x = a > 89.0f ? 89.0f : a;\n"
            "    x = x < -104.0f ? -104.0f : x; /* exp(a) rounds to +0 below -104 */\n"
            "    const float kd = (x * 1.44269502f + shift) - shift;\n"
            "    const float r = (x - kd * 0.693145752f) - kd * 1.42860677e-06f;\n"
            f"    float p = {lit[0]};\n{poly}\n"
            "    const float k1 = (kd * 0.5f + shift) - shift, k2 = kd - k1;\n"
            "    union { float f; uint32_t u; } s1, s2;\n"
            "    s1.f = k1 + (shift + 127.0f);\n"
            "    s2.f = k2 + (shift + 127.0f);\n"
            "    s1.u = (s1.u & 0xffu) << 23;\n"
            "    s2.u = (s2.u & 0xffu) << 23;\n"
            "    return a < -104.0f ? 0.0f : p * s1.f * s2.f;\n}"
        )
    coeffs = [1.0 / math.factorial(i) for i in range(13, -1, -1)]
    poly = "\n".join(f"    p = p * r + {c!r};" for c in coeffs[1:])
    return (
        f"static double {name}(double a)\n{{\n"
        "    const double shift = 6755399441055744.0; /* 1.5 * 2^52 */\n"
        "    double x = a > 710.0 ? 710.0 : a;\n"
        "    x = x < -746.0 ? -746.0 : x; /* exp(a) rounds to +0 below -746 */\n"
        "    const double kd = (x * 1.4426950408889634 + shift) - shift;\n"
        "    /* ln 2 in two parts: kd * 0.6931471803691238 is exact for |kd| < 2^21 */\n"
        "    const double r = (x - kd * 0.6931471803691238) - kd * 1.9082149292705877e-10;\n"
        f"    double p = {coeffs[0]!r};\n{poly}\n"
        "    const double k1 = (kd * 0.5 + shift) - shift, k2 = kd - k1;\n"
        "    union { double d; uint64_t u; } s1, s2;\n"
        "    s1.d = k1 + (shift + 1023.0);\n"
        "    s2.d = k2 + (shift + 1023.0);\n"
        "    s1.u = (s1.u & 0x7ffu) << 52;\n"
        "    s2.u = (s2.u & 0x7ffu) << 52;\n"
        "    return a < -746.0 ? 0.0 : p * s1.d * s2.d;\n}"
    )


def _float_lit(c: float) -> str:
    s = repr(float(np.float32(c)))
    return (s if any(ch in s for ch in ".e") else s + ".0") + "f"


_HELPERS = {"max": _max, "min": _min, "sign": _sign, "ipow": _ipow, "exp": _exp}


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
