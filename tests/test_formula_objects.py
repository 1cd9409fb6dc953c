"""The formulas as values: Problem, the formula objects' solve, and the controllers that hold
them. Answers are checked against the mpmath references (tests/mpref.py, filter_cases)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.errors import ParameterError
from safestab.formulas import (
    CBFFormula,
    CombinedFormula,
    MultiFormula,
    Problem,
    RelaxedFormula,
    SontagFormula,
)

from . import filter_cases, mpref


def _pairs(seed, n=40, m=3):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        a, c = rng.normal() * 3, rng.normal() * 3
        b, d = rng.normal(size=m), rng.normal(size=m)
        params = dict(kappa=rng.uniform(0, 1), rho=rng.uniform(0, 1),
                      phi=rng.uniform(0, 2), varphi=rng.uniform(0, 2))  # fmt: skip
        out.append((a, b, c, d, params))
    return out


@pytest.mark.parametrize("slack_weight", [None, 7.0])
def test_combined_and_relaxed_solve_match_the_mpmath_qp(slack_weight):
    formula = CombinedFormula() if slack_weight is None else RelaxedFormula()
    for a, b, c, d, params in _pairs(1):
        problem = Problem(a, b, c, d, **params, slack_weight=slack_weight)
        res = jax.jit(formula.solve)(problem)
        u_ref, chi_ref, region, ratio = mpref.solve(a, b, c, d, **params, slack_weight=slack_weight)
        if region == ss.Region.INCOMPATIBLE or ratio < 1e-6:
            continue  # the fallback and the tolerance's edge are tested in test_formulas
        assert int(res.region) == int(region)
        assert mpref.rel_error(np.asarray(res.u), u_ref) < 1e-12


def test_single_formulas_report_multipliers_that_give_their_input():
    # Sontag: u = -lambda1 b; the CBF formula: u = lambda2 d (their closed forms, eq. (3), (6))
    for a, b, c, d, params in _pairs(2):
        problem = Problem(a, b, c, d, **params)
        s = SontagFormula().solve(problem)
        np.testing.assert_allclose(np.asarray(s.u), -float(s.multipliers[0]) * b, rtol=1e-13)
        # the public eq. (3), from (a, b) alone: the same input to rounding
        sontag_u = ss.clf_sontag(a, b, kappa=params["kappa"], phi=params["phi"]).u
        np.testing.assert_allclose(np.asarray(s.u), np.asarray(sontag_u), rtol=1e-14)
        f = CBFFormula().solve(problem)
        np.testing.assert_allclose(np.asarray(f.u), float(f.multipliers[1]) * d, rtol=1e-13)
        assert int(s.region) == ss.Region.P1 and int(f.region) == ss.Region.P2


def test_a_cbf_margin_tightens_the_condition_by_its_amount():
    for a, b, c, d, params in _pairs(3):
        res = CBFFormula().solve(Problem(a, b, c, d, **params, cbf_margin=0.25))
        Gamma = float(np.sqrt(c**2 + params["varphi"] * np.dot(d, d) ** 2))
        # the CBF formula meets its (tightened) condition with equality where it is active
        lhs = c + float(d @ np.asarray(res.u)) - params["rho"] * Gamma
        B = params["rho"] * Gamma - c + 0.25
        assert lhs == pytest.approx(0.25 if B > 0 else lhs, abs=1e-12 * (abs(c) + 10))


def test_multi_formula_solves_filter_cases_like_the_reference():
    rng = np.random.default_rng(4)
    for signature in [(1, 2, 2, None, True, False), (2, 3, 3, 10.0, True, True)]:
        case = filter_cases.random_case(rng, "generic", signature)
        a, b, c, d = filter_cases.arrays(case)
        kw = filter_cases.kwargs(case)
        problem = Problem(
            a, b, c, d, kw["kappa"], kw["rho"], kw["phi"], kw["varphi"],
            slack_weight=kw.get("slack_weight"), u_min=kw.get("u_min"), u_max=kw.get("u_max"),
            u_nom=kw.get("u_nom"), H=kw.get("H"),
        )  # fmt: skip
        res = MultiFormula().solve(problem)
        status, u_ref, *_ = filter_cases.reference(case)
        assert ss.MultiStatus(int(res.status)).name == status
        assert mpref.rel_error(np.asarray(res.u), u_ref) < 1e-9


def test_formulas_are_static_values_and_problems_are_pytrees():
    assert jax.tree_util.tree_leaves(CombinedFormula(1e-9)) == []
    assert hash(CombinedFormula(1e-9)) == hash(CombinedFormula(1e-9))
    problem = Problem(1.0, jnp.ones(2), 0.5, jnp.ones(2), slack_weight=3.0)
    assert len(jax.tree_util.tree_leaves(problem)) == 9  # 4 terms, 4 parameters, the weight

    def u_of(w):
        return RelaxedFormula().solve(problem.replace(slack_weight=w)).u[0]

    g = jax.grad(u_of)(3.0)
    fd = (u_of(3.0 + 1e-6) - u_of(3.0 - 1e-6)) / 2e-6
    assert float(g) == pytest.approx(float(fd), rel=1e-6)


def test_a_formula_refuses_fields_it_does_not_use():
    problem = Problem(1.0, jnp.ones(2), 0.5, jnp.ones(2), u_nom=jnp.zeros(2))
    with pytest.raises(ParameterError, match="CombinedFormula does not use u_nom"):
        CombinedFormula().solve(problem)
    with pytest.raises(ParameterError, match="needs the problem's slack_weight"):
        RelaxedFormula().solve(problem.replace(u_nom=None))


def _system():
    sys = ss.ControlAffineSystem(lambda x: jnp.array([x[1], -x[0]]), lambda x: jnp.eye(2), 2)
    clf = ss.CLF(lambda x: jnp.sum(x**2), lam=1.0)
    cbf = ss.CBF(lambda x: 1.0 - x[0], beta=1.0)
    return sys, clf, cbf


def test_a_controller_built_from_a_formula_object_is_the_named_one():
    sys, clf, cbf = _system()
    p = dict(kappa=0.5, rho=0.2, phi=0.3, varphi=0.1)
    x = np.random.default_rng(5).uniform(-2, 2, (200, 2))
    pairs = [
        (dict(formula=RelaxedFormula(), slack_weight=4.0), dict(slack_weight=4.0)),
        (dict(formula=SontagFormula()), dict(formula="sontag")),
        (dict(formula=CBFFormula()), dict(formula="cbf")),
        (dict(formula=CombinedFormula(1e-6)), dict(parallel_rtol=1e-6)),
    ]
    for by_object, by_name in pairs:
        one = ss.UniversalController(sys, clf, cbf, **p, **by_object)
        two = ss.UniversalController(sys, clf, cbf, **p, **by_name)
        assert type(one.formula) is type(two.formula)
        for f in ("u", "region", "compatible", "slack", "status"):
            np.testing.assert_array_equal(
                np.asarray(getattr(one.step(x), f)), np.asarray(getattr(two.step(x), f))
            )


def test_controllers_refuse_a_formula_that_is_not_theirs():
    sys, clf, cbf = _system()
    p = dict(kappa=0.5, rho=0.2, phi=0.3, varphi=0.1)
    with pytest.raises(ParameterError, match="use SafetyFilter"):
        ss.UniversalController(sys, clf, cbf, **p, formula=MultiFormula())
    with pytest.raises(ParameterError, match="RelaxedFormula needs slack_weight"):
        ss.UniversalController(sys, clf, cbf, **p, formula=RelaxedFormula())
    with pytest.raises(ParameterError, match="formula must be 'combined', 'sontag', 'cbf' or"):
        ss.UniversalController(sys, clf, cbf, **p, formula="qp")


def test_a_filter_is_the_controller_with_the_several_row_formula():
    sys, clf, cbf = _system()
    filt = ss.SafetyFilter(sys, [cbf], clfs=[clf], max_iter=7)
    ctrl = ss.UniversalController(sys, clf, cbf, kappa=0.0, rho=0.0, phi=0.0, varphi=0.0)
    assert isinstance(filt, ss.Controller) and isinstance(ctrl, ss.Controller)
    assert filt.formula == MultiFormula(7)
    assert ctrl.clfs == (clf,) and ctrl.cbfs == (cbf,)
    # one CLF, one CBF, no nominal input or limits: the filter's problem is the combined QP
    x = np.random.default_rng(6).uniform(-2, 2, (100, 2))
    np.testing.assert_allclose(
        np.asarray(filt.step(x).u), np.asarray(ctrl.step(x).u), rtol=1e-10, atol=1e-12
    )


@pytest.mark.parametrize("formula", [CombinedFormula(), RelaxedFormula()])
def test_a_formula_certifies_its_result_from_the_problem_alone(formula):
    # residuals(problem, result) is kkt_residuals without the terms given again; on the
    # formula's own answer every residual vanishes to rounding of the terms' scale
    w = 5.0 if isinstance(formula, RelaxedFormula) else None
    for a, b, c, d, params in _pairs(7):
        problem = Problem(a, b, c, d, **params, slack_weight=w)
        res = formula.solve(problem)
        if int(res.region) == ss.Region.INCOMPATIBLE:
            continue  # the fallback is not the QP's optimum (test_formulas covers it)
        mine = formula.residuals(problem, res)
        theirs = ss.kkt_residuals(a, b, c, d, res, **params, slack_weight=w)
        fields = list(vars(mine))
        scale = abs(a) + abs(c) + np.linalg.norm(b) + np.linalg.norm(d) + 1.0
        for f in fields:  # the same residuals (eager here, jitted there: rounding apart)
            np.testing.assert_allclose(
                np.asarray(getattr(mine, f)), np.asarray(getattr(theirs, f)),
                rtol=1e-12, atol=1e-14 * scale**2,
            )  # fmt: skip
        assert max(float(getattr(mine, f)) for f in fields) < 1e-12 * scale**2
        # with a CBF margin the answer meets the tightened condition; judged without it, the
        # CBF row holds with room to spare
        tight = problem.replace(cbf_margin=0.5)
        res_t = formula.solve(tight)
        if int(res_t.region) != ss.Region.INCOMPATIBLE:
            assert float(formula.residuals(tight, res_t).cbf_violation) < 1e-12 * scale**2
