"""The export's NumPy folding of known values gives XLA's bits (what JAX would fold)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from safestab.export._primitives import fold_exact

_SPECIAL = np.array([0.0, -0.0, 1.0, -1.5, 1e-30, -1e308, 3.4e38, np.inf, -np.inf, np.nan])


def _values(dtype, n=64, seed=0):
    """Normal numbers, zeros of both signs, overflow to inf, inf and NaN (no subnormals)."""
    rng = np.random.default_rng(seed)
    top = 15 if dtype == np.float32 else 150
    x = rng.normal(size=n) * 10.0 ** rng.integers(-top, top, n)
    with np.errstate(over="ignore"):
        x = np.concatenate([x, _SPECIAL]).astype(dtype)
    return x


def _same_bits(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype and a.shape == b.shape
    if a.dtype.kind == "f":  # NaN payloads aside, every bit
        nan = np.isnan(a)
        assert np.array_equal(nan, np.isnan(b))
        a, b = a[~nan], b[~nan]
        return np.array_equal(a.view(f"u{a.dtype.itemsize}"), b.view(f"u{b.dtype.itemsize}"))
    return np.array_equal(a, b)


def _xla(prim, *args, **params):
    # one equation of the primitive, run by XLA on device arrays
    return jax.jit(lambda *xs: prim.bind(*xs, **params))(*[jnp.asarray(a) for a in args])


BINARY = {"add": lax.add_p, "sub": lax.sub_p, "mul": lax.mul_p, "div": lax.div_p,
          "eq": lax.eq_p, "ne": lax.ne_p, "lt": lax.lt_p, "le": lax.le_p, "gt": lax.gt_p,
          "ge": lax.ge_p}  # fmt: skip
UNARY = {"neg": lax.neg_p, "abs": lax.abs_p, "sqrt": lax.sqrt_p, "square": lax.square_p,
         "is_finite": lax.is_finite_p}  # fmt: skip


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_elementwise_folds_give_xlas_bits(dtype):
    x, y = _values(dtype, seed=1), _values(dtype, seed=2)[::-1].copy()
    for name, prim in BINARY.items():
        got = fold_exact(name, [x, y], {})
        assert got is not None, name
        assert _same_bits(got[0], _xla(prim, x, y)), name
    for name, prim in UNARY.items():
        got = fold_exact(name, [x], {})
        assert got is not None, name
        assert _same_bits(got[0], _xla(prim, x)), name


def test_select_logic_and_conversions_give_xlas_bits():
    x, y = _values(np.float64, seed=3), _values(np.float64, seed=4)
    x32 = _values(np.float32, seed=3)
    which = x > y
    got = fold_exact("select_n", [which, x, y], {})[0]
    assert _same_bits(got, _xla(lax.select_n_p, which, x, y))
    b = np.array([True, False, True, False])
    c = np.array([True, True, False, False])
    for name, prim in {"and": lax.and_p, "or": lax.or_p, "xor": lax.xor_p}.items():
        assert _same_bits(fold_exact(name, [b, c], {})[0], _xla(prim, b, c)), name
    assert _same_bits(fold_exact("not", [b], {})[0], _xla(lax.not_p, b))
    i = np.array([-(2**31), -7, 0, 5, 2**31 - 1], dtype=np.int32)
    # float64 values that float32 rounds (and overflows to inf), none below float32's tiny
    with np.errstate(over="ignore", invalid="ignore"):
        x64 = _values(np.float32, seed=5).astype(np.float64) * (1 + 2.0**-30)
    for src, new in ((x64, np.float32), (x32, np.float64), (b, np.float64),
                     (b, np.int32), (i, np.float64)):  # fmt: skip
        params = {"new_dtype": np.dtype(new), "weak_type": False, "sharding": None}
        got = fold_exact("convert_element_type", [src], params)[0]
        assert _same_bits(got, _xla(lax.convert_element_type_p, src, **params)), (src.dtype, new)


def test_what_ieee_does_not_fix_is_left_to_xla():
    x = _values(np.float64)
    params = {"new_dtype": np.dtype(np.int32), "weak_type": False, "sharding": None}
    assert fold_exact("convert_element_type", [x], params) is None  # truncation, range, NaN
    assert fold_exact("max", [x, x], {}) is None  # the sign of a zero
    assert fold_exact("exp", [x], {}) is None
    assert fold_exact("div", [np.arange(3), np.arange(1, 4)], {}) is None  # integer division
    assert fold_exact("reduce_sum", [x], {"axes": (0,)}) is None


def test_subnormals_are_left_to_xla_which_flushes_them():
    tiny = np.finfo(np.float64).tiny
    x = np.array([1.0, 1e-310])  # a subnormal input
    assert fold_exact("add", [x, x], {}) is None
    y = np.array([tiny, 2.0 * tiny])
    assert fold_exact("mul", [y, np.array([0.25, 1.0])], {}) is None  # a subnormal result
    # why: XLA's CPU code flushes it, IEEE does not
    assert float(_xla(lax.mul_p, y, np.array([0.25, 1.0]))[0]) == 0.0 != y[0] * 0.25
    np.testing.assert_array_equal(fold_exact("mul", [y, np.array([4.0, 1.0])], {})[0],
                                  [4 * tiny, 2 * tiny])  # fmt: skip
