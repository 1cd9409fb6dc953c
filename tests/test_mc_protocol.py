"""Monte Carlo for any scenario: the trial-study protocol, the obstacle's study, and a third
scenario written in this file against the protocol alone."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import pytest

import safestab as ss
from safestab.errors import ParameterError, ScenarioError
from safestab.learning import collect_data
from safestab.montecarlo import (
    RECORD_FIELDS,
    metrics_document,
    plot_montecarlo,
    run_montecarlo,
    summarize,
    trial_function,
)
from safestab.montecarlo.protocol import TrialStudy
from safestab.montecarlo.report import study_settings
from safestab.scenarios import MonteCarloSpec, load

# a 4 x 1 start grid (all outside the obstacle), 1 s at 50 Hz, a small GP
OBSTACLE = load(
    "obstacle",
    overrides={"starts.n_x1": 4, "starts.n_x2": 1, "simulation.t_final": 1.0,
               "learning.n_samples": 60, "learning.hyper_subset": 30},
)  # fmt: skip
SPEC = MonteCarloSpec(controllers=("true model", "GP-robust"), chunk_size=4, trials=6)


def test_obstacle_trials_reproduce_the_simulator():
    """The fixed distribution visits the start grid in order; each trial's records equal
    ss.simulate's on the same closed loop (the true-model controller with the limits)."""
    study = OBSTACLE.trial_study(SPEC)
    assert isinstance(study, TrialStudy) and study.h_unit == "m^2"
    starts = OBSTACLE.start_states()
    x0, params = study.draw_trials(0, np.arange(5))
    np.testing.assert_array_equal(np.asarray(x0), starts[np.arange(5) % len(starts)])
    true_sys, _ = study.systems()
    clf, cbf = study.certificates()
    ctrl = ss.UniversalController(true_sys, clf, cbf, **study.controller_options())
    run = trial_function([ctrl], plant=true_sys, n_steps=study.n_steps, dt=study.dt)
    rec = jax.jit(jax.vmap(run))(x0[:3], params)
    for i in range(3):
        traj = ss.simulate(ctrl, starts[i], t_final=OBSTACLE.t_final, dt=OBSTACLE.dt,
                           plant=true_sys)  # fmt: skip
        assert float(rec["min_h"][i, 0]) == pytest.approx(float(np.min(traj.h)), abs=1e-9)
        assert float(rec["final_V"][i, 0]) == pytest.approx(float(traj.V[-1]), rel=1e-9)
        assert np.max(np.abs(traj.u)) <= OBSTACLE.input_limit  # the limits are applied


def test_obstacle_box_draws_and_spec_checks():
    spec = SPEC.replace(initial_distribution="box", initial_low=(-8.0, -1.0),
                        initial_high=(-6.0, 1.0))  # fmt: skip
    x0, _ = OBSTACLE.trial_study(spec).draw_trials(1, np.arange(50))
    x0 = np.asarray(x0)
    assert x0.shape == (50, 2) and np.all((x0 >= [-8, -1]) & (x0 <= [-6, 1]))
    with pytest.raises(ParameterError, match=r"initial.low must have 2 entries \(x1 m, x2 m\)"):
        OBSTACLE.trial_study(SPEC.replace(initial_distribution="box",
                                          initial_low=(0.0, 0.0, 0.0),
                                          initial_high=(1.0, 1.0, 1.0)))  # fmt: skip
    with pytest.raises(ParameterError, match=r"lead.kind must be 'fixed' for the obstacle"):
        OBSTACLE.trial_study(SPEC.replace(lead_kind="random"))
    with pytest.raises(ScenarioError, match=r"initial.low and montecarlo.initial.high must have"):
        SPEC.replace(initial_distribution="box", initial_low=(0.0,), initial_high=(1.0, 2.0))


def _obstacle_file(tmp_path, table):
    from importlib import resources

    base = resources.files("safestab.scenarios").joinpath("obstacle.toml").read_text()
    base = base.split("\n[montecarlo]")[0]  # the preset's own table (its cap), replaced
    path = tmp_path / "o.toml"
    path.write_text(base + "\n" + table)
    return path


def test_obstacle_file_takes_a_montecarlo_table(tmp_path):
    sc = load(
        _obstacle_file(
            tmp_path,
            "[montecarlo]\ntrials = 7\n[montecarlo.initial]\n"
            "distribution = 'box'\nlow = [-8.0, -1.0]\nhigh = [-6.0, 1.0]\n",
        )
    )
    assert sc.montecarlo.trials == 7 and sc.montecarlo.initial_low == (-8.0, -1.0)
    with pytest.raises(ScenarioError, match=r"montecarlo.initial.low must be an array of 2"):
        load(_obstacle_file(tmp_path, "[montecarlo.initial]\nlow = [1.0, 2.0, 3.0]\n"))
    with pytest.raises(ScenarioError, match=r"unknown key 'lead' in \[montecarlo\]"):
        load(_obstacle_file(tmp_path, "[montecarlo.lead]\nkind = 'random'\n"))


def test_obstacle_trials_with_the_filter_reproduce_the_simulator():
    """``controller.limit_method``: the trials build the study's controller (the preset's
    SafetyFilter, the projecting formula otherwise) and reproduce ss.simulate's loop."""
    for method, kind in (("filter", ss.SafetyFilter), ("projection", ss.UniversalController)):
        study = OBSTACLE.replace(limit_method=method).trial_study(SPEC)
        true_sys, _ = study.systems()
        clf, cbf = study.certificates()
        ctrl = study.build_controller(true_sys, clf, cbf, **study.controller_options())
        assert type(ctrl) is kind
        # the documents record how the limits were kept, with the box and the gains
        recorded = study_settings(study)["controller_settings"]
        assert recorded["limit_method"] == method
        assert recorded["u_max"] == [OBSTACLE.input_limit] * 2
        assert recorded["kappa"] == OBSTACLE.kappa
        json.dumps(recorded, allow_nan=False)
    assert OBSTACLE.limit_method == "filter"  # the preset
    starts = OBSTACLE.start_states()
    x0, params = study.draw_trials(0, np.arange(3))
    filt = OBSTACLE.trial_study(SPEC).build_controller(
        true_sys, clf, cbf, **study.controller_options()
    )

    # the trials with the controller as an argument of the program, as simulate runs it:
    # the same arithmetic, so the same bits. (The obstacle's loop is sensitive: one ulp in
    # x0 moves min h by up to 1e-4 here, so a program that holds the numbers as constants,
    # as the study's chunk does, agrees only to that.)
    @jax.jit
    def trials(ctrl, x0, params):
        run = trial_function([ctrl], plant=true_sys, n_steps=study.n_steps, dt=study.dt)
        return jax.vmap(run)(x0, params)

    rec = trials(filt, x0, params)
    for i in range(3):
        traj = ss.simulate(filt, starts[i], t_final=OBSTACLE.t_final, dt=OBSTACLE.dt,
                           plant=true_sys)  # fmt: skip
        assert float(rec["min_h"][i, 0]) == pytest.approx(float(np.min(traj.h)), abs=1e-9)
        assert float(rec["final_V"][i, 0]) == pytest.approx(float(traj.V[-1, 0]), rel=1e-9)
        # steps whose whole problem was not solved (a fallback) count as incompatible
        unsolved = int(np.sum(~np.asarray(traj.compatible)[:-1]))
        assert int(rec["incompatible_steps"][i, 0]) == unsolved
    # with a box too small to hold the CBF against the current (0.3 m/s), the filter relaxes
    # the CBF at some steps: counted, and equal to the simulator's unsolved steps
    tight = OBSTACLE.replace(limit_method="filter", input_limit=0.3).trial_study(SPEC)
    small = tight.build_controller(true_sys, clf, cbf, **tight.controller_options())
    rec = trials(small, x0, params)
    counts = [int(c) for c in np.asarray(rec["incompatible_steps"][:, 0])]
    assert max(counts) > 0
    for i in range(3):
        traj = ss.simulate(small, starts[i], t_final=OBSTACLE.t_final, dt=OBSTACLE.dt,
                           plant=true_sys)  # fmt: skip
        assert counts[i] == int(np.sum(~np.asarray(traj.compatible)[:-1]))


def test_gp_robust_filter_step_with_given_uncertainty_is_its_step():
    """The Monte Carlo loop evaluates the GP once per step and hands it to the filter."""

    class Band:
        n_states = 2

        def mean_std(self, x):
            return 0.05 * jnp.sin(x), 0.1 + 0.01 * x**2

    sc = OBSTACLE
    band = Band()
    filt = ss.SafetyFilter(
        sc.system("nominal"), sc.certificates()[1], clfs=sc.certificates()[0],
        slack_weight=sc.slack_weight, u_min=-1.5, u_max=1.5, uncertainty=band, gp_beta=3.0,
    )  # fmt: skip
    for x in (jnp.array([-5.0, 0.3]), jnp.array([-2.0, 1.4]), jnp.array([1.0, -0.5])):
        mean, std = band.mean_std(x)
        ref, got = filt.step_fn(x), filt.step_with_uncertainty(x, mean, std)
        for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(got),
                        strict=True):  # fmt: skip
            # the same arithmetic, compiled apart (a jitted step against an eager one)
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=0)
    # the given values are the ones used: another std gives another input
    x = jnp.array([-5.0, 0.3])
    mean, std = band.mean_std(x)
    other = filt.step_with_uncertainty(x, mean, 5 * std)
    assert not np.allclose(np.asarray(other.u), np.asarray(filt.step_fn(x).u))
    with pytest.raises(ss.ParameterError, match="needs a filter with an uncertainty model"):
        ss.SafetyFilter(sc.system("nominal"), sc.certificates()[1]).step_with_uncertainty(
            x, mean, std
        )


def test_obstacle_study_runs_end_to_end():
    run = run_montecarlo(OBSTACLE, spec=SPEC, trials=6, datasets=1, seed=1)
    assert run.records["min_h"].shape == (6, 2) and set(run.records) == set(RECORD_FIELDS)
    summary = summarize(run)
    assert summary["h_unit"] == "m^2"
    # trials i and i + 4 start at the same grid point (4 starts): the same records
    for key in RECORD_FIELDS:
        np.testing.assert_array_equal(run.records[key][:2], run.records[key][4:6])
    assert run.records["lemma2_violations"][0, 0] == -1  # the true model has no GP


# -- a third scenario, written against the protocol only --------------------------------


@dataclasses.dataclass(frozen=True)
class ScalarTrials:
    """x' = -x + u + omega(x), omega = 0.5 sin(x); nominal without omega; h = 4 - x^2."""

    spec: MonteCarloSpec
    name: str = "scalar"
    n_states: int = 1
    n_steps: int = 20
    dt: float = 0.05
    t_final: float = 1.0
    h_unit: str = "m^2"
    exogenous: Any = None

    def systems(self):
        g = lambda x: jnp.ones((1, 1))  # noqa: E731
        true = ss.ControlAffineSystem(lambda x: -x + 0.5 * jnp.sin(x), g, 1)
        return true, ss.ControlAffineSystem(lambda x: -x, g, 1)

    def certificates(self):
        return ss.CLF(lambda x: x[0] ** 2, lam=1.0), ss.CBF(lambda x: 4.0 - x[0] ** 2, beta=2.0)

    def controller_options(self):
        return dict(kappa=0.1, rho=0.1, phi=0.01, varphi=0.01)

    def omega(self, x):
        return 0.5 * jnp.sin(jnp.asarray(x))

    def gp_settings(self):
        return dict(n_samples=40, kernel="se", hyper_subset=40, gp_beta=2.0)

    def calibration_shape(self):
        return 5, 1

    def collect(self, n_samples, seed):
        true, nominal = self.systems()
        return collect_data(true, nominal, x0=([-1.9], [1.9]), u_low=-1.0, u_high=1.0,
                            n_samples=n_samples, rate=10.0, horizon=0.5, noise_std=0.01,
                            seed=seed)  # fmt: skip

    def draw_trials(self, seed, indices):
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(seed), i))(
            jnp.asarray(indices)
        )
        x0 = jax.vmap(lambda k: jax.random.uniform(k, (1,), minval=-1.5, maxval=1.5))(keys)
        return x0, {}


@dataclasses.dataclass(frozen=True)
class ScalarScenario:
    name: str = "scalar"
    montecarlo: Any = None

    def trial_study(self, spec):
        return ScalarTrials(spec)


def test_a_third_scenario_plugs_in_through_the_protocol():
    spec = MonteCarloSpec(controllers=("true model", "mismatched model", "GP-robust"),
                          chunk_size=8)  # fmt: skip
    run = run_montecarlo(ScalarScenario(), spec=spec, trials=8, datasets=1, seed=0)
    assert run.records["min_h"].shape == (8, 3)
    doc = metrics_document(run)  # the outputs read the study, not the scenario
    assert doc["scenario"] == "scalar" and doc["settings"]["n_samples"] == 40
    # a study without the optional controller_settings member records its GP settings only
    assert doc["settings"]["gp_settings"] == run.study.gp_settings()
    assert doc["settings"]["controller_settings"] is None
    assert doc["summary"]["h_unit"] == "m^2"
    plt.close(plot_montecarlo(run))
    # independent check of one trial: the true-model controller by ss.simulate
    study = run.study
    x0, _ = study.draw_trials(0, np.arange(8))
    true, _ = study.systems()
    ctrl = ss.UniversalController(true, *study.certificates(), **study.controller_options())
    traj = ss.simulate(ctrl, np.asarray(x0[5]), t_final=1.0, dt=0.05, plant=true)
    assert run.records["min_h"][5, 0] == pytest.approx(float(np.min(traj.h)), abs=1e-9)


def test_a_scenario_without_the_protocol_is_refused_before_work():
    with pytest.raises(ParameterError, match=r"scenario must provide trial_study\(spec\)"):
        run_montecarlo(object(), spec=SPEC, trials=2)

    @dataclasses.dataclass(frozen=True)
    class Wrong:
        name: str = "wrong"

        def trial_study(self, spec):
            return object()

    with pytest.raises(ParameterError, match=r"must return a TrialStudy"):
        run_montecarlo(Wrong(), spec=SPEC, trials=2)

    @dataclasses.dataclass(frozen=True)
    class OwnSpec:
        name: str = "own"

        def trial_study(self, spec):
            return ScalarTrials(spec.replace(chunk_size=3))

    with pytest.raises(ParameterError, match=r"must keep the spec it was given"):
        run_montecarlo(OwnSpec(), spec=SPEC, trials=2)
