"""The Monte Carlo GP caches against the learning package's GP and FastGP."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safestab.learning import GaussianProcessModel, collect_data
from safestab.montecarlo import (
    BatchedUncertainty,
    Hyperparameters,
    condition,
    inducing_cache,
)
from safestab.scenarios import load_scenario

SC = load_scenario("stress")


@pytest.fixture(scope="module")
def fitted():
    data = collect_data(
        SC.system("true"), SC.system("nominal"), x0=(SC.x0_low, SC.x0_high), u_low=-0.3,
        u_high=0.3, n_samples=300, rate=SC.sample_rate, horizon=SC.sample_horizon,
        noise_std=0.01, seed=1,
    )  # fmt: skip
    gp = GaussianProcessModel(kernel="se", noise=0.01).fit(data.x[:200], data.y[:200])
    post = condition(Hyperparameters.from_model(gp), data.x[:200], data.y[:200])
    x = np.random.default_rng(0).uniform(SC.x0_low, SC.x0_high, (64, 3))
    return gp, post, data.x[200:], x


def test_conditioning_matches_the_model(fitted):
    gp, post, _, x = fitted
    mean, var = (np.asarray(a) for a in gp.predict(x))
    m, s = (np.asarray(a) for a in post.mean_std_batch(jnp.asarray(x)))
    # both solve the same SPD system; with noise 0.01 its condition number is modest (< 1e8),
    # so the two factorisations agree to about cond * eps relative to the target scale
    np.testing.assert_allclose(m, mean, atol=1e-7 * np.abs(mean).max())
    np.testing.assert_allclose(s**2, var, atol=1e-8 * gp.amplitude_.max() ** 2)


def test_inducing_cache_widened_band_contains_the_exact_band_where_calibrated(fitted):
    """The Monte Carlo cache (inducing points, measured widening, as FastGP was before issue 14)
    against the exact posterior: its mean is close, and on the states it was calibrated on its
    widened band contains the exact band (what the measured widening promises, no more)."""
    gp, post, x_check, x = fitted
    cache = inducing_cache(post, 16, x_check=x_check, beta=2.0)
    assert int(cache.mask.sum()) >= 16  # every component has its inducing points
    mc, sc = (np.asarray(a) for a in cache.mean_std_batch(jnp.asarray(x_check)))
    me, se = (np.asarray(a) for a in post.mean_std_batch(jnp.asarray(x_check)))
    comps = list(gp.components_)
    lo_c, hi_c = mc - 2.0 * sc, mc + 2.0 * sc
    lo_e, hi_e = me - 2.0 * se, me + 2.0 * se
    # containment to rounding (1e-9 of the amplitude) on the calibration states
    tol = 1e-9 * gp.amplitude_.max()
    assert np.all(lo_c[:, comps] <= lo_e[:, comps] + tol)
    assert np.all(hi_c[:, comps] >= hi_e[:, comps] - tol)
    # 16 of 200 points carry the posterior mean to a small fraction of its range
    span = np.abs(me[:, comps]).max()
    assert np.abs(mc[:, comps] - me[:, comps]).max() <= 0.05 * span


def test_batched_uncertainty_rule_equals_the_batch(fitted):
    _, post, x_check, x = fitted
    cache = inducing_cache(post, 16, x_check=x_check)
    model = BatchedUncertainty(cache)
    m_rule, s_rule = jax.jit(jax.vmap(model.mean_std))(jnp.asarray(x))
    m_batch, s_batch = jax.jit(cache.mean_std_batch)(jnp.asarray(x))
    np.testing.assert_array_equal(np.asarray(m_rule), np.asarray(m_batch))
    np.testing.assert_array_equal(np.asarray(s_rule), np.asarray(s_batch))
    m1, s1 = model.mean_std(jnp.asarray(x[5]))  # one state, no vmap
    # a separate compilation may fuse differently: rounding only
    np.testing.assert_allclose(np.asarray(m1), np.asarray(m_batch)[5], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(s1), np.asarray(s_batch)[5], rtol=1e-9, atol=1e-15)
