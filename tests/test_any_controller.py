"""Any controller in any loop: a user's own law (PolicyController) and every controller kind
the package makes, run by simulate, the Monte Carlo trial loop and the C export alike.

The references are independent: the Lie terms and the conditions written out by hand in
NumPy, the trajectory of ``simulate`` for the trial records, the JAX step for the native one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.controllers import controller_step
from safestab.formulas import ExplicitFilter
from safestab.montecarlo import trial_function

from .jax_events import traces_while

S = ss.StepStatus
BETA1, BETA2 = 1.0, 2.0
GOAL = np.array([0.6, -0.2])


def drift(x):
    return jnp.array([0.5 * x[1] + 0.2, -0.5 * x[0]])


SYSTEM = ss.ControlAffineSystem(drift, lambda x: jnp.array([[1.0], [0.5]]), 2, name="toy")
DISC = ss.CBF(lambda x: 1.0 - x @ x, beta=BETA1)
WALL = ss.CBF(lambda x: x[0] + 0.8, beta=BETA2)
CLF = ss.CLF(lambda x: (x - GOAL) @ (x - GOAL), lam=1.0)


def law(x, w):
    return jnp.array([w @ (jnp.asarray(GOAL) - x)])


def hand_conditions(x, u):
    """Per barrier ``c_i + d_i u`` and ``d_i`` at states (N, 2) with inputs (N,), by hand."""
    x0, x1 = x[:, 0], x[:, 1]
    f = np.stack([0.5 * x1 + 0.2, -0.5 * x0], -1)
    g = np.array([1.0, 0.5])
    grads = [np.stack([-2 * x0, -2 * x1], -1), np.broadcast_to([1.0, 0.0], x.shape)]
    hs = [1.0 - x0**2 - x1**2, x0 + 0.8]
    rates = [BETA1, BETA2]
    c = np.stack([np.sum(gr * f, -1) + b * h for gr, h, b in zip(grads, hs, rates)], -1)
    d = np.stack([gr @ g for gr in grads], -1)
    return c, d


def test_policy_controller_statuses_against_a_direct_check():
    """u is the law's input projected onto the limits; the status is OK exactly where every
    barrier's condition holds at u, and otherwise names why, as a direct check says."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-1.2, 1.2, (3000, 2))
    x[:300, 1] = -2.0 * x[:300, 0]  # d_disc = -2 x0 - x1 = 0 exactly on this line
    w = np.array([1.5, -0.7])
    ctrl = ss.PolicyController(SYSTEM, law, weights=w, cbfs=(DISC, WALL), clfs=CLF,
                               u_min=-0.5, u_max=0.5)  # fmt: skip
    out = ctrl.step(x)
    u_raw = (GOAL - x) @ w
    u = np.clip(u_raw, -0.5, 0.5)
    np.testing.assert_allclose(np.asarray(out.u)[:, 0], u, rtol=1e-14, atol=1e-15)
    c, d = hand_conditions(x, u)
    cond = c + d * u[:, None]
    box = c + np.abs(d) * 0.5  # each barrier alone at its best input in [-0.5, 0.5]
    scale = np.abs(c) + np.abs(d) * 0.5
    clear = np.all((np.abs(cond) > 1e-9 * scale) & (np.abs(box) > 1e-9 * scale), -1)
    unmet = cond < 0
    expected = np.where(
        ~np.any(unmet, -1),
        S.OK,
        np.where(
            np.any(unmet & (d == 0), -1),
            S.CBF_UNACTUATED,
            np.where(np.any(unmet & (box < 0), -1), S.CBF_INFEASIBLE, S.CBF_UNMET),
        ),
    )
    status = np.asarray(out.status)
    assert clear.sum() > 2900
    np.testing.assert_array_equal(status[clear], expected[clear])
    for name in ("OK", "CBF_UNACTUATED", "CBF_INFEASIBLE", "CBF_UNMET"):  # each case is met
        assert np.sum(expected[clear] == S[name]) > 10, name
    np.testing.assert_array_equal(np.asarray(out.cbf_satisfied)[clear], ~unmet[clear])
    np.testing.assert_array_equal(np.asarray(out.safety_certified), status == S.OK)
    assert np.all(np.asarray(out.formula_status) == ss.MultiStatus.SOLVED)
    # the limit rows (after 1 CLF and 2 CBF rows) are active exactly where the law was clipped
    act = np.asarray(out.active)
    np.testing.assert_array_equal(act[:, 3], u_raw >= 0.5)
    np.testing.assert_array_equal(act[:, 4], u_raw <= -0.5)
    with pytest.raises(ss.InfeasibleError, match="CBF_"):
        ctrl.step(x[~np.asarray(out.safety_certified)][:1], strict=True)


def test_policy_weights_are_data_new_weights_run_the_same_program():
    ctrl = ss.PolicyController(SYSTEM, law, weights=np.array([1.0, 0.0]), cbfs=DISC)
    x = jnp.array([0.1, 0.2])
    controller_step(ctrl, x, None)

    gains = [np.array([k, -k / 2.0]) for k in range(5)]
    five = [ctrl.replace(weights=w) for w in gains]  # building traces the law's shape
    outs = []
    assert traces_while(lambda: outs.extend(controller_step(c, x, None) for c in five)) == []
    for out, w in zip(outs, gains):  # no new trace, so no new program, and the new numbers
        assert float(out.u[0]) == pytest.approx((GOAL - np.asarray(x)) @ w, rel=1e-14)
    other = ss.PolicyController(SYSTEM, lambda x, w: law(x, w), weights=np.ones(2), cbfs=DISC)
    assert "controller_step" in traces_while(lambda: controller_step(other, x, None))
    # the derivative reaches the weights: d u / d w = goal - x (no limits)
    grad = jax.grad(lambda w: controller_step(ctrl.replace(weights=w), x, None).u[0])(
        jnp.array([1.0, 0.0])
    )
    np.testing.assert_allclose(np.asarray(grad), GOAL - np.asarray(x), rtol=1e-14)


def test_policy_controller_names_bad_input():
    with pytest.raises(ss.InputTypeError, match="policy must be a function"):
        ss.PolicyController(SYSTEM, np.zeros(1))
    with pytest.raises(ss.DimensionError, match=r"policy must return the input of shape \(1,\)"):
        ss.PolicyController(SYSTEM, lambda x: x)
    with pytest.raises(ss.InputTypeError, match=r"weights\['K'\]"):
        ss.PolicyController(SYSTEM, lambda x, w: w["K"] @ x, weights={"K": np.array([True])})
    with pytest.raises(ss.ParameterError, match="sample_time shifts the barriers"):
        ss.PolicyController(SYSTEM, lambda x: -x[:1], sample_time=0.1, ddh_bound=1.0)
    flat = ss.CBF(lambda x: x[1] - 2.0 * x[0] + 5.0, beta=1.0)  # L_g h = 0.5 - 2 < 0: moved
    ss.PolicyController(SYSTEM, lambda x: -x[:1], cbfs=flat)
    level = ss.CBF(lambda x: x[1] - 0.5 * x[0], beta=1.0)  # L_g h = 0.5 - 0.5 = 0 everywhere
    with pytest.raises(ss.RelativeDegreeError):
        ss.PolicyController(SYSTEM, lambda x: -x[:1], cbfs=level)


def _controllers():
    """One controller of each kind the package makes, and a user's law."""
    lim = {"u_min": -1.0, "u_max": 1.0}
    gains = {"kappa": 0.2, "rho": 0.1, "phi": 1.0, "varphi": 1.0}
    return {
        "combined": ss.UniversalController(SYSTEM, CLF, DISC, **gains, **lim),
        "cbf only": ss.UniversalController(SYSTEM, None, DISC, formula="cbf", **gains),
        "sontag, no cbf": ss.UniversalController(SYSTEM, CLF, None, formula="sontag", **gains),
        "filter, two barriers": ss.SafetyFilter(SYSTEM, (DISC, WALL), clfs=CLF,
                                                slack_weight=10.0, **lim),
        "explicit filter": ss.SafetyFilter(SYSTEM, DISC, u_nom=lambda x: jnp.array([1.5]),
                                           formula=ExplicitFilter()),
        "policy": ss.PolicyController(SYSTEM, law, weights=np.array([2.0, 1.0]),
                                      cbfs=(DISC, WALL), clfs=CLF, **lim),
    }  # fmt: skip


@pytest.mark.parametrize("kind", list(_controllers()))
def test_every_controller_runs_in_simulate_and_the_trial_loop_with_the_same_records(kind):
    """The trial loop's records (scored on the disc and the wall, and the CLF) equal what
    the trajectory of simulate gives, for every controller kind."""
    ctrl = _controllers()[kind]
    dt, n_steps = 0.05, 60
    x0 = np.array([[0.3, -0.5], [-0.6, 0.1], [0.0, 0.8]])
    traj = ss.simulate(ctrl, x0, t_final=n_steps * dt, dt=dt, substeps=3)
    run = trial_function([ctrl], plant=SYSTEM, n_steps=n_steps, dt=dt, clf=CLF,
                         cbfs=(DISC, WALL), substeps=3)  # fmt: skip
    rec = jax.jit(jax.vmap(run, in_axes=(0, None)))(jnp.asarray(x0), None)
    xs = np.asarray(traj.x)  # (3, K + 1, 2)
    h = np.minimum(1.0 - np.sum(xs**2, -1), xs[..., 0] + 0.8)
    v = np.sum((xs - GOAL) ** 2, -1)
    status = np.asarray(traj.status)[:, :-1]  # the steps k < K
    np.testing.assert_allclose(np.asarray(rec["min_h"])[:, 0], h.min(-1), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(rec["final_V"])[:, 0], v[:, -1], rtol=1e-12)
    assert np.all(np.asarray(rec["min_h_between"])[:, 0] <= h.min(-1) + 1e-12)
    np.testing.assert_array_equal(
        np.asarray(rec["barrier_unmet_steps"])[:, 0], np.sum(status >= S.CBF_UNACTUATED, -1)
    )
    assert np.all(np.asarray(rec["first_bad_status"]) == 0)
    # steps whose input sits on a limit (+-1 where the controller has limits)
    u = np.asarray(traj.u)[:, :-1, 0]
    on_limit = np.sum(np.abs(u) >= 1.0 - 1e-12, -1) if ctrl.u_min is not None else 0
    np.testing.assert_array_equal(np.asarray(rec["limit_steps"])[:, 0], on_limit)


def test_the_trial_loop_scores_a_controller_without_a_clf_and_names_bad_input():
    ctrl = _controllers()["cbf only"]
    run = trial_function([ctrl], plant=SYSTEM, n_steps=10, dt=0.05)  # its own CBF, no CLF
    rec = run(jnp.array([0.2, 0.1]), None)
    assert float(rec["final_V"][0]) == -1.0 and float(rec["clf_true_fraction"][0]) == -1.0
    with pytest.raises(ss.ParameterError, match="settle_time .* needs a CLF"):
        trial_function([ctrl], plant=SYSTEM, n_steps=10, dt=0.05, reference=ctrl)
    no_barrier = ss.PolicyController(SYSTEM, lambda x: -x[:1])
    with pytest.raises(ss.ParameterError, match="give cbfs="):
        trial_function([no_barrier], plant=SYSTEM, n_steps=10, dt=0.05)
    trial_function([no_barrier], plant=SYSTEM, n_steps=10, dt=0.05, cbfs=DISC)
    with pytest.raises(ss.InputTypeError, match="controllers must be"):
        trial_function([lambda x: x], plant=SYSTEM, n_steps=10, dt=0.05)
    takes = ss.PolicyController(SYSTEM, lambda x, p: -p * x[:1], params=1.0, cbfs=DISC)
    with pytest.raises(ss.ParameterError, match="passes no run-time parameters"):
        trial_function([takes], plant=SYSTEM, n_steps=10, dt=0.05)


def test_a_policy_exports_to_c_and_the_native_step_agrees():
    """A small tanh network as the law, two barriers, a CLF and limits: the native step
    gives the JAX step's input and statuses."""
    rng = np.random.default_rng(1)
    net = {"W1": rng.normal(size=(8, 2)), "b1": rng.normal(size=8), "W2": rng.normal(size=(1, 8))}

    def mlp(x, w):
        return 2.0 * w["W2"] @ jnp.tanh(w["W1"] @ x + w["b1"])

    ctrl = ss.PolicyController(SYSTEM, mlp, weights=net, cbfs=(DISC, WALL), clfs=CLF,
                               u_min=-1.0, u_max=1.0)  # fmt: skip
    native = ss.NativeController(ctrl, name="policy")
    assert "law 'mlp' passes through unchanged" in native.exported.header
    x = rng.uniform(-1.2, 1.2, (400, 2))
    ref, got = ctrl.step(x), native.step(x)
    np.testing.assert_allclose(got.u, np.asarray(ref.u), rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(got.status, np.asarray(ref.status))
    assert len(set(np.asarray(ref.status).tolist())) >= 2  # OK and a named miss both occur


@pytest.mark.parametrize("kind", list(_controllers()))
def test_every_controller_kind_exports_and_the_native_step_agrees(kind):
    ctrl = _controllers()[kind]
    native = ss.NativeController(ctrl, name="any")
    x = np.random.default_rng(2).uniform(-1.2, 1.2, (200, 2))
    ref, got = ctrl.step(x), native.step(x)
    np.testing.assert_allclose(got.u, np.asarray(ref.u), rtol=1e-11, atol=1e-13)
    np.testing.assert_array_equal(got.status, np.asarray(ref.status))


def test_a_law_that_is_not_finite_or_not_jax_is_named():
    robot = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)
    disc = ss.CBF(lambda x: 1.0 - x @ x, beta=1.0)
    blows_up = ss.PolicyController(robot, lambda x: jnp.array([1.0 / (x[0] - 0.5), 0.0]),
                                   cbfs=disc, u_min=-1.0, u_max=1.0)  # fmt: skip
    out = blows_up.step(jnp.array([0.5, 0.0]))  # inf clipped to the limit: still named
    assert int(out.status) == S.NONFINITE_INPUT and np.all(np.isnan(np.asarray(out.u)))
    with pytest.raises(ss.InputTypeError, match="policy must be a JAX function"):
        ss.PolicyController(robot, lambda x: np.asarray(x) * 1.0, cbfs=disc)
    with pytest.raises(ss.InputTypeError, match=r"policy is called as policy\(x, weights\)"):
        ss.PolicyController(robot, lambda x: -x, weights=np.ones(2))
    mine = ss.PolicyController(robot, lambda x, w: -w * x, weights=np.ones(2), cbfs=disc)
    with pytest.raises(ss.InputTypeError, match="policy is called as"):
        mine.replace(weights=np.ones(3))  # the new weights are checked as the first
    with pytest.raises(ss.InputTypeError, match="system must be a ControlAffineSystem"):
        ss.PolicyController(None, lambda x: -x)
    with pytest.raises(TypeError, match="clfs must be a CLF"):
        ss.PolicyController(robot, lambda x: -x, clfs=disc)
    with pytest.raises(ss.DimensionError, match="plant dimensions"):
        trial_function(mine, plant=SYSTEM, n_steps=5, dt=0.1)
    monitored = mine.step(jnp.array([0.2, 0.0]), u_nom=jnp.array([5.0, 0.0]))  # another action
    assert float(monitored.u[0]) == 5.0 and int(monitored.status) == S.CBF_UNMET
