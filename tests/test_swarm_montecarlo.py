"""The swarm's Monte Carlo: the exact distance between samples, trial seeds, the CLI."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from safestab.cli import app
from safestab.errors import ParameterError, ScenarioError
from safestab.formulas import MultiStatus
from safestab.scenarios import kinds
from safestab.scenarios.pipeline import MonteCarloOptions
from safestab.scenarios.swarm import SwarmScenario, simulate_swarm
from safestab.scenarios.swarm_montecarlo import (
    guarantee,
    least_distance_over_hold,
    metrics_document,
    run_swarm_montecarlo,
    trial_seed,
)

#: Four robots for two seconds: a swap that the unfiltered swarm does not finish safely.
SMALL = SwarmScenario(name="small", n_robots=4, arena_radius=1.2, t_final=2.0, dt=0.02)

SMALL_TOML = """kind = "swarm"
name = "tiny"

[swarm]
n_robots = 4
arena_radius = 1.2
safety_distance = 0.6
speed_limit = 1.0
gain = 1.0
beta = 2.0
t_final = 1.0
dt = 0.02
start_jitter = 0.02
goal_tolerance = 0.05
seed = 0
"""


def test_least_distance_over_hold_against_dense_sampling():
    rng = np.random.default_rng(0)
    n, dt = 2000, 0.3
    d0 = rng.normal(size=(n, 2))
    dv = rng.normal(size=(n, 2)) * rng.choice([0.0, 0.1, 1.0, 10.0], size=(n, 1))
    exact = np.asarray(least_distance_over_hold(d0, dv, dt))
    s = np.linspace(0.0, dt, 20_001)
    dense = np.linalg.norm(d0[:, None, :] + s[None, :, None] * dv[:, None, :], axis=-1).min(1)
    # the exact minimum is attained at some s, so it is at most the grid's minimum, and the
    # grid's minimum is within half a grid step of travel of it: |dv| (dt / 20,000) / 2
    step = np.linalg.norm(dv, axis=-1) * dt / 20_000 / 2
    assert np.all(exact <= dense + 1e-15)
    assert np.all(dense - exact <= step + 1e-12)
    # the minimum is inside the hold for some pairs (else the test would only see endpoints)
    inside = dense < np.minimum(np.linalg.norm(d0, axis=-1), np.linalg.norm(d0 + dt * dv, axis=-1))
    assert inside.sum() > 100
    # a pair that does not move relative to the other: its distance
    assert float(least_distance_over_hold(np.array([3.0, 4.0]), np.zeros(2), dt)) == 5.0
    # a head-on pass within the hold: distance 0
    assert float(least_distance_over_hold(np.array([1.0, 0.0]), np.array([-10.0, 0.0]), dt)) == 0


def test_trial_seed_depends_on_seed_and_index_only():
    assert trial_seed(3, 7) == trial_seed(3, 7)
    assert len({trial_seed(3, i) for i in range(50)} | {trial_seed(4, 0)}) == 51
    assert all(0 <= trial_seed(2**32 - 1, i) <= 2**32 - 1 for i in range(5))


@pytest.fixture(scope="module")
def five_trials():
    return run_swarm_montecarlo(SMALL, trials=5, seed=1, chunk_size=2, workers=2)


def test_a_trial_does_not_depend_on_chunks_trials_or_workers(five_trials):
    other = run_swarm_montecarlo(SMALL, trials=3, seed=1, chunk_size=3, workers=1)
    for key, value in other.records.items():
        np.testing.assert_array_equal(value, five_trials.records[key][:3], err_msg=key)
    assert five_trials.records["min_distance"].shape == (5, 3)
    assert not np.array_equal(  # another seed: other jitter
        run_swarm_montecarlo(SMALL, trials=1, seed=2, modes=("unfiltered",)).records[
            "min_distance"
        ],
        five_trials.records["min_distance"][:1, 2:],
    )


@pytest.mark.parametrize("index", [0, 4])
def test_a_trial_equals_simulate_swarm_from_its_seed(five_trials, index):
    """Trial i's records against a full-history run of the scenario with trial i's seed,
    reduced here with NumPy (and the between-sample minimum by dense sampling)."""
    sc = SMALL.replace(seed=trial_seed(1, index))
    rec = {k: v[index] for k, v in five_trials.records.items()}
    i, j = np.triu_indices(sc.n_robots, 1)
    for c, mode in enumerate(five_trials.modes):
        run = simulate_swarm(sc, mode)
        dist = run.min_distance()
        goal = sc.starts_and_goals()[1]
        err = np.max(np.linalg.norm(run.p - goal, axis=-1), axis=-1)
        arrived = np.flatnonzero(err <= sc.goal_tolerance)
        s = np.linspace(0.0, sc.dt, 401)
        d0, dv = run.p[:-1, i] - run.p[:-1, j], run.u[:, i] - run.u[:, j]  # (K, P, 2)
        hold = np.linalg.norm(d0[..., None, :] + s[:, None] * dv[..., None, :], axis=-1)
        hold = hold.min(axis=(1, 2))  # (K,)
        nominal = np.clip(run.u_nom, -sc.speed_limit, sc.speed_limit)
        change = np.linalg.norm(run.u - nominal, axis=-1)
        # 1e-12: the batched loop and the single run are the same program under vmap (their
        # roundings may differ in the last bits)
        close = dict(rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(rec["min_distance_at_samples"][c], dist.min(), **close)
        # dense sampling: within half a grid step of travel (speeds <= 2 sqrt(2) m/s)
        # (the exact minimum is of the batched trial's path, the samples of the single run's:
        # the same to the rounding allowed above)
        gap = hold.min() - rec["min_distance"][c]
        assert -1e-12 <= gap <= 2 * np.sqrt(2) * sc.dt / 800 + 1e-12
        assert rec["samples_below"][c] == np.sum(dist < sc.safety_distance)
        assert rec["holds_below"][c] == np.sum(hold < sc.safety_distance - 1e-9)
        expected = run.t[arrived[0]] if arrived.size else np.nan
        np.testing.assert_allclose(rec["arrival_time"][c], expected, **close)
        np.testing.assert_allclose(rec["final_max_goal_error"][c], err[-1], **close)
        np.testing.assert_allclose(rec["mean_input_change"][c], change.mean(), **close)
        counts = [np.sum(run.status == s) for s in MultiStatus]
        np.testing.assert_array_equal(rec["statuses"][c], counts)
    # the unfiltered swap comes closer than the safety distance, the filters do not
    assert rec["samples_below"][2] > 0 and rec["min_distance"][2] < SMALL.safety_distance
    assert np.all(rec["min_distance"][:2] >= SMALL.safety_distance)


def test_document_rates_worst_trial_and_guarantee(five_trials):
    doc = metrics_document(five_trials)
    assert doc["status"] == "ok"
    json.dumps(doc, allow_nan=False)
    nominal = doc["summary"]["modes"]["unfiltered"]
    least = five_trials.records["min_distance"][:, 2]
    assert nominal["safe"]["count"] == int(np.sum(least >= SMALL.safety_distance))
    worst = nominal["worst_trial"]
    assert worst["index"] == int(np.argmin(least))
    assert worst["seed"] == trial_seed(1, worst["index"])
    lo, hi = doc["summary"]["modes"]["centralized"]["safe"]["ci95"]
    assert hi == 1.0 and 0.47 < lo < 0.48  # Clopper-Pearson for 5 of 5: 0.025^(1/5) = 0.478
    assert nominal["solver_statuses"] == {}
    assert doc["summary"]["modes"]["centralized"]["solver_statuses"] == {"SOLVED": 5 * 100 * 4}
    assert "here beta dt = 0.04" in doc["summary"]["guarantee"]["over_the_hold"]
    slow = guarantee(SMALL.replace(beta=100.0))["over_the_hold"]
    assert "beta dt = 2 > 1, so nothing is promised" in slow


def test_bad_arguments_raise():
    with pytest.raises(ParameterError, match="trials must be an integer >= 1, got 0"):
        run_swarm_montecarlo(SMALL, trials=0)
    with pytest.raises(ScenarioError, match="modes must be one of"):
        run_swarm_montecarlo(SMALL, modes=("fast",))
    with pytest.raises(ParameterError, match="modes must be distinct"):
        run_swarm_montecarlo(SMALL, modes=("unfiltered", "unfiltered"))
    plan = kinds.plan_mc(SMALL, MonteCarloOptions(controllers=("unfiltered",), trials=2))
    assert plan.checked.modes == ("unfiltered",) and plan.checked.trials == 2


def test_a_kind_without_monte_carlo_is_refused_by_name(monkeypatch):
    every = kinds.studies()
    bare = {k: dataclasses.replace(s, montecarlo=None) if k == "swarm" else s
            for k, s in every.items()}  # fmt: skip
    monkeypatch.setattr(kinds, "studies", lambda: bare)
    expected = (r"--scenario must be a scenario of a kind with a Monte Carlo \('acc', "
                r"'obstacle'\), got 'small' of kind 'swarm'")  # fmt: skip
    with pytest.raises(ScenarioError, match=expected):
        kinds.plan_mc(SMALL, MonteCarloOptions(), name="--scenario")


def _strict(text: str):
    def refuse(token):
        raise AssertionError(f"non-strict JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def test_cli_mc_swarm_writes_the_four_files(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(SMALL_TOML)
    out = tmp_path / "out"
    args = ["mc", "--scenario", str(path), "--trials", "3", "--chunk-size", "2",
            "--controllers", "centralized,unfiltered", "--seed", "5",
            "--out", str(out)]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    names = {"mc_tiny.png", "mc_tiny_metrics.json", "mc_tiny_trials.npz", "mc_tiny_run.json"}
    assert {p.name for p in out.iterdir()} == names
    doc = _strict((out / "mc_tiny_metrics.json").read_text())
    assert doc["kind"] == "swarm" and doc["settings"]["trials"] == 3
    assert list(doc["summary"]["modes"]) == ["centralized", "unfiltered"]
    assert set(_strict((out / "mc_tiny_run.json").read_text())["files"]) == names
    with np.load(out / "mc_tiny_trials.npz") as z:
        assert z["min_distance"].shape == (3, 2) and list(z["modes"]) == [
            "centralized",
            "unfiltered",
        ]
        assert z["trial_seed"][2] == trial_seed(5, 2)
    assert "Monte Carlo 'tiny': 3 trials" in res.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--controllers", "centralized,GP mean"],
         r"--controllers\[1\] must be one of the swarm's modes 'centralized', 'decentralized', "
         r"'unfiltered', got 'GP mean'"),
        (["--controllers", "unfiltered,unfiltered"], "--controllers must be distinct swarm modes"),
        (["--datasets", "2"], "--datasets does not apply to the swarm"),
        (["--backend", "ray"], "--backend must be 'local' for the swarm"),
        (["--trials", "0"], "--trials must be >= 1, got 0"),
    ],
)  # fmt: skip
def test_cli_mc_swarm_refuses_bad_options(tmp_path, args, message):
    import re

    res = CliRunner().invoke(
        app, ["mc", "--scenario", "swarm", *args, "--out", str(tmp_path / "o")]
    )
    assert res.exit_code == 2, res.output
    assert re.search(message, " ".join(res.output.split())), res.output
    assert not (tmp_path / "o").exists()  # refused before any work


def test_a_least_distance_at_the_safety_distance_to_rounding_is_safe_and_counted_apart(
    five_trials,
):
    # a filter's active barrier holds a pair at the safety distance; the count must not turn
    # on which side of it rounding puts the record
    d = SMALL.safety_distance
    rec = {k: v.copy() for k, v in five_trials.records.items()}
    rec["min_distance"][:, 0] = [d - 1e-12, d + 1e-12, d, d - 1e-6, d + 1e-3]
    doc = metrics_document(dataclasses.replace(five_trials, records=rec))
    centralized = doc["summary"]["modes"]["centralized"]
    assert centralized["safe"]["count"] == 4  # only d - 1e-6 is below, beyond rounding
    assert centralized["at_safety_distance"] == 3
    assert doc["summary"]["rounding_band_m"] == 1e-9
