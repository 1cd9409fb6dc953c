"""Autodiff Lie terms against central finite differences, and hand-written gradients."""

import jax.numpy as jnp
import numpy as np
import pytest

from safestab import CBF, CLF, lie_terms

from .systems_zoo import pendulum_two_inputs, unicycle_obstacle


def _fd_grad(fn, x, eps=1e-6):
    x = np.asarray(x, float)
    out = np.zeros_like(x)
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = eps
        out[i] = (float(fn(jnp.asarray(x + e))) - float(fn(jnp.asarray(x - e)))) / (2 * eps)
    return out


@pytest.mark.parametrize("make", [pendulum_two_inputs, unicycle_obstacle])
def test_lie_terms_match_finite_differences(make):
    system, clf, cbf = make()
    rng = np.random.default_rng(3)
    xs = rng.normal(size=(6, system.n_states))
    terms = lie_terms(system, clf, cbf, xs)
    assert terms.a.shape == (6,) and terms.b.shape == (6, system.n_inputs)
    for i, x in enumerate(xs):
        f = np.asarray(system.f(jnp.asarray(x)))
        g = np.asarray(system.g(jnp.asarray(x)))
        gV = _fd_grad(clf.V, x)
        gh = _fd_grad(cbf.h, x)
        a = gV @ f + clf.lam * float(clf.V(jnp.asarray(x)))
        c = gh @ f + cbf.beta * float(cbf.h(jnp.asarray(x)))
        # Central differences with eps = 1e-6 err by O(eps^2 |f'''|) + O(1e-16/eps) ~ 1e-9.
        np.testing.assert_allclose(terms.a[i], a, rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(terms.b[i], gV @ g, rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(terms.c[i], c, rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(terms.d[i], gh @ g, rtol=1e-7, atol=1e-8)


def test_hand_gradient_used_and_equal():
    system, clf, cbf = pendulum_two_inputs()
    hand = CLF(clf.V, lam=clf.lam, grad=lambda x: jnp.array([x[0] + 0.2 * x[1], x[1] + 0.2 * x[0]]))
    assert hand.hand_gradient and not clf.hand_gradient
    xs = np.random.default_rng(0).normal(size=(5, 2))
    np.testing.assert_allclose(
        lie_terms(system, hand, cbf, xs).b, lie_terms(system, clf, cbf, xs).b, rtol=1e-14
    )


def test_batch_shapes_preserved():
    system, clf, cbf = unicycle_obstacle()
    x = np.zeros((4, 5, 3)) + 0.1
    t = lie_terms(system, clf, cbf, x)
    assert t.a.shape == (4, 5) and t.d.shape == (4, 5, 2)
    np.testing.assert_allclose(t.b[2, 3], lie_terms(system, clf, cbf, x[2, 3]).b, rtol=1e-15)


def test_scalar_and_barrier_names():
    cbf = CBF(lambda x: x[0], beta=0.5)
    assert cbf.beta == 0.5 and cbf.h is cbf.fn
