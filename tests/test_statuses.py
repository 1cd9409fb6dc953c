"""A status of OK means the barriers hold at the step; otherwise the status names why.

Each case is checked against a direct computation: the limits' best input by hand, the zero
of L_g h by hand, a filter built with the nominal input against one given per call.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab import StepStatus as S

LINE = ss.ControlAffineSystem(
    lambda x: jnp.array([x[1], 0.0]), lambda x: jnp.array([[0.0], [1.0]]), 2
)  # a double integrator: position, speed; the input is the acceleration
PLANE = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)


def test_a_barrier_the_input_cannot_move_is_refused_where_it_is_built():
    """Position limit on a double integrator: L_g h = [1, 0] . [0, 1] = 0 everywhere."""
    wall = ss.CBF(lambda x: 4.0 - x[0], beta=1.0)
    clf = ss.CLF(lambda x: x @ x, lam=1.0)
    with pytest.raises(ss.RelativeDegreeError, match=r"cbfs: L_g h is zero at every probe"):
        ss.SafetyFilter(LINE, wall, u_nom=lambda x: jnp.array([1.0]))
    with pytest.raises(ss.RelativeDegreeError, match=r"cbfs\[1\]: .*high_order_cbf"):
        ss.SafetyFilter(LINE, [ss.CBF(lambda x: 4.0 - x[0] - x[1], beta=1.0), wall])
    with pytest.raises(ss.RelativeDegreeError, match=r"^cbf: L_g h is zero"):
        ss.UniversalController(LINE, clf, wall, kappa=0.1, rho=0.0, phi=0.0, varphi=0.0)
    # the same constraint of relative degree 2, built as such, is accepted
    ss.SafetyFilter(LINE, ss.high_order_cbf(LINE, lambda x: 4.0 - x[0], alpha1=1.0, beta=1.0))


def test_a_barrier_unactuated_at_some_states_gets_a_named_status_there():
    """h = 1 - x0^2 - x1^2 with g = (0, 1): d = -2 x1, zero on the axis x1 = 0, where the
    condition c = -2 x0 x1 + beta h >= 0 fails outside the disc (h < 0)."""
    disc = ss.CBF(lambda x: 1.0 - x[0] ** 2 - x[1] ** 2, beta=1.0)
    clf = ss.CLF(lambda x: x @ x, lam=1.0)
    x = np.array([[1.5, 0.0], [0.5, 0.0], [1.5, 0.2]])
    h = 1.0 - np.sum(x * x, -1)
    d = -2.0 * x[:, 1]
    want = np.where((d == 0) & (h < 0), S.CBF_UNACTUATED, S.OK)  # by hand; row 3 is moved
    filt = ss.SafetyFilter(LINE, disc)
    ctrl = ss.UniversalController(LINE, clf, disc, kappa=0.1, rho=0.0, phi=0.0, varphi=0.0,
                                  slack_weight=10.0)  # fmt: skip
    for out in (filt.step(x), ctrl.step(x)):
        np.testing.assert_array_equal(np.asarray(out.status), want)
        assert np.all(np.isfinite(np.asarray(out.u)))  # an input all the same
        assert not np.asarray(out.safety_certified)[0]
    with pytest.raises(ss.InfeasibleError, match=r"status CBF_UNACTUATED.*L_g h = 0"):
        ctrl.step(x, strict=True)


@pytest.mark.parametrize("seed", range(2))
def test_statuses_against_a_direct_check_of_the_limits(seed):
    """Two inputs, a plane robot's barrier, a box [-1, 1]^2: with the paper's projection the
    status is OK where the projected input meets the condition, CBF_INFEASIBLE where no input
    of the box does (by hand: the best d.u over the box is |d|_1, at a corner), CBF_UNMET
    where one does but the projection does not (the projection of a 2-vector onto a box can
    leave the half-plane); safety-first saturation is for one input: the filter keeps the
    limits inside its problem, and never gives CBF_UNMET."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1, 1, 2)
    bar = ss.CBF(lambda x: 1.0 - (x - centre) @ (x - centre), beta=3.0)
    drift = ss.ControlAffineSystem(lambda x: jnp.array([x[1], -x[0]]), lambda x: jnp.eye(2), 2)
    clf = ss.CLF(lambda x: (x - 2.0) @ (x - 2.0), lam=1.0)
    box = dict(u_min=-1.0, u_max=1.0)
    x = rng.uniform(-2.5, 2.5, size=(4000, 2))
    terms = ss.lie_terms(drift, clf, bar, x)
    c, d = np.asarray(terms.c), np.asarray(terms.d)
    best = c + np.sum(np.abs(d), -1)
    clear = np.abs(best) > 1e-9 * (np.abs(c) + np.sum(np.abs(d), -1))  # off the boundary
    ctrl = ss.UniversalController(drift, clf, bar, kappa=0.5, rho=0.0, phi=0.0, varphi=0.0,
                                  slack_weight=10.0, **box)  # fmt: skip
    filt = ss.SafetyFilter(drift, bar, clfs=clf, kappa=0.5, slack_weight=10.0, **box)
    for out, projected in ((ctrl.step(x), True), (filt.step(x), False)):
        status = np.asarray(out.status)
        du = np.asarray(out.u) * d
        meets = c + du.sum(-1) >= -1e-12 * (np.abs(c) + np.abs(du).sum(-1))
        np.testing.assert_array_equal((status == S.OK)[clear], meets[clear])
        np.testing.assert_array_equal((status == S.CBF_INFEASIBLE)[clear], (best < 0)[clear])
        unmet = (status == S.CBF_UNMET)[clear]
        np.testing.assert_array_equal(unmet, (~meets & (best >= 0))[clear])
        assert (best < 0).sum() > 10  # infeasible states are drawn
        assert unmet.sum() > 10 if projected else not unmet.any()


def test_a_trajectory_of_conflicting_steps_is_not_ok_and_says_how_many():
    """A speed limit too small to turn back: every step CBF_INFEASIBLE (it said ok)."""
    disc = ss.CBF(lambda x: 1.0 - x @ x, beta=1.0)
    filt = ss.SafetyFilter(PLANE, disc, u_nom=lambda x: jnp.array([1.0, 0.0]),
                           u_min=-0.05, u_max=0.05)  # fmt: skip
    traj = ss.simulate(filt, np.array([1.2, 0.0]), t_final=0.5, dt=0.1)
    status = np.asarray(traj.status)
    assert np.all(status == S.CBF_INFEASIBLE) and not traj.ok
    assert traj.barrier_unmet_steps == status.size
    assert traj.failure_summary() == (
        f"CBF_INFEASIBLE first at step 0 (t = 0 s); {status.size} of {status.size} steps "
        "missed a CBF condition"
    )
    with pytest.raises(ss.InfeasibleError, match="CBF_INFEASIBLE first at step 0"):
        ss.simulate(filt, np.array([1.2, 0.0]), t_final=0.5, dt=0.1, strict=True)


def test_the_nominal_input_given_per_call_is_the_filters_own():
    """filter.step(x, u_nom=...) against filters built with each nominal input."""
    disc = ss.CBF(lambda x: 1.0 - x @ x, beta=5.0)
    filt = ss.SafetyFilter(PLANE, disc, u_min=-1.0, u_max=1.0)
    rng = np.random.default_rng(3)
    x = rng.uniform(-1.1, 1.1, size=(6, 2))
    u_nom = rng.uniform(-2, 2, size=(6, 2))
    got = filt.step(x, u_nom=u_nom)
    for i in range(6):
        own = ss.SafetyFilter(PLANE, disc, u_min=-1.0, u_max=1.0, u_nom=u_nom[i]).step(x[i])
        np.testing.assert_array_equal(np.asarray(got.u)[i], np.asarray(own.u))
        assert int(np.asarray(got.status)[i]) == int(own.status)
    shared = filt.step(x, u_nom=u_nom[0])  # one nominal input for the whole batch
    np.testing.assert_array_equal(np.asarray(shared.u)[0], np.asarray(got.u)[0])
    with pytest.raises(ss.DimensionError, match=r"u_nom must have shape \(2,\) or the batch"):
        filt.step(x, u_nom=np.ones(3))
    with pytest.raises(ss.NonFiniteError, match="u_nom"):
        filt.step(x, u_nom=[np.nan, 0.0])
