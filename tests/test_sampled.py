"""The sampled-data margin (safestab.sampled): h >= 0 between the samples, not only at them.

The oracle is the flow itself: for a single integrator ``x' = u`` the held flow is the
straight line ``x_k + s u_k`` (exact, no integrator), and ``h'' = -2 |u|^2`` by hand.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.sampled import ddh_bound, hold_second_derivative, sampled_shift

PLANE = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)
U_MAX = 1.0
#: -h'' = 2 |u|^2 <= 2 (m U_MAX^2) for the disc barrier under the single integrator
M_DISC = 2.0 * 2 * U_MAX**2


def _disc(beta=5.0):
    return ss.CBF(lambda x: 1.0 - x @ x, beta=beta)  # inside the unit disc: concave


def test_shift_is_the_hand_formula():
    # h >= 0: M T / 2 plus the rate's excess over 1 / T; h < 0: M T / 2 alone
    T, M = 0.1, 3.0
    h = np.array([0.5, 0.5, 0.0, -0.2])
    alpha = np.array([20.0 * 0.5, 2.0 * 0.5, 0.0, 20.0 * -0.2])
    want = M * T / 2 + np.array([20 * 0.5 - 0.5 / T, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(np.asarray(sampled_shift(h, alpha, T, M)), want, rtol=1e-15)


def test_second_derivative_is_the_hand_derivation():
    rng = np.random.default_rng(1)
    x, u = rng.normal(size=(50, 2)), rng.normal(size=(50, 2))
    got = np.asarray(hold_second_derivative(PLANE, _disc(), x, u))
    np.testing.assert_allclose(got, -2.0 * np.sum(u * u, -1), rtol=1e-13)
    # the estimate over the box: the worst -h'' is at a corner of the input box, times 1.5
    np.testing.assert_allclose(ddh_bound(PLANE, _disc(), -1.0, 1.0, u_min=-1, u_max=1), 1.5 * 4.0)


def test_second_derivative_of_the_acc_barrier_against_its_hand_form():
    """ACC: h = D - tau v_f, v_f' = (u - F_r(v_f)) / M, D' = v_l - v_f, v_l' = a (constant w).

    h'' = a - v_f' - tau v_f'' with v_f'' = -F_r'(v_f) v_f' / M."""
    Mass, f0, f1, f2, tau = 1650.0, 0.1, 5.0, 0.25, 1.8
    Fr = lambda v: f0 + f1 * v + f2 * v**2  # noqa: E731
    acc = ss.ControlAffineSystem(
        lambda x: jnp.array([-Fr(x[0]) / Mass, 0.0, x[1] - x[0]]),
        lambda x: jnp.array([[1.0 / Mass], [0.0], [0.0]]),
        3,
    )
    cbf = ss.CBF(lambda x: x[2] - tau * x[0], beta=0.5)
    rng = np.random.default_rng(2)
    x = rng.uniform([5, 5, 10], [30, 30, 100], size=(200, 3))
    u = rng.uniform(-0.3 * Mass * 9.81, 0.3 * Mass * 9.81, size=(200, 1))
    a = rng.uniform(-3, 3, size=200)
    w = np.stack([np.zeros(200), a, np.zeros(200)], -1)
    vdot = (u[:, 0] - Fr(x[:, 0])) / Mass
    want = a - vdot - tau * (-(f1 + 2 * f2 * x[:, 0]) * vdot / Mass)
    got = np.asarray(hold_second_derivative(acc, cbf, x, u, w))
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_margined_condition_at_the_sample_keeps_h_until_the_next(seed):
    """Random states of the disc, rates, hold times and inputs in the box that meet the
    margined condition at the sample: h stays >= 0 on a fine grid of the exact held flow.
    Without the margin, inputs that meet the plain condition leave the disc (so this can
    fail)."""
    rng = np.random.default_rng(seed)
    n = 20_000
    r = np.sqrt(rng.uniform(0, 1, n))
    ang = rng.uniform(0, 2 * np.pi, n)
    x = np.stack([r * np.cos(ang), r * np.sin(ang)], -1)
    u = rng.uniform(-U_MAX, U_MAX, size=(n, 2))
    T = rng.uniform(0.01, 0.5, n)
    beta = rng.uniform(0.1, 30.0, n)
    h = 1.0 - np.sum(x * x, -1)
    hdot = -2.0 * np.sum(x * u, -1)  # c + d.u - beta h for this barrier (L_f h = 0)
    s = np.linspace(0.0, 1.0, 201)[:, None] * T  # (201, n): the hold interval
    path = x[None] + s[..., None] * u[None]
    least = np.min(1.0 - np.sum(path * path, -1), 0)
    shift = np.asarray(sampled_shift(h, beta * h, T, M_DISC))
    margined = hdot + beta * h >= shift
    assert margined.sum() > 1000
    assert np.all(least[margined] >= -1e-12)  # rounding of the grid's h only
    plain = hdot + beta * h >= 0.0
    assert np.any(least[plain] < -1e-3)  # the continuous-time condition alone is not enough


def _outward():
    return dict(u_nom=lambda x: 2.0 * (jnp.array([2.0, 0.5]) - x), u_min=-U_MAX, u_max=U_MAX)


@pytest.mark.parametrize("dt", [0.1, 0.2])
def test_filter_with_the_margin_keeps_every_start_inside_between_samples(dt):
    """64 starts pushed out of the disc by their nominal input, filtered at 10 and 5 Hz."""
    x0 = np.random.default_rng(0).uniform(-0.7, 0.7, size=(64, 2))
    plain = ss.SafetyFilter(PLANE, _disc(), **_outward())
    held = plain.replace(sample_time=dt, ddh_bound=M_DISC)
    t_plain = ss.simulate(plain, x0, t_final=3.0, dt=dt, substeps=20)
    t_held = ss.simulate(held, x0, t_final=3.0, dt=dt, substeps=20)
    assert float(np.nanmin(t_plain.h_between)) < -0.01  # leaves the disc without it
    assert float(np.nanmin(t_held.h_between)) >= 0.0
    assert t_held.ok  # every step met its (margined) condition within the limits


def test_h_between_is_the_least_h_on_the_substep_grid_of_the_exact_flow():
    """Keep out of a disc (convex h): a straight hold can cut the disc between two samples
    outside it; h_between is min_i h(x_k + (i/N) dt u_k) (the flow is exact under RK4)."""
    centre = jnp.array([1.0, 0.2])
    obstacle = ss.CBF(lambda x: (x - centre) @ (x - centre) - 0.0625, beta=50.0)
    filt = ss.SafetyFilter(PLANE, obstacle, u_nom=lambda x: jnp.array([1.0, 0.0]))
    # samples at x1 = 0, 0.4, 0.8, 1.2 (h = 0.0175 at the last two), the disc cut between
    N, dt = 16, 0.4
    traj = ss.simulate(filt, np.array([0.0, 0.0]), t_final=2.0, dt=dt, substeps=N)
    x, u = np.asarray(traj.x)[:-1], np.asarray(traj.u)[:-1]
    grid = x[:, None] + (np.arange(N + 1) / N * dt)[None, :, None] * u[:, None]
    want = np.min(np.sum((grid - [1.0, 0.2]) ** 2, -1) - 0.0625, 1)
    got = np.asarray(traj.h_between)[:-1, 0]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert np.isnan(np.asarray(traj.h_between)[-1, 0])
    assert np.min(np.asarray(traj.h)) > 0.0 > np.min(want) + 0.02  # a dip the samples miss
    # the cap on the rate alone keeps it out (h'' = 2|u|^2 >= 0 here, so M = 0)
    capped = ss.simulate(filt.replace(sample_time=dt, ddh_bound=0.0), np.array([0.0, 0.0]),
                         t_final=2.0, dt=dt, substeps=N)  # fmt: skip
    assert float(np.nanmin(capped.h_between)) >= 0.0


def test_the_controller_takes_the_margin_and_differentiates_in_it():
    clf = ss.CLF(lambda x: (x - jnp.array([2.0, 0.5])) @ (x - jnp.array([2.0, 0.5])), lam=1.0)
    kw = dict(kappa=0.1, rho=0.0, phi=0.0, varphi=0.0, slack_weight=10.0)
    ctrl = ss.UniversalController(PLANE, clf, _disc(), sample_time=0.1, ddh_bound=M_DISC, **kw)
    plain = ss.UniversalController(PLANE, clf, _disc(), **kw)
    x = np.array([[0.65, 0.65], [0.1, -0.2]])  # the CBF active (P3), and not (P1)
    out, ref = ctrl.step(x), plain.step(x)
    assert np.asarray(out.region).tolist() == [ss.Region.P3, ss.Region.P1]
    h = 1.0 - np.sum(x * x, -1)
    shift = np.asarray(sampled_shift(h, 5.0 * h, 0.1, M_DISC))
    np.testing.assert_allclose(np.asarray(out.terms.c), np.asarray(ref.terms.c) - shift, rtol=1e-14)
    assert set(ctrl.tunables()) >= {"sample_time", "ddh_bound"}

    def u0(T):
        return ctrl.replace(sample_time=T).step_fn(jnp.asarray(x[0])).u[0]

    g = float(jax.grad(u0)(0.1))
    fd = (float(u0(0.1 + 1e-6)) - float(u0(0.1 - 1e-6))) / 2e-6
    assert abs(g) > 1e-3 and abs(g - fd) <= 1e-6 * abs(g)  # central differences: O(h^2)


def test_bad_margin_arguments_are_named():
    with pytest.raises(ss.ParameterError, match="give sample_time and ddh_bound together"):
        ss.SafetyFilter(PLANE, _disc(), sample_time=0.1)
    with pytest.raises(ss.ParameterError, match="sample_time must be a finite number > 0"):
        ss.SafetyFilter(PLANE, _disc(), sample_time=0.0, ddh_bound=1.0)
    with pytest.raises(ss.ParameterError, match=r"ddh_bound must be >= 0, got \[-1.0\]"):
        ss.SafetyFilter(PLANE, _disc(), sample_time=0.1, ddh_bound=[-1.0])
    with pytest.raises(ss.DimensionError, match=r"ddh_bound must be a scalar or shape \(1,\)"):
        ss.SafetyFilter(PLANE, _disc(), sample_time=0.1, ddh_bound=[1.0, 2.0])
    with pytest.raises(ss.ParameterError, match="substeps must be an integer >= 1, got 0"):
        ss.simulate(ss.SafetyFilter(PLANE, _disc()), np.zeros(2), t_final=0.1, substeps=0)
    with pytest.raises(ss.ParameterError, match="the state box: lower must be <= upper"):
        ddh_bound(PLANE, _disc(), 1.0, -1.0, u_min=-1, u_max=1)


def test_the_margin_and_the_statuses_export_to_c():
    """The exported step computes the shifted condition and the named statuses: the same
    statuses as the JAX step at states where the limits conflict with the barrier, and the
    same input to rounding."""
    filt = ss.SafetyFilter(PLANE, _disc(), sample_time=0.2, ddh_bound=M_DISC, **_outward())
    native = ss.NativeController(filt)
    x = np.random.default_rng(0).uniform(-1.3, 1.3, size=(2000, 2))
    got, want = native.step(x), filt.step(x)
    status = np.asarray(want.status)
    assert {0, int(ss.StepStatus.CBF_INFEASIBLE)} <= set(np.unique(status))
    np.testing.assert_array_equal(got.status, status)
    # C and XLA round the same operations in another order: a few units of the last place
    np.testing.assert_allclose(got.u, np.asarray(want.u), rtol=0, atol=1e-13)


def test_the_monte_carlo_loop_records_the_least_h_between_samples():
    """trial_function(substeps=N)'s min_h_between against simulate's full history of the same
    loop (h_between, checked against the exact flow above), on a coarse pass-by."""
    from safestab.montecarlo import trial_function

    centre = jnp.array([1.0, 0.2])
    obstacle = ss.CBF(lambda x: (x - centre) @ (x - centre) - 0.0625, beta=50.0)
    goal = ss.CLF(lambda x: (x - jnp.array([3.0, 0.0])) @ (x - jnp.array([3.0, 0.0])), lam=1.0)
    ctrl = ss.UniversalController(PLANE, goal, obstacle, kappa=0.0, rho=0.0, phi=0.0,
                                  varphi=0.0, slack_weight=1e3, u_min=-1.0, u_max=1.0)  # fmt: skip
    x0 = np.array([0.0, 0.0])
    for n_sub in (1, 16):
        run = trial_function([ctrl], plant=PLANE, n_steps=8, dt=0.4, substeps=n_sub)
        rec = {k: float(np.asarray(v)[0]) for k, v in jax.jit(run)(x0, {}).items()}
        traj = ss.simulate(ctrl, x0, t_final=3.2, dt=0.4, substeps=n_sub)
        assert rec["min_h"] == pytest.approx(float(np.min(traj.h)), rel=1e-12)
        if n_sub == 1:  # the samples alone
            assert rec["min_h_between"] == rec["min_h"]
        else:
            want = float(np.nanmin(traj.h_between))
            assert rec["min_h_between"] == pytest.approx(want, rel=1e-12)
            assert rec["min_h_between"] < 0.0 < rec["min_h"]  # a dip the samples miss
