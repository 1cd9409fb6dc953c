"""One-sided and infinite input limits, for controllers, filters and the export.

Checked against the same problems with the missing side replaced by a bound no input
reaches (the optimum is then the same, bit for bit), the projection written by hand, and
Clarabel as a second opinion.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss

PLANE = ss.ControlAffineSystem(lambda x: jnp.array([x[1], -x[0]]), lambda x: jnp.eye(2), 2)
DISC = ss.CBF(lambda x: 1.0 - x @ x, beta=2.0)
GOAL = ss.CLF(lambda x: (x - 2.0) @ (x - 2.0), lam=1.0)


def _states():
    return np.random.default_rng(0).uniform(-1.2, 1.2, size=(1000, 2))


@pytest.mark.parametrize(
    "limits, far",
    [
        (dict(u_max=1.0), dict(u_min=-1e6, u_max=1.0)),
        (dict(u_min=-0.5), dict(u_min=-0.5, u_max=1e6)),
        (dict(u_min=[-np.inf, -0.5], u_max=[1.0, np.inf]),
         dict(u_min=[-1e6, -0.5], u_max=[1.0, 1e6])),
    ],
)  # fmt: skip
def test_a_filter_with_a_missing_side_is_the_filter_with_a_bound_never_reached(limits, far):
    u_nom = lambda x: jnp.array([3.0, -2.0])  # noqa: E731  (pushes against both sides)
    x = _states()
    got = ss.SafetyFilter(PLANE, DISC, clfs=GOAL, slack_weight=10.0, u_nom=u_nom, **limits)
    want = ss.SafetyFilter(PLANE, DISC, clfs=GOAL, slack_weight=10.0, u_nom=u_nom, **far)
    a, b = got.step(x), want.step(x)
    assert np.max(np.abs(np.asarray(b.u))) < 1e3  # the far bound is never reached
    np.testing.assert_array_equal(np.asarray(a.u), np.asarray(b.u))
    np.testing.assert_array_equal(np.asarray(a.status), np.asarray(b.status))
    np.testing.assert_array_equal(np.asarray(a.formula_status), np.asarray(b.formula_status))
    # the export takes the infinite bounds too
    native = ss.NativeController(got)
    np.testing.assert_allclose(native.step(x).u, np.asarray(a.u), rtol=0, atol=1e-12)


def test_a_one_sided_filter_against_clarabel():
    qpsolvers = pytest.importorskip("qpsolvers")
    from scipy import sparse

    rng = np.random.default_rng(1)
    filt = ss.SafetyFilter(PLANE, DISC, u_max=[0.5, 0.5])
    for x in rng.uniform(-0.9, 0.9, size=(30, 2)):
        u_nom = rng.uniform(-3, 3, 2)
        out = filt.step(x, u_nom=u_nom)
        t = ss.lie_terms(PLANE, GOAL, DISC, x)
        c, d = float(t.c), np.asarray(t.d)
        # min 1/2 |u - u_nom|^2  s.t.  -d.u <= c,  u <= 0.5
        G = np.vstack([-d, np.eye(2)])
        h = np.array([c, 0.5, 0.5])
        ref = qpsolvers.solve_qp(sparse.csc_matrix(np.eye(2)), -u_nom, sparse.csc_matrix(G), h,
                                 solver="clarabel")  # fmt: skip
        assert ref is not None
        # Clarabel's interior point stops at its tolerance: 1e-6 of these unit-sized inputs
        np.testing.assert_allclose(np.asarray(out.u), ref, rtol=0, atol=1e-6)


def test_a_controller_with_one_side_projects_by_hand():
    x = _states()
    kw = dict(kappa=0.1, rho=0.0, phi=0.0, varphi=0.0, slack_weight=10.0)
    free = ss.UniversalController(PLANE, GOAL, DISC, **kw).step(x)
    capped = ss.UniversalController(PLANE, GOAL, DISC, u_max=[0.3, np.inf], **kw).step(x)
    want = np.minimum(np.asarray(free.u), [0.3, np.inf])  # the projection onto u_1 <= 0.3
    np.testing.assert_array_equal(np.asarray(capped.u), want)
    assert np.any(np.asarray(free.u)[:, 0] > 0.3)  # the cap acts
    # a state where the cap breaks the barrier is named, not OK
    status = np.asarray(capped.status)
    assert set(np.unique(status)) <= {ss.StepStatus.OK, ss.StepStatus.CBF_UNMET,
                                      ss.StepStatus.CBF_INFEASIBLE}  # fmt: skip


def test_limits_that_leave_no_input_are_named():
    with pytest.raises(ss.NonFiniteError, match=r"u_min must be a number, or -inf where"):
        ss.SafetyFilter(PLANE, DISC, u_min=[np.inf, 0.0])
    with pytest.raises(ss.NonFiniteError, match=r"u_max must be a number, or \+inf where"):
        ss.SafetyFilter(PLANE, DISC, u_max=[np.nan, 0.0])
