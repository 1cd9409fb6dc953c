"""The smooth one-barrier filters (formulas/smooth.py) against 30-digit references.

The reference writes each law out in mpmath from its definition (Cohen, Ong, Bahati and
Ames, 2023): u = u_nom + lambda(c', |d|^2) d with c' = c + d.u_nom - |d|^2 / epsilon.
"""

import math

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest

import safestab as ss
from safestab.formulas import (
    ExplicitFilter,
    HalfSontagFilter,
    Problem,
    SoftplusFilter,
    SontagFilter,
)

mpmath.mp.dps = 30
LAWS = [
    ExplicitFilter(),
    SontagFilter(0.1),
    HalfSontagFilter(0.5),
    SoftplusFilter(0.05),
    SontagFilter(0.2, epsilon=3.0),
    SoftplusFilter(0.1, epsilon=0.5),
]


def _reference_lambda(law, a, bb):
    a, bb = mpmath.mpf(a), mpmath.mpf(bb)
    if bb == 0:
        return mpmath.mpf(0)
    if isinstance(law, SoftplusFilter):
        return law.sigma * mpmath.log(1 + mpmath.exp(-a / (law.sigma * bb)))
    if isinstance(law, SontagFilter):  # HalfSontagFilter is one
        lam = (-a + mpmath.sqrt(a * a + law.sigma * bb * bb)) / bb
        return lam / 2 if isinstance(law, HalfSontagFilter) else lam
    return max(-a, mpmath.mpf(0)) / bb


def _draw(n, m, seed):
    rng = np.random.default_rng(seed)
    c = rng.standard_normal(n) * 10.0 ** rng.uniform(-3, 3, n)
    d = rng.standard_normal((n, m)) * 10.0 ** rng.uniform(-2, 2, (n, 1))
    u_nom = rng.standard_normal((n, m))
    d[:50] = 0.0  # d = 0: the law is u_nom
    c[50:100] = -np.sum(d[50:100] * u_nom[50:100], -1)  # c' = 0 (epsilon = inf)
    return c, d, u_nom


def _solve(law, c, d, u_nom):
    problem = Problem(
        jnp.zeros(c.shape + (0,)), jnp.zeros(c.shape + (0, d.shape[-1])),
        c[..., None], d[..., None, :], 0.0, 0.0, 0.0, 0.0, u_nom=u_nom,
    )  # fmt: skip
    return law.solve(problem)


@pytest.mark.parametrize("law", LAWS, ids=repr)
def test_each_law_against_its_30_digit_definition(law):
    n, m = 10_000, 2
    c, d, u_nom = _draw(n, m, seed=7)
    u = np.asarray(_solve(law, c, d, u_nom).u)
    assert np.all(np.isfinite(u))
    ref = np.empty_like(u)
    scale = np.empty(n)
    for i in range(n):
        dm = [mpmath.mpf(v) for v in d[i]]
        bb = sum(v * v for v in dm)
        a = mpmath.mpf(c[i]) + sum(mpmath.mpf(u_nom[i, j]) * dm[j] for j in range(m))
        if not math.isinf(law.epsilon):
            a -= bb / law.epsilon
        lam = _reference_lambda(law, a, bb)
        ref[i] = [float(mpmath.mpf(u_nom[i, j]) + lam * dm[j]) for j in range(m)]
        scale[i] = float(max(abs(u_nom[i]).max(), abs(lam) * max(abs(v) for v in dm)))
    # u = u_nom + lambda d: rounding of the sum, relative to its larger term (1e-12 leaves
    # room for the rounding of c' itself, c + d.u_nom, which the law amplifies by at most
    # the ratio of the terms' sizes within the drawn range)
    err = np.max(np.abs(u - ref), -1)
    assert np.all(err <= 1e-12 * np.maximum(scale, 1e-300)), np.max(err / scale)
    np.testing.assert_array_equal(u[:50], u_nom[:50])  # d = 0
    # and every law meets the condition c + d.u >= |d|^2 / epsilon (>= 0) where d != 0
    margin = (c + np.sum(d * u, -1) - np.sum(d * d, -1) / law.epsilon)[50:]
    # the rounding's scale: every term the law sums, the nominal input's d.u_nom among them
    size = np.abs(c) + np.sum(np.abs(d * u) + np.abs(d * u_nom), -1)
    size = (size + np.sum(d * d, -1) / law.epsilon)[50:]
    assert np.all(margin >= -1e-13 * size)


@pytest.mark.parametrize("law", LAWS, ids=repr)
def test_derivatives_are_exact_and_finite_where_d_or_c_prime_is_zero(law):
    c, d, u_nom = _draw(100, 2, seed=3)

    def u0(cv, dv, un):
        return _solve(law, cv[None], dv[None], un[None]).u[0, 0]

    grad = jax.jit(jax.grad(u0, argnums=(0, 1, 2)))
    for i in (0, 60, 99):  # d = 0, c' = 0, a generic point
        g = [np.asarray(v) for v in grad(c[i], d[i], u_nom[i])]
        assert all(np.all(np.isfinite(v)) for v in g)
        if i == 99 and not isinstance(law, ExplicitFilter):  # smooth: central differences
            h = 1e-6 * max(1.0, abs(c[i]))
            fd = float(u0(c[i] + h, d[i], u_nom[i])) - float(u0(c[i] - h, d[i], u_nom[i]))
            fd /= 2 * h
            # central differences: truncation of order h^2 times the third derivative, which
            # the smooth laws' curvature 1 / (sigma |d|^2) makes large, plus rounding eps / h
            assert abs(float(g[0]) - fd) <= 1e-4 * max(1.0, abs(fd))


def test_the_filter_takes_a_law_and_the_explicit_one_is_the_qp():
    plane = ss.ControlAffineSystem(lambda x: jnp.array([x[1], -x[0]]), lambda x: jnp.eye(2), 2)
    disc = ss.CBF(lambda x: 1.0 - x @ x, beta=2.0)
    kw = dict(u_nom=lambda x: jnp.array([1.0, 0.5]))
    x = np.random.default_rng(0).uniform(-1.2, 1.2, size=(400, 2))
    qp = ss.SafetyFilter(plane, disc, **kw).step(x)
    explicit = ss.SafetyFilter(plane, disc, formula=ExplicitFilter(), **kw).step(x)
    np.testing.assert_allclose(np.asarray(explicit.u), np.asarray(qp.u), rtol=0, atol=1e-13)
    smooth = ss.SafetyFilter(plane, disc, formula=SoftplusFilter(0.05), **kw)
    assert np.all(np.asarray(smooth.step(x).status) == ss.StepStatus.OK)
    native = ss.NativeController(smooth)
    np.testing.assert_allclose(native.step(x).u, np.asarray(smooth.step(x).u), rtol=0, atol=1e-13)
    with pytest.raises(ss.ParameterError, match=r"takes no a CLF, u_min/u_max"):
        ss.SafetyFilter(plane, disc, clfs=ss.CLF(lambda x: x @ x, lam=1.0), u_min=-1.0,
                        u_max=1.0, formula=SontagFilter(0.1), **kw)  # fmt: skip
    with pytest.raises(ss.ParameterError, match="rho > 0"):
        ss.SafetyFilter(plane, disc, rho=0.1, formula=SontagFilter(0.1), **kw)
    with pytest.raises(ss.ParameterError, match="sigma must be a finite number > 0, got -1"):
        SontagFilter(-1)
    with pytest.raises(ss.ParameterError, match="epsilon must be a number > 0"):
        SoftplusFilter(0.1, epsilon=0.0)


def test_eq_6_is_the_sontag_filter_without_a_nominal_input():
    """docs/theory.md's relation: eq. (6) with rho = 1 and varphi = sigma is SontagFilter."""
    plane = ss.ControlAffineSystem(lambda x: jnp.array([x[1], -x[0]]), lambda x: jnp.eye(2), 2)
    disc = ss.CBF(lambda x: 1.0 - x @ x, beta=2.0)
    x = np.random.default_rng(1).uniform(-1.2, 1.2, size=(300, 2))
    eq6 = ss.UniversalController(plane, None, disc, formula="cbf", kappa=0.0, rho=1.0, phi=0.0,
                                 varphi=0.3)  # fmt: skip
    sontag = ss.SafetyFilter(plane, disc, formula=SontagFilter(0.3))
    np.testing.assert_allclose(
        np.asarray(sontag.step(x).u), np.asarray(eq6.step(x).u), rtol=1e-12, atol=1e-14
    )
