import pytest

from safestab.errors import ScenarioError
from safestab.scenarios import MonteCarloSpec, load_scenario

STRESS = load_scenario("stress")


def _write(tmp_path, table: str):
    from importlib import resources

    base = resources.files("safestab.scenarios").joinpath("stress.toml").read_text()
    base = base.split("\n[montecarlo]")[0]  # the preset without its own table
    path = tmp_path / "s.toml"
    path.write_text(base + "\n" + table)
    return path


def test_presets_carry_a_checked_table():
    for name in ("paper", "stress", "stress-ood"):
        spec = load_scenario(name).montecarlo
        assert isinstance(spec, MonteCarloSpec)
        assert spec.initial_distribution == "box" and spec.lead_kind == "random"


def test_absent_table_is_none_and_empty_table_takes_defaults(tmp_path):
    assert load_scenario(_write(tmp_path, "")).montecarlo is None
    assert load_scenario(_write(tmp_path, "[montecarlo]\n")).montecarlo == MonteCarloSpec()


def test_values_are_read(tmp_path):
    spec = load_scenario(
        _write(
            tmp_path,
            """
[montecarlo]
trials = 12
controllers = ["GP mean", "true model"]
[montecarlo.initial]
distribution = "normal"
mean = [18.0, 14.0, 60.0]
std = [1.0, 0.0, 5.0]
[montecarlo.lead]
kind = "random"
segments = 3
""",
        )
    ).montecarlo
    assert spec.trials == 12 and spec.controllers == ("GP mean", "true model")
    assert spec.initial_mean == (18.0, 14.0, 60.0) and spec.lead_segments == 3


@pytest.mark.parametrize(
    "table, match",
    [
        ("[montecarlo]\ntrials = 0", r"montecarlo.trials must be an integer in \[1, "),
        ("[montecarlo]\ntrials = 1.5", r"montecarlo.trials must be an integer"),
        ("[montecarlo]\nbogus = 1", r"unknown key 'bogus' in \[montecarlo\]"),
        ("[montecarlo.lead]\nbogus = 1", r"unknown key 'bogus' in \[montecarlo.lead\]"),
        ("[montecarlo]\nlead = 3", r"montecarlo.lead must be a table"),
        ("[montecarlo]\ncontrollers = []", r"montecarlo.controllers must be a non-empty"),
        ("[montecarlo]\ncontrollers = ['x']", r"montecarlo.controllers\[0\] must be one of"),
        ("[montecarlo]\ncontrollers = ['GP mean', 'GP mean']", r"a name appears twice"),
        ("[montecarlo]\ndelta = 1.0", r"montecarlo.delta must be a finite number in"),
        ("[montecarlo]\ngp = 'sparse'", r"montecarlo.gp must be one of 'fast', 'exact'"),
        ("[montecarlo.initial]\ndistribution = 'box'", r"initial.low is required"),
        ("[montecarlo.initial]\ndistribution = 'normal'\nmean = [1.0, 2.0, 3.0]",
         r"initial.std is required"),
        ("[montecarlo.initial]\ndistribution = 'box'\nlow = [1.0, 2.0, 3.0]\n"
         "high = [0.0, 2.0, 3.0]", r"initial.low\[0\] must be <= montecarlo.initial.high\[0\]"),
        ("[montecarlo.initial]\nlow = [1.0, 2.0]", r"initial.low must be an array of 3"),
        ("[montecarlo.initial]\nstd = [1.0, -2.0, 0.0]", r"initial.std must be an array of 3 "
         r"finite numbers >= 0"),
        ("[montecarlo.lead]\nduration_min = 9.0\nduration_max = 3.0",
         r"lead.duration_min must be <= montecarlo.lead.duration_max"),
        ("[montecarlo.lead]\ndecel_max = -0.1", r"montecarlo.lead.decel_max must be a finite"),
    ],
)  # fmt: skip
def test_bad_tables_name_the_key(tmp_path, table, match):
    with pytest.raises(ScenarioError, match=match):
        load_scenario(_write(tmp_path, table))


def test_top_level_scalar_is_refused(tmp_path):
    path = _write(tmp_path, "")
    path.write_text("montecarlo = 3\n" + path.read_text())
    with pytest.raises(ScenarioError, match=r"montecarlo must be a table, got 3"):
        load_scenario(path)


def test_spec_checks_itself():
    with pytest.raises(ScenarioError, match=r"montecarlo.chunk_size must be an integer"):
        MonteCarloSpec(chunk_size=0)
    with pytest.raises(ScenarioError, match=r"montecarlo must be a MonteCarloSpec or None"):
        STRESS.replace(montecarlo={"trials": 3})
