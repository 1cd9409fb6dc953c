"""Issue 8, points 4 and 5: named statuses for non-finite values, and validation gaps."""

import io
import re
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

from safestab import (
    CBF,
    CLF,
    ControlAffineSystem,
    DimensionError,
    FormulaResult,
    InputTypeError,
    ModelError,
    NonFiniteError,
    NumericalError,
    ParameterError,
    StepStatus,
    UniversalController,
    clf_cbf,
    clf_cbf_relaxed,
    kkt_residuals,
    lie_terms,
    project_box,
    simulate,
    zeta,
)

from . import mpref

P = {"kappa": 0.1, "rho": 0.1, "phi": 1.0, "varphi": 1.0}


def _integrator(f=None, g=None, V=None, h=None):
    """A 2-state, 1-input system whose parts can be replaced by faulty ones."""
    system = ControlAffineSystem(
        f or (lambda x: jnp.array([x[1], -x[0]])),
        g or (lambda x: jnp.array([[0.0], [1.0]])),
        2,
    )
    clf = CLF(V or (lambda x: x @ x), lam=1.0)
    cbf = CBF(h or (lambda x: 4.0 - x[0] ** 2 - x[1] ** 2), beta=1.0)
    return system, clf, cbf


# NaN only where x[0] > 1, so construction (which traces, not evaluates) succeeds
def _nan_above_one(value):
    return lambda x: jnp.where(x[0] > 1.0, jnp.nan, 1.0) * value(x)


FAULTS = {
    "f(x)": {"f": _nan_above_one(lambda x: jnp.array([x[1], -x[0]]))},
    "g(x)": {"g": _nan_above_one(lambda x: jnp.array([[0.0], [1.0]]))},
    "V(x)": {"V": _nan_above_one(lambda x: x @ x)},
    "h(x)": {"h": _nan_above_one(lambda x: 4.0 - x[0] ** 2 - x[1] ** 2)},
}


@pytest.mark.parametrize("part", list(FAULTS))
def test_nan_from_the_model_is_a_named_status(part):
    system, clf, cbf = _integrator(**FAULTS[part])
    ctrl = UniversalController(system, clf, cbf, **P)
    x = np.array([[0.5, 0.2], [1.5, 0.2]])  # the second state triggers the NaN
    out = ctrl.step(x)
    assert out.status.tolist() == [StepStatus.OK, StepStatus.NONFINITE_MODEL]
    assert np.all(np.isfinite(np.asarray(out.u[0])))
    assert np.all(np.isnan(np.asarray(out.u[1])))
    # the old d = 0 branch read NaN as zero and said compatible: no flag may claim anything
    assert not bool(out.compatible[1])
    assert not bool(out.cbf_satisfied[1]) and not bool(out.clf_satisfied[1])
    with pytest.raises(
        NonFiniteError, match=rf"NONFINITE_MODEL at state index 1 .*{re.escape(part)}"
    ):
        ctrl.step(x, strict=True)


class _Uncertainty:
    """A hand-made uncertainty model with a fault at x[0] > 1."""

    n_states = 2

    def __init__(self, kind):
        self.kind = kind

    def mean_std(self, x):
        bad = x[0] > 1.0
        mean = jnp.zeros(2)
        std = jnp.full(2, 0.1)
        if self.kind == "nan_mean":
            mean = jnp.where(bad, jnp.nan, mean)
        elif self.kind == "negative_std":
            std = jnp.where(bad, -0.1, std)
        return mean, std


def test_nan_from_the_uncertainty_model_is_a_named_status():
    system, clf, cbf = _integrator()
    ctrl = UniversalController(system, clf, cbf, uncertainty=_Uncertainty("nan_mean"), **P)
    out = ctrl.step(np.array([[0.5, 0.0], [1.5, 0.0]]))
    assert out.status.tolist() == [StepStatus.OK, StepStatus.NONFINITE_UNCERTAINTY]
    with pytest.raises(NonFiniteError, match=r"NONFINITE_UNCERTAINTY .*uncertainty mean"):
        ctrl.step(np.array([1.5, 0.0]), strict=True)


def test_negative_std_is_an_error():
    system, clf, cbf = _integrator()
    ctrl = UniversalController(system, clf, cbf, uncertainty=_Uncertainty("negative_std"), **P)
    assert int(ctrl.step(np.array([0.5, 0.0])).status) == StepStatus.OK
    with pytest.raises(ModelError, match=r"negative standard deviation at state index 1"):
        ctrl.step(np.array([[0.5, 0.0], [1.5, 0.0]]))
    with pytest.raises(ModelError, match=r"negative standard deviation during the run"):
        simulate(ctrl, np.array([1.5, 0.0]), t_final=0.05, dt=0.01)


def test_diverging_plant_gets_a_status_and_the_first_time():
    system, clf, cbf = _integrator()
    ctrl = UniversalController(system, clf, cbf, **P)
    # the plant's drift x0' = x0^3 blows up in finite time from x0 = 1 (t* = 0.5 s)
    plant = ControlAffineSystem(
        lambda x: jnp.array([x[0] ** 3, 0.0]), lambda x: jnp.array([[0.0], [1.0]]), 2
    )
    traj = simulate(ctrl, np.array([1.0, 0.0]), t_final=1.0, dt=0.01, plant=plant)
    x = np.asarray(traj.x)
    first_bad = int(np.argmax(~np.all(np.isfinite(x), axis=-1)))  # independent: from x itself
    assert first_bad > 0 and not traj.ok
    status = np.asarray(traj.status)
    assert status[first_bad] == StepStatus.NONFINITE_STATE
    # before it the run stays on x1 = 0, where L_g h = -2 x1 = 0: once h < 0 (x0 > 2) the CBF
    # condition fails there and no input can move h, which the step names
    before = status[:first_bad]
    h = 4.0 - x[:first_bad, 0] ** 2 - x[:first_bad, 1] ** 2
    assert np.all(x[:first_bad, 1] == 0.0)
    np.testing.assert_array_equal(before == StepStatus.CBF_UNACTUATED, h < 0)
    np.testing.assert_array_equal(before == StepStatus.OK, h >= 0)
    first_unmet = int(np.argmax(h < 0))
    assert int(traj.first_failure_index) == first_unmet
    assert traj.failure_summary().startswith(f"CBF_UNACTUATED first at step {first_unmet}")
    assert f"{int(np.sum(h < 0))} of {status.size} steps missed a CBF condition" in (
        traj.failure_summary()
    )
    with pytest.raises(NonFiniteError, match=r"NONFINITE_STATE first at step"):
        simulate(ctrl, np.array([1.0, 0.0]), t_final=1.0, dt=0.01, plant=plant, strict=True)


# -- point 5: validation -------------------------------------------------------------------


def test_batch_axes_may_not_broadcast_into_a_bigger_batch():
    with pytest.raises(DimensionError, match=r"bigger batch \(3, 3\) than any argument's"):
        clf_cbf(np.ones((3, 1)), np.ones((3, 2)), np.ones(3), np.ones((3, 2)), **P)
    # a scalar a with a batch of b is fine and keeps the batch
    assert clf_cbf(1.0, np.ones((3, 2)), np.ones(3), np.ones((3, 2)), **P).u.shape == (3, 2)


def test_parameter_arrays_must_fit_the_batch():
    with pytest.raises(DimensionError, match=r"kappa must be a scalar or broadcast to the batch"):
        clf_cbf(
            np.ones(3), np.ones((3, 2)), np.ones(3), np.ones((3, 2)), **{**P, "kappa": np.ones(4)}
        )
    ok = clf_cbf(
        np.ones(3), np.ones((3, 2)), np.ones(3), np.ones((3, 2)), **{**P, "kappa": np.ones(3)}
    )
    assert ok.u.shape == (3, 2)


def test_project_box_bounds_must_fit_u():
    with pytest.raises(DimensionError, match=r"u_min must be a scalar or broadcast to the input"):
        project_box(np.zeros(2), -np.ones(3), np.ones(3))


def test_kkt_residuals_checks_its_arguments():
    res = clf_cbf(1.0, [1.0, 0.5], -1.0, [0.3, 1.0], **P)
    with pytest.raises(NonFiniteError, match=r"a must be finite"):
        kkt_residuals(np.nan, [1.0, 0.5], -1.0, [0.3, 1.0], res, **P)
    with pytest.raises(ParameterError, match=r"rho must be >= 0.0"):
        kkt_residuals(1.0, [1.0, 0.5], -1.0, [0.3, 1.0], res, **{**P, "rho": -1.0})
    with pytest.raises(DimensionError, match=r"u must have shape \(3,\)"):
        kkt_residuals(1.0, [1.0, 0.5, 0.0], -1.0, [0.3, 1.0, 0.0], res, **P)
    bad = FormulaResult(
        u=res.u, region=res.region, multipliers=res.multipliers[:1], slack=res.slack
    )
    with pytest.raises(DimensionError, match=r"result.multipliers must have shape \(2,\)"):
        kkt_residuals(1.0, [1.0, 0.5], -1.0, [0.3, 1.0], bad, **P)
    with pytest.raises(InputTypeError, match=r"result must be a FormulaResult"):
        kkt_residuals(1.0, [1.0, 0.5], -1.0, [0.3, 1.0], (res.u, res.region), **P)


@pytest.mark.parametrize(
    "pos, value, what",
    [
        (0, True, "bool"),
        (1, np.array([1.0 + 1j]), "complex"),
        (2, "1.0", "string"),
        (3, np.array([True]), "bool"),
    ],
)
def test_non_real_lie_terms_are_rejected(pos, value, what):
    args = [1.0, [1.0], -1.0, [1.0]]
    args[pos] = value
    name = "abcd"[pos]
    with pytest.raises(
        InputTypeError, match=rf"{name} must be a real number or array, got .*{what}"
    ):
        clf_cbf(*args, **P)


def test_non_real_states_are_rejected():
    system, clf, cbf = _integrator()
    ctrl = UniversalController(system, clf, cbf, **P)
    with pytest.raises(InputTypeError, match=r"x must be a real number or array, got dtype bool"):
        ctrl.step(np.array([True, False]))
    with pytest.raises(
        InputTypeError, match=r"x must be a real number or array, got dtype complex"
    ):
        lie_terms(system, clf, cbf, np.array([1.0 + 0j, 0.0]))


def test_model_functions_must_return_one_array():
    with pytest.raises(InputTypeError, match=r"f must return one JAX array .* got list"):
        ControlAffineSystem(lambda x: [x[1], -x[0]], lambda x: jnp.array([[0.0], [1.0]]), 2)


def test_certificate_rates_must_be_scalars():
    with pytest.raises(DimensionError, match=r"lam must be a scalar, got an array of shape \(2,\)"):
        CLF(lambda x: x @ x, lam=np.array([1.0, 2.0]))


def test_lie_terms_with_a_vector_V():
    system, _, cbf = _integrator()
    with pytest.raises(DimensionError, match=r"V must return a scalar, got shape \(2,\)"):
        lie_terms(system, CLF(lambda x: x, lam=1.0), cbf, np.zeros(2))


def test_limits_must_have_the_input_length():
    system, clf, cbf = _integrator()
    with pytest.raises(
        DimensionError, match=r"u_min must be a scalar or have shape \(n_inputs,\) = \(1,\)"
    ):
        UniversalController(system, clf, cbf, u_min=[-1.0, -1.0], u_max=[1.0, 1.0], **P)


def test_mean_std_must_return_the_state_shape():
    system, clf, cbf = _integrator()

    class Wrong:
        n_states = 2

        def mean_std(self, x):
            return jnp.zeros(3), jnp.zeros(3)

    with pytest.raises(
        DimensionError, match=r"mean_std\(x\) must return \(mean, std\), each of shape \(2,\)"
    ):
        UniversalController(system, clf, cbf, uncertainty=Wrong(), **P)


def test_exogenous_must_return_the_state_shape():
    system, clf, cbf = _integrator()
    ctrl = UniversalController(system, clf, cbf, **P)
    with pytest.raises(
        DimensionError, match=r"exogenous\(t\) must return shape \(2,\), got \(3,\)"
    ):
        simulate(ctrl, np.zeros(2), t_final=0.1, exogenous=lambda t: jnp.zeros(3))


def test_simulate_horizon_checks():
    system, clf, cbf = _integrator()
    ctrl = UniversalController(system, clf, cbf, **P)
    with pytest.raises(ParameterError, match=r"t_final must be >= dt \(at least one step\)"):
        simulate(ctrl, np.zeros(2), t_final=0.005, dt=0.01)
    with pytest.raises(ParameterError, match=r"t_final / dt must be <= 10000000 steps"):
        simulate(ctrl, np.zeros(2), t_final=1.0, dt=1e-9)


def test_tiny_slack_weight_and_huge_rho_stay_finite_or_are_rejected():
    # a subnormal weight would be flushed to zero by XLA: rejected with a named error
    with pytest.raises(ParameterError, match=r"slack_weight must be >= 2.2250738585072014e-308"):
        clf_cbf_relaxed(1.0, [1.0], -1.0, [1.0], slack_weight=1e-310, **P)
    # the smallest normal weight and rho = 1e155 give finite, exact answers
    params = {**P, "rho": 1e155}
    for kwargs in ({"slack_weight": 2.3e-308, **P}, {"slack_weight": 10.0, **params}):
        res = clf_cbf_relaxed(2.0, [1.0, 0.5], 0.5, [0.3, 1.0], **kwargs)
        assert np.all(np.isfinite(np.asarray(res.u))) and np.isfinite(float(res.slack))
        sw = kwargs.pop("slack_weight")
        u_ref, _, _, _ = mpref.solve(2.0, [1.0, 0.5], 0.5, [0.3, 1.0], slack_weight=sw, **kwargs)
        assert mpref.rel_error(np.asarray(res.u), u_ref) <= 1e-12
    res = clf_cbf(2.0, [1.0, 0.5], 0.5, [0.3, 1.0], **params)
    u_ref, _, _, _ = mpref.solve(2.0, [1.0, 0.5], 0.5, [0.3, 1.0], **params)
    assert mpref.rel_error(np.asarray(res.u), u_ref) <= 1e-12


# ------------------------------------------------------------------------------------------
# issue 27, section 4: bad inputs named before any work


def test_controller_without_a_clf_is_a_named_error():
    system = ControlAffineSystem(lambda x: jnp.zeros(1), lambda x: jnp.ones((1, 1)), 1)
    cbf = CBF(lambda x: 1.0 - x[0], beta=1.0)
    kw = dict(kappa=0.1, rho=0.1, phi=0.0, varphi=0.0)
    with pytest.raises(InputTypeError, match="clf must be a CLF, got NoneType.*SafetyFilter"):
        UniversalController(system, None, cbf, **kw)
    with pytest.raises(InputTypeError, match=r"cbf must be a CBF \(or None with .*\), got list"):
        UniversalController(system, CLF(lambda x: x[0] ** 2, lam=1.0), [cbf], **kw)


def test_a_preset_of_another_kind_is_named_as_such():
    from typer.testing import CliRunner

    from safestab.cli import app

    # `mc` runs any kind (tests/test_mc_protocol.py); `acc` runs the ACC only
    res = CliRunner().invoke(app, ["acc", "--scenario", "obstacle"])
    assert res.exit_code == 2
    assert "'obstacle' is a preset of another kind" in res.output
    assert "neither a preset" not in res.output


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (dict(precision="quad"), "precision must be 'double' or 'float', got 'quad'"),
        (dict(name="bad name;"), "name must be a C identifier"),
        (dict(n_inducing=0), "n_inducing must be an integer >= 1, got 0"),
    ],
)
def test_export_options_are_checked_before_the_data(option, message, tmp_path, monkeypatch):
    import safestab.scenarios.acc_study as acc_study
    from safestab.scenarios.export_study import export_scenario

    def no_data(*args, **kwargs):  # the check must come first: fail if data are collected
        raise AssertionError("data collected before the options were checked")

    monkeypatch.setattr(acc_study, "collect_study_data", no_data)
    with pytest.raises(ParameterError, match=re.escape(message)):
        export_scenario("stress", tmp_path / "out", controller="gp", **option)


def test_collect_data_refuses_a_diverging_system_and_a_short_box():
    from safestab import NonFiniteError
    from safestab.learning import collect_data

    blowup = ControlAffineSystem(lambda x: x**3, lambda x: jnp.eye(2), 2)  # finite escape time
    kw = dict(u_low=-1.0, u_high=1.0, n_samples=40, horizon=4.0, rate=5.0)
    with pytest.raises(NonFiniteError, match=r"of 40 samples are not finite .*diverged"):
        collect_data(blowup, blowup, x0=([2.0, 2.0], [3.0, 3.0]), **kw)
    stable = ControlAffineSystem(lambda x: -x, lambda x: jnp.eye(2), 2)
    with pytest.raises(DimensionError, match=r"x0 must be .*shape \(2,\), got \[\(1,\), \(1,\)\]"):
        collect_data(stable, stable, x0=([0.0], [1.0]), **kw)
    with pytest.raises(DimensionError, match=r"u_low must be a scalar or have shape \(2,\)"):
        collect_data(stable, stable, x0=(0.0, 1.0), **{**kw, "u_low": [-1.0, -1.0, -1.0]})
    with pytest.raises(NonFiniteError, match="x0 high"):
        collect_data(stable, stable, x0=(0.0, np.inf), **kw)


def test_gp_fit_names_huge_and_non_real_data():
    from safestab.learning import GaussianProcessModel

    x = np.random.default_rng(0).normal(size=(30, 1))
    with pytest.raises(ParameterError, match=r"y has entries up to 1e\+300 .*rescale"):
        GaussianProcessModel().fit(x, np.full((30, 1), 1e300))
    with pytest.raises(InputTypeError, match="x must be a real number or array, got dtype string"):
        GaussianProcessModel().fit(x.astype(str), x)


def test_simulate_takes_a_safety_filter():
    # once a raw AttributeError (no attribute 'clf'): a filter is a controller to its users
    from safestab import SafetyFilter

    system = ControlAffineSystem(lambda x: jnp.zeros(1), lambda x: jnp.ones((1, 1)), 1)
    filt = SafetyFilter(system, CBF(lambda x: 1.0 - x[0], beta=1.0), u_nom=np.ones(1))
    traj = simulate(filt, np.zeros(1), t_final=1.0, dt=0.1)
    assert traj.h.shape == (11, 1) and traj.V.shape == (11, 0) and traj.ok
    # u = min(1, 1 - x) keeps h = 1 - x >= 0 and approaches it from above
    assert np.all(np.asarray(traj.h) >= 0) and np.all(np.diff(np.asarray(traj.h)[:, 0]) < 0)


def test_mc_help_keeps_its_bracketed_words():
    from typer.testing import CliRunner

    from safestab.cli import app

    res = CliRunner().invoke(app, ["mc", "--help"], env={"COLUMNS": "120"})
    assert res.exit_code == 0
    assert "[montecarlo]" in res.output  # rich markup ate "[montecarlo]"


def test_mc_table_fits_an_80_column_terminal():
    from rich.console import Console

    from safestab.montecarlo.plugin import summary_table as mc_table

    entry = {"rate": 0.99987, "ci95": [0.99961, 1.0]}
    names = ("true model", "mismatched model", "GP mean", "GP-robust", "GP-robust Lemma 2")
    claim = {"claimed_probability": 0.9703, "unit": "data set"}
    summary = {
        "trials": 10000, "datasets": 1000,
        "controllers": {
            n: {"safe": entry, "safe_per_dataset": entry, "lemma2_per_dataset": entry,
                "min_h_quantiles": {"0.01": 12.345},
                "guarantee": claim if "Lemma" in n else None}
            for n in names
        },
    }  # fmt: skip
    console = Console(width=80, record=True, file=io.StringIO())
    console.print(mc_table("stress", summary))
    text = console.export_text()
    assert "…" not in text  # nothing cut
    assert max(len(line) for line in text.splitlines()) <= 80
    assert text.count("[1.000, 1.000]") == 15  # every interval whole (names may wrap)
    assert text.count("0.9703") == 1  # the claim only where the beta carries one
    assert "mismatched" in text and "Lemma 2" in text
    assert "10000 trials, 1000 data sets" in text


def test_counts_take_their_nouns_in_the_right_number():
    from safestab.montecarlo.report import counted

    assert counted(1, "data set") == "1 data set"
    assert counted(0, "trial") == "0 trials"
    assert counted(1000, "data set") == "1000 data sets"


def test_ecdf_axis_is_linear_only_near_zero():
    from safestab.montecarlo.report import symlog_threshold

    rng = np.random.default_rng(0)
    tight = rng.uniform(0.5e-3, 1.5e-3, 200)  # a controller that grazes h = 0 (about 1 mm)
    wide = rng.uniform(5.0, 50.0, 200)  # the Lemma-2 controller's tens of metres
    lin = symlog_threshold(np.stack([wide, tight, np.full(200, np.nan)], 1))
    assert np.isclose(lin, np.median(tight) / 10)  # the millimetre curve gets its own decades
    assert symlog_threshold(np.zeros((5, 2))) == 1.0


def test_a_none_term_is_named_not_a_raw_jax_error():
    # found by tests/test_properties.py: c=None passed the check (None meant "no CBF pair")
    with pytest.raises(InputTypeError, match="c must be a real number or array"):
        clf_cbf(0.0, np.ones(2), None, np.ones(2), kappa=0, rho=0, phi=0, varphi=0)


def test_zeta_names_its_overflow():
    # sqrt(phi) |b|^2 = 1e600: not representable; once returned inf without an error
    with pytest.raises(NumericalError, match="zeta: the exact zeta is not representable"):
        zeta(0.0, np.array([0.0, 1e300]), 1.0)
    assert float(zeta(0.0, np.array([0.0, 1e100]), 1.0)) == pytest.approx(1e200)


def test_lie_terms_name_a_model_that_overflows_at_a_finite_state():
    # found by tests/test_properties.py: V = |x|^2 at x = 1e300 gave inf terms, no error
    system, clf, cbf = _integrator()
    with pytest.raises(NonFiniteError, match=r"the Lie term a is not finite at state index 1"):
        lie_terms(system, clf, cbf, np.array([[0.5, 0.0], [1e300, 0.0]]))


def test_collect_data_counts_must_be_integers():
    from safestab.learning import collect_data

    system = ControlAffineSystem(lambda x: -x, lambda x: jnp.ones((1, 1)), 1)
    for bad in (None, 2.5, "20", True):
        with pytest.raises(ParameterError, match=r"n_samples must be an integer >= 1, got"):
            collect_data(system, system, x0=(-1.0, 1.0), u_low=-1.0, u_high=1.0, n_samples=bad)


def test_gp_predict_refuses_complex_states():
    # once silently dropped the imaginary part (a NumPy ComplexWarning)
    from safestab.learning import GaussianProcessModel

    x = np.linspace(-1, 1, 25)[:, None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = GaussianProcessModel().fit(x, np.sin(x) + 0.01 * np.cos(7 * x))
    with pytest.raises(InputTypeError, match="x must be a real number or array, got dtype complex"):
        gp.predict(np.zeros((2, 1)) + 1j)
