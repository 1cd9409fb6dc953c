"""The swarm scenario: pair barriers by hand and autodiff, the filters' claims, the command."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from safestab.cli import app
from safestab.errors import ScenarioError
from safestab.formulas import MultiStatus
from safestab.scenarios.swarm import SwarmScenario, pair_terms, simulate_swarm
from safestab.scenarios.swarm_study import run_swarm_study

SMALL = SwarmScenario(n_robots=6, arena_radius=2.0, t_final=8.0, dt=0.04)


def test_pair_terms_are_the_gradients_of_the_pair_barriers():
    pos = jnp.asarray(np.random.default_rng(0).uniform(-2, 2, (5, 2)))
    h, c, d = pair_terms(pos, beta=2.0, safety_distance=0.5)
    i, j = np.triu_indices(5, 1)

    def barriers(flat):
        p = flat.reshape(5, 2)
        return jnp.sum((p[i] - p[j]) ** 2, -1) - 0.25

    assert np.allclose(np.asarray(h), np.asarray(barriers(pos.reshape(-1))), rtol=1e-15)
    assert np.allclose(np.asarray(c), 2.0 * np.asarray(h), rtol=1e-15)
    jac = jax.jacobian(barriers)(pos.reshape(-1))
    assert np.allclose(np.asarray(d), np.asarray(jac), rtol=1e-14, atol=1e-14)


def test_filters_keep_every_pair_apart_where_the_nominal_swarm_collides():
    study = run_swarm_study(SMALL)
    doc = study.metrics_document()
    assert doc["status"] == "ok"
    for mode in ("centralized", "decentralized"):
        run = doc["runs"][mode]
        # the exact barrier condition with Euler steps of an integrator: each pair keeps
        # h >= 0 up to the discretisation of the continuous condition (dt |u|^2 terms)
        assert run["min_distance_m"] >= SMALL.safety_distance * (1 - 1e-3), mode
        assert set(run["solver_statuses"]) == {"SOLVED"}, mode
        assert run["max_abs_input_mps"] <= SMALL.speed_limit
    assert doc["runs"]["unfiltered"]["steps_below_safety_distance"] > 0
    assert doc["runs"]["centralized"]["arrival_time_s"] is not None


def test_centralized_inputs_match_quadprog_along_the_run():
    quadprog = pytest.importorskip("quadprog")
    run = simulate_swarm(SMALL, "centralized")
    m = 2 * SMALL.n_robots
    for k in range(0, len(run.u), 20):
        _, c, d = (np.array(v) for v in pair_terms(run.p[k], SMALL.beta, SMALL.safety_distance))
        C = np.concatenate([d, -np.eye(m), np.eye(m)]).T  # C' u >= b: barriers, then limits
        b = np.concatenate([-c, np.full(2 * m, -SMALL.speed_limit)])
        ref = quadprog.solve_qp(np.eye(m), np.array(run.u_nom[k]).reshape(-1), C, b, 0)[0]
        assert np.max(np.abs(run.u[k].reshape(-1) - ref)) <= 1e-10
        assert np.all(run.status[k] == MultiStatus.SOLVED)


def test_bad_parameters_are_named():
    with pytest.raises(ScenarioError, match=r"swarm.n_robots must be an integer in \[2, 200\]"):
        SwarmScenario(n_robots=1)
    with pytest.raises(ScenarioError, match=r"swarm.seed must be an integer in \[0, "):
        SMALL.replace(seed=-1)  # replace() checks like the file
    with pytest.raises(ScenarioError, match="swarm.t_final / swarm.dt must give between 1 and"):
        SMALL.replace(t_final=0.001)
    with pytest.raises(ScenarioError, match="not more than the safety distance"):
        SwarmScenario(n_robots=40, arena_radius=1.0)
    with pytest.raises(ScenarioError, match="unknown parameter"):
        SMALL.replace(robots=3)
    with pytest.raises(ScenarioError, match="mode must be"):
        simulate_swarm(SMALL, "central")


def test_command_writes_the_figure_and_metrics(tmp_path):
    out = tmp_path / "out"
    res = CliRunner().invoke(
        app, ["run", "--scenario", "swarm", "--t-final", "1", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "swarm_swarm.pdf", "swarm_swarm.png", "swarm_swarm_metrics.json", "swarm_swarm_run.json"
    ]  # fmt: skip
    doc = json.loads((out / "swarm_swarm_metrics.json").read_text())
    assert doc["settings"]["t_final"] == 1.0
    bad = CliRunner().invoke(
        app, ["run", "--scenario", "swarm", "--set", "a.b=1", "--out", str(tmp_path / "x")]
    )
    assert bad.exit_code == 2
    assert "unknown" in bad.output and "'a'" in bad.output, bad.output
    bad = CliRunner().invoke(
        app, ["run", "--scenario", "swarm", "--n-samples", "50", "--out", str(tmp_path / "x")]
    )
    assert bad.exit_code == 2
    assert "a swarm scenario has no n_samples to override" in bad.output, bad.output
    for args in (["--seed", "-1"], ["--set", "swarm.t_final=0.001"]):
        bad = CliRunner().invoke(
            app, ["run", "--scenario", "swarm", *args, "--out", str(tmp_path / "x")]
        )
        assert bad.exit_code == 2, bad.output
        assert "swarm.seed must be" in bad.output or "swarm.t_final / swarm.dt" in bad.output
    assert not (tmp_path / "x").exists()  # refused before any work


def test_the_old_mode_name_nominal_is_read_for_one_release_as_unfiltered():
    from safestab.scenarios.swarm import MODES, UNFILTERED, check_mode

    assert UNFILTERED in MODES and "nominal" not in MODES
    old = "swarm mode 'nominal' is deprecated; use 'unfiltered'"
    with pytest.warns(DeprecationWarning, match=old):
        assert check_mode("nominal") == UNFILTERED
    with pytest.raises(ScenarioError, match="mode must be one of"):
        check_mode("unfilterd")
