"""Hypothesis strategies for Lie terms, with degenerate and badly scaled cases."""

import numpy as np
from hypothesis import strategies as st

KINDS = ["general", "parallel", "antiparallel", "b_zero", "d_zero", "both_zero"]


def _unit(draw, m):
    # XLA on CPU flushes subnormal numbers to zero, so they are left out (docs/theory.md).
    v = np.array(draw(st.lists(st.floats(-1, 1, allow_subnormal=False), min_size=m, max_size=m)))
    n = np.linalg.norm(v)
    if n < 1e-3:
        v = np.zeros(m)
        v[0] = 1.0
        n = 1.0
    return v / n


def _signed_scalar(draw, lo=-4.0, hi=4.0):
    if draw(st.integers(0, 9)) == 0:
        return 0.0
    sign = draw(st.sampled_from([-1.0, 1.0]))
    return sign * 10.0 ** draw(st.floats(lo, hi))


@st.composite
def lie_cases(draw, max_m=4):
    """(a, b, c, d, params) with m in 1..max_m and |b|, |d| from 1e-6 to 1e6."""
    m = draw(st.integers(1, max_m))
    kind = draw(st.sampled_from(KINDS))
    b = _unit(draw, m) * 10.0 ** draw(st.floats(-6, 6))
    d = _unit(draw, m) * 10.0 ** draw(st.floats(-6, 6))
    if kind == "parallel":
        d = b * 10.0 ** draw(st.floats(-3, 3))
    elif kind == "antiparallel":
        d = -b * 10.0 ** draw(st.floats(-3, 3))
    if kind in ("b_zero", "both_zero"):
        b = np.zeros(m)
    if kind in ("d_zero", "both_zero"):
        d = np.zeros(m)
    a = _signed_scalar(draw)
    c = _signed_scalar(draw)
    params = {
        "kappa": draw(st.sampled_from([0.0, 0.2, 1.0, 2.0])),
        "rho": draw(st.sampled_from([0.0, 0.1, 1.0])),
        "phi": draw(st.sampled_from([0.0, 1e-3, 1.0, 10.0])),
        "varphi": draw(st.sampled_from([0.0, 1e-3, 1.0, 10.0])),
    }
    return a, b, c, d, params
