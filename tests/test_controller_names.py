"""One name per controller: the list in controller_names.py, imported everywhere; old names."""

import ast
import warnings
from pathlib import Path

import pytest

import safestab
from safestab import controller_names as names
from safestab.montecarlo import price, stats
from safestab.scenarios import (
    CONTROLLERS,
    acc_study,
    check_controllers,
    load_scenario,
    obstacle_study,
)

SRC = Path(safestab.__file__).parent


def test_every_module_uses_the_one_list():
    assert CONTROLLERS is names.CONTROLLERS
    assert set(names.DESCRIPTIONS) == set(CONTROLLERS)
    assert acc_study.CONTROLLERS == obstacle_study.CONTROLLERS == names.STUDY_CONTROLLERS
    assert price.PRICE_CONTROLLERS == (names.TRUE_MODEL, *names.GP_CONTROLLERS)
    assert set(stats.GUARANTEES) <= set(CONTROLLERS)
    assert set(names.EXPORT_CHOICES.values()) == set(names.STUDY_CONTROLLERS)
    assert set(names.RENAMED.values()) <= set(CONTROLLERS)


def test_no_module_spells_a_controller_name_of_its_own():
    # a string constant equal to a controller name (current or old) outside controller_names.py:
    # a list of its own; docstrings and messages that mention a name are longer strings
    spelled = set(CONTROLLERS) | set(names.RENAMED)
    found = []
    for path in sorted(SRC.rglob("*.py")):
        if path.name == "controller_names.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and node.value in spelled:
                found.append(f"{path.relative_to(SRC)}:{node.lineno}: {node.value!r}")
    assert not found, "controller names spelled outside controller_names.py:\n" + "\n".join(found)


def test_the_old_name_in_a_scenario_file_is_read_with_a_warning(tmp_path):
    text = (SRC / "scenarios" / "paper.toml").read_text(encoding="utf-8")
    line = next(x for x in text.splitlines() if x.startswith("controllers ="))
    path = tmp_path / "old.toml"
    path.write_text(text.replace(line, 'controllers = ["true model", "GP-corrected"]'))
    with pytest.warns(DeprecationWarning, match=r"controllers\[1\].*'GP-corrected'.*'GP-robust'"):
        sc = load_scenario(path)
    assert sc.montecarlo.controllers == ("true model", "GP-robust")


def test_the_old_name_on_the_command_line_is_read_with_a_warning():
    # safestab mc --controllers goes through check_controllers
    with pytest.warns(DeprecationWarning, match="use 'GP-robust'"):
        got = check_controllers("--controllers", ["GP-corrected", "GP mean"], "command line")
    assert got == ("GP-robust", "GP mean")


def test_an_old_name_and_its_new_one_together_are_one_name_twice():
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match="appears twice"):
        check_controllers("--controllers", ["GP-corrected", "GP-robust"], "command line")


def test_name_map_reads_old_keys_with_a_warning():
    old_file = {"true model": {"min_h_m": 1.0}, "GP-corrected": {"min_h_m": 2.0}}
    with pytest.warns(DeprecationWarning, match="'GP-corrected' is deprecated; use 'GP-robust'"):
        metrics = names.NameMap(old_file, where="acc metrics")
    assert list(metrics) == ["true model", "GP-robust"]  # keys renamed, order kept
    with pytest.warns(DeprecationWarning, match="use 'GP-robust'"):
        assert metrics["GP-corrected"] == {"min_h_m": 2.0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert metrics["GP-robust"]["min_h_m"] == 2.0  # the current name: no warning
    with pytest.raises(KeyError, match="GP median"):
        metrics["GP median"]


def test_the_study_controllers_answer_to_the_old_name():
    sc = load_scenario("paper")
    ctrls = acc_study.study_controllers(sc)  # without a GP: the two model-based ones
    assert tuple(ctrls) == names.MODEL_CONTROLLERS
    with pytest.raises(KeyError):  # no GP-robust controller, so no old name for it either
        ctrls["GP-corrected"]


def test_build_compared_stands_each_controller_on_its_model_and_gives_the_gp_ones_theirs():
    from safestab.controller_names import (
        CONTROLLERS,
        GP_CONTROLLERS,
        MODEL_OF,
        build_compared,
    )

    models = {"true": "T", "nominal": "N", "learned": "L"}
    calls = []

    def build(model, **kw):
        calls.append((model, kw))
        return (model, kw)

    for name in CONTROLLERS:
        model, kw = build_compared(
            name, build, models, uncertainty="gp", gp_beta=2.0, robust_options={"r": 1}, k=3
        )
        assert model == models[MODEL_OF[name]]
        if name in GP_CONTROLLERS:
            assert kw == {"uncertainty": "gp", "gp_beta": 2.0, "k": 3, "r": 1}
        else:  # a model controller ignores the GP and its options
            assert kw == {"k": 3}
    assert MODEL_OF["true model"] == "true" and MODEL_OF["GP-robust"] == "learned"
    with pytest.raises(ValueError, match="needs an uncertainty model"):
        build_compared("GP-robust", build, models)
    with pytest.raises(ValueError, match="controller must be one of"):
        build_compared("GP-corected", build, models)
    with pytest.warns(DeprecationWarning, match="GP-corrected"):
        assert build_compared("GP-corrected", build, models, uncertainty="gp")[0] == "L"


def test_export_takes_the_controllers_names_as_well_as_its_short_ones():
    from safestab.controller_names import EXPORT_CHOICES, export_choice
    from safestab.scenarios.export_study import export_scenario

    for short, full in EXPORT_CHOICES.items():
        assert export_choice(short) == short and export_choice(full) == short
    with pytest.warns(DeprecationWarning):
        assert export_choice("GP-corrected") == "gp"
    assert export_choice("GP mean") == "GP mean"  # not exported: left for the caller's check
    with pytest.raises(safestab.ParameterError, match=r"'gp' \('GP-robust'\).*got 'GP mean'"):
        export_scenario("paper", "/nonexistent/never-made", controller="GP mean")
