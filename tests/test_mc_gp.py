"""The Monte Carlo GP caches against the learning package's GP, FastGP and dense algebra."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safestab.errors import DimensionError, NonFiniteError, ParameterError
from safestab.learning import (
    BatchedUncertainty,
    Dataset,
    ExactPosterior,
    FastGP,
    GaussianProcessModel,
    Hyperparameters,
    condition,
    inducing_cache,
)
from safestab.scenarios import load_scenario

SC = load_scenario("stress")


@pytest.fixture(scope="module")
def fitted():
    """A GP with given hyperparameters on 300 states of the stress preset's data box (no
    optimisation: seconds instead of a minute of fitting); targets the true omega plus noise."""
    rng = np.random.default_rng(1)
    xd = rng.uniform(SC.x0_low, SC.x0_high, (300, 3))
    yd = np.asarray(SC.omega(xd)) + 0.01 * rng.standard_normal((300, 3))
    data = Dataset(x=xd, u=np.zeros((300, 1)), xdot=yd, y=yd, t=np.zeros(300))
    gp = GaussianProcessModel.from_hyperparameters(
        xd[:200], yd[:200], amplitude=np.array([0.7, 0.05, 0.05]), noise=np.full(3, 0.01),
        lengthscale=np.tile([25.0, 25.0, 250.0], (3, 1)),
    )  # fmt: skip
    x_in = rng.uniform(SC.x0_low, SC.x0_high, (64, 3))
    # far outside the data box (speeds 10-30 m/s, gaps 20-200 m): many lengthscales away
    x_far = rng.uniform(np.array(SC.x0_low) - 60.0, np.array(SC.x0_high) + 300.0, (64, 3))
    return gp, data, np.concatenate([x_in, x_far])


def _dense_posterior(x_train, y, amp, noise, ls, mu, x):
    """Mean and std by dense NumPy algebra in the units of x (no standardisation, no factor
    reuse): an independent reference."""

    def k(a, b):
        return amp**2 * np.exp(-0.5 * np.sum(((a[:, None] - b[None]) / ls) ** 2, -1))

    kxx = k(x_train, x_train) + noise**2 * np.eye(len(x_train))
    ks = k(x, x_train)
    mean = ks @ np.linalg.solve(kxx, y - mu) + mu
    var = amp**2 - np.sum(ks * np.linalg.solve(kxx, ks.T).T, 1)
    return mean, np.sqrt(np.maximum(var, 0.0))


def test_conditioning_with_reused_hyperparameters_matches_dense_algebra(fitted):
    gp, data, x = fitted
    hyper = Hyperparameters.from_model(gp)
    model = condition(hyper, data.x[100:300], data.y[100:300])  # another data set
    mean, std = model.predict(x, return_std=True)
    var = std**2
    exact = ExactPosterior.from_model(model)
    m_b, s_b = (np.asarray(a) for a in jax.jit(exact.mean_std_batch)(jnp.asarray(x)))
    for j, comp in enumerate(gp.components_):
        m_ref, s_ref = _dense_posterior(
            data.x[100:300], data.y[100:300, comp], gp.amplitude_[j], gp.noise_[j],
            gp.lengthscale_[j], gp.mean_[j], x,
        )  # fmt: skip
        # the same SPD system (noise 0.01: condition number < 1e8) solved two ways: agreement
        # to about cond * eps relative to the scales of the targets and of amplitude^2
        scale = np.abs(data.y[:, comp]).max()
        np.testing.assert_allclose(mean[:, comp], m_ref, atol=1e-7 * scale)
        np.testing.assert_allclose(m_b[:, comp], m_ref, atol=1e-7 * scale)
        np.testing.assert_allclose(var[:, comp], s_ref**2, atol=1e-8 * gp.amplitude_[j] ** 2)
        np.testing.assert_allclose(s_b[:, comp] ** 2, s_ref**2, atol=1e-8 * gp.amplitude_[j] ** 2)
    assert model.n_starts_ == 0 and np.all(model.n_iter_ == 0)


def test_batched_cache_is_fastgp_and_contains_the_exact_band_far_from_the_data(fitted):
    """The batched cache is FastGP's proven band: equal to FastGP.predict to rounding, and its
    band contains the exact band at every state, including states far outside the data (no
    calibration states involved)."""
    gp, _, x = fitted
    fast = FastGP(gp, 48)  # at 32 the first component is capped (band 1.57 times the exact)
    cache = inducing_cache(gp, 48)
    m_c, s_c = (np.asarray(a) for a in jax.jit(cache.mean_std_batch)(jnp.asarray(x)))
    m_f, s_f = fast.predict(x, return_std=True)
    # the same arrays and formula; only the summation order of the dot products may differ:
    # a few eps relative to the mean's and the std's own rounding scales, per state
    mean_scale, std_scale = fast.rounding_scales(x)
    assert np.all(np.abs(s_c - s_f) <= 64 * np.finfo(float).eps * std_scale)
    assert np.all(np.abs(m_c - m_f) <= 64 * np.finfo(float).eps * mean_scale)
    comps = list(gp.components_)
    mean_ex, s_ex = (a[:, comps] for a in gp.predict(x, return_std=True))
    for beta in (1.0, 2.0, 10.0):  # every beta >= min_beta = 1
        assert np.all(m_c[:, comps] - beta * s_c[:, comps] <= mean_ex - beta * s_ex)
        assert np.all(m_c[:, comps] + beta * s_c[:, comps] >= mean_ex + beta * s_ex)
    assert float(cache.min_beta) == 1.0
    # each component keeps FastGP's inducing inputs (not its padding to the largest count),
    # rounded up to 1, 2, 4 or a multiple of 4 with masked rows: FastGP uses 48, 29 and 29
    assert list(np.asarray(fast.arrays()["mask"]).sum(1)) == [48, 29, 29]
    assert [int(m.sum()) for m in cache.mask] == [48, 29, 29]
    assert [z.shape[0] for z in cache.zl] == [48, 32, 32]
    assert [li.shape for li in cache.li] == [(48, 48), (32, 32), (32, 32)]


def test_inducing_buckets():
    from safestab.learning._posterior import bucket

    table = {0: 1, 1: 1, 2: 2, 3: 4, 4: 4, 5: 8, 8: 8, 9: 12, 12: 12, 13: 16, 32: 32}
    assert {used: bucket(used) for used in table} == table


def test_batched_uncertainty_rule_equals_the_batch(fitted):
    gp, _, x = fitted
    cache = inducing_cache(gp, 48)
    model = BatchedUncertainty(cache)
    m_rule, s_rule = jax.jit(jax.vmap(model.mean_std))(jnp.asarray(x))
    m_batch, s_batch = jax.jit(cache.mean_std_batch)(jnp.asarray(x))
    np.testing.assert_array_equal(np.asarray(m_rule), np.asarray(m_batch))
    np.testing.assert_array_equal(np.asarray(s_rule), np.asarray(s_batch))
    m1, s1 = model.mean_std(jnp.asarray(x[5]))  # one state, no vmap
    # a separate compilation may fuse differently: rounding only
    np.testing.assert_allclose(np.asarray(m1), np.asarray(m_batch)[5], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(s1), np.asarray(s_batch)[5], rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize(
    "change, error, match",
    [
        (dict(amplitude=[1.0, 1.0]), DimensionError, r"amplitude must have shape \(3,\)"),
        (dict(noise=[0.1, 0.0, 0.1]), ParameterError, "noise"),
        (dict(lengthscale=np.ones((3, 2))), DimensionError, r"lengthscale must have shape"),
        (dict(lengthscale=-np.ones((3, 3))), ParameterError, "lengthscale"),
        (dict(mean=[0.0, np.nan, 0.0]), NonFiniteError, "mean"),
        (dict(kernel="rbf"), ParameterError, "kernel must be one of"),
        (dict(components=[0, 0, 1]), DimensionError, "components must be distinct"),
        (dict(y=np.ones((5, 3))), DimensionError, r"x and y must be \(Q, n\) arrays"),
        (dict(x=np.full((10, 3), np.nan)), NonFiniteError, "x"),
    ],
)  # fmt: skip
def test_from_hyperparameters_rejects_bad_input(change, error, match):
    args = dict(
        x=np.random.default_rng(0).normal(size=(10, 3)),
        y=np.zeros((10, 3)),
        amplitude=[1.0, 1.0, 1.0],
        noise=[0.1, 0.1, 0.1],
        lengthscale=np.ones((3, 3)),
    )
    args.update(change)  # fmt: skip
    x, y = args.pop("x"), args.pop("y")
    with pytest.raises(error, match=match):
        GaussianProcessModel.from_hyperparameters(x, y, **args)
