"""The constant input-gain error learned with the GP (safestab.learning.input_gain)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.errors import DimensionError, NonFiniteError, ParameterError, ScenarioError
from safestab.learning import (
    GaussianProcessModel,
    InputGain,
    estimate_input_gain,
    fit_input_gain,
)
from safestab.learning.input_gain import with_input_gain

D_TRUE = np.array([[0.2, -0.05], [0.0, 0.1]])
NOISE = 0.01


def _data(q=160, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-2.0, 2.0, (q, 2))
    u = rng.uniform(-1.5, 1.5, (q, 2))
    omega = np.stack([0.5 * np.sin(x[:, 0]), 0.3 * np.cos(x[:, 1]) * x[:, 0]], -1)
    y = omega + u @ D_TRUE.T + NOISE * rng.standard_normal((q, 2))
    return x, u, y


def _fit(x, y):
    return GaussianProcessModel(kernel="se").fit(x, y, hyper_subset=len(x), seed=0)


def test_gls_estimate_matches_a_dense_hand_computation():
    """The estimate is (U^T K^-1 U)^-1 U^T K^-1 (y - mu), K built here by hand from the
    model's hyperparameters (SE kernel on the standardised inputs, plus noise^2 I)."""
    x, u, y = _data(q=80)
    model = GaussianProcessModel.from_hyperparameters(
        x, y, amplitude=[0.4, 0.3], noise=[0.05, 0.04], lengthscale=[[1.0, 2.0], [1.5, 0.8]],
        mean=[0.01, -0.02],
    )  # fmt: skip
    got = estimate_input_gain(model, u)
    xs = (x - model.x_offset_) / model.x_scale_
    for j in range(2):
        diff = (xs[:, None, :] - xs[None, :, :]) / model.lengthscale_std_[j]
        k = model.amplitude_[j] ** 2 * np.exp(-0.5 * np.sum(diff**2, -1))
        k += model.noise_[j] ** 2 * np.eye(len(x))
        kinv_u = np.linalg.solve(k, u)
        a = u.T @ kinv_u
        d = np.linalg.solve(a, kinv_u.T @ (y[:, j] - model.mean_[j]))
        np.testing.assert_allclose(got.matrix[j], d, rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(got.std[j], np.sqrt(np.diag(np.linalg.inv(a))), rtol=1e-8)


def test_fit_recovers_the_gain_and_the_sensor_noise():
    """Against the known D: within 4 standard errors; the GP's noise is the sensor's again,
    where a GP of y alone takes D u for noise."""
    x, u, y = _data()
    plain = _fit(x, y)
    model, gain = fit_input_gain(_fit, x, u, y)
    assert np.all(np.abs(gain.matrix - D_TRUE) <= 4 * gain.std)
    assert np.all(gain.std < 0.01)
    assert np.all(model.noise_ < 2 * NOISE)
    assert np.all(plain.noise_ > 3 * NOISE)
    # the model learns y - D u: its targets are exactly those
    np.testing.assert_allclose(model.y_train_, y - u @ gain.matrix.T, rtol=0, atol=1e-15)


def test_corrected_system_adds_the_matrix_to_g():
    sys = ss.ControlAffineSystem(
        lambda x: -x, lambda x: jnp.array([[1.0, x[0]], [0.0, 2.0]]), 2, name="plant"
    )
    gain = InputGain(D_TRUE, np.zeros((2, 2)))
    corrected = gain.corrected(sys)
    xs = np.random.default_rng(1).normal(size=(5, 2))
    np.testing.assert_allclose(
        np.asarray(corrected.input_matrix(xs)), np.asarray(sys.input_matrix(xs)) + D_TRUE
    )
    np.testing.assert_array_equal(np.asarray(corrected.drift(xs)), np.asarray(sys.drift(xs)))
    # a system with run-time parameters keeps them
    psys = ss.ControlAffineSystem(
        lambda x, p: -p["k"] * x, lambda x, p: p["k"] * jnp.eye(2), 2, params={"k": 1.0}
    )
    pc = with_input_gain(psys, D_TRUE)
    np.testing.assert_allclose(
        np.asarray(pc.input_matrix(xs[0], {"k": 3.0})), 3.0 * np.eye(2) + D_TRUE
    )
    with pytest.raises(DimensionError, match=r"shape \(3,\).*needs \(2, 2\)"):
        with_input_gain(sys, np.ones(3))


def test_bad_inputs_are_named():
    x, u, y = _data(q=40)
    model = GaussianProcessModel.from_hyperparameters(
        x, y, amplitude=[0.4, 0.3], noise=[0.05, 0.04], lengthscale=[[1.0, 2.0], [1.5, 0.8]]
    )
    with pytest.raises(DimensionError, match=r"u must have shape \(Q, m\) = \(40, m\)"):
        estimate_input_gain(model, u[:10])
    with pytest.raises(NonFiniteError, match="u contains non-finite"):
        estimate_input_gain(model, np.where(np.arange(40)[:, None] == 3, np.nan, u))
    with pytest.raises(NonFiniteError, match="never excited"):
        estimate_input_gain(model, np.stack([u[:, 0], np.zeros(40)], -1))


def test_obstacle_scenario_key_and_learned_system(tmp_path):
    from safestab.scenarios import load

    preset = load("obstacle")
    assert preset.input_gain == "learned" and preset.learned_gain is None  # set by the study
    sc = preset.replace(input_gain="nominal")
    # without a learned gain, "learned" is the nominal model
    x = np.array([1.0, -2.0])
    np.testing.assert_array_equal(
        np.asarray(sc.system("learned").input_matrix(x)),
        np.asarray(sc.system("nominal").input_matrix(x)),
    )
    learned = sc.replace(input_gain="learned", learned_gain=((0.1, 0.0), (0.01, 0.1)))
    np.testing.assert_allclose(
        np.asarray(learned.system("learned").input_matrix(x)),
        sc.gain_nominal * np.eye(2) + np.array([[0.1, 0.0], [0.01, 0.1]]),
    )
    with pytest.raises(ParameterError, match="which must be 'true', 'nominal' or 'learned'"):
        sc.system("estimated")
    with pytest.raises(ScenarioError, match="learning.input_gain"):
        load("obstacle", overrides={"learning.input_gain": "fitted"})
    with pytest.raises(ScenarioError, match="learned_gain must be a finite 2 x 2"):
        preset.replace(learned_gain=((0.1, 0.0),))
    with pytest.raises(ScenarioError, match="learned_gain is set only with"):
        sc.replace(learned_gain=((0.1, 0.0), (0.0, 0.1)))


def test_obstacle_study_fit_learns_the_gain_and_the_controller_uses_it():
    """The preset's gain error (true 1.1, nominal 1.0) is recovered from 120 rows, and the
    GP-robust controller's model is k_nom I + D."""
    from safestab.scenarios import load
    from safestab.scenarios.obstacle_study import fit_obstacle_gp, obstacle_controller

    sc = load("obstacle").replace(
        input_gain="learned", n_samples=120, hyper_subset=120, n_inducing=0
    )
    _, gp, _, gain = fit_obstacle_gp(sc)
    true_d = (sc.gain_true - sc.gain_nominal) * np.eye(2)
    assert np.all(np.abs(gain.matrix - true_d) <= 5 * gain.std + 1e-3)
    sc = sc.replace(learned_gain=tuple(map(tuple, gain.matrix.tolist())))
    ctrl = obstacle_controller(sc, "GP-robust", gp)
    np.testing.assert_allclose(
        np.asarray(ctrl.system.input_matrix(np.zeros(2))), np.eye(2) + gain.matrix
    )
    # the other controllers keep their models
    np.testing.assert_array_equal(
        np.asarray(obstacle_controller(sc, "mismatched model").system.input_matrix(np.zeros(2))),
        np.eye(2),
    )


def test_monte_carlo_data_sets_learn_the_gain_with_and_without_reused_hyperparameters():
    from safestab.montecarlo.trials import fit_dataset
    from safestab.scenarios import load

    sc = load("obstacle").replace(input_gain="learned", n_samples=120, hyper_subset=120)
    study = sc.trial_study()
    assert study.gp_settings()["input_gain"] == "learned"
    first = fit_dataset(study, 3, 0, None)
    again = fit_dataset(study, 3, 1, first.hyper)
    true_d = (sc.gain_true - sc.gain_nominal) * np.eye(2)
    for model in (first, again):
        assert model.input_gain.shape == (2, 2)
        np.testing.assert_allclose(model.input_gain, true_d, atol=0.01)
    plain = fit_dataset(load("obstacle").replace(input_gain="nominal", n_samples=120,
                                                 hyper_subset=120).trial_study(),
                        3, 0, None)  # fmt: skip
    assert plain.input_gain is None


def test_monte_carlo_gp_controllers_run_on_the_learned_model():
    """The chunk gives the GP controllers g + D: their records change with D, the model
    controllers' do not. Against D = 0, the nominal input matrix as data: the same compiled
    chunk, so that only D differs between the two runs (``input_gain=None``, the chunk
    without the term, is every other Monte Carlo test's)."""
    import dataclasses

    from safestab.montecarlo.trials import fit_dataset, run_chunk
    from safestab.scenarios import load

    sc = load("obstacle").replace(input_gain="learned", n_samples=120, hyper_subset=120)
    study = sc.trial_study()
    model = fit_dataset(study, 3, 0, None)
    learned = run_chunk(study, model, 3, np.arange(3))
    zero = np.zeros_like(model.input_gain)
    nominal = run_chunk(study, dataclasses.replace(model, input_gain=zero), 3, np.arange(3))
    names = list(study.spec.controllers)
    # (the Lemma 2 beta is so large that its controller keeps to the start's h in both)
    gp = [names.index("GP mean"), names.index("GP-robust")]
    fixed = [i for i, n in enumerate(names) if not n.startswith("GP")]
    assert gp and fixed
    for key in ("min_h", "final_V"):
        np.testing.assert_array_equal(learned[key][:, fixed], nominal[key][:, fixed])
        assert np.all(learned[key][:, gp] != nominal[key][:, gp]), (key, names)


def test_monte_carlo_reused_hyperparameters_give_the_gls_estimate_and_its_gp():
    """Data set 1 with data set 0's hyperparameters: D is the GLS estimate under that kernel,
    and the shipped cache is the GP of y - D u (its mean at the held-out states)."""
    from safestab.learning import BatchedUncertainty, condition
    from safestab.montecarlo.trials import dataset_draw, fit_dataset
    from safestab.scenarios import load

    sc = load("obstacle").replace(input_gain="learned", n_samples=120, hyper_subset=120)
    study = sc.trial_study()
    first = fit_dataset(study, 3, 0, None)
    again = fit_dataset(study, 3, 1, first.hyper)
    data = dataset_draw(study, 3, 1)
    x, u, y = data.x[:120], data.u[:120], data.y[:120]
    d = estimate_input_gain(condition(first.hyper, x, y), u).matrix
    np.testing.assert_allclose(again.input_gain, d, rtol=1e-10, atol=1e-13)
    gp = condition(first.hyper, x, y - u @ d.T)
    x_test = data.x[120:140]
    mean, _ = BatchedUncertainty(again.cache).mean_std_batch(x_test)
    exact = gp.predict(x_test, return_std=False)
    wrong = condition(first.hyper, x, y).predict(x_test, return_std=False)
    err = np.max(np.abs(np.asarray(mean) - exact))
    assert err < 0.1 * np.max(np.abs(wrong - exact))


def test_obstacle_gp_robust_verdict_reads_the_learned_model():
    """The GP-robust verdict and maps use k_nom I + D; the other controllers do not."""
    from safestab.scenarios import load
    from safestab.scenarios.obstacle_study import compatibility_maps, verdict

    class Band:
        def mean_std(self, x):
            return jnp.zeros(2), jnp.full(2, 0.05)

    sc = load("obstacle").replace(gp_beta=1.0)
    # a learned D = I makes the GP-robust model's gain 2: the same verdicts as a scenario
    # whose nominal gain is 2, and other ones than the nominal gain's on the parallel set
    big = sc.replace(input_gain="learned", learned_gain=((1.0, 0.0), (0.0, 1.0)))
    ref = sc.replace(gain_nominal=2.0)
    pts = sc.parallel_set()
    learned = verdict(big, "GP-robust", pts, Band())
    np.testing.assert_array_equal(learned, verdict(ref, "GP-robust", pts, Band()))
    assert np.any(learned != verdict(sc, "GP-robust", pts, Band()))
    np.testing.assert_array_equal(
        verdict(big, "mismatched model", pts), verdict(sc, "mismatched model", pts)
    )
    maps = compatibility_maps(big, Band())
    maps0 = compatibility_maps(sc, Band())
    np.testing.assert_array_equal(maps.nominal_compatible, maps0.nominal_compatible)
    assert np.any(maps.robust_updated != maps0.robust_updated)


def test_stale_or_malformed_learned_gain_is_refused():
    from safestab.scenarios import load

    sc = load("obstacle").replace(input_gain="nominal")
    with pytest.raises(ScenarioError, match="learned_gain is set only with"):
        sc.replace(learned_gain=((0.1, 0.0), (0.0, 0.1)))
    with pytest.raises(ScenarioError, match="finite 2 x 2"):
        sc.replace(input_gain="learned", learned_gain=((0.1, "a"), (0.0, 0.1)))
    with pytest.raises(ScenarioError, match="finite 2 x 2"):
        sc.replace(input_gain="learned", learned_gain=((0.1,), (0.0, 0.1)))
    sys = sc.system("nominal")
    with pytest.raises(NonFiniteError, match="not finite"):
        with_input_gain(sys, np.array([[np.nan, 0.0], [0.0, 0.0]]))
