"""Every preset's export passes its own harness, and the float export stays safe.

* ``export_scenario`` for each preset (stress, paper, obstacle), controller (gp, nominal,
  true) and precision (double, float): the recorded harness, compiled with the strict flags,
  reports 0 mismatches. The GP ones fit the study's GP (tens of seconds each): slow-marked,
  run by ``bash scripts/run-tests.sh -m slow`` (README).
* ``cbf_margin``: the formula enforces the CBF condition with the margin and the flag reports
  it with half of it (checked against the Lie terms, by hand).
* The float export: wherever its ``cbf_satisfied`` says 1, the exact (float64, unmargined)
  step's Lie terms satisfy the CBF condition at the float step's input, on the harness box,
  its corners and far states; the float-widened GP band evaluated in float32 arithmetic
  contains the exact GP band.
"""

from __future__ import annotations

import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.errors import ParameterError
from safestab.export import NativeController, compile_native, export_function
from safestab.export.float_safety import box_test_states, float_safe_controller
from safestab.learning import FastGP
from safestab.scenarios import load_scenario
from safestab.scenarios.acc_study import study_controllers
from safestab.scenarios.export_study import export_scenario

from .systems_zoo import small_stress_gp

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")

PRESETS = ("stress", "paper", "obstacle")


def _check(rep):
    assert rep.passed, rep.harness_output[-3000:]
    assert " 0 mismatches" in rep.harness_output


@pytest.mark.parametrize("precision", ["double", "float"])
@pytest.mark.parametrize("controller", ["nominal", "true"])
@pytest.mark.parametrize("scenario", PRESETS)
def test_model_controllers_pass_their_harness(scenario, controller, precision, tmp_path):
    rep = export_scenario(scenario, tmp_path, controller=controller, precision=precision)
    _check(rep)
    header = next(tmp_path.glob("*.h")).read_text()
    assert ("CBF margin" in header) == (precision == "float")


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::safestab.errors.InducingPointsWarning")
@pytest.mark.parametrize(
    "scenario, precision",
    [(s, p) for s in PRESETS for p in ("double", "float") if (s, p) != ("stress", "float")],
)
def test_gp_controllers_pass_their_harness(scenario, precision, tmp_path):
    _check(export_scenario(scenario, tmp_path, controller="gp", precision=precision))


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::safestab.errors.InducingPointsWarning")
def test_float_export_of_an_unresolvable_gp_is_refused(tmp_path):
    # the stress preset's drag: posterior std 0.01 under a prior std of 34, a variance 1e-7
    # of the prior's, which float (7 digits) cannot form from amp^2 - |a|^2
    with pytest.raises(ParameterError, match="cannot evaluate this GP cache.*Export in double"):
        export_scenario("stress", tmp_path, controller="gp", precision="float")


# -- cbf_margin -------------------------------------------------------------------------


def _acc_controller(**kw):
    sc = load_scenario("paper")
    return sc, study_controllers(sc, None)["true model"].replace(**kw)


def test_cbf_margin_enforces_and_reports_the_tightened_condition():
    sc, base = _acc_controller()
    rng = np.random.default_rng(0)
    x = rng.uniform(sc.x0_low, sc.x0_high, (2000, 3))
    margin = 0.05
    tight = base.replace(cbf_margin=margin)
    out = tight.step_fn(x)
    a, b, c, d = (np.asarray(t) for t in out.terms)
    u = np.asarray(out.u_unconstrained)
    gamma = np.sqrt(c * c + float(tight.params["varphi"]) * np.sum(d * d, -1) ** 2)
    cond = c + np.sum(d * u, -1) - float(tight.params["rho"]) * gamma
    scale = np.abs(c) + gamma + np.sum(np.abs(d * u), -1)
    # the formula keeps the margin wherever the CBF constraint can be met (slack on the CLF)
    assert np.all(cond >= margin - 1e-12 * scale)
    active = np.abs(cond - margin) <= 1e-9 * scale
    assert active.sum() > 50  # states where the margin is what binds
    # the base controller is on the boundary there: the margin moved the input
    base_out = base.step_fn(x[active])
    assert np.all(np.asarray(base_out.u)[:, 0] != np.asarray(out.u)[active, 0])
    assert np.all(np.asarray(out.cbf_satisfied)[active])
    # the flag asks for half the margin: pin the input (a one-point box) to leave a quarter
    # or three quarters of it at one active state
    k = int(np.flatnonzero(active)[0])
    for share, expected in ((0.25, False), (0.75, True)):
        u_pin = float(u[k, 0] - (1.0 - share) * margin / d[k, 0])
        pinned = tight.replace(u_min=u_pin, u_max=u_pin).step_fn(x[k])
        assert float(pinned.u[0]) == u_pin
        assert bool(pinned.cbf_satisfied) is expected
        exact = ss.conditions_satisfied(a[k], b[k], c[k], d[k], [u_pin], **_params(tight))
        assert bool(exact.cbf_satisfied)  # the exact condition holds either way


def _params(ctrl):
    p = ctrl.params
    return {k: float(p[k]) for k in ("kappa", "rho", "phi", "varphi")}


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), [0.1, 0.2]])
def test_cbf_margin_bad_values_are_named(bad):
    with pytest.raises((ParameterError, ss.errors.DimensionError), match="cbf_margin"):
        _acc_controller(cbf_margin=bad)


def test_cbf_margin_is_a_tunable_leaf():
    _, ctrl = _acc_controller(cbf_margin=0.1)
    assert "cbf_margin" in ctrl.tunables()
    u = jax.jit(lambda c, x: c.step_fn(x).u)(ctrl, jnp.array([20.0, 18.0, 60.0]))
    assert np.all(np.isfinite(np.asarray(u)))


# -- float safety -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "scenario, which",
    [(s, w) for s in ("paper", "stress", "obstacle") for w in ("nominal", "true")]
    + [pytest.param(s, "gp", marks=pytest.mark.slow) for s in ("paper", "obstacle")],
)
@pytest.mark.filterwarnings("ignore::safestab.errors.InducingPointsWarning")
def test_float_flag_never_claims_a_violated_condition(scenario, which):
    from safestab.scenarios.export_study import scenario_controller
    from safestab.scenarios.loading import load

    sc = load(scenario)
    exact, *_ = scenario_controller(sc, which)
    ctrl_f, margin = float_safe_controller(exact, sc.x0_low, sc.x0_high)
    assert margin > 0
    native = NativeController(ctrl_f, name=f"f_{scenario}_{which}", precision="float")
    x = box_test_states(sc.x0_low, sc.x0_high)
    out_f = native.step(x)
    u_f = np.asarray(out_f.u, dtype=np.float64)
    flag = np.asarray(out_f.cbf_satisfied)
    ok = np.asarray(out_f.status) == 0
    # the exact step's Lie terms (float64, no margin, the float64 GP cache) at the float
    # step's input
    terms = exact.step_fn(x).terms
    flags = ss.conditions_satisfied(*terms, np.where(ok[:, None], u_f, 0.0), **_params(exact))
    assert flag.sum() > 0.5 * len(x)
    lied = flag & ok & ~np.asarray(flags.cbf_satisfied)
    assert not lied.any(), x[lied][:5]


def test_float_widened_gp_band_contains_the_exact_band_in_float32_arithmetic():
    """FastGP.for_precision("float") evaluated in float (its exported C, float variant)
    still contains the exact GP's band, in and far from the data."""
    sc, gp, rng = small_stress_gp()
    fast = FastGP(gp, 48).for_precision("float")  # 32 caps the drag (a warning)
    x = np.concatenate(
        [
            rng.uniform(sc.x0_low, sc.x0_high, (500, 3)),
            rng.uniform(np.array(sc.x0_low) - 60.0, np.array(sc.x0_high) + 300.0, (100, 3)),
        ]
    ).astype(np.float32)
    # the cache's mean and std as exported C in float (every operation rounded to float)
    native = compile_native(export_function(fast.mean_std, 3, "gpf", precision="float"))
    (mean32, std32), status = native.columns(np.ascontiguousarray(x))
    assert np.all(np.asarray(status) == 0)
    mean32, std32 = np.asarray(mean32, np.float64), np.asarray(std32, np.float64)
    mean_ex, std_ex = gp.predict(x.astype(np.float64), return_std=True)
    for beta in (1.0, 2.0, 5.0):
        assert np.all(mean32 - beta * std32 <= mean_ex - beta * std_ex)
        assert np.all(mean32 + beta * std32 >= mean_ex + beta * std_ex)
    # and the widening is what float needs, not a blanket: within 3x of the float64 cache
    _, std64 = FastGP(gp, 48).predict(x.astype(np.float64), return_std=True)
    assert np.median(std32 / std64) < 3.0


@pytest.mark.filterwarnings("ignore::safestab.errors.InducingPointsWarning")
def test_exported_gp_controller_runs_with_the_studys_beta_method():
    """learning.beta_method = "conformal": the exported GP controller's beta is the split
    conformal one of the exported cache (as the study calibrates its own), named in the
    header's description; with "chosen", the file's gp_beta."""
    from safestab.scenarios import load
    from safestab.scenarios.export_study import scenario_controller
    from safestab.scenarios.obstacle_study import calibrate_beta, fit_obstacle_gp

    sc = load("obstacle").replace(n_samples=60, hyper_subset=60)
    assert sc.beta_method == "conformal"
    ctrl, description, _ = scenario_controller(sc, "gp", n_inducing=8)
    _, gp, _, _ = fit_obstacle_gp(sc.replace(n_inducing=0))
    expected = calibrate_beta(sc, FastGP(gp, n_inducing=8))["beta"]
    assert expected != sc.gp_beta
    np.testing.assert_array_equal(np.asarray(ctrl.gp_beta), expected)
    assert f"GP beta = {expected:.6g}, split conformal on 100 fresh trajectories" in description
    # the preset's boundary layer on the robust CLF term reaches the controller and the
    # exported header's description
    assert float(ctrl.robust_clf_layer) == sc.robust_clf_layer == 0.2
    exported = ss.export.export_c(ctrl, "obstacle")
    assert "Boundary layer on the robust CLF term, eps = 0.2" in exported.header
    chosen = sc.replace(beta_method="chosen")
    ctrl, description, _ = scenario_controller(chosen, "gp", n_inducing=8)
    np.testing.assert_array_equal(np.asarray(ctrl.gp_beta), sc.gp_beta)
    assert "GP beta = 2 (learning.gp_beta)" in description


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::safestab.errors.InducingPointsWarning")
def test_a_float_target_build_of_an_unresolvable_gp_picks_double_and_says_so(tmp_path, tools):
    # benchmarks/embedded.py's stress, gp, cortex-m4 row runs the same export
    said = []
    rep = export_scenario("stress", tmp_path, controller="gp", precision="float", cases=8,
                          target="cortex-m4", progress=said.append)  # fmt: skip
    assert rep.exported.precision == "double"
    assert rep.embedded.precision == "double"
    assert len(rep.notes) == 1 and "cannot evaluate this GP cache" in rep.notes[0]
    assert "in double instead" in rep.notes[0] and rep.notes[0] in said
    assert "Double, not float" in next(tmp_path.glob("*.h")).read_text()
    _check(rep)
    assert rep.embedded.harness_mismatches == 0


# -- the float safety filter --------------------------------------------------------------


def _filter_condition_holds(filt, x, u):
    """Every CBF condition of ``filt`` (float64 rows, no margin) at ``u``: (N, k)."""
    _, _, c, d, _ = jax.vmap(filt.rows)(jnp.asarray(x))
    c, d = np.asarray(c), np.asarray(d)
    du = d * u[:, None, :]
    return c + du.sum(-1) >= -1e-13 * (np.abs(c) + np.abs(du).sum(-1))  # rho = 0 here


@pytest.mark.parametrize("margin", [True, False])
# the host gcc's vectoriser crashes on the float filter (an internal compiler error); the
# export compiles it again without it and says so (safestab/export/native.py)
@pytest.mark.filterwarnings("ignore:.*internal compiler error:RuntimeWarning")
def test_float_filter_flag_never_claims_a_violated_condition(margin):
    from tests.systems_zoo import disc_filter

    exact = disc_filter()
    lo, hi = [-2.5, -2.5], [8.0, 4.0]
    ctrl_f, m = float_safe_controller(exact, lo, hi)
    assert ctrl_f.precision == "float" and m > 0
    if not margin:  # float's tolerances without the margin: the test can fail
        ctrl_f = ctrl_f.replace(cbf_margin=None)
    native = NativeController(ctrl_f, name=f"ffilt{int(margin)}", precision="float")
    x = box_test_states(lo, hi)
    out_f = native.step(x)
    u_f = np.asarray(out_f.u, dtype=np.float64)
    ok = np.asarray(out_f.status) == 0
    flag = np.asarray(out_f.cbf_satisfied) & ok[:, None]
    holds = _filter_condition_holds(exact, x, np.where(ok[:, None], u_f, 0.0))
    lied = flag & ~holds
    if margin:
        assert ok.mean() > 0.5, np.unique(np.asarray(out_f.status), return_counts=True)
        assert not lied.any(), x[lied.any(-1)][:5]
    else:
        assert lied.any()  # a tight row in float misses the float64 condition by rounding


def test_float_filter_takes_floats_tolerances_and_the_double_filters_decisions():
    """precision="float" scales the solver's tolerances to float's rounding: in float64
    arithmetic it ends on the double filter's active sets and statuses at these states."""
    from safestab.formulas._dual_active_set import UNIT_FLOAT
    from tests.systems_zoo import disc_filter, disc_states

    exact = disc_filter()
    x = disc_states()
    as_float = exact.replace(precision="float")
    assert as_float.formula.unit == UNIT_FLOAT and as_float.precision == "float"
    out, out_f = exact.step_fn(x), as_float.step_fn(x)
    np.testing.assert_array_equal(np.asarray(out_f.status), np.asarray(out.status))
    np.testing.assert_array_equal(np.asarray(out_f.active), np.asarray(out.active))
    np.testing.assert_allclose(np.asarray(out_f.u), np.asarray(out.u), rtol=0, atol=1e-4)
    with pytest.raises(ParameterError, match="precision must be one of"):
        exact.replace(precision="half")


@pytest.mark.slow
def test_float_filter_passes_its_harness_on_the_cortex_m4f(tmp_path, tools):
    # benchmarks/embedded.py's float filter row runs such an export (8 discs, its own box)
    from safestab.export.embedded import export_for_target
    from tests.systems_zoo import disc_filter, disc_states

    ctrl_f, _ = float_safe_controller(disc_filter(), [-2.5, -2.5], [8.0, 4.0])
    rep = export_for_target(ctrl_f, "ffilt", tmp_path, disc_states()[:64], "cortex-m4",
                            precision="float")  # fmt: skip
    assert rep.precision == "float"
    assert rep.harness_mismatches == 0, rep.harness_output[-2000:]


def _rho_filter(**kw):
    from tests.systems_zoo import disc_robot

    system, cbfs = disc_robot()
    return ss.SafetyFilter(system, cbfs, u_nom=lambda x: jnp.array([1.0, 0.0]), rho=0.5,
                           varphi=0.3, u_min=-1.0, u_max=1.0, **kw)  # fmt: skip


def test_filter_cbf_margin_tightens_each_condition_by_the_margin_and_flags_at_half():
    """With rho > 0 (Gamma depends on c) the margin is added after Gamma, as the controllers'
    cbf_margin: the binding row sits at rho Gamma + m exactly, and the flag is judged at m/2
    (a hand check of each row against the rows' own terms)."""
    m = 0.05
    plain, tight = _rho_filter(), _rho_filter(cbf_margin=m)
    x = np.array([[-1.6, 0.1], [-1.3, -0.4], [1.5, 3.4], [-2.5, 0.0]])  # outside the discs
    out = tight.step_fn(x)
    assert np.all(np.asarray(out.status) == 0)
    _, _, c, d, _ = jax.vmap(tight.rows)(jnp.asarray(x))
    c, d, u = np.asarray(c), np.asarray(d), np.asarray(out.u)
    gamma = np.sqrt(c * c + 0.3 * np.sum(d * d, -1) ** 2)
    slack = c + np.sum(d * u[:, None, :], -1) - 0.5 * gamma  # c + d.u - rho Gamma
    active = np.asarray(out.active)[:, : c.shape[1]]
    assert active.any()  # some barrier binds
    np.testing.assert_allclose(slack[active], m, rtol=0, atol=1e-12)
    assert np.all(slack >= m - 1e-12)
    # the same states without the margin: the binding rows sit at 0
    out0 = plain.step_fn(x)
    act0 = np.asarray(out0.active)[:, : c.shape[1]]
    slack0 = c + np.sum(d * np.asarray(out0.u)[:, None, :], -1) - 0.5 * gamma
    np.testing.assert_allclose(slack0[act0], 0.0, rtol=0, atol=1e-12)
    # the flag is the hand check at m/2 (the binding rows, at m, are flagged)
    flags = np.asarray(out.cbf_satisfied)
    np.testing.assert_array_equal(flags, slack >= 0.5 * m - 1e-12)


@pytest.mark.parametrize("bad", [-0.1, float("nan"), [0.1, 0.2]])
def test_filter_cbf_margin_bad_values_are_named(bad):
    with pytest.raises((ParameterError, ss.errors.DimensionError), match="cbf_margin"):
        _rho_filter(cbf_margin=bad)


def test_filter_cbf_margin_is_refused_with_a_smooth_formula_and_float_safety_refuses_a_policy():
    from tests.systems_zoo import disc_robot

    system, cbfs = disc_robot()
    with pytest.raises(ParameterError, match="cbf_margin"):
        ss.SafetyFilter(system, cbfs[0], u_nom=lambda x: jnp.array([1.0, 0.0]),
                        formula=ss.formulas.ExplicitFilter(), cbf_margin=0.1)  # fmt: skip
    policy = ss.PolicyController(system, lambda x: jnp.array([1.0, 0.0]), cbfs=cbfs)
    with pytest.raises(ParameterError, match="PolicyController"):
        float_safe_controller(policy, [-1.0, -1.0], [1.0, 1.0])


def test_a_new_filter_cbf_margin_runs_the_same_program():
    from tests.jax_events import traces_while

    a = _rho_filter(cbf_margin=0.05)
    b = a.replace(cbf_margin=0.2)
    assert "cbf_margin" in a.tunables()
    x = jnp.array([-1.6, 0.1])
    ua = a.step_fn(x).u
    traces = []
    traces += traces_while(lambda: b.step_fn(x).u.block_until_ready())
    assert traces == [], traces
    assert not np.allclose(np.asarray(ua), np.asarray(b.step_fn(x).u))  # the numbers reached it
