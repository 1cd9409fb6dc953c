"""Uncertainty models as data: their arrays are pytree leaves, the closed loop's arguments.

A fitted GP, FastGP cache or batched cache is a pytree whose leaves are its arrays, so
:func:`~safestab.simulate` compiles its loop with those arrays as arguments (not constants
of the size of the data), and the exact GP's one-state solve runs on row panels of its
factor (``_posterior.solve_panels``), checked here against extended-precision substitution.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab._values import register_model
from safestab.learning import FastGP, GaussianProcessModel
from safestab.learning._posterior import panels, solve_panels
from safestab.learning.batched import BatchedUncertainty, ExactPosterior
from safestab.simulation import simulate


def _ill_conditioned_factor(q, seed=0):
    # the factor of an SE kernel matrix with a small nugget: cond(K) about 1e9
    x = np.sort(np.random.default_rng(seed).uniform(0, 10, q))
    k = np.exp(-0.5 * (x[:, None] - x[None, :]) ** 2) + 1e-9 * np.eye(q)
    return np.linalg.cholesky(k)


@pytest.mark.parametrize("rows", [7, 16, 128])
@pytest.mark.parametrize("n_rhs", [None, 3])
def test_solve_panels_is_backward_stable(rows, n_rhs):
    # backward stability, the property of forward substitution (Higham, Thm 8.5):
    # |L v - b| <= c Q u |L| |v| componentwise, the residual computed in extended precision
    q = 61
    chol = _ill_conditioned_factor(q)
    shape = (q,) if n_rhs is None else (q, n_rhs)
    b = np.random.default_rng(1).standard_normal(shape)
    pan = panels(chol[None], rows)[0]
    assert len(pan) == -(-q // rows)
    v = np.asarray(jax.jit(solve_panels)(pan, jnp.asarray(b)))
    lh, vh = chol.astype(np.longdouble), v.astype(np.longdouble)
    resid = np.abs(lh @ vh - b.astype(np.longdouble))
    bound = q * np.finfo(float).eps * (np.abs(lh) @ np.abs(vh))
    assert np.all(resid <= bound)
    # and it is a solve: the solution to within cond(L) u of the dense one
    want = np.linalg.solve(chol, b)
    cond = np.linalg.cond(chol)
    assert np.max(np.abs(v - want)) <= 10 * cond * np.finfo(float).eps * np.max(np.abs(want))


@pytest.fixture(scope="module")
def gp_pair():
    rng = np.random.default_rng(0)
    models = []
    for _ in range(2):
        x = rng.uniform(-2, 2, size=(300, 2))  # 300 rows: three panels and a partial one
        y = np.stack([np.sin(x[:, 0]), np.zeros(300)], 1) + 0.01 * rng.normal(size=(300, 2))
        models.append(GaussianProcessModel(max_iter=30, n_restarts=0).fit(x, y, components=[0]))
    return models


def _rounding_scales(gp):
    # of the two formulas: the mean sums k_i alpha_i (each at most amp^2 |alpha_i|: the
    # sum cancels where alpha is large), the variance subtracts |v|^2 <= amp^2 from amp^2
    amp2 = float(gp.amplitude_[0]) ** 2
    q = len(gp.x_train_)
    mean_scale = q * np.finfo(float).eps * amp2 * float(np.sum(np.abs(gp.alpha_[0])))
    return mean_scale, q * np.finfo(float).eps * amp2


def test_exact_point_on_panels_equals_the_whole_factor_solve(gp_pair):
    gp = gp_pair[0]
    xq = np.random.default_rng(2).uniform(-2.5, 2.5, size=(20, 2))
    mean_b, std_b = gp.predict(xq, return_std=True)  # solves with the whole factor
    var_b = std_b**2
    mean_scale, var_scale = _rounding_scales(gp)
    for x, m_b, v_b in zip(xq, np.asarray(mean_b), np.asarray(var_b), strict=True):
        mean, std = gp.mean_std(jnp.asarray(x))
        assert abs(float(mean[0]) - m_b[0]) <= mean_scale
        assert abs(float(std[0]) ** 2 - v_b[0]) <= var_scale
        assert float(mean[1]) == float(std[1]) == 0.0  # a component not learned


def test_a_fitted_gp_is_a_pytree_of_its_arrays(gp_pair):
    a, b = gp_pair
    leaves = jax.tree_util.tree_leaves(a)
    assert any(leaf is a.posterior_["chol"] for leaf in leaves)
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    assert jax.tree_util.tree_leaves(GaussianProcessModel()) == []  # unfitted: no arrays
    traces = []

    @jax.jit
    def at(model, x):
        traces.append(1)
        return model.mean_std(x)

    x = jnp.array([0.3, -0.7])
    for model in (a, b):
        (m_got, s_got), (m_want, s_want) = at(model, x), model.mean_std(x)
        mean_scale, var_scale = _rounding_scales(model)
        assert abs(float(m_got[0] - m_want[0])) <= mean_scale
        assert abs(float(s_got[0]) ** 2 - float(s_want[0]) ** 2) <= var_scale
    assert len(traces) == 1  # one program for both models: their arrays are arguments
    assert not np.allclose(at(a, x)[0], at(b, x)[0])


def test_refit_replaces_the_panels():
    rng = np.random.default_rng(3)
    x1, x2 = rng.uniform(-2, 2, size=(2, 50, 1))
    y1, y2 = np.sin(x1) + 0.01 * rng.normal(size=(50, 1)), np.cos(x2)
    gp = GaussianProcessModel(noise=0.01, max_iter=30, n_restarts=0).fit(x1, y1)
    gp.mean_std(jnp.zeros(1))  # makes the panels of the first factor
    gp.fit(x2, y2)
    fresh = GaussianProcessModel(noise=0.01, max_iter=30, n_restarts=0).fit(x2, y2)
    for got, want in zip(gp.mean_std(jnp.zeros(1)), fresh.mean_std(jnp.zeros(1)), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12)


def test_caches_are_pytrees_of_their_arrays(gp_pair):
    gp = gp_pair[0]
    fast = FastGP(gp, n_inducing=16, warn=False)
    batched = BatchedUncertainty(ExactPosterior.from_model(gp))
    x = jnp.array([0.1, 0.2])
    mean_scale, var_scale = _rounding_scales(gp)
    for model in (fast, fast.unpadded(), batched):
        assert jax.tree_util.tree_leaves(model)
        (m_got, s_got), (m_want, s_want) = (
            jax.jit(lambda m, x: m.mean_std(x))(model, x),
            model.mean_std(x),
        )
        assert abs(float(m_got[0] - m_want[0])) <= mean_scale
        # a std's rounding: that of its variance (at most var_scale), through the square root
        assert abs(float(s_got[0] - s_want[0])) <= np.sqrt(var_scale)
        assert float(m_got[1]) == float(s_got[1]) == 0.0


class _LinearModel:
    """A model ``omega(x) = w x`` whose ``w`` is its one array; records what it was given."""

    n_states = 1
    seen: list = []

    def __init__(self, w):
        self.w = jnp.asarray(w)

    def mean_std(self, x):
        _LinearModel.seen.append(isinstance(self.w, jax.core.Tracer))
        return self.w @ x, 0.1 * jnp.ones(1)


register_model(_LinearModel, lambda m: {"w": m.w}, lambda m: (_LinearModel,))


def _integrator(uncertainty):
    system = ss.ControlAffineSystem(lambda x: jnp.zeros(1), lambda x: jnp.ones((1, 1)), 1)
    clf = ss.CLF(lambda x: x[0] ** 2, lam=1.0)
    cbf = ss.CBF(lambda x: 2.0 - x[0], beta=1.0)
    return ss.UniversalController(
        system, clf, cbf, kappa=1.0, rho=0.1, phi=1.0, varphi=1.0, uncertainty=uncertainty
    )


def test_simulate_passes_the_models_arrays_as_arguments():
    # the step is one jitted function for every controller of a structure: forget the
    # programs an earlier test traced, so this run traces its own
    jax.clear_caches()
    _LinearModel.seen.clear()
    ctrl = _integrator(_LinearModel(jnp.array([[0.5]])))
    traj = simulate(ctrl, np.array([1.5]), t_final=0.5, dt=0.01)
    # traced inside the loop: the array is an argument of the compiled loop, not a constant
    assert any(_LinearModel.seen)
    # the loop's inputs are the controller's at the recorded states
    for k in (0, 17, 50):
        np.testing.assert_allclose(traj.u[k], ctrl(traj.x[k]), rtol=1e-12, atol=1e-15)
    # a model that is not a pytree is used as the controller holds it
    plain = type("Plain", (), {"n_states": 1, "mean_std": _LinearModel.mean_std})()
    plain.w = jnp.array([[0.5]])
    other = simulate(_integrator(plain), np.array([1.5]), t_final=0.5, dt=0.01)
    np.testing.assert_allclose(other.x, traj.x, rtol=1e-14)


def test_in_threads_keeps_the_order_of_its_items_and_raises_their_errors():
    import threading
    import time

    from safestab._batching import in_threads

    names, counts = set(), []

    def work(k):
        names.add(threading.current_thread().name)
        time.sleep(0.02 * (5 - k))  # the first items finish last
        return k * k

    assert in_threads(work, range(5), 2, counts.append) == [0, 1, 4, 9, 16]
    assert counts == [1, 2, 3, 4, 5] and len(names) == 2  # two worker threads

    def fail(k):
        if k == 3:
            raise ValueError("item 3")
        return k

    with pytest.raises(ValueError, match="item 3"):
        in_threads(fail, range(5), 2, lambda count: None)
    assert in_threads(work, [4], 2, counts.append) == [16]  # one item: no threads

    started = []

    def first_fails(k):
        started.append(k)
        if k == 0:
            raise ValueError("item 0")
        time.sleep(0.2)
        return k

    with pytest.raises(ValueError, match="item 0"):
        in_threads(first_fails, range(20), 2, lambda count: None)
    assert len(started) <= 4  # the items not started when it failed are dropped
