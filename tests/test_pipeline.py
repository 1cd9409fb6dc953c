"""The study pipeline and its kinds: loading by kind, overrides, the shared learning steps,
outputs."""

import dataclasses
import json

import numpy as np
import pytest

from safestab.errors import ScenarioError
from safestab.scenarios import KINDS, kinds, load, pipeline, scenario_kind
from safestab.scenarios.swarm import SwarmScenario, load_swarm_scenario
from safestab.scenarios.swarm_study import MODES


def test_every_kind_is_a_study_whose_presets_load_as_its_scenario():
    studies = kinds.studies()
    assert tuple(studies) == KINDS
    for kind, study in studies.items():
        assert study.kind == kind and study.presets
        for preset in study.presets:
            sc = load(preset)
            assert isinstance(sc, study.scenario_type)
            assert kinds.study_of(sc) is study and scenario_kind(preset) == kind
    # the swarm preset file holds the dataclass's defaults
    assert load("swarm") == SwarmScenario()
    with pytest.raises(ScenarioError, match="scenario must be one of .* got int"):
        kinds.study_of(3)


def test_a_file_is_loaded_by_its_kind_key(tmp_path):
    text = (
        'kind = "swarm"\n[swarm]\nn_robots = 4\narena_radius = 2.0\nsafety_distance = 0.5\n'
        "speed_limit = 1.0\ngain = 1.0\nbeta = 2.0\nt_final = 1.0\ndt = 0.05\n"
        "start_jitter = 0.0\ngoal_tolerance = 0.05\nseed = 7\n"
    )
    path = tmp_path / "four.toml"
    path.write_text(text)
    sc = load(path)
    assert sc == SwarmScenario(name="four", n_robots=4, arena_radius=2.0, safety_distance=0.5,
                               t_final=1.0, dt=0.05, start_jitter=0.0, seed=7)  # fmt: skip
    # an override is checked like the file, and names the key
    with pytest.raises(ScenarioError, match=r"swarm.dt must be a finite number in .* got -1"):
        load(path, overrides={"swarm.dt": -1})
    # without the kind key a file is an ACC file, whose schema has no [swarm] table
    path.write_text(text.replace('kind = "swarm"\n', ""))
    with pytest.raises(ScenarioError, match="unknown"):
        load(path)
    path.write_text(text.replace('"swarm"', '"flock"', 1))
    with pytest.raises(ScenarioError, match="kind must be one of 'acc', 'obstacle', 'swarm'"):
        load(path)
    path.write_text(text + "[montecarlo]\ntrials = 3\n")
    with pytest.raises(ScenarioError, match="has no \\[montecarlo\\] table"):
        load_swarm_scenario(path)
    path.write_text(text.replace("seed = 7", ""))
    with pytest.raises(ScenarioError, match="swarm.seed"):
        load(path)


def test_overrides_name_the_field_a_kind_does_not_have():
    swarm = load("swarm")
    assert kinds.with_overrides(swarm, seed=None, n_samples=None) is swarm
    assert kinds.with_overrides(swarm, seed=3).seed == 3
    with pytest.raises(ScenarioError, match="a swarm scenario has no n_samples to override"):
        kinds.with_overrides(swarm, n_samples=50)
    paper = load("paper")
    assert kinds.with_overrides(paper, n_samples=50, t_final=2.0).n_samples == 50
    with pytest.raises(ScenarioError, match="learning.n_samples"):
        kinds.with_overrides(paper, n_samples=1)  # checked like the file


def test_study_data_are_the_first_rows_of_one_collected_stream():
    sc = load("obstacle").replace(n_samples=40)
    n_test = pipeline.held_out_rows(40)
    assert n_test == 50 and pipeline.held_out_rows(400) == 100
    train, held_out = pipeline.collect_study_data(sc)
    whole = sc.trial_study().collect(40 + 2 * n_test, sc.seed)  # a longer stream, same start
    np.testing.assert_array_equal(train.x, whole.x[:40])
    np.testing.assert_array_equal(train.y, whole.y[:40])
    np.testing.assert_array_equal(held_out.x, whole.x[40 : 40 + n_test])
    # overrides of the seed and Q
    train2, _ = pipeline.collect_study_data(sc, seed=sc.seed + 1, n_samples=30)
    assert len(train2) == 30 and not np.array_equal(train2.x, train.x[:30])


def test_run_writes_every_output_and_a_record_naming_them(tmp_path):
    sc = dataclasses.replace(
        load("swarm"), name="small", n_robots=4, arena_radius=2.0, t_final=0.5, dt=0.05
    )
    reports = []
    done = kinds.run(
        sc, tmp_path / "out", progress=lambda msg, frac: reports.append(frac), command="test"
    )
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == sorted(p.name for p in done.written)
    assert names == ["swarm_small.pdf", "swarm_small.png", "swarm_small_metrics.json",
                     "swarm_small_run.json"]  # fmt: skip
    record = json.loads((tmp_path / "out" / "swarm_small_run.json").read_text())
    assert record["command"] == "test" and record["files"] == names and record["seed"] == 0
    metrics = json.loads((tmp_path / "out" / "swarm_small_metrics.json").read_text())
    assert metrics == json.loads(json.dumps(done.document))
    done.result.write_metrics(tmp_path / "again.json")  # every result writes its document
    assert json.loads((tmp_path / "again.json").read_text()) == metrics
    assert reports[-1] == 1.0 and reports == sorted(reports)
    summary = done.summary()
    assert [row[0] for row in summary.rows] == list(MODES)
    assert all(len(row) == len(summary.columns) for row in summary.rows)
    assert pipeline.other_runs(tmp_path / "out", done.written[-1]) is None
    # a second run in the same folder names the first
    again = kinds.run(sc.replace(name="again"), tmp_path / "out", command="test")
    note = pipeline.other_runs(tmp_path / "out", again.written[-1])
    assert note is not None and "1 other run(s): swarm_small" in note
