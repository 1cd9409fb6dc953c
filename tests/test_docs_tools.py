"""The documentation tooling: the gallery script and the offline check of the built site."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GALLERY = ROOT / "docs" / "gallery"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


make_gallery = _load("make_gallery")
check_site_offline = _load("check_site_offline")


# -- gallery ------------------------------------------------------------------------------


def test_gallery_files_are_exactly_the_scripts_figures() -> None:
    # No figure placed by hand: every PNG in docs/gallery is one the script makes, and the
    # manifest the script writes has an entry (with the command) for each.
    expected = {file for file, _ in make_gallery.FIGURES.values()}
    assert {p.name for p in GALLERY.glob("*.png")} == expected
    manifest = json.loads((GALLERY / "manifest.json").read_text())
    assert set(manifest) == set(make_gallery.FIGURES)
    for name, entry in manifest.items():
        assert entry["file"] == make_gallery.FIGURES[name][0]
        assert entry["command"] and entry["seconds"] >= 0


def test_gallery_page_shows_every_figure() -> None:
    page = (ROOT / "docs" / "gallery.md").read_text()
    shown = set(re.findall(r"\]\(gallery/([^)]+\.png)\)", page))
    assert shown == {file for file, _ in make_gallery.FIGURES.values()}


def test_gallery_script_makes_figures_and_manifest(tmp_path: Path) -> None:
    # The two figures that need no simulation (a few seconds), through the script's main().
    assert make_gallery.main(["--only", "formulas", "qp_geometry", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "formulas.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "qp_geometry.png").stat().st_size > 10_000
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert set(manifest) == {"formulas", "qp_geometry"}
    assert manifest["qp_geometry"]["file"] == "qp_geometry.png"
    # A later partial run keeps the earlier entries.
    make_gallery.main(["--only", "formulas", "--out", str(tmp_path)])
    assert set(json.loads((tmp_path / "manifest.json").read_text())) == {"formulas", "qp_geometry"}


def test_gallery_script_rejects_unknown_figure(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        make_gallery.main(["--only", "no_such_figure"])
    assert "invalid choice: 'no_such_figure'" in capsys.readouterr().err


# -- offline check of the built site -----------------------------------------------------

PAGE = """<!doctype html><html><head>
<link rel="stylesheet" href="assets/main.css">
<link rel="stylesheet" href="https://fonts.googleapis.com/css?family=Roboto">
<link rel="canonical" href="https://example.org/page/">
<script src="//cdn.example.org/lib.js"></script>
<script src="assets/local.js"></script>
</head><body><a href="https://example.org">a plain link is fine</a>
<img src="gallery/fig.png"><img src="http://example.org/remote.png"></body></html>
"""


def test_offline_check_finds_remote_resources(tmp_path: Path) -> None:
    (tmp_path / "index.html").write_text(PAGE)
    (tmp_path / "assets").mkdir()
    (tmp_path / "assets" / "main.css").write_text(
        '@import url("https://example.org/x.css");\nbody { background: url(img/local.png) }\n'
    )
    found = check_site_offline.problems(tmp_path)
    assert found == [
        "assets/main.css: css https://example.org/x.css",
        "index.html: <link rel=stylesheet href=https://fonts.googleapis.com/css?family=Roboto>",
        "index.html: <script src=//cdn.example.org/lib.js>",
        "index.html: <img src=http://example.org/remote.png>",
        "index.html: web font host fonts.googleapis.com",
    ]
    assert check_site_offline.main([str(tmp_path)]) == 1


def test_offline_check_passes_a_local_site_and_needs_a_built_one(tmp_path: Path) -> None:
    (tmp_path / "index.html").write_text('<html><a href="https://example.org">x</a></html>')
    assert check_site_offline.problems(tmp_path) == []
    assert check_site_offline.main([str(tmp_path)]) == 0
    assert check_site_offline.main([str(tmp_path / "missing")]) == 1


# -- the griffe extension that turns Sphinx markup into Markdown for the API reference ---------


def test_sphinx_markup_becomes_markdown() -> None:
    griffe = pytest.importorskip("griffe", reason="the docs extra (griffe) is not installed")
    roles = _load("griffe_sphinx_roles")
    pkg = griffe.load("safestab", search_paths=[str(ROOT / "src")], resolve_aliases=False)
    formulas = pkg["formulas"]
    fast_gp = pkg["learning"]["fast"]["FastGP"]
    text = (
        "See :func:`clf_cbf`, :class:`~safestab.formulas.Region`, :meth:`calibrate`,\n"
        ":mod:`decimal_nowhere` and :data:`NOT_A_NAME`.\n"
        "kappa : float\n"
        "    >= 0, and a >>> prompt stays.\n"
        "Dynamics::\n\n    x' = u\n"
        "=====  =========\n"
        "name   value\n"
        "=====  =========\n"
        "P1     a | b\n"
        "P2     2\n"
        "=====  =========\n"
    )
    out = roles.convert(formulas, text)
    assert '<autoref identifier="safestab.formulas.clf_cbf" optional><code>clf_cbf</code>' in out
    assert '<autoref identifier="safestab.formulas.Region" optional><code>Region</code>' in out
    assert "`decimal_nowhere`" in out and "`NOT_A_NAME`" in out  # unresolved: plain code
    assert "    \\>= 0, and a >>> prompt stays." in out
    assert "Dynamics:\n\n    x' = u" in out
    assert "| name | value |\n|---|---|\n| P1 | a \\| b |\n| P2 | 2 |" in out
    # a method name resolves from inside its class first
    assert 'identifier="safestab.learning.fast.FastGP.mean_std"' in roles.convert(
        fast_gp, ":meth:`mean_std`"
    )


def test_sphinx_comment_docstrings(tmp_path: Path) -> None:
    griffe = pytest.importorskip("griffe", reason="the docs extra (griffe) is not installed")
    roles = _load("griffe_sphinx_roles")
    (tmp_path / "demo").mkdir()
    (tmp_path / "demo" / "__init__.py").write_text(
        '"""Demo."""\n\nimport enum\n\n#: The answer,\n#: on two lines.\nANSWER = 42\n\n'
        "NOTHING = 0\n\n\nclass Colour(enum.IntEnum):\n"
        '    """Colours."""\n\n    RED = 1  #: like a rose\n    BLUE = 2\n'
    )
    pkg = griffe.load("demo", search_paths=[str(tmp_path)])
    assert roles.comment_docstring(pkg["ANSWER"]) == "The answer,\non two lines."
    assert roles.comment_docstring(pkg["NOTHING"]) is None
    assert roles.comment_docstring(pkg["Colour"]["RED"]) == "like a rose"
    assert roles.comment_docstring(pkg["Colour"]["BLUE"]) is None
    assert roles.comment_docstring(pkg["Colour"]) is None  # only attributes


# -- reproduce-docs -------------------------------------------------------------------------

reproduce_docs = _load("reproduce_docs")


def test_every_generated_block_in_the_docs_is_written_by_a_step():
    found = {}
    for page in sorted((ROOT / "docs").rglob("*.md")):
        for name in reproduce_docs.blocks(page.read_text()):
            assert name not in found, f"block {name} in {found.get(name)} and {page}"
            found[name] = page
    produced = {b for names in reproduce_docs.PRODUCES.values() for b in names}
    assert set(found) == produced
    assert set(reproduce_docs.PRODUCES) == set(reproduce_docs.STEPS)


def test_replace_block_rewrites_only_the_named_block():
    text = (
        "a\n<!-- generated: one -->\nold 1\n<!-- end generated -->\nb\n"
        "<!-- generated: two -->\nold 2\n<!-- end generated -->\n"
    )
    out = reproduce_docs.replace_block(text, "two", "new\n")
    assert reproduce_docs.blocks(out) == {"one": "old 1\n", "two": "new\n"}
    assert out.startswith("a\n<!-- generated: one -->\nold 1\n")
    with pytest.raises(KeyError, match="three"):
        reproduce_docs.replace_block(text, "three", "x\n")


def test_obstacle_table_from_a_metrics_document():
    stuck = [{"end_flag_compatible": False, "end_verdict_compatible": False},
             {"end_flag_compatible": True, "end_verdict_compatible": False}]  # fmt: skip
    doc = {"runs": {
        "true model / no limits": {"outcomes": {"converged": 70, "stuck": 2, "unsafe": 0,
                                                "moving": 0}, "stuck": stuck,
                                   "min_h_m2": 0.0199937, "max_abs_u_mps": 2.02635,
                                   "median_input_variation_mps2": 0.05216,
                                   "input_variation_in_ball_share": 0.0615,
                                   "max_input_variation_in_ball_mps2": 0.0712,
                                   "median_converge_time_s": 13.42},
        "mismatched model / input limits": {"outcomes": {"converged": 66, "stuck": 0,
                                                         "unsafe": 6, "moving": 0},
                                            "stuck": [], "min_h_m2": -0.2314722,
                                            "max_abs_u_mps": 1.5,
                                            "median_input_variation_mps2": 0.04912,
                                            "input_variation_in_ball_share": 0.0,
                                            "max_input_variation_in_ball_mps2": 0.0,
                                            "median_converge_time_s": None},
    }}  # fmt: skip
    lines = reproduce_docs.obstacle_table(doc).splitlines()
    assert len(lines[0].split("|")) == len(lines[1].split("|")) == len(lines[2].split("|"))
    assert lines[2] == (
        "| true model | none | 70 | 2 | 0 | 0 | 0.020 | 2.03 | 0.052 | 0.06 | 0.07 | 13.4 | 1 / 2 |"
    )
    assert lines[3] == (
        "| mismatched model | +-1.5 m/s (projection) | 66 | 0 | 6 | 0 | -0.231 | 1.50 | 0.049 "
        "| 0.00 | 0.00 | - | - |"
    )
    doc["settings"] = {"limit_method": "filter"}  # controller.limit_method, as recorded
    assert "| mismatched model | +-1.5 m/s (filter) | 66 |" in reproduce_docs.obstacle_table(doc)


def test_obstacle_layer_table_from_two_metrics_documents():
    def run(variation, ball_max, settle):
        return {
            "outcomes": {"converged": 68, "stuck": 4, "unsafe": 0, "moving": 0},
            "min_h_m2": 0.18914,
            "max_abs_u_mps": 4.8294,
            "median_input_variation_mps2": variation,
            "input_variation_in_ball_share": 0.6118,
            "max_input_variation_in_ball_mps2": ball_max,
            "median_converge_time_s": settle,
        }

    def doc(layer, ball_max):
        return {"settings": {"robust_clf_layer_m": layer},
                "runs": {"GP-robust / no limits": run(0.38259, ball_max, 5.29),
                         "GP-robust / input limits": run(0.1043, 0.026, None)}}  # fmt: skip

    lines = reproduce_docs.obstacle_layer_table(doc(0.2, 1.2273), doc(0.0, 90.47)).splitlines()
    assert len(lines) == 6 and all(len(ln.split("|")) == 11 for ln in lines)
    assert lines[2] == (
        "| 0.2 m (preset) | none | 68 / 4 / 0 / 0 | 0.189 | 4.83 | 0.383 | 0.61 | 1.23 | 5.3 |"
    )
    assert lines[5] == (
        "| 0 (Lemma 3) | +-1.5 m/s (projection) | 68 / 4 / 0 / 0 | 0.189 | 4.83 | 0.104 | 0.61 "
        "| 0.03 | - |"
    )


def test_obstacle_limits_table_puts_the_filter_beside_the_projection():
    def doc(method, unsafe):
        run = {"outcomes": {"converged": 72 - unsafe, "stuck": 0, "unsafe": unsafe, "moving": 0},
               "min_h_m2": -0.1484 if unsafe else 0.0183, "median_input_variation_mps2": 0.04,
               "median_converge_time_s": None if unsafe == 72 else 13.46}  # fmt: skip
        names = ("true model", "mismatched model", "GP-robust")
        return {"settings": {"limit_method": method},
                "runs": {f"{n} / input limits": run for n in names}}  # fmt: skip

    lines = reproduce_docs.obstacle_limits_table(doc("filter", 0), doc("projection", 72))
    lines = lines.splitlines()
    assert len(lines) == 8 and all(len(ln.split("|")) == 8 for ln in lines)
    assert lines[2] == "| true model | filter | 72 / 0 / 0 / 0 | 0.018 | 0.040 | 13.5 |"
    assert lines[7] == "| GP-robust | projection | 0 / 0 / 0 / 72 | -0.148 | 0.040 | - |"


def test_obstacle_gp_table_from_a_metrics_document():
    gp = {"beta": 5.8356, "per_component": [1.0, 0.99], "rmse_mps": [0.13729, 0.04021],
          "cache": {"n_inducing": [101, 190], "std_over_exact_at_training_median": [1.0653, 1.0247],
                    "std_over_exact_at_training_max": [1.3257, 1.2698]}}  # fmt: skip
    lines = reproduce_docs.obstacle_gp_table({"gp": gp}).splitlines()
    assert len(lines[0].split("|")) == len(lines[1].split("|")) == len(lines[2].split("|"))
    assert lines[2] == "| x1 (m/s) | 101: 1.07 / 1.33 | 5.84 | 1.00 | 0.137 |"
    assert lines[3] == "| x2 (m/s) | 190: 1.02 / 1.27 | 5.84 | 0.99 | 0.040 |"
    del gp["cache"]
    assert (
        reproduce_docs.obstacle_gp_table({"gp": gp})
        .splitlines()[2]
        .startswith("| x1 (m/s) | exact GP |")
    )


def test_obstacle_seed_table_names_the_beta_of_each_seed():
    run = {"outcomes": {"converged": 68, "stuck": 4, "unsafe": 0, "moving": 0},
           "min_h_m2": 0.1803, "max_abs_u_mps": 5.2249}  # fmt: skip
    maps = {"nominal_incompatible_points": 15, "robust_incompatible_points": 16}
    docs = [
        {"settings": {"seed": 0}, "runs": {"GP-robust / no limits": run},
         "gp": {"beta": 5.8356, "beta_method": "conformal"}, "maps": maps},
        {"settings": {"seed": 1}, "runs": {"GP-robust / no limits": run | {"outcomes": {
            "converged": 63, "stuck": 4, "unsafe": 1, "moving": 4}}}, "gp": {"beta": 2.0},
         "maps": maps | {"robust_incompatible_points": 98}},
    ]  # fmt: skip
    lines = reproduce_docs.obstacle_seed_table(docs).splitlines()
    assert len(lines[0].split("|")) == len(lines[1].split("|")) == len(lines[2].split("|"))
    assert lines[2] == "| 0 | 5.84 (conformal) | 68 / 4 / 0 / 0 | 0.180 | 5.2 | - | - | 15 / 16 |"
    assert lines[3] == "| 1 | 2.00 | 63 / 4 / 4 / 1 | 0.180 | 5.2 | - | - | 15 / 98 |"
    docs[0]["runs"]["GP-robust / no limits"]["max_abs_u_off_axis_mps"] = 2.0016
    docs[0]["runs"]["GP-robust / input limits"] = run | {"min_h_m2": 0.0221}
    line = reproduce_docs.obstacle_seed_table(docs).splitlines()[2]
    assert line == (
        "| 0 | 5.84 (conformal) | 68 / 4 / 0 / 0 | 0.180 | 5.2 | 2.00 | 68 / 4 / 0 / 0, 0.022 "
        "| 15 / 16 |"
    )


def _acc_controller(min_h: float, gap: float | None, u: float) -> dict:
    c = {"min_h_m": min_h, "time_h_negative_s": 53.66 if min_h < 0 else 0.0,
         "rms_speed_error_mps": 9.8951, "incompatible_steps": 6001, "max_abs_u_over_Mg": u,
         "region_fraction": {"INCOMPATIBLE": 0.0, "P1": 0.25, "P3": 0.75}}  # fmt: skip
    if gap is not None:
        c |= {"max_abs_h_gap_to_true_m": gap, "rms_vf_gap_to_true_mps": 3.6e-5}
    return c


def test_acc_table_from_a_metrics_document():
    doc = {
        "controllers": {"true model": _acc_controller(0.0150811, None, 0.50900),
                        "mismatched model": _acc_controller(-0.89951, 1.66410, 0.55009)},
        "gp": {"n_samples": 2000, "beta": 2.0, "held_out_coverage": [1.0, 0.96],
               "held_out_joint_coverage": 0.955, "held_out_rmse": [5.14e-5, 8.29e-10]},
    }  # fmt: skip
    lines = reproduce_docs.acc_table(doc).splitlines()
    assert len(lines[0].split("|")) == len(lines[1].split("|")) == len(lines[2].split("|"))
    assert (
        lines[2] == "| true model | +0.015 | 0 | 9.895 | 0 | 0 | 0.509 | 6,001 | P1 25 %, P3 75 % |"
    )
    assert lines[3].startswith("| mismatched model | -0.900 | 53.66 | 9.895 | 1.664 | 3.6e-05 |")
    assert lines[-1] == (
        "GP (2,000 samples): held-out coverage of `omega` at `beta = 2` 100 %, 96 % per "
        "component (96 % jointly); held-out RMSE per component 5.1e-05, 8.3e-10 m/s^2."
    )


def test_swarm_tables_from_a_metrics_document():
    def run(dist, below, arrival, change, statuses):
        return {"min_distance_m": dist, "steps_below_safety_distance": below,
                "arrival_time_s": arrival, "final_max_goal_error_m": 5.1724,
                "mean_input_change_mps": change, "solver_statuses": statuses}  # fmt: skip

    doc = {
        "runs": {"centralized": run(0.6000094, 0, 11.6, 0.30051, {"SOLVED": 9600}),
                 "decentralized": run(0.6, 0, None, 1.0978, {"SOLVED": 9590, "MAX_ITER": 10}),
                 "unfiltered": run(0.0075920, 183, 9.98, 0.0, {})},
        "loose_solvers_on_centralized_states": {
            "osqp": {"states": 32, "max_input_gap_mps": 0.011756, "median_input_gap_mps": 6.79e-5,
                     "max_barrier_violation_m2ps": 0.00405, "share_of_states_violating": 0.4375},
            "clarabel": {"note": "not installed"},
        },
    }  # fmt: skip
    results, solvers = reproduce_docs.swarm_tables(doc)
    lines = results.splitlines()
    assert lines[2] == "| centralized | 0.600009 | 0 | at 11.60 s | 0.301 | SOLVED 9,600 |"
    assert lines[3] == (
        "| decentralized | 0.600000 | 0 | never (largest goal error 5.17 m at the end) | 1.098 "
        "| SOLVED 9,590, MAX_ITER 10 |"
    )
    assert lines[4] == "| unfiltered (no filter) | 0.007592 | 183 | at 9.98 s | 0.000 | - |"
    assert "- Without a filter the robots pass within 7.6 mm of each other." in lines
    assert "- The centralized filter arrives 1.62 s after the unfiltered swarm." in lines
    rows = solvers.splitlines()
    assert rows[2] == "| OSQP (32 states) | 0.01176 | 6.8e-05 | 44 % | 4.0e-03 |"
    assert rows[3] == "| Clarabel | not installed |  |  |  |"


@pytest.mark.slow
def test_reproduce_docs_check(tmp_path):
    # Reruns every quick study behind a generated table (about 20 minutes here) and fails when
    # a number in one of them would change; writes nothing in docs/.
    before = {p: p.read_bytes() for p in (ROOT / "docs").rglob("*") if p.is_file()}
    assert reproduce_docs.main(["--check", "--out", str(tmp_path)]) == 0
    after = {p: p.read_bytes() for p in (ROOT / "docs").rglob("*") if p.is_file()}
    assert after == before


def test_price_table_from_a_study_document():
    def entry(count, median):
        return {"safe_per_dataset": {"count": count, "datasets": 30},
                "min_h_excess": {"0.5": median}, "settle_time_excess": {"0.5": 2.345},
                "mean_input_gap": {"0.5": 0.01234}}  # fmt: skip

    doc = {
        "settings": {"reference": "true model",
                     "controllers": ["true model", "GP mean", "GP-robust"]},
        "h_unit": "m",
        "points": [
            {"n_samples": 25, "controllers": {"true model": entry(30, 0.0),
                                              "GP mean": entry(0, -0.9037),
                                              "GP-robust": entry(30, 12.34)}},
            {"n_samples": 4000, "controllers": {"true model": entry(30, 0.0),
                                                "GP mean": entry(17, -1.2e-4),
                                                "GP-robust": entry(30, 0.0123)}},
        ],
    }  # fmt: skip
    lines = reproduce_docs.price_table(doc).splitlines()
    assert lines[0] == (
        "| Q | GP mean: safe data sets, median min h - min h_true (m) | GP-robust: safe data "
        "sets, median min h - min h_true (m) |"
    )
    assert lines[2] == "| 25 | 0/30, -0.9 | 30/30, +12 |"
    assert lines[3] == "| 4,000 | 17/30, -0.00012 | 30/30, +0.012 |"
    assert lines[5].startswith("| Q | GP mean: median settle time - settle time_true (s), median")
    assert lines[7] == "| 25 | +2.35, 0.012 | +2.35, 0.012 |"


def test_the_benchmarks_page_keeps_every_block_and_paragraph_it_did_not_measure(
    tmp_path, monkeypatch
):
    """``benchmarks/run.py`` rewrites only its own block of performance.md: from the committed
    results, the committed page comes back byte for byte (it rebuilt the whole page, losing
    the jax block and the paragraphs written beside the other blocks: 78 lines)."""
    import shutil
    import sys

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    monkeypatch.delitem(sys.modules, "run", raising=False)
    import run

    for path in (ROOT / "docs").glob("performance*"):
        shutil.copy(path, tmp_path / path.name)
    page = (tmp_path / "performance.md").read_text()
    assert page.index(run.BEGIN) < page.index(run.END) < page.index("<!-- montecarlo:begin -->")
    run.write_page(json.loads((tmp_path / "performance.json").read_text()), tmp_path)
    assert (tmp_path / "performance.md").read_text() == page
