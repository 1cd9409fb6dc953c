"""Rerun the studies behind the docs' result tables and figures, and rewrite them in place.

    bash scripts/reproduce-docs.sh                 # every quick study (about 12 min here)
    bash scripts/reproduce-docs.sh --long          # also the 1,000-data-set Monte Carlo (15 min),
                                                   # the deployed study at 1,000 data sets
                                                   # (deployed-long: about 1 h here)
                                                   # and the price of robustness (price,
                                                   # price-obstacle)
    bash scripts/reproduce-docs.sh --only mc-presets obstacle
    bash scripts/reproduce-docs.sh --check         # write nothing, fail if a table would change

A generated table sits in a page between ``<!-- generated: NAME -->`` and
``<!-- end generated -->``; this script writes it from the result files of its step, never
by hand. Each step's figures are copied into docs/figures or docs/gallery. Timing tables
(docs/performance*.md) are measurements of a time and place and are left alone
(``scripts/run-benchmarks.sh`` rewrites them). The script prints what it reran and how long
each step took. ``--check`` writes nothing: it exits 1 if a generated table would change, and
lists the figures whose bytes would change (which does not fail: a figure's bytes also depend
on the matplotlib and FreeType versions) and the blocks of ``MEASURED_TIMES`` that would
change (a study's own measured time, which does not fail either). The slow test
``tests/test_docs_tools.py::test_reproduce_docs_check`` runs the check.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
SAFESTAB = [sys.executable, "-m", "safestab.cli"]
BLOCK = re.compile(r"(<!-- generated: ([\w.-]+) -->\n)(.*?)(<!-- end generated -->)", re.S)


def blocks(text: str) -> dict[str, str]:
    """The generated blocks of a page, by name."""
    return {m.group(2): m.group(3) for m in BLOCK.finditer(text)}


def replace_block(text: str, name: str, body: str) -> str:
    """``text`` with block ``name``'s content replaced by ``body`` (which ends in a newline).

    Raises
    ------
    KeyError
        If the page has no block of that name.
    """
    found = False

    def sub(m: re.Match) -> str:
        nonlocal found
        if m.group(2) != name:
            return m.group(0)
        found = True
        return m.group(1) + body + m.group(4)

    out = BLOCK.sub(sub, text)
    if not found:
        raise KeyError(f"no block '<!-- generated: {name} -->' in the page")
    return out


# -- tables ------------------------------------------------------------------------------


def _table(header: list[str], align: list[str], rows: list[list[str]]) -> str:
    """A Markdown table: ``align`` holds each column's rule (``---`` or ``---:``)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(align) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _run_cells(run: dict) -> list[str]:
    """One obstacle run's min h, largest input, input variation and convergence cells."""
    settle = run["median_converge_time_s"]
    return [
        f"{run['min_h_m2']:.3f}", f"{run['max_abs_u_mps']:.2f}",
        f"{run['median_input_variation_mps2']:.3f}",
        f"{run['input_variation_in_ball_share']:.2f}",
        f"{run['max_input_variation_in_ball_mps2']:.2f}",
        "-" if settle is None else f"{settle:.1f}",
    ]  # fmt: skip


def _outcomes(o: dict) -> str:
    """One obstacle run's outcome counts: converged / stuck / moving / unsafe."""
    return " / ".join(str(o[k]) for k in ("converged", "stuck", "moving", "unsafe"))


def obstacle_table(doc: dict) -> str:
    """The obstacle page's outcome table from a metrics document."""
    rows = []
    for key, run in doc["runs"].items():
        name, limits = key.split(" / ")
        o, stuck = run["outcomes"], run["stuck"]
        both = sum(not s["end_flag_compatible"] and not s["end_verdict_compatible"] for s in stuck)
        rows.append([
            name, _limits_cell(limits, doc),
            *(str(o[k]) for k in ("converged", "stuck", "unsafe", "moving")),
            *_run_cells(run), f"{both} / {len(stuck)}" if stuck else "-",
        ])  # fmt: skip
    header = ["controller", "limits", "converged", "stuck", "unsafe", "moving", "min h (m^2)",
              "max abs u (m/s)", "input variation (m/s^2, median)",
              "share of the variation within the goal ball",
              "largest variation within the goal ball (m/s^2, one start)",
              "time to converge (s, median)", "stuck ends incompatible"]  # fmt: skip
    return _table(header, ["---"] * 2 + ["---:"] * 11, rows)


def _limit_method(doc: dict) -> str:
    """``controller.limit_method`` of a run; documents from before the key projected."""
    return doc.get("settings", {}).get("limit_method", "projection")


def _limits_cell(limits: str, doc: dict) -> str:
    """``none``, or the box and how the run kept it (``controller.limit_method``)."""
    return "none" if limits == "no limits" else f"+-1.5 m/s ({_limit_method(doc)})"


def obstacle_limits_table(doc: dict, doc_projected: dict) -> str:
    """Each controller's runs with the input limits: the filter (preset) and the projection."""
    rows = []
    for d in (doc, doc_projected):
        for name in ("true model", "mismatched model", "GP-robust"):
            run = d["runs"][f"{name} / input limits"]
            rows.append([
                name, _limit_method(d), _outcomes(run["outcomes"]),
                f"{run['min_h_m2']:.3f}", f"{run['median_input_variation_mps2']:.3f}",
                "-" if run["median_converge_time_s"] is None
                else f"{run['median_converge_time_s']:.1f}",
            ])  # fmt: skip
    header = ["controller", "limits kept by", "converged / stuck / moving / unsafe",
              "min h (m^2)", "input variation (m/s^2, median)",
              "time to converge (s, median)"]  # fmt: skip
    return _table(header, ["---"] * 3 + ["---:"] * 3, rows)


def obstacle_layer_table(doc: dict, doc_plain: dict) -> str:
    """The GP-robust rows with the preset's boundary layer and without it (layer 0)."""
    rows = []
    layer = doc["settings"]["robust_clf_layer_m"]
    for eps, d in ((f"{layer:g} m (preset)", doc), ("0 (Lemma 3)", doc_plain)):
        for limits in ("no limits", "input limits"):
            run = d["runs"][f"GP-robust / {limits}"]
            o = run["outcomes"]
            rows.append([
                eps, _limits_cell(limits, d),
                _outcomes(o),
                *_run_cells(run),
            ])  # fmt: skip
    header = ["boundary layer eps", "limits", "converged / stuck / moving / unsafe",
              "min h (m^2)", "max abs u (m/s)", "input variation (m/s^2, median)",
              "share of the variation within the goal ball",
              "largest variation within the goal ball (m/s^2, one start)",
              "time to converge (s, median)"]  # fmt: skip
    return _table(header, ["---"] * 3 + ["---:"] * 6, rows)


def obstacle_gain_table(doc: dict, doc_learned: dict) -> str:
    """The GP-robust rows with the nominal gain and with the learned gain error (preset)."""
    rows = []
    for gain, d in (("nominal", doc), ("learned (preset)", doc_learned)):
        gp = d["gp"]
        for limits in ("no limits", "input limits"):
            run = d["runs"][f"GP-robust / {limits}"]
            o = run["outcomes"]
            rows.append([
                gain, _limits_cell(limits, d),
                " / ".join(f"{v:.4f}" for v in gp["noise_mps"]), f"{gp['beta']:.2f}",
                _outcomes(o),
                f"{run['min_h_m2']:.3f}", f"{run['max_abs_u_mps']:.2f}",
                f"{run['max_abs_u_off_axis_mps']:.2f}",
                f"{run['median_input_variation_mps2']:.3f}",
                f"{run['median_converge_time_s']:.1f}",
            ])  # fmt: skip
    true = doc["runs"]["true model / no limits"]
    o = true["outcomes"]
    rows.append([
        "(true model)", "none", "-", "-",
        _outcomes(o),
        f"{true['min_h_m2']:.3f}", f"{true['max_abs_u_mps']:.2f}",
        f"{true['max_abs_u_off_axis_mps']:.2f}", f"{true['median_input_variation_mps2']:.3f}",
        f"{true['median_converge_time_s']:.1f}",
    ])  # fmt: skip
    header = ["input gain", "limits", "GP noise std (m/s, x1 / x2)", "beta (conformal)",
              "converged / stuck / moving / unsafe",
              "min h (m^2)", "max abs u (m/s)", "max abs u off the axis (m/s, 68 starts)",
              "input variation (m/s^2, median)", "time to converge (s, median)"]  # fmt: skip
    return _table(header, ["---"] * 5 + ["---:"] * 5, rows)


def obstacle_gain_estimate(doc_learned: dict) -> str:
    """The learned D with its standard errors, against the true one."""
    est = doc_learned["gp"]["input_gain"]
    rows = []
    for i in range(2):
        rows.append([f"row {i + 1}"] + [
            f"{est['matrix'][i][j]:.4f} +- {est['std'][i][j]:.4f} (true {est['true'][i][j]:.2f})"
            for j in range(2)
        ])  # fmt: skip
    return _table(["D (m/s per m/s)", "column 1 (u1)", "column 2 (u2)"], ["---"] * 3, rows)


def obstacle_axis_table(rows_in: list) -> str:
    """benchmarks/obstacle_axis.py: the axis starts on the axis and 1 mm off it."""
    rows = []
    for r in rows_in:
        o = r["outcomes"]
        name = r["controller"] + ("" if r["input_gain"] == "-" else f" ({r['input_gain']} gain)")
        rows.append([
            name, f"{r['offset_m'] * 1000:g}",
            "none" if r["limits"] == "no limits" else f"+-1.5 m/s ({r['limit_method']})",
            _outcomes(o),
            f"{r['min_h_m2']:.3f}", f"{r['max_abs_u_mps']:.2f}",
        ])  # fmt: skip
    header = ["controller", "x2 offset (mm)", "limits", "converged / stuck / moving / unsafe",
              "min h (m^2)", "max abs u (m/s)"]  # fmt: skip
    return _table(header, ["---"] * 4 + ["---:"] * 2, rows)


def obstacle_gp_table(doc: dict) -> str:
    """The obstacle GP per component: the cache's width, beta and held-out coverage."""
    gp = doc["gp"]
    cache = gp.get("cache")
    rows = []
    for j, name in enumerate(("x1 (m/s)", "x2 (m/s)")):
        width = (
            "exact GP"
            if cache is None
            else f"{cache['n_inducing'][j]}: "
            f"{cache['std_over_exact_at_training_median'][j]:.2f} / "
            f"{cache['std_over_exact_at_training_max'][j]:.2f}"
        )
        rows.append([
            name, width, f"{gp['beta']:.2f}", f"{gp['per_component'][j]:.2f}",
            f"{gp['rmse_mps'][j]:.3f}",
        ])  # fmt: skip
    header = ["component", "inducing inputs: cache std / exact std at the training inputs "
              "(median / max)", "beta", "held-out coverage", "held-out RMSE (m/s)"]  # fmt: skip
    return _table(header, ["---", "---", "---:", "---:", "---:"], rows)


def obstacle_seed_table(docs: list[dict]) -> str:
    """The GP-robust controller without limits over data seeds, with the beta it used."""
    rows = []
    for doc in docs:
        run, gp = doc["runs"]["GP-robust / no limits"], doc["gp"]
        o = run["outcomes"]
        beta = f"{gp['beta']:.2f}" + (
            " (conformal)" if gp.get("beta_method") == "conformal" else ""
        )
        off_axis = run.get("max_abs_u_off_axis_mps")
        limited = doc["runs"].get("GP-robust / input limits")
        rows.append([
            str(doc["settings"]["seed"]), beta,
            _outcomes(o), f"{run['min_h_m2']:.3f}", f"{run['max_abs_u_mps']:.1f}",
            "-" if off_axis is None else f"{off_axis:.2f}",
            "-" if limited is None
            else f"{_outcomes(limited['outcomes'])}, {limited['min_h_m2']:.3f}",
            f"{doc['maps']['nominal_incompatible_points']} / "
            f"{doc['maps']['robust_incompatible_points']}",
        ])  # fmt: skip
    header = ["data seed", "beta", "GP-robust, no limits: converged / stuck / moving / unsafe",
              "min h (m^2)", "largest input (m/s)", "largest input off the axis (m/s)",
              "GP-robust, limits: converged / stuck / moving / unsafe, min h (m^2)",
              "incompatible map points: nominal / GP-robust"]  # fmt: skip
    return _table(header, ["---:", "---:", "---", "---:", "---:", "---:", "---", "---:"], rows)


def gp_coverage_table(rows: list[dict]) -> str:
    """docs/learning.md's coverage table from benchmarks/gp_coverage.py's --json rows."""
    keys = ("state_coverage_chosen", "state_coverage_conformal", "trajectory_coverage_chosen",
            "trajectory_coverage_conformal")  # fmt: skip
    body = [[str(r["seed"]), f"{r['beta_conformal']:.2f}", *(f"{r[k]:.3f}" for k in keys),
             f"{r['max_score']:.2f}"] for r in rows]  # fmt: skip
    header = ["data seed", "conformal beta", "states in band, beta = 2",
              "states in band, conformal", "trajectories entirely in band, beta = 2",
              "trajectories entirely in band, conformal",
              "max over components of abs(omega - m)/sigma"]  # fmt: skip
    return _table(header, ["---:"] * 7, body)


def fast_band_table(rows: list[dict]) -> str:
    """docs/learning.md's cache-width table from benchmarks/fast_band.py's rows."""
    body = [[r["preset"], str(r["component"]), f"{r['n_inducing']} of {r['n_inducing_cap']}",
             f"{r['ratio_training_median']:.3f} / {r['ratio_training_max']:.3f}",
             f"{r['ratio_held_out_median']:.3f}", f"{r['mean_error_norm']:.2g}",
             f"{r['coverage_training']:.3f} / {r['coverage_held_out']:.3f}",
             str(r["warnings"])] for r in rows]  # fmt: skip
    header = ["preset", "component", "inducing inputs (of the cap)",
              "cache std / exact std, training inputs (median / max)",
              "the same, held-out states (median)", "E",
              "band contains the exact band, beta = 1 (training / held-out)",
              "InducingPointsWarning"]  # fmt: skip
    return _table(header, ["---", "---:", "---:", "---:", "---:", "---:", "---:", "---:"], body)


def mc_band_table(rows: list[dict]) -> str:
    """docs/learning.md's Monte Carlo cache-width table from benchmarks/mc_band_width.py's rows.

    One row per preset and component, over its data sets: the inducing inputs kept, the
    largest of the per-data-set median ratios (training inputs, ten times the box), the least
    containment, and how many data sets are above ``STD_RATIO_WARN`` (recorded in each row)
    and warned.
    """
    groups: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["preset"], r["component"]), []).append(r)
    body = []
    for (preset, comp), rs in groups.items():
        counts = [r["n_inducing"] for r in rs]
        above = [r for r in rs if r["ratio_training_median"] > r["std_ratio_warn"]]
        body.append([
            preset, str(comp), str(len(rs)), f"{min(counts)} - {max(counts)} of {rs[0]['cap']}",
            f"{max(r['ratio_training_median'] for r in rs):.3f}",
            f"{max(r['ratio_far_median'] for r in rs):.3f}",
            f"{min(r['contains_exact'] for r in rs):.3f}",
            f"{len(above)} / {sum(r['warned'] for r in above)}",
        ])  # fmt: skip
    header = ["preset", "component", "data sets", "inducing inputs (of the cap)",
              "cache std / exact std, training inputs (largest median)",
              "the same, ten times the box (largest median)",
              "band contains the exact band, beta = 1 (least)",
              "data sets above 1.5 / of them warned"]  # fmt: skip
    return _table(header, ["---", "---:", "---:", "---:", "---:", "---:", "---:", "---:"], body)


def safe_rl_table(rows: list[dict]) -> str:
    """docs/tutorials/safe-rl.md's table from benchmarks/gym_highway.py's --json rows."""
    body = [[
        r["variant"], f"{r['crashes']} / {r['episodes']}", f"{r['steps']:,}",
        f"{r['steps_changed']:,}", f"{r['mean_intervention']:.3f}",
        ", ".join(f"{k} {v:,}" for k, v in sorted(r["statuses"].items())) or "-",
    ] for r in rows]  # fmt: skip
    header = ["filter", "episodes that crashed", "steps", "steps whose action it changed",
              "mean change of the action (of 1)", "statuses"]  # fmt: skip
    return _table(header, ["---", "---:", "---:", "---:", "---:", "---"], body)


def _signed(x: float) -> str:
    """A least ``h`` with its sign: four decimals, or two digits below 1e-3 (no ``+0.0000``)."""
    return f"{x:+.4f}" if abs(x) >= 1e-3 or x == 0 else f"{x:+.1e}"


def _margin_cell(r: dict) -> str:
    """The margin's name and its bound ``M``."""
    return r["margin"] + ("" if r["ddh_bound"] is None else f" (M = {r['ddh_bound']:.3g})")


def price_cells(price: dict | None) -> list[str]:
    """The margin's paired price: median min h gain and median settle-time change."""
    if price is None:
        return ["-", "-"]
    gain, settle = price["median_min_h_gain"], price["median_settle_time_change"]
    return [
        "-" if gain is None else _signed(gain),
        "not measured" if settle is None else f"{settle:+.2f}",
    ]


def deployed_mc_table(rows: list[dict]) -> str:
    """docs/deployed.md's Monte Carlo table from benchmarks/deployed.py's --json rows.

    Per study, controller and margin: the trials below ``h = 0`` at and between the samples,
    the least ``h`` there and its median over trials, the data sets whose every trial was
    safe with the Clopper-Pearson interval, the trials (and steps) the limits could not make
    safe, the share of steps on the limit, and, on the margin's rows, its price against the
    same controller without it on the same trials.
    """
    body = []
    for r in rows:
        safe = r["safe_per_dataset"]
        low, high = safe["ci95"]
        # three decimals from 100 data sets on: 1,000 of 1,000 gives [0.996, 1.000], which
        # two decimals would round to [1.00, 1.00]
        digits = 3 if safe["datasets"] >= 100 else 2
        body.append([
            r["study"], r["controller"], _margin_cell(r),
            f"{r['left_at_samples']} / {r['trials']}",
            f"{r['left_between_samples']} / {r['trials']}",
            _signed(r["min_h_samples"]), _signed(r["min_h_between"]),
            _signed(r["median_min_h"]),
            f"{safe['count']}/{safe['datasets']}", f"[{low:.{digits}f}, {high:.{digits}f}]",
            f"{r['trials_with_unmet_steps']} ({r['unmet_steps']} steps)",
            f"{r['limit_step_fraction']:.3g}",
            *price_cells(r["price"]),
        ])  # fmt: skip
    header = ["study", "controller", "sampled-data margin", "trials below h = 0 at the samples",
              "trials below h = 0 between the samples", "min h at the samples",
              "min h between the samples", "median of each trial's min h",
              "safe data sets", "95 % interval",
              "trials with steps the limits could not make safe", "share of steps on the limit",
              "margin's price: median min h gain",
              "margin's price: median settle time change (s)"]  # fmt: skip
    align = ["---", "---", "---"] + ["---:"] * 11
    return _table(header, align, body)


def deployed_mc_timing(doc: dict) -> str:
    """The Monte Carlo part's measured time per data set and the projection to 1,000.

    From ``montecarlo_timings_s`` of benchmarks/deployed.py's --json document: every run's
    ``total`` (data sets and trials, the compilation included), summed over the two studies
    and the two margins, divided by the data sets. The projection scales it linearly, which
    overstates the time by the fixed compilation.
    """
    settings = doc["montecarlo_settings"]
    k = settings["datasets"]
    total = sum(t["total"] for runs in doc["montecarlo_timings_s"].values()
                for t in runs.values())  # fmt: skip
    per_set = total / k
    trials = "; ".join(f"{study.split(',')[0]}: {n} trials each"
                       for study, n in settings["trials_per_dataset"].items())  # fmt: skip
    text = (
        f"Measured here: {k:,} data sets ({trials}), both studies without and with the "
        f"margin, in {total:.0f} s: {per_set:.1f} s per data set, compilation included."
    )
    if k < 1000:  # the long step's own time needs no projection
        text += (
            f" 1,000 data sets would take about {1000 * per_set / 3600:.1f} h at that rate (an "
            f"overestimate: the compilation does not grow with the data sets)."
        )
    return text + "\n"


def deployed_table(rows: list[dict]) -> str:
    """docs/deployed.md's table from benchmarks/deployed.py's --json rows."""
    body = []
    for r in rows:
        statuses = ", ".join(f"{k} {v}" for k, v in r["statuses"].items()) or "-"
        body.append([
            r["case"], f"{r['rate_hz']:g}",
            r["margin"] + ("" if r["ddh_bound"] is None else f" (M = {r['ddh_bound']:.3g})"),
            f"{r['left_at_samples']} / {r['runs']}", f"{r['left_between_samples']} / {r['runs']}",
            _signed(r["min_h_samples"]), _signed(r["min_h_between"]),
            f"{r['steps_not_ok']} of {r['steps']}", statuses,
        ])  # fmt: skip
    header = ["loop", "rate (Hz)", "sampled-data margin", "runs below h = 0 at the samples",
              "runs below h = 0 between the samples", "min h at the samples",
              "min h between the samples", "steps not OK", "their statuses"]  # fmt: skip
    return _table(
        header, ["---", "---:", "---", "---:", "---:", "---:", "---:", "---:", "---"], body
    )


def _num(x: float | None) -> str:
    """A measured value as the tables print it.

    0 as ``0``; at least 0.01 to four significant digits; smaller in scientific notation with
    two; ``None`` (a non-finite value in strict JSON) as ``n/a``.
    """
    if x is None:
        return "n/a"
    if x == 0:
        return "0"
    return f"{x:.4g}" if abs(x) >= 0.01 else f"{x:.1e}"


def acc_table(doc: dict) -> str:
    """docs/acc.md's table for one ACC preset, and its GP line, from a metrics document."""
    from safestab.controller_names import NameMap

    rows = []  # NameMap: a document written before a rename is read with the current names
    for name, c in NameMap(doc["controllers"], where="acc metrics").items():
        regions = ", ".join(f"{k} {100 * v:.0f} %" for k, v in c["region_fraction"].items() if v)
        rows.append([
            name, f"{c['min_h_m']:+.3f}", _num(c["time_h_negative_s"]),
            f"{c['rms_speed_error_mps']:.3f}", _num(c.get("max_abs_h_gap_to_true_m", 0.0)),
            _num(c.get("rms_vf_gap_to_true_mps", 0.0)), _num(c["max_abs_u_over_Mg"]),
            f"{c['incompatible_steps']:,}", regions,
        ])  # fmt: skip
    header = ["controller", "min h (m)", "time with h < 0 (s)", "RMS of v_f - v_d (m/s)",
              "largest abs(h - h_true) (m)", "RMS of v_f - v_f,true (m/s)",
              "largest abs(u) (M g)", "steps where CLF and CBF are incompatible",
              "regions (Theorem 3)"]  # fmt: skip
    gp = doc["gp"]
    cover = ", ".join(f"{100 * c:.0f} %" for c in gp["held_out_coverage"])
    rmse = ", ".join(f"{r:.1e}" for r in gp["held_out_rmse"])
    line = (
        f"GP ({gp['n_samples']:,} samples): held-out coverage of `omega` at `beta = "
        f"{gp['beta']:g}` {cover} per component ({100 * gp['held_out_joint_coverage']:.0f} % "
        f"jointly); held-out RMSE per component {rmse} m/s^2."
    )
    return _table(header, ["---"] + ["---:"] * 7 + ["---"], rows) + "\n" + line + "\n"


def swarm_tables(doc: dict) -> tuple[str, str]:
    """docs/swarm.md's results (table and the figures the text quotes) and its solver table."""
    runs = doc["runs"]
    rows = []
    for mode, label in (("centralized", "centralized"), ("decentralized", "decentralized"),
                        ("unfiltered", "unfiltered (no filter)")):  # fmt: skip
        r = runs[mode]
        if r["arrival_time_s"] is not None:
            arrival = f"at {r['arrival_time_s']:.2f} s"
        else:
            arrival = f"never (largest goal error {r['final_max_goal_error_m']:.2f} m at the end)"
        statuses = ", ".join(f"{k} {v:,}" for k, v in r["solver_statuses"].items()) or "-"
        rows.append([label, f"{r['min_distance_m']:.6f}", str(r["steps_below_safety_distance"]),
                     arrival, f"{r['mean_input_change_mps']:.3f}", statuses])  # fmt: skip
    header = ["filter", "least pair distance (m)", "steps below the safety distance",
              "all robots within the goal tolerance", "mean change to the input (m/s)",
              "solver statuses (robot-steps)"]  # fmt: skip
    results = _table(header, ["---", "---:", "---:", "---:", "---:", "---"], rows)
    cen, nom = runs["centralized"], runs["unfiltered"]
    facts = [f"Without a filter the robots pass within {1000 * nom['min_distance_m']:.1f} mm of "
             "each other."]  # fmt: skip
    if cen["arrival_time_s"] is not None and nom["arrival_time_s"] is not None:
        delay = cen["arrival_time_s"] - nom["arrival_time_s"]
        facts.append(f"The centralized filter arrives {delay:.2f} s after the unfiltered swarm.")
    results += "\n" + "\n".join(f"- {f}" for f in facts) + "\n"
    solver_rows = []
    for solver, label in (("osqp", "OSQP"), ("clarabel", "Clarabel")):
        r = doc["loose_solvers_on_centralized_states"].get(solver, {})
        if "states" not in r:
            solver_rows.append([label, r.get("note", "not run"), "", "", ""])
            continue
        solver_rows.append([
            f"{label} ({r['states']} states)", _num(r["max_input_gap_mps"]),
            _num(r["median_input_gap_mps"]), f"{100 * r['share_of_states_violating']:.0f} %",
            _num(r["max_barrier_violation_m2ps"]),
        ])  # fmt: skip
    header = ["solver (qpsolvers, default tolerances)", "largest input difference (m/s)",
              "median (m/s)", "states where a barrier is violated",
              "largest violation of `c + d.u >= 0` (m^2/s)"]  # fmt: skip
    return results, _table(header, ["---"] + ["---:"] * 4, solver_rows)


def price_table(doc: dict) -> str:
    """docs/price.md's tables for one scenario (benchmarks/price_of_robustness.py's JSON).

    Per size and GP controller: the safe data sets and the median margin paid over the true
    model; then the median time to converge beyond the true model's and the median input gap
    to the true-model controller at the same state.
    """
    ref = doc["settings"]["reference"]
    names = [n for n in doc["settings"]["controllers"] if n != ref]
    unit = doc["h_unit"]
    safety, effort = [], []
    for point in doc["points"]:
        q = f"{point['n_samples']:,}"
        row_s, row_e = [q], [q]
        for n in names:
            e = point["controllers"][n]
            s = e["safe_per_dataset"]
            row_s.append(f"{s['count']}/{s['datasets']}, {e['min_h_excess']['0.5']:+.2g}")
            row_e.append(f"{e['settle_time_excess']['0.5']:+.3g}, "
                         f"{e['mean_input_gap']['0.5']:.2g}")  # fmt: skip
        safety.append(row_s)
        effort.append(row_e)
    head_s = ["Q"] + [f"{n}: safe data sets, median min h - min h_true ({unit})" for n in names]
    head_e = ["Q"] + [f"{n}: median settle time - settle time_true (s), median input gap"
                      for n in names]  # fmt: skip
    align = ["---:"] * (len(names) + 1)
    return _table(head_s, align, safety) + "\n" + _table(head_e, align, effort)


def price_limited_table(doc: dict) -> str:
    """docs/price.md's table under the input limits: a row per size and controller.

    Safe data sets with the exact interval, the median margin and settle time paid over the
    true model, the share of steps with the input on a limit, and the trials (and steps)
    whose status said the barrier's condition could not be met in the limits.
    """
    unit = doc["h_unit"]
    rows = []
    for point in doc["points"]:
        for name in doc["settings"]["controllers"]:
            e = point["controllers"][name]
            s = e["safe_per_dataset"]
            lo, hi = s["ci95"]
            rows.append([
                f"{point['n_samples']:,}", name, f"{s['count']}/{s['datasets']}",
                f"[{lo:.2f}, {hi:.2f}]", f"{e['min_h_excess']['0.5']:+.2g}",
                f"{e['settle_time_excess']['0.5']:+.3g}", f"{e['limit_step_fraction']:.3g}",
                f"{e['barrier_unmet_trials']} ({e['barrier_unmet_steps']} steps)",
            ])  # fmt: skip
    trials = doc["settings"]["datasets"] * doc["settings"]["trials_per_dataset"]
    header = ["Q", "controller", "safe data sets", "95 % interval",
              f"median min h - min h_true ({unit})", "median settle time - settle time_true (s)",
              "share of steps on the limit",
              f"trials (of {trials}) with steps the limits could not make safe"]  # fmt: skip
    return _table(header, ["---:", "---"] + ["---:"] * 6, rows)


def mc_table(doc: dict) -> str:
    """A Monte Carlo metrics document's table (safestab.montecarlo.report.markdown_table)."""
    from safestab.montecarlo.report import markdown_table

    return markdown_table(doc)


# -- steps -------------------------------------------------------------------------------

#: Files a step makes besides its tables (figures, a JSON summary), by path under the
#: repository root; ``main`` writes them, or with ``--check`` only compares them.
FILES: dict[str, bytes] = {}
#: Files rewritten on every run (timings inside), never compared.
MANIFESTS: dict[str, str] = {}


def _run(cmd: list[str]) -> None:
    print("  $ " + shlex.join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)


def _all_controllers() -> str:
    """Every controller a Monte Carlo study can compare, as ``--controllers`` takes them."""
    from safestab.controller_names import CONTROLLERS

    return ",".join(CONTROLLERS)


def _load(path: Path) -> dict:
    return json.loads(path.read_text())


def _copy(src: Path, dst: str) -> None:
    """Queue ``src`` to be copied to ``docs/<dst>``."""
    FILES[f"docs/{dst}"] = src.read_bytes()


@functools.cache
def _gallery_figures() -> dict[str, str]:
    """scripts/make_gallery.py's figures: name to file name (its module loaded once)."""
    spec = importlib.util.spec_from_file_location(
        "make_gallery", ROOT / "scripts" / "make_gallery.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return {name: file for name, (file, _) in module.FIGURES.items()}


def _gallery(out: Path, names: list[str], results: Path | None = None) -> None:
    """Run make_gallery.py for ``names`` into ``out``; queue the figures and manifest entries.

    The manifest keeps the entries of the figures not remade (it records each figure's
    command and seconds, so its text changes on every run and is not compared by --check).
    """
    folder = out / "gallery"
    cmd = [sys.executable, "scripts/make_gallery.py", "--out", str(folder), "--only", *names]
    _run(cmd + (["--results", str(results)] if results else []))
    files = _gallery_figures()
    for name in names:
        _copy(folder / files[name], f"gallery/{files[name]}")
    manifest = _load(DOCS / "gallery" / "manifest.json")
    manifest.update({n: e for n, e in _load(folder / "manifest.json").items() if n in names})
    MANIFESTS["docs/gallery/manifest.json"] = json.dumps(dict(sorted(manifest.items())),
                                                         indent=2) + "\n"  # fmt: skip


def step_acc(out: Path) -> dict[str, tuple[str, str]]:
    """The ACC presets (``safestab acc``, through scripts/make_gallery.py): docs/acc.md."""
    folder = out / "acc"
    _gallery(out, ["acc_paper", "acc_stress"], results=folder)
    return {f"acc-{p}": ("docs/acc.md", acc_table(_load(folder / f"acc_{p}_metrics.json")))
            for p in ("paper", "stress")}  # fmt: skip


def step_gallery(out: Path) -> dict[str, tuple[str, str]]:
    """The gallery's other figures (formulas, QP geometry, regions, GP band...): no tables."""
    _gallery(out, [name for name in _gallery_figures() if not name.startswith("acc_")])
    return {}


def step_swarm(out: Path) -> dict[str, tuple[str, str]]:
    """The swarm preset: docs/swarm.md's two tables and its figure."""
    folder = out / "swarm"
    _run([*SAFESTAB, "run", "--scenario", "swarm", "--out", str(folder)])
    _copy(folder / "swarm_swarm.png", "figures/swarm.png")
    results, solvers = swarm_tables(_load(folder / "swarm_swarm_metrics.json"))
    return {"swarm-results": ("docs/swarm.md", results),
            "swarm-loose-solvers": ("docs/swarm.md", solvers)}  # fmt: skip


def swarm_mc_table(doc: dict) -> str:
    """docs/swarm.md's Monte Carlo table: per mode the safe trials, least distances, arrivals."""
    s = doc["summary"]
    rows = []
    for mode, m in s["modes"].items():
        lo, hi = m["safe"]["ci95"]
        q = m["min_distance_quantiles_m"]
        at = m["arrival_time_quantiles_s"]
        arrived = f"{m['arrived']['count']} of {m['arrived']['trials']}"
        if at is not None:
            arrived += f" (median {at['0.5']:.2f} s)"
        worst = m["worst_trial"]
        statuses = ", ".join(f"{k} {v:,}" for k, v in m["solver_statuses"].items()) or "-"
        rows.append([mode, f"{m['safe']['count']} of {m['safe']['trials']} [{lo:.3f}, {hi:.3f}]",
                     str(m["at_safety_distance"]), f"{q['0.0']:.6f} / {q['0.5']:.6f}",
                     f"{worst['index']} (seed {worst['seed']})", arrived, statuses])  # fmt: skip
    header = ["mode", "safe trials [95 % CI]",
              f"of which at the safety distance (to {s['rounding_band_m']:g} m)",
              "least pair distance (m): min / median", "worst trial", "all robots arrived",
              "solver statuses (robot-steps)"]  # fmt: skip
    return _table(header, ["---", "---:", "---:", "---:", "---:", "---:", "---"], rows)


def step_swarm_mc(out: Path) -> dict[str, tuple[str, str]]:
    """``safestab mc --scenario swarm`` with its defaults: docs/swarm.md's Monte Carlo block.

    Its table, its figure and the command's measured wall time.
    """
    folder = out / "swarm-mc"
    t0 = time.perf_counter()
    _run([*SAFESTAB, "mc", "--scenario", "swarm", "--out", str(folder)])
    wall = time.perf_counter() - t0
    _copy(folder / "mc_swarm.png", "figures/swarm_mc.png")
    doc = _load(folder / "mc_swarm_metrics.json")
    timing = (
        f"Measured here: {wall:.0f} s for the command ({doc['settings']['trials']} trials of "
        f"each mode, chunks of {doc['settings']['chunk_size']}), of which "
        f"{doc['timings_s']['total']:.0f} s ran the trials, compilation included.\n"
    )
    return {"swarm-mc": ("docs/swarm.md", swarm_mc_table(doc)),
            "swarm-mc-time": ("docs/swarm.md", timing)}  # fmt: skip


def step_obstacle(out: Path) -> dict[str, tuple[str, str]]:
    """The obstacle preset (main job): its outcome table and both figures."""
    folder = out / "obstacle"
    _run([*SAFESTAB, "run", "--scenario", "obstacle", "--out", str(folder)])
    for src, dst in (("obstacle_obstacle.png", "obstacle.png"),
                     ("obstacle_obstacle_maps.png", "obstacle_maps.png")):  # fmt: skip
        _copy(folder / src, f"figures/{dst}")
    doc = _load(folder / "obstacle_obstacle_metrics.json")
    # the same run without the boundary layer on the robust CLF term (the chattering it ends)
    plain = out / "obstacle-no-layer"
    _run([*SAFESTAB, "run", "--scenario", "obstacle", "--set", "controller.robust_clf_layer=0",
          "--out", str(plain)])  # fmt: skip
    doc_plain = _load(plain / "obstacle_obstacle_metrics.json")
    # the same run trusting the nominal input gain (the GP of omega alone)
    nominal = out / "obstacle-nominal-gain"
    _run([*SAFESTAB, "run", "--scenario", "obstacle", "--set", "learning.input_gain=nominal",
          "--out", str(nominal)])  # fmt: skip
    doc_nominal = _load(nominal / "obstacle_obstacle_metrics.json")
    # the same run with the input limits kept by the projection (eq. (26))
    projected = out / "obstacle-projection"
    _run([*SAFESTAB, "run", "--scenario", "obstacle", "--set",
          "controller.limit_method=projection", "--out", str(projected)])  # fmt: skip
    doc_projected = _load(projected / "obstacle_obstacle_metrics.json")
    axis = out / "obstacle_axis.json"
    _run([sys.executable, "benchmarks/obstacle_axis.py", "--json", str(axis)])
    return {
        "obstacle-outcomes": ("docs/obstacle.md", obstacle_table(doc)),
        "obstacle-gp": ("docs/obstacle.md", obstacle_gp_table(doc)),
        "obstacle-layer": ("docs/obstacle.md", obstacle_layer_table(doc, doc_plain)),
        "obstacle-gain": ("docs/obstacle.md", obstacle_gain_table(doc_nominal, doc)),
        "obstacle-gain-estimate": ("docs/obstacle.md", obstacle_gain_estimate(doc)),
        "obstacle-limits": ("docs/obstacle.md", obstacle_limits_table(doc, doc_projected)),
        "obstacle-axis": ("docs/obstacle.md", obstacle_axis_table(_load(axis))),
    }


def step_obstacle_seeds(out: Path) -> dict[str, tuple[str, str]]:
    """The obstacle preset at data seeds 0 to 4: the GP-robust rows' spread."""
    docs = []
    for seed in range(5):
        folder = out / f"obstacle-seed{seed}"
        _run([*SAFESTAB, "run", "--scenario", "obstacle", "--seed", str(seed), "--out",
              str(folder)])  # fmt: skip
        docs.append(_load(folder / "obstacle_obstacle_metrics.json"))
    return {"obstacle-seeds": ("docs/obstacle.md", obstacle_seed_table(docs))}


def step_mc_presets(out: Path) -> dict[str, tuple[str, str]]:
    """The three 200-trial, 2-data-set Monte Carlo runs: tables and figures."""
    tables = {}
    folder = out / "mc"
    for preset in ("stress", "paper", "stress-ood"):
        _run([*SAFESTAB, "mc", "--scenario", preset, "--trials", "200", "--datasets", "2",
              "--out", str(folder), "--seed", "0"])  # fmt: skip
        _copy(folder / f"mc_{preset}.png", f"figures/mc_{preset}.png")
        doc = _load(folder / f"mc_{preset}_metrics.json")
        tables[f"mc-{preset}"] = ("docs/montecarlo.md", mc_table(doc))
    return tables


def step_mc_datasets(out: Path) -> dict[str, tuple[str, str]]:
    """The 1,000-data-set stress study (--long): table, figure, summary JSON."""
    folder = out / "datasets"
    _run([*SAFESTAB, "mc", "--scenario", "stress", "--trials", "10000", "--datasets", "1000",
          "--controllers", _all_controllers(), "--out", str(folder)])  # fmt: skip
    _copy(folder / "mc_stress.png", "figures/mc_stress_datasets.png")
    doc = _load(folder / "mc_stress_metrics.json")
    FILES["docs/montecarlo_datasets.json"] = datasets_summary(folder).encode()
    return {"mc-datasets": ("docs/montecarlo.md", mc_table(doc))}


def datasets_summary(folder: Path) -> str:
    """docs/montecarlo_datasets.json: the study's command, settings, summary and timings.

    The per-data-set list (1,000 entries) stays in the result file.
    """
    doc = _load(folder / "mc_stress_metrics.json")
    record = _load(folder / "mc_stress_run.json")
    summary = {k: doc[k] for k in ("scenario", "status", "settings", "summary", "timings_s")}
    summary["datasets_with_cache_warnings"] = [d["index"] for d in doc["datasets"]
                                               if d["cache_warnings"]]  # fmt: skip
    summary["run"] = record
    return json.dumps(summary, indent=1, allow_nan=False) + "\n"


def _price_step(scenario: str, extra: list[str]):
    """The price-of-robustness study of one scenario (--long): its table and figure."""

    def step(out: Path) -> dict[str, tuple[str, str]]:
        folder = out / "price"
        _run([sys.executable, "benchmarks/price_of_robustness.py", "--scenario", scenario,
              "--out", str(folder), *extra])  # fmt: skip
        _copy(folder / f"price_{scenario}.png", f"figures/price_{scenario}.png")
        doc = _load(folder / f"price_{scenario}.json")
        return {f"price-{scenario}": ("docs/price.md", price_table(doc))}

    step.__doc__ = f"benchmarks/price_of_robustness.py --scenario {scenario} (--long)."
    return step


def step_price_limited(out: Path) -> dict[str, tuple[str, str]]:
    """The price study under the input limits, small counts (stress-limited, about 5 min)."""
    folder = out / "price-limited"
    _run([sys.executable, "benchmarks/price_of_robustness.py", "--scenario", "stress-limited",
          "--out", str(folder), *PRICE_LIMITED_ARGS])  # fmt: skip
    _copy(folder / "price_stress-limited.png", "figures/price_stress-limited.png")
    doc = _load(folder / "price_stress-limited.json")
    return {"price-limited": ("docs/price.md", price_limited_table(doc))}


#: The limited price study's counts: 4 sizes, 10 data sets of 2 trials (a normal step).
PRICE_LIMITED_ARGS = ["--q", "25", "100", "500", "2000", "--datasets", "10",
                      "--trials-per-dataset", "2"]  # fmt: skip

#: The price study's runs: scenario and arguments beyond the script's defaults (steps
#: ``price`` and ``price-obstacle``).
PRICE_RUNS = {
    "stress": [],
    "obstacle": ["--q", "25", "50", "100", "200", "400", "800", "1600", "--datasets", "20"],
}
step_price = _price_step("stress", PRICE_RUNS["stress"])
step_price_obstacle = _price_step("obstacle", PRICE_RUNS["obstacle"])


def step_gp_coverage(out: Path) -> dict[str, tuple[str, str]]:
    """benchmarks/gp_coverage.py over ten data seeds: docs/learning.md's table."""
    out.mkdir(parents=True, exist_ok=True)
    rows = out / "gp_coverage.json"
    seeds = [str(s) for s in range(10)]
    _run([sys.executable, "benchmarks/gp_coverage.py", "--seeds", *seeds, "--json", str(rows)])
    return {"gp-coverage": ("docs/learning.md", gp_coverage_table(_load(rows)))}


def step_fast_band(out: Path) -> dict[str, tuple[str, str]]:
    """benchmarks/fast_band.py over the four presets: docs/learning.md's cache-width table."""
    out.mkdir(parents=True, exist_ok=True)
    rows = out / "fast_band.json"
    _run([sys.executable, "benchmarks/fast_band.py", "--json", str(rows)])
    return {"fastgp-width": ("docs/learning.md", fast_band_table(_load(rows)))}


def step_mc_band(out: Path) -> dict[str, tuple[str, str]]:
    """benchmarks/mc_band_width.py on the stress and obstacle Monte Carlo's first 20 data sets."""
    out.mkdir(parents=True, exist_ok=True)
    rows = out / "mc_band_width.json"
    _run([sys.executable, "benchmarks/mc_band_width.py", "--presets", "stress", "obstacle",
          "--datasets", "20", "--json", str(rows)])  # fmt: skip
    return {"mc-band-width": ("docs/learning.md", mc_band_table(_load(rows)))}


def step_deployed(out: Path) -> dict[str, tuple[str, str]]:
    """benchmarks/deployed.py: docs/deployed.md's table (sampled loops, limits, between)."""
    out.mkdir(parents=True, exist_ok=True)
    rows = out / "deployed.json"
    _run([sys.executable, "benchmarks/deployed.py", "--json", str(rows)])
    doc = _load(rows)
    return {
        "deployed": ("docs/deployed.md", deployed_table(doc["loops"])),
        "deployed-mc": ("docs/deployed.md", deployed_mc_table(doc["montecarlo"])),
        "deployed-mc-time": ("docs/deployed.md", deployed_mc_timing(doc)),
    }


#: What a --long step's block says until that step has run (the docs' tests accept it).
LONG_PLACEHOLDER = "Not yet generated"

#: The 1,000-data-set deployed study's arguments to benchmarks/deployed.py (--long).
DEPLOYED_LONG_ARGS = ["--no-loops", "--datasets", "1000", "--trials-per-dataset", "10",
                      "--obstacle-trials-per-dataset", "10"]  # fmt: skip


def step_deployed_long(out: Path) -> dict[str, tuple[str, str]]:
    """The deployed Monte Carlo study at 1,000 data sets (--long): docs/deployed.md's block."""
    out.mkdir(parents=True, exist_ok=True)
    rows = out / "deployed_long.json"
    _run([sys.executable, "benchmarks/deployed.py", *DEPLOYED_LONG_ARGS, "--json", str(rows)])
    doc = _load(rows)
    return {
        "deployed-mc-long": ("docs/deployed.md", deployed_mc_table(doc["montecarlo"])),
        "deployed-mc-long-time": ("docs/deployed.md", deployed_mc_timing(doc)),
    }


def step_safe_rl(out: Path) -> dict[str, tuple[str, str]]:
    """benchmarks/gym_highway.py: the safe-RL tutorial's table and figure (highway-env)."""
    out.mkdir(parents=True, exist_ok=True)
    rows, fig = out / "safe_rl.json", out / "safe_rl.png"
    _run([sys.executable, "benchmarks/gym_highway.py", "--json", str(rows), "--figure", str(fig)])
    _copy(fig, "figures/safe_rl.png")
    return {"safe-rl": ("docs/tutorials/safe-rl.md", safe_rl_table(_load(rows)))}


STEPS: dict[str, Callable[[Path], dict[str, tuple[str, str]]]] = {
    "acc": step_acc,
    "swarm": step_swarm,
    "swarm-mc": step_swarm_mc,
    "obstacle": step_obstacle,
    "obstacle-seeds": step_obstacle_seeds,
    "mc-presets": step_mc_presets,
    "gp-coverage": step_gp_coverage,
    "fast-band": step_fast_band,
    "mc-band": step_mc_band,
    "deployed": step_deployed,
    "safe-rl": step_safe_rl,
    "gallery": step_gallery,
    "mc-datasets": step_mc_datasets,
    "deployed-long": step_deployed_long,
    "price": step_price,
    "price-obstacle": step_price_obstacle,
    "price-limited": step_price_limited,
}
LONG = {"mc-datasets", "deployed-long", "price", "price-obstacle"}
#: Blocks that state a measured time: written like the others, but a difference is reported,
#: not failed, by --check (a time depends on the machine and its load, like a figure's bytes).
MEASURED_TIMES = {"deployed-mc-time", "deployed-mc-long-time", "swarm-mc-time"}
#: The generated blocks each step writes (tests/test_docs_tools.py checks that every block
#: in docs/ is written by a step).
PRODUCES = {
    "acc": ["acc-paper", "acc-stress"],
    "swarm": ["swarm-results", "swarm-loose-solvers"],
    "swarm-mc": ["swarm-mc", "swarm-mc-time"],
    "obstacle": [
        "obstacle-outcomes",
        "obstacle-gp",
        "obstacle-layer",
        "obstacle-gain",
        "obstacle-gain-estimate",
        "obstacle-limits",
        "obstacle-axis",
    ],
    "obstacle-seeds": ["obstacle-seeds"],
    "mc-presets": ["mc-stress", "mc-paper", "mc-stress-ood"],
    "gp-coverage": ["gp-coverage"],
    "fast-band": ["fastgp-width"],
    "mc-band": ["mc-band-width"],
    "deployed": ["deployed", "deployed-mc", "deployed-mc-time"],
    "safe-rl": ["safe-rl"],
    "gallery": [],
    "mc-datasets": ["mc-datasets"],
    "deployed-long": ["deployed-mc-long", "deployed-mc-long-time"],
    "price": ["price-stress"],
    "price-obstacle": ["price-obstacle"],
    "price-limited": ["price-limited"],
}


def main(argv: list[str] | None = None) -> int:
    """Run the steps and rewrite their tables and files.

    With ``--check``, write nothing and return 1 if a table would change.
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", choices=sorted(STEPS), help="run these steps")
    parser.add_argument("--long", action="store_true", help="include " + ", ".join(LONG))
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 if a generated table would change")  # fmt: skip
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "docs",
                        help="folder for the runs' result files")  # fmt: skip
    args = parser.parse_args(argv)
    names = args.only or [n for n in STEPS if args.long or n not in LONG]
    changed: list[str] = []
    files_changed: list[str] = []
    times_changed: list[str] = []  # measured times: reported, never failed
    pages: dict[Path, str] = {}  # with --check, the pages as they would be
    total = time.perf_counter()
    for name in names:
        print(f"[{name}]", flush=True)
        t0 = time.perf_counter()
        FILES.clear()
        MANIFESTS.clear()
        written = STEPS[name](args.out)
        assert sorted(written) == sorted(PRODUCES[name]), (name, sorted(written))
        for block, (page, table) in written.items():
            body = "\n" + table + "\n"  # blank lines: Markdown renders the table apart
            path = ROOT / page
            text = pages.get(path, path.read_text())
            if blocks(text).get(block) != body:
                (times_changed if block in MEASURED_TIMES else changed).append(f"{page}: {block}")
            pages[path] = replace_block(text, block, body)
        files_changed += [
            rel for rel, data in FILES.items()
            if not (ROOT / rel).exists() or (ROOT / rel).read_bytes() != data
        ]  # fmt: skip
        if not args.check:  # written after each step, so a later failure keeps them
            for path, text in pages.items():
                path.write_text(text)
            for rel, data in FILES.items():
                (ROOT / rel).write_bytes(data)
            for rel, text in MANIFESTS.items():
                (ROOT / rel).write_text(text)
        print(f"[{name}] {time.perf_counter() - t0:.0f} s", flush=True)
    print(f"reran {', '.join(names)} in {time.perf_counter() - total:.0f} s")
    # figures are compared byte for byte and reported, but do not fail --check: their bytes
    # depend on the matplotlib and FreeType versions as well as on the numbers
    if files_changed:
        print("files whose bytes differ: " + ", ".join(files_changed))
    if times_changed:
        print("measured times that differ: " + ", ".join(times_changed))
    if changed:
        print(("would change: " if args.check else "changed: ") + ", ".join(changed))
        return 1 if args.check else 0
    print("no generated table changed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
