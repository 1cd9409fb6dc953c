"""The ACC Monte Carlo study end to end on tiny settings: determinism, Ray, the simulator."""

import json

import jax
import numpy as np
import pytest

import safestab as ss
from safestab.errors import ParameterError
from safestab.learning import BatchedUncertainty, condition, conformal_beta
from safestab.learning.fast import STD_RATIO_WARN
from safestab.montecarlo import (
    RECORD_FIELDS,
    metrics_document,
    run_montecarlo,
    start_ray,
    summarize,
    trial_function,
)
from safestab.montecarlo.report import study_settings
from safestab.montecarlo.trials import calibration_draw, dataset_draw, fit_dataset, run_chunk
from safestab.scenarios import load_scenario
from safestab.scenarios.trial_studies import lead_acceleration

# tiny: 60 GP samples, 0.3 s horizon (30 steps), two controllers; the point is the machinery
SC = load_scenario("stress").replace(n_samples=60, hyper_subset=30, t_final=0.3)
SPEC = SC.montecarlo.replace(controllers=("mismatched model", "GP-robust"), chunk_size=5)
STUDY = SC.trial_study(SPEC)
N, K = 10, 2


pytestmark = pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # Ray starts processes


@pytest.fixture(scope="module")
def local_run():
    return run_montecarlo(SC, spec=SPEC, trials=N, datasets=K, seed=3)


def _same(a, b):
    assert set(a.records) == set(RECORD_FIELDS)
    for key in RECORD_FIELDS:
        assert np.array_equal(a.records[key], b.records[key], equal_nan=True), key


def test_records_have_one_row_per_trial(local_run):
    for key in RECORD_FIELDS:
        assert local_run.records[key].shape == (N, 2)
    assert np.array_equal(local_run.dataset_index, np.arange(N) % K)
    assert np.all(local_run.records["lemma2_violations"][:, 0] == -1)  # no GP
    assert np.all(local_run.records["lemma2_violations"][:, 1] >= 0)


@pytest.mark.slow  # one more compilation (the chunk shape); the toy covers chunking quickly
def test_identical_for_any_chunk_size(local_run):
    # the same data sets, the trials of data set 0 in chunks of 2 instead of 5
    spec = SPEC.replace(chunk_size=2)
    idx = np.arange(0, N, K)
    rows = [run_chunk(SC.trial_study(spec), local_run.datasets[0], 3, idx[i : i + 2], pad_to=2)
            for i in range(0, idx.size, 2)]  # fmt: skip
    for key in RECORD_FIELDS:
        got = np.concatenate([r[key] for r in rows])
        assert np.array_equal(got, local_run.records[key][idx], equal_nan=True), key


@pytest.fixture(scope="module")
def local_run_3n():
    """3N trials: six chunks of 5 (the compiled shape of local_run), three per data set."""
    return run_montecarlo(SC, spec=SPEC, trials=3 * N, datasets=K, seed=3, workers=2)


def test_identical_for_any_number_of_workers(local_run, local_run_3n):
    # six chunks: run two at a time in threads after the compilation, or in turn; the same
    # bits either way
    _same(local_run_3n, run_montecarlo(SC, spec=SPEC, trials=3 * N, datasets=K, seed=3,
                                       workers=1))  # fmt: skip
    # and the first N trials' records equal local_run's where the chunks coincide (data set
    # j's trials are j, j + K, ...; with 3N trials its first chunk holds the same 5 trials)
    for key in RECORD_FIELDS:
        assert np.array_equal(local_run_3n.records[key][:N], local_run.records[key],
                              equal_nan=True)  # fmt: skip


def test_trial_draws_depend_on_seed_and_index_only():
    x_all, p_all = STUDY.draw_trials(7, np.arange(20))
    x_some, p_some = STUDY.draw_trials(7, np.array([13, 2]))
    assert np.array_equal(np.asarray(x_all)[[13, 2]], np.asarray(x_some))
    assert np.array_equal(np.asarray(p_all["acc"])[[13, 2]], np.asarray(p_some["acc"]))
    x_other, _ = STUDY.draw_trials(8, np.arange(20))
    assert not np.array_equal(np.asarray(x_all), np.asarray(x_other))
    lo, hi = np.array(SPEC.initial_low), np.array(SPEC.initial_high)
    assert np.all((np.asarray(x_all) >= lo) & (np.asarray(x_all) <= hi))
    g = SC.gravity
    acc = np.asarray(p_all["acc"])
    assert np.all((acc >= -SPEC.lead_decel_max * g) & (acc <= SPEC.lead_accel_max * g))


def test_lead_acceleration_follows_the_segment_convention():
    """Segments ``t <= ends[0]``, then ``(ends[j-1], ends[j]]``, 0 after the last, against a
    direct loop over the segments, at the boundaries and between them; a stopped lead does not
    brake further."""
    ends = np.array([2.0, 3.5, 7.0])
    acc = np.array([-1.5, 0.75, 2.0])
    params = {"ends": jax.numpy.asarray(ends), "acc": jax.numpy.asarray(acc)}
    moving = np.array([10.0, 5.0, 30.0])
    times = [0.0, 1.0, 2.0, np.nextafter(2.0, 3.0), 3.5, 5.0, 7.0, np.nextafter(7.0, 8.0), 9.0]
    for t in times:
        expected = 0.0
        for j in range(len(ends) - 1, -1, -1):
            if t <= ends[j] and (j == 0 or t > ends[j - 1]):
                expected = acc[j]
        got = np.asarray(lead_acceleration(t, moving, params))
        np.testing.assert_array_equal(got, [0.0, expected, 0.0], err_msg=f"t = {t}")
    stopped = np.array([10.0, 0.0, 30.0])
    assert float(lead_acceleration(0.5, stopped, params)[1]) == 0.0  # would brake: held at 0
    assert float(lead_acceleration(3.0, stopped, params)[1]) == 0.75  # may accelerate


@pytest.mark.slow  # compiles a 2-controller loop and two simulations
def test_fixed_trial_reproduces_the_simulator():
    # fixed initial state and lead profile: the batched loop's min h for the mismatched
    # controller equals ss.simulate's (an independent code path) on the same closed loop
    spec = SPEC.replace(initial_distribution="fixed", lead_kind="fixed")
    sc = SC.replace(t_final=3.0)
    x0, params = sc.trial_study(spec).draw_trials(0, np.arange(1))
    clf, cbf = sc.certificates()
    p = dict(kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi,
             slack_weight=sc.slack_weight)  # fmt: skip
    ctrls = [ss.UniversalController(sc.system(w), clf, cbf, **p) for w in ("true", "nominal")]
    run = trial_function(ctrls, plant=sc.system("true"), n_steps=300, dt=sc.dt,
                         exogenous=lead_acceleration)  # fmt: skip
    rec = jax.jit(jax.vmap(run))(x0, params)
    for c, ctrl in enumerate(ctrls):
        traj = ss.simulate(ctrl, np.asarray(sc.x0), t_final=sc.t_final, dt=sc.dt,
                           plant=sc.system("true"), exogenous=sc.exogenous)  # fmt: skip
        # the same arithmetic in another order (one RK4 per step either way): rounding only
        assert float(rec["min_h"][0, c]) == pytest.approx(float(np.min(traj.h)), abs=1e-9)
        assert float(rec["final_V"][0, c]) == pytest.approx(float(traj.V[-1]), rel=1e-9)


def test_conformal_beta_is_calibrated_on_a_separate_draw(local_run):
    """Split conformal: the calibration states come from their own draw, seeded from (seed,
    data set) and disjoint from the fitting and held-out rows; the beta equals conformal_beta
    on that draw (an independent call) and the draw is reproducible."""
    sc = SC  # the data sets' collection is compiled already (local_run)
    spec = SPEC.replace(controllers=("GP-robust", "GP-robust conformal"), delta=0.05)
    hyper = local_run.datasets[0].hyper  # conditioning only, no fit
    study = sc.trial_study(spec)
    model = fit_dataset(study, 3, 1, hyper)
    cal = calibration_draw(study, 3, 1)
    assert len(np.unique(cal.trajectory)) == 100  # max(100, ceil(1 / 0.05))
    assert not np.array_equal(calibration_draw(study, 3, 0).x, cal.x)
    # no calibration state is a row of the data set (fitting or held out)
    data = dataset_draw(study, 3, 1)
    assert len(data) == sc.n_samples + max(50, sc.n_samples // 4)
    rows = {tuple(r) for r in np.round(data.x, 12)}
    assert not any(tuple(r) in rows for r in np.round(cal.x, 12))
    ref = conformal_beta(BatchedUncertainty(model.cache), cal.x, np.asarray(sc.omega(cal.x)),
                         0.05, groups=cal.trajectory)  # fmt: skip
    np.testing.assert_array_equal(model.betas["GP-robust conformal"], ref.beta)


def test_summary_and_strict_json(local_run):
    s = summarize(local_run)
    for entry in s["controllers"].values():
        lo, hi = entry["safe"]["ci95"]
        assert lo <= entry["safe"]["rate"] <= hi
    assert "lemma2_every_state" in s["controllers"]["GP-robust"]
    assert "lemma2_every_state" not in s["controllers"]["mismatched model"]
    text = json.dumps(metrics_document(local_run), allow_nan=False)
    settings = json.loads(text)["settings"]
    assert settings["trials"] == N
    # what the study learned with and how its controllers were set, from the scenario
    sc = local_run.study.scenario
    assert settings["gp_settings"] == {
        "n_samples": sc.n_samples, "kernel": sc.kernel, "hyper_subset": sc.hyper_subset,
        "gp_beta": sc.gp_beta, "input_gain": "nominal",
    }  # fmt: skip
    assert sc.input_limit is None and settings["controller_settings"]["limit_method"] is None
    # with limits, the ACC's controllers project onto them (eq. (26)), in input units (M g)
    limited = study_settings(SC.replace(input_limit=0.3).trial_study(SPEC))["controller_settings"]
    assert limited["limit_method"] == "projection"
    assert limited["u_min"] == [-0.3] and limited["u_max"] == [0.3]
    assert settings["controller_settings"]["slack_weight"] == sc.slack_weight


def test_each_data_sets_std_ratio_is_recorded_and_checked_against_the_dense_gp(local_run):
    """std_over_exact per data set: the batched cache's std over the exact GP's (a dense
    predict at every training input; Q = 60 <= FastGP's sample of 128, so the median is over
    all of them), in the metrics JSON; a ratio above STD_RATIO_WARN comes with a warning."""
    doc = json.loads(json.dumps(metrics_document(local_run), allow_nan=False))
    for model, entry in zip(local_run.datasets, doc["datasets"], strict=True):
        data_seed = int(np.random.SeedSequence([3, model.index]).generate_state(1)[0])
        data = dataset_draw(STUDY, 3, model.index)
        x, y = data.x[: SC.n_samples], data.y[: SC.n_samples]
        gp = condition(local_run.datasets[0].hyper, x, y, seed=data_seed)
        comps = list(gp.components_)
        exact = gp.predict(x, return_std=True)[1][:, comps]
        cached = np.asarray(BatchedUncertainty(model.cache).mean_std_batch(x)[1])[:, comps]
        ratio = np.median(cached / exact, axis=0)
        # the batched form changes the summation order only (docs/montecarlo.md)
        np.testing.assert_allclose(entry["std_over_exact"], ratio, rtol=1e-6)
        for j, comp in enumerate(comps):
            named = any(f"component {comp}," in w for w in entry["cache_warnings"])
            assert named == bool(ratio[j] > STD_RATIO_WARN), (model.index, comp, ratio[j])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(trials=0), r"trials must be an integer >= 1, got 0"),
        (dict(trials=2, datasets=3), r"datasets must be <= trials"),
        (dict(seed=-1), r"seed must be an integer >= 0"),
        (dict(backend="dask"), r"backend must be one of \('local', 'ray'\), got 'dask'"),
        (dict(workers=0), r"workers must be an integer >= 1 or None, got 0"),
    ],
)  # fmt: skip
def test_bad_arguments_raise_before_work(kwargs, match):
    kwargs = {"spec": SPEC, "trials": N, **kwargs}
    with pytest.raises(ParameterError, match=match):
        run_montecarlo(SC, **kwargs)


@pytest.fixture(scope="module")
def ray_session():
    # the workers share this process's compilation cache (start_ray passes it on): they load
    # the chunk loops local_run_3n compiled (a cache folder set here after JAX's first
    # compilation would not be used: JAX reads it once)
    ray = pytest.importorskip("ray")
    start_ray(num_cpus=2)
    yield ray
    ray.shutdown()


def test_a_local_cluster_gets_this_processs_caches(monkeypatch, tmp_path):
    """What start_ray gives ray.init (a stand-in Ray records it): the cache folders for a
    local cluster, ``off`` when this process has none, nothing for a cluster at an address
    or when the caller names a cache."""
    import sys
    import types

    from safestab.montecarlo import runner

    calls = []
    fake = types.SimpleNamespace(is_initialized=lambda: False,
                                 init=lambda **kwargs: calls.append(kwargs))  # fmt: skip
    monkeypatch.setitem(sys.modules, "ray", fake)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)

    def env_vars(folder, **kwargs):
        monkeypatch.setattr(runner, "compilation_cache_dir", lambda: folder)
        start_ray(**kwargs)
        return calls[-1]["runtime_env"]["env_vars"]

    monkeypatch.setattr(runner, "fit_cache_dir", lambda: tmp_path / "fits")
    env = env_vars(tmp_path)
    assert env["SAFESTAB_COMPILATION_CACHE"] == str(tmp_path)
    assert env["SAFESTAB_FIT_CACHE"] == str(tmp_path / "fits")  # as `safestab run` does
    assert env_vars(None)["SAFESTAB_COMPILATION_CACHE"] == "off"
    env = env_vars(tmp_path, address="ray://h:10001")
    assert "SAFESTAB_COMPILATION_CACHE" not in env and "SAFESTAB_FIT_CACHE" not in env
    given = {"env_vars": {"JAX_COMPILATION_CACHE_DIR": "/shared"}}
    env = env_vars(tmp_path, runtime_env=given)
    assert "SAFESTAB_COMPILATION_CACHE" not in env and env["JAX_COMPILATION_CACHE_DIR"] == "/shared"
    given = {"env_vars": {"SAFESTAB_COMPILATION_CACHE": "/shared"}}
    assert env_vars(tmp_path, runtime_env=given)["SAFESTAB_COMPILATION_CACHE"] == "/shared"


def test_ray_backend_is_identical_to_local(local_run_3n, ray_session):
    # six chunks (data set 0's three, then data set 1's). Default workers (2, the local
    # cluster's CPUs): three tasks of two chunks in threads, the middle one holding chunks of
    # both data sets; workers=1: a task per chunk. Progress is reported per task.
    for workers, step in ((None, 2), (1, 1)):
        calls: list[tuple[int, int]] = []
        run = run_montecarlo(
            SC, spec=SPEC, trials=3 * N, datasets=K, seed=3, backend="ray", workers=workers,
            progress=lambda done, total, calls=calls: calls.append((done, total)),
        )  # fmt: skip
        _same(local_run_3n, run)
        assert calls == [(done, 6) for done in range(step, 7, step)]


def test_ray_workers_beyond_a_node_raise(ray_session, tmp_path):
    with pytest.raises(ParameterError, match=r"largest node \(2\), got 3"):
        run_montecarlo(SC, spec=SPEC, trials=N, datasets=K, seed=3, backend="ray", workers=3)
    # the command line: a bad input (exit 2), found once Ray is connected, before any work
    from typer.testing import CliRunner

    from safestab.cli import app

    args = ["mc", "--backend", "ray", "--workers", "3", "--trials", "4", "--datasets", "1"]
    res = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert "workers (--workers) must be at most" in res.output
    assert not (tmp_path / "o" / "mc_stress_metrics.json").exists()


def test_cli_mc_checks_inputs_before_work(tmp_path):
    from typer.testing import CliRunner

    from safestab.cli import app

    runner = CliRunner()
    bad = [
        (["--scenario", "nope"], "is neither a preset"),
        (["--backend", "dask"], "--backend must be one of"),
        (["--trials", "0"], "--trials must be >= 1, got 0"),
        (["--workers", "0"], "--workers must be >= 1, got 0"),
        (["--chunk-size", "0"], "--chunk-size must be >= 1, got 0"),
        (["--seed", "-1"], r"--seed must be in \[0, 2\*\*32 - 1\]"),
        (["--controllers", "true model,bogus"], r"--controllers\[1\] must be one of"),
        (["--controllers", "GP mean,GP mean"], r"--controllers must be .* appears twice"),
    ]
    for args, match in bad:
        res = runner.invoke(app, ["mc", *args, "--out", str(tmp_path / "o")])
        assert res.exit_code == 2, (args, res.output)
        import re

        assert re.search(match, res.output), (args, res.output)


@pytest.mark.slow
# 60 samples keep the test short; on so few the fit rightly warns that the targets' offset
# dwarfs their spread (DataWarning); the warning is the GP's concern, tested in test_learning
@pytest.mark.filterwarnings("ignore::safestab.errors.DataWarning")
def test_cli_mc_writes_all_outputs(tmp_path):
    from typer.testing import CliRunner

    from safestab.cli import app

    text = tmp_path / "tiny.toml"
    from importlib import resources

    base = resources.files("safestab.scenarios").joinpath("stress.toml").read_text()
    # outputs are named after the scenario's name, not the file's
    base = base.replace('name = "stress"', 'name = "tiny"')
    base = (
        base.replace("n_samples = 2000", "n_samples = 60")
        .replace("hyper_subset = 500", "hyper_subset = 30")
        .replace("t_final = 60.0", "t_final = 0.3")
    )
    base = base.replace(
        'controllers = ["true model", "mismatched model", "GP mean", '
        '"GP-robust", "GP-robust Lemma 2"]',
        'controllers = ["mismatched model", "GP-robust"]',
    )
    text.write_text(base)
    out = tmp_path / "out"
    res = CliRunner().invoke(
        app,
        [
            "mc",
            "--scenario",
            str(text),
            "--trials",
            "6",
            "--datasets",
            "1",
            "--out",
            str(out),
            "--seed",
            "2",
            "--chunk-size",
            "3",
        ],
    )
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "mc_tiny_metrics.json").read_text())
    assert doc["settings"]["trials"] == 6 and doc["status"] in ("ok", "non-finite")
    with np.load(out / "mc_tiny_trials.npz") as z:
        assert z["min_h"].shape == (6, 2)
    assert (out / "mc_tiny.png").stat().st_size > 0


def test_calibration_draw_keeps_the_same_times_of_every_trajectory():
    """Thinning by position within the trajectory: 5 rows per trajectory, stride 2 keeps
    rows 0, 2 and 4 of each (thinning the concatenated rows would keep 0, 2, 4 of the first
    and 1, 3 of the second)."""
    from safestab.learning import Dataset

    class Stub:
        spec = SPEC.replace(delta=0.05)

        def calibration_shape(self):
            return 5, 2

        def collect(self, n, seed):
            t = np.tile(np.arange(5) * 0.1, n // 5)
            z = np.zeros((n, 1))
            return Dataset(x=t[:, None], u=z, xdot=z, y=z, t=t, trajectory=np.arange(n) // 5)

    cal = calibration_draw(Stub(), 0, 0)
    assert len(np.unique(cal.trajectory)) == 100
    for k in np.unique(cal.trajectory):
        np.testing.assert_allclose(cal.t[cal.trajectory == k], [0.0, 0.2, 0.4])
