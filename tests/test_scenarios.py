"""Scenario files: every key checked for type, finiteness and range when the file is loaded."""

import math
import re
from importlib import resources

import pytest

from safestab import ScenarioError
from safestab.scenarios import LIMITS, acc_study, load_scenario, trial_studies


def _paper_text():
    return resources.files("safestab.scenarios").joinpath("paper.toml").read_text()


def _load_edited(tmp_path, old, new, name="s.toml"):
    text = _paper_text()
    assert old in text, old  # the edit must apply, or the test proves nothing
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1))
    return load_scenario(path)


FINITE_POS = r"a finite number in \[1e-9, 1e9\]"
FINITE_NONNEG = r"a finite number in \[0, 1e9\]"
FINITE = r"a finite number in \[-1e9, 1e9\]"

# (old text, new text, expected message: key with table path, expected, received)
BAD_FIELDS = [
    # the reproducers of issue 8, point 6
    ("mass = 1650.0", "mass = inf", rf"vehicle\.mass must be {FINITE_POS}, got inf"),
    (
        "t_final = 80.0",
        "t_final = 1e12",
        rf"simulation\.t_final must be {FINITE_POS}, got 1000000000000\.0",
    ),
    (
        "[50.0, 0.0], [60.0, -1.0]",
        "[50.0, 0.0], [60.0, nan]",
        rf"lead\.profile\[5\]\[1\] must be {FINITE}, got nan",
    ),
    ("v_d = 22.0", "v_d = nan", rf"certificates\.v_d must be {FINITE_NONNEG}, got nan"),
    ("seed = 0", "seed = -1", r"learning\.seed must be an integer in \[0, 4294967295\], got -1"),
    (
        "n_samples = 2000",
        "n_samples = 1000000000000",
        r"learning\.n_samples must be an integer in \[10, 10000\], got 1000000000000",
    ),
    (
        "n_samples = 2000",
        "n_samples = 1e12",
        r"learning\.n_samples must be an integer in \[10, 10000\], got 1000000000000\.0",
    ),
    (
        "[drag.nominal]",
        "[drag.other]\nf0 = 1.0\n\n[drag.nominal]",
        r"unknown key 'drag\.other' in \[drag\]; expected one of nominal, true",
    ),
    (
        "input_limit = false",
        "input_limit = true",
        r"controller\.input_limit must be a finite number in \[1e-9, 1e9\] \(the limit on \|F\| "
        r"as a fraction of M g\) or false \(no limits\), got true \(a boolean\)",
    ),
    # types
    (
        "mass = 1650.0",
        'mass = "heavy"',
        rf"vehicle\.mass must be {FINITE_POS}, got 'heavy' \(a string\)",
    ),
    ("mass = 1650.0", "mass = true", r"vehicle\.mass must be .*, got true \(a boolean\)"),
    ("mass = 1650.0", "mass = 1979-05-27", r"vehicle\.mass must be .*, got .*\(a date/time\)"),
    ("mass = 1650.0", "mass = [1650.0]", r"vehicle\.mass must be .*, got \[1650\.0\] \(an array\)"),
    ("mass = 1650.0", "mass = {value = 1.0}", r"vehicle\.mass must be .*, got a table"),
    ("seed = 0", "seed = 1.0", r"learning\.seed must be an integer in \[0, 4294967295\], got 1\.0"),
    ("seed = 0", "seed = false", r"learning\.seed must be an integer .*, got false \(a boolean\)"),
    ("n_samples = 2000", "n_samples = 2000.5", r"learning\.n_samples must be an integer"),
    # finiteness and ranges
    ("mass = 1650.0", "mass = nan", rf"vehicle\.mass must be {FINITE_POS}, got nan"),
    ("mass = 1650.0", "mass = -1.0", rf"vehicle\.mass must be {FINITE_POS}, got -1\.0"),
    ("mass = 1650.0", "mass = 0", rf"vehicle\.mass must be {FINITE_POS}, got 0"),
    ("gravity = 9.81", "gravity = -inf", r"vehicle\.gravity must be .*, got -inf"),
    ("f2 = 0.25", "f2 = -0.25", rf"drag\.true\.f2 must be {FINITE_NONNEG}, got -0\.25"),
    ("f0 = 10.0", "f0 = 1e300", rf"drag\.nominal\.f0 must be {FINITE_NONNEG}, got 1e\+300"),
    ("v_f = 18.0", "v_f = -1.0", r"initial\.v_f must be .*, got -1\.0"),
    ("D = 150.0", "D = nan", r"initial\.D must be .*, got nan"),
    ("tau = 1.8", "tau = 0.0", rf"certificates\.tau must be {FINITE_POS}, got 0\.0"),
    ("lam = 4.0", "lam = inf", r"certificates\.lam must be .*, got inf"),
    ("beta = 0.5", "beta = -0.5", r"certificates\.beta must be .*, got -0\.5"),
    ("rho = 0.1", "rho = -0.1", rf"controller\.rho must be {FINITE_NONNEG}, got -0\.1"),
    ("kappa = 0.2", "kappa = nan", r"controller\.kappa must be .*, got nan"),
    ("phi = 1.0 ", "phi = -1.0 ", r"controller\.phi must be .*, got -1\.0"),
    ("varphi = 1.0", "varphi = inf", r"controller\.varphi must be .*, got inf"),
    (
        "slack_weight = 10.0",
        "slack_weight = 1e-310",
        r"controller\.slack_weight must be .*, got 1e-310",
    ),
    ("input_limit = false", "input_limit = 0.0", r"controller\.input_limit must be .*, got 0\.0"),
    ("input_limit = false", "input_limit = nan", r"controller\.input_limit must be .*, got nan"),
    (
        'input_units = "newton"',
        'input_units = "lbf"',
        r"controller\.input_units must be one of 'newton', 'normalized', got 'lbf' \(a string\)",
    ),
    (
        'kernel = "se"',
        'kernel = "rbf"',
        r"learning\.kernel must be one of 'se', 'matern52', got 'rbf'",
    ),
    ("dt = 0.01", "dt = 0.0", r"simulation\.dt must be .*, got 0\.0"),
    ("sample_rate = 10.0", "sample_rate = nan", r"learning\.sample_rate must be .*, got nan"),
    ("sample_horizon = 20.0", "sample_horizon = -20.0", r"learning\.sample_horizon must be"),
    ("noise_std = 0.001", "noise_std = -0.001", r"learning\.noise_std must be .*, got -0\.001"),
    ("gp_beta = 2.0", "gp_beta = inf", r"learning\.gp_beta must be .*, got inf"),
    ("excitation_limit = 0.3", "excitation_limit = -0.3", r"learning\.excitation_limit must be"),
    ("seed = 0", "seed = 4294967296", r"learning\.seed must be an integer .*, got 4294967296"),
    ("n_samples = 2000", "n_samples = 5", r"learning\.n_samples must be an integer .*, got 5"),
    (
        "hyper_subset = 500",
        "hyper_subset = 0",
        r"learning\.hyper_subset must be an integer .*, got 0",
    ),
    (
        'name = "paper"',
        'name = "../evil"',
        r"name must be a string of 1 to 64 letters.*, got '\.\./evil'",
    ),
    ('name = "paper"', 'name = ""', r"name must be a string .*, got ''"),
    ('name = "paper"', "name = 3", r"name must be a string .*, got 3"),
    # arrays
    (
        "x0_low = [10.0, 10.0, 20.0]",
        "x0_low = [10.0, 10.0]",
        r"learning\.x0_low must be an array of 3 finite numbers \(v_f m/s, v_l m/s, D m\), "
        r"got \[10\.0, 10\.0\] \(an array\)",
    ),
    (
        "x0_low = [10.0, 10.0, 20.0]",
        "x0_low = [10.0, nan, 20.0]",
        rf"learning\.x0_low\[1\] must be {FINITE}, got nan",
    ),
    (
        "x0_high = [30.0, 30.0, 200.0]",
        'x0_high = [30.0, 30.0, "far"]',
        r"learning\.x0_high\[2\] must be .*, got 'far'",
    ),
    (
        "x0_low = [10.0, 10.0, 20.0]",
        "x0_low = [10.0, 10.0, 300.0]",
        r"learning\.x0_low\[2\] must be <= learning\.x0_high\[2\] = 200\.0, got 300\.0",
    ),
    (
        "profile = [[8.0, 0.0], [18.0",
        "profile = [[28.0, 0.0], [18.0",
        r"lead\.profile\[1\]\[0\] must be an end time after the previous one, 28\.0 "
        r"\(end times must increase\), got 18\.0",
    ),
    (
        "profile = [[8.0, 0.0],",
        "profile = [[nan, 0.0],",
        rf"lead\.profile\[0\]\[0\] must be {FINITE_POS}, got nan",
    ),
    (
        "profile = [[8.0, 0.0],",
        "profile = [[-8.0, 0.0],",
        r"lead\.profile\[0\]\[0\] must be .*, got -8\.0",
    ),
    (
        "profile = [[8.0, 0.0],",
        "profile = [[8.0],",
        r"lead\.profile\[0\] must be a pair \[end_time s, acceleration m/s\^2\], got \[8\.0\]",
    ),
    (
        "profile = [[8.0, 0.0],",
        "profile = [3.0,",
        r"lead\.profile\[0\] must be a pair .*, got 3\.0",
    ),
    (
        "profile = [[8.0, 0.0], [18.0, 1.2], [30.0, 0.0], [40.0, 0.5], [50.0, 0.0], [60.0, -1.0]]",
        "profile = 3.0",
        r"lead\.profile must be an array of \[end_time, acceleration\] pairs, got 3\.0",
    ),
    # counts derived from several keys
    (
        "t_final = 80.0",
        "t_final = 100000.0",
        r"simulation\.t_final / simulation\.dt must give between 1 and 1,000,000 simulation "
        r"steps, got 1e\+07",
    ),
    (
        "t_final = 80.0",
        "t_final = 0.001",
        r"simulation\.t_final / simulation\.dt must give between 1 .*, got 0\.1",
    ),
    (
        "sample_horizon = 20.0",
        "sample_horizon = 0.01",
        r"learning\.sample_horizon \* learning\.sample_rate must give between 1 and 1,000,000 "
        r"samples per excitation trajectory, got 0\.1",
    ),
    # structure
    ("kappa = 0.2\n", "", r"missing key controller\.kappa"),
    ("kappa = 0.2", "kappa = 0.2\nkapa = 1.0", r"unknown key 'controller\.kapa' in \[controller\]"),
    ("f0 = 0.1 ", "f0 = 0.1\ng0 = 1.0 ", r"unknown key 'drag\.true\.g0' in \[drag\.true\]"),
    ("[simulation]", "[simulations]", r"unknown key 'simulations'; expected one of certificates"),
    ("[initial]", "[initial\n", r"invalid TOML"),
    ("[drag.nominal]", "[drag.nominal_model]", r"unknown key 'drag\.nominal_model' in \[drag\]"),
]


@pytest.mark.parametrize("old, new, match", BAD_FIELDS)
def test_bad_field_rejected_at_load_naming_key_received_expected(tmp_path, old, new, match):
    with pytest.raises(ScenarioError, match=match) as info:
        _load_edited(tmp_path, old, new)
    assert str(info.value).startswith(str(tmp_path / "s.toml") + ": ")  # names the file


def test_missing_table(tmp_path):
    text = _paper_text()
    start, end = text.index("[simulation]"), text.index("[learning]")
    path = tmp_path / "s.toml"
    path.write_text(text[:start] + text[end:])
    with pytest.raises(ScenarioError, match=r"s\.toml: missing table \[simulation\]"):
        load_scenario(path)


def test_scalar_where_a_table_belongs(tmp_path):
    text = _paper_text()
    start, end = text.index("[drag.true]"), text.index("[initial]")
    path = tmp_path / "s.toml"
    path.write_text(
        text[:start].replace('name = "paper"', 'name = "paper"\ndrag = 1.0') + text[end:]
    )
    with pytest.raises(ScenarioError, match=r"s\.toml: drag must be a table, got 1\.0"):
        load_scenario(path)


@pytest.mark.parametrize("data", [b"\xff\xfe" + b"x = 1", "# caf\u00e9\n".encode("latin-1")])
def test_non_utf8_file_named_error(tmp_path, data):
    path = tmp_path / "latin.toml"
    path.write_bytes(data + _paper_text().encode())
    with pytest.raises(
        ScenarioError,
        match=rf"{re.escape(str(path))}: a scenario file must be UTF-8 text \(TOML\), got byte "
        r"0x[ef][9f] at offset \d+, which is not UTF-8",
    ):
        load_scenario(path)


def test_unreadable_file_named_error(tmp_path, monkeypatch):
    path = tmp_path / "s.toml"
    path.write_text(_paper_text())

    def deny(self):
        raise PermissionError(13, "Permission denied")

    # root reads any file whatever its mode: simulate the denial at the read itself
    monkeypatch.setattr(type(path), "read_bytes", deny)
    with pytest.raises(ScenarioError, match=r"s\.toml: cannot read the file \(Permission denied\)"):
        load_scenario(path)


def test_unknown_scenario():
    presets = r"\('paper', 'stress', 'stress-ood', 'paper-limited', 'stress-limited'\)"
    with pytest.raises(ScenarioError, match=rf"'nope' is neither a preset {presets}"):
        load_scenario("nope")


def test_name_defaults_to_a_valid_stem(tmp_path):
    text = _paper_text().replace('name = "paper"\n', "")
    (tmp_path / "my_case.toml").write_text(text)
    assert load_scenario(tmp_path / "my_case.toml").name == "my_case"
    (tmp_path / "my case.toml").write_text(text)
    with pytest.raises(ScenarioError, match=r"got 'my case' .*its stem was used; add name = "):
        load_scenario(tmp_path / "my case.toml")


def test_valid_edges_are_accepted(tmp_path):
    """The bounds are inclusive where documented: the loader must not reject these."""
    sc = _load_edited(tmp_path, "input_limit = false", "input_limit = 0.5")
    assert sc.input_limit == 0.5
    sc = _load_edited(tmp_path, "seed = 0", f"seed = {LIMITS.max_seed}")
    assert sc.seed == 2**32 - 1
    sc = _load_edited(tmp_path, "n_samples = 2000", f"n_samples = {LIMITS.max_n_samples}")
    assert sc.n_samples == 10_000
    sc = _load_edited(tmp_path, "t_final = 80.0", "t_final = 10000")  # 1e6 steps of 0.01 s
    assert sc.t_final == 10000.0 and isinstance(sc.t_final, float)
    sc = _load_edited(tmp_path, "mass = 1650.0", "mass = 1650")  # a TOML integer is a number
    assert sc.mass == 1650.0 and isinstance(sc.mass, float)
    sc = _load_edited(tmp_path, "profile = [[8.0, 0.0], [18.0, 1.2], [30.0, 0.0], [40.0, 0.5], "
                      "[50.0, 0.0], [60.0, -1.0]]", "profile = []")  # fmt: skip
    assert sc.lead_profile == () and float(sc.lead_acceleration(3.0)) == 0.0


@pytest.mark.parametrize(
    "change, match",
    [
        ({"mass": math.inf}, r"scenario 'paper': vehicle\.mass must be .*, got inf"),
        ({"seed": -1}, r"learning\.seed must be an integer in \[0, 4294967295\], got -1"),
        ({"n_samples": 10**12}, r"learning\.n_samples must be an integer .*, got 1000000000000"),
        ({"t_final": math.nan}, r"simulation\.t_final must be .*, got nan"),
        ({"lead_profile": ((8.0, math.nan),)}, r"lead\.profile\[0\]\[1\] must be .*, got nan"),
        ({"input_limit": True}, r"controller\.input_limit must be .*, got true \(a boolean\)"),
        ({"name": "a/b"}, r"name must be a string .*, got 'a/b'"),
    ],
)
def test_replace_is_checked_like_the_file(change, match):
    sc = load_scenario("paper")
    with pytest.raises(ScenarioError, match=match):
        sc.replace(**change)


def test_run_study_rejects_bad_overrides_before_any_work(monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("data collection started for an invalid override")

    # the study collects its data through the scenario's trial study (scenarios/trial_studies.py)
    monkeypatch.setattr(trial_studies, "collect_data", no_work)
    sc = load_scenario("stress")
    with pytest.raises(ScenarioError, match=r"learning\.n_samples must be an integer .*, got 10"):
        acc_study.run_study(sc, n_samples=10**12)
    with pytest.raises(ScenarioError, match=r"learning\.seed must be an integer .*, got -1"):
        acc_study.run_study(sc, seed=-1)
    with pytest.raises(ScenarioError, match=r"simulation\.t_final / simulation\.dt .*, got 1e\+08"):
        acc_study.run_study(sc, t_final=1e6)
