"""The price-of-robustness study (safestab.montecarlo.price) against hand computations."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from safestab.errors import ParameterError
from safestab.montecarlo import clopper_pearson, run_montecarlo
from safestab.montecarlo.loop import RECORD_FIELDS
from safestab.montecarlo.price import PRICE_CONTROLLERS, plot_price, price_point, price_study
from safestab.scenarios import load_scenario


def _fake_run(min_h: np.ndarray, final_v: np.ndarray, sets: np.ndarray, names: tuple):
    """A MonteCarloRun with given records (N, C): what summarize and price_point read."""
    n, c = min_h.shape
    rec = {k: np.zeros((n, c)) for k in RECORD_FIELDS}
    rec.update(min_h=min_h, final_V=final_v, lemma2_violations=-np.ones((n, c)),
               clf_true_fraction=np.linspace(0, 1, n * c).reshape(n, c))  # fmt: skip
    rec["first_bad_step"] = -np.ones((n, c))
    k = int(sets.max()) + 1
    model = SimpleNamespace(hyper=SimpleNamespace(components=(0,)))
    return SimpleNamespace(
        records=rec, dataset_index=sets, datasets=[model] * k, controllers=names,
        study=SimpleNamespace(h_unit="m", n_steps=50), spec=SimpleNamespace(delta=0.01),
    )  # fmt: skip


def test_price_point_pairs_each_trial_with_the_reference():
    rng = np.random.default_rng(0)
    n = 40
    names = ("true model", "GP-robust")
    min_h = np.column_stack([rng.uniform(0.0, 1.0, n), rng.uniform(-0.5, 3.0, n)])
    final_v = rng.uniform(0, 5, (n, 2))
    sets = np.arange(n) % 8
    point = price_point(_fake_run(min_h, final_v, sets, names))
    excess = min_h[:, 1] - min_h[:, 0]
    for q in ("0.1", "0.5", "0.9"):
        assert point["GP-robust"]["min_h_excess"][q] == pytest.approx(np.quantile(excess, float(q)))
        assert point["true model"]["min_h_excess"][q] == 0.0
    frac = np.linspace(0, 1, 2 * n).reshape(n, 2)
    assert point["GP-robust"]["clf_fraction_deficit"] == pytest.approx(
        np.mean(frac[:, 0] - frac[:, 1])
    )
    # safe per data set: every trial of the set has min h >= 0 (counted by hand)
    safe = min_h[:, 1] >= 0
    count = sum(bool(np.all(safe[sets == j])) for j in range(8))
    entry = point["GP-robust"]["safe_per_dataset"]
    assert entry["count"] == count and entry["datasets"] == 8
    assert entry["ci95"] == pytest.approx(list(clopper_pearson(count, 8)))


def test_price_point_counts_the_limit_and_the_unmet_barrier():
    """limit_step_fraction, limit_trials, barrier_unmet_trials and _steps against hand sums."""
    n, names = 12, ("true model", "GP-robust")
    run = _fake_run(np.ones((n, 2)), np.ones((n, 2)), np.arange(n) % 3, names)
    limit = np.zeros((n, 2), int)
    limit[[1, 4, 7], 1] = [50, 3, 10]  # 63 of 12 * 50 steps, in 3 trials
    unmet = np.zeros((n, 2), int)
    unmet[[4, 9], 1] = [2, 5]
    run.records.update(limit_steps=limit, barrier_unmet_steps=unmet)
    point = price_point(run)
    e = point["GP-robust"]
    assert e["limit_step_fraction"] == pytest.approx(63 / 600)
    assert (e["limit_trials"], e["barrier_unmet_trials"], e["barrier_unmet_steps"]) == (3, 2, 7)
    assert point["true model"]["limit_trials"] == 0


def test_price_point_needs_the_reference():
    run = _fake_run(np.zeros((4, 1)), np.zeros((4, 1)), np.arange(4) % 2, ("GP-robust",))
    with pytest.raises(ParameterError, match="reference must be one of"):
        price_point(run)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"q_values": []}, "non-empty list of integers"),
        ({"q_values": [100, 50]}, "must increase"),
        ({"q_values": [100, True]}, "non-empty list of integers"),
        ({"datasets": 0}, "datasets must be an integer >= 1"),
        ({"trials_per_dataset": 2.5}, "trials_per_dataset must be an integer >= 1"),
        ({"controllers": ("GP-robust",)}, "must include 'true model'"),
    ],
)
def test_price_study_refuses_bad_input_before_any_work(kwargs, match):
    args = {"q_values": [50, 100], "datasets": 2, "trials_per_dataset": 2} | kwargs
    with pytest.raises(ParameterError, match=match):
        price_study(load_scenario("stress"), **args)


def test_price_study_checks_every_size_before_any_work():
    from safestab.errors import ScenarioError

    with pytest.raises(ScenarioError, match="n_samples"):
        price_study(load_scenario("stress"), [50, 10**9], datasets=2, trials_per_dataset=2)


@pytest.mark.slow
# at Q = 30 the data are a slice of one excitation run: the fit warns, as it should
@pytest.mark.filterwarnings("ignore::safestab.errors.DataWarning")
def test_price_study_matches_a_direct_monte_carlo_run(tmp_path):
    # Two small sizes of a short stress run; the second size's point is recomputed from a
    # direct run_montecarlo call at that size (same seed, same trials).
    sc = load_scenario("stress").replace(t_final=3.0)
    doc = price_study(sc, [30, 60], datasets=2, trials_per_dataset=2, seed=3,
                      controllers=PRICE_CONTROLLERS[:3])  # fmt: skip
    json.dumps(doc, allow_nan=False)  # strict JSON
    assert doc["settings"]["gp_settings"]["kernel"] == sc.kernel
    assert "n_samples" not in doc["settings"]["gp_settings"]  # it is each point's
    assert doc["settings"]["controller_settings"]["kappa"] == sc.kappa
    assert [p["n_samples"] for p in doc["points"]] == [30, 60]
    spec = sc.montecarlo.replace(controllers=PRICE_CONTROLLERS[:3], price_metrics=True)
    run = run_montecarlo(sc.replace(n_samples=60), trials=4, datasets=2, seed=3, spec=spec)
    rec = run.records
    excess = rec["min_h"][:, 2] - rec["min_h"][:, 0]
    got = doc["points"][1]["controllers"]["GP-robust"]["min_h_excess"]["0.5"]
    assert got == pytest.approx(float(np.median(excess)), abs=1e-12)
    # the price metrics are on: the reference's input gap to itself is exactly 0
    ref = doc["points"][1]["controllers"]["true model"]
    assert ref["mean_input_gap"] == {"0.1": 0.0, "0.5": 0.0, "0.9": 0.0}
    assert ref["settle_time_excess"]["0.5"] == 0.0
    assert doc["points"][1]["controllers"]["GP-robust"]["mean_input_gap"]["0.9"] >= 0.0
    fig = plot_price(doc)
    fig.savefig(tmp_path / "price.png")
    assert (tmp_path / "price.png").stat().st_size > 10_000


def test_settle_time_and_input_gap_against_a_simulated_history():
    # The running statistics of the Monte Carlo loop against the full history of
    # ss.simulate (the same closed loop with the trajectory recorder), recomputed in NumPy:
    # settle time from V(x_k), and the input gap from the reference controller evaluated at
    # every recorded state.
    import jax
    import jax.numpy as jnp

    import safestab as ss
    from safestab.montecarlo import trial_function
    from safestab.montecarlo.loop import SETTLE_FRACTION

    plant = ss.ControlAffineSystem(lambda x: jnp.array([x[1], 0.5 * x[1]]),
                                   lambda x: jnp.array([[0.0], [1.0]]), 2)  # fmt: skip
    clf = ss.CLF(lambda x: x[0] ** 2 + x[0] * x[1] + x[1] ** 2, lam=1.0)
    cbf = ss.CBF(lambda x: 4.0 - x[0] - x[1], beta=1.0)  # the input moves h (d = -1)
    ctrl = ss.UniversalController(
        plant, clf, cbf, kappa=0.5, rho=0.1, phi=1.0, varphi=1.0, slack_weight=10.0
    )
    other = ss.ControlAffineSystem(lambda x: jnp.array([x[1], 1.0 * x[1]]),
                                   lambda x: jnp.array([[0.0], [1.0]]), 2)  # fmt: skip
    ref = ss.UniversalController(other, clf, cbf, kappa=0.5, rho=0.1, phi=1.0, varphi=1.0,
                                 slack_weight=10.0)  # fmt: skip
    n_steps, dt, x0 = 1000, 0.01, jnp.array([2.0, -1.0])
    run = trial_function([ctrl], plant=plant, n_steps=n_steps, dt=dt, reference=ref)
    rec = jax.jit(run)(x0, None)
    traj = ss.simulate(ctrl, x0, t_final=n_steps * dt, dt=dt)
    v = np.asarray(traj.V)
    assert v.shape == (n_steps + 1,)
    unsettled = np.flatnonzero(v > SETTLE_FRACTION * v[0])
    expected = (n_steps if unsettled[-1] == n_steps else unsettled[-1] + 1) * dt
    assert float(rec["settle_time"][0]) == pytest.approx(expected, abs=1e-12)
    assert 0 < expected < n_steps * dt  # the example settles inside the horizon
    u_ref = np.array([np.asarray(ref.step_fn(x).u) for x in np.asarray(traj.x)[:-1]])
    gap = np.mean(np.max(np.abs(np.asarray(traj.u)[:n_steps] - u_ref), axis=1))
    assert float(rec["mean_input_gap"][0]) == pytest.approx(gap, rel=1e-9)
    assert gap > 1e-3  # the reference's model differs: so do the inputs
    # without a reference, both are -1
    plain = jax.jit(trial_function([ctrl], plant=plant, n_steps=n_steps, dt=dt))(x0, None)
    assert float(plain["settle_time"][0]) == -1.0 and float(plain["mean_input_gap"][0]) == -1.0


def test_price_metrics_is_a_checked_boolean():
    from safestab.errors import ScenarioError
    from safestab.scenarios import MonteCarloSpec

    assert MonteCarloSpec().price_metrics is False
    assert MonteCarloSpec(price_metrics=True).price_metrics is True
    with pytest.raises(ScenarioError, match="price_metrics must be true or false, got 1"):
        MonteCarloSpec(price_metrics=1)
