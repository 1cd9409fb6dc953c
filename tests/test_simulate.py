"""Closed-loop simulation: integrator order, batching, flags and strict mode."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.scenarios import load_scenario
from safestab.simulation import rk4_step, simulate


def test_rk4_fourth_order():
    # xdot = [[0, 1], [-1, 0]] x: exact solution a rotation. Halving dt divides the global
    # error by 2^4 = 16 for a fourth-order method.
    def rhs(t, x):
        return jnp.array([x[1], -x[0]])

    errs = []
    for n in (20, 40):
        dt, x = 2.0 / n, jnp.array([1.0, 0.0])
        for k in range(n):
            x = rk4_step(rhs, k * dt, x, dt)
        errs.append(float(jnp.linalg.norm(x - jnp.array([np.cos(2.0), -np.sin(2.0)]))))
    assert 14.0 < errs[0] / errs[1] < 18.0


def _stress_controller():
    sc = load_scenario("stress")
    clf, cbf = sc.certificates()
    p = dict(kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi, slack_weight=sc.slack_weight)
    return sc, ss.UniversalController(sc.system("true"), clf, cbf, **p)


def test_relaxed_formula_keeps_cbf_flag_in_closed_loop():
    # Regression: in P3 the input is a difference of large terms; the satisfied-flag tolerance
    # must scale with those terms or exact equalities are reported as violations.
    sc, ctrl = _stress_controller()
    tr = simulate(ctrl, np.array(sc.x0), t_final=15.0, dt=0.01, exogenous=sc.exogenous)
    assert np.all(np.asarray(tr.region) == ss.Region.P3)
    assert np.all(np.asarray(tr.cbf_satisfied))
    assert float(np.min(np.asarray(tr.h))) >= 0.0


def test_batch_equals_single_and_zoh():
    sc, ctrl = _stress_controller()
    x0s = np.array([sc.x0, (20.0, 15.0, 80.0), (15.0, 12.0, 40.0)])
    batch = simulate(ctrl, x0s, t_final=2.0, dt=0.01, exogenous=sc.exogenous)
    assert batch.x.shape == (3, 201, 3) and batch.u.shape == (3, 201, 1)
    one = simulate(ctrl, x0s[1], t_final=2.0, dt=0.01, exogenous=sc.exogenous)
    np.testing.assert_allclose(batch.x[1], one.x, rtol=1e-12)
    # zero-order hold: the recorded input is the controller's output at the recorded state
    np.testing.assert_allclose(one.u[37], ctrl(one.x[37]), rtol=1e-12)
    np.testing.assert_allclose(one.h, one.x[:, 2] - sc.tau * one.x[:, 0], rtol=1e-12)


def test_strict_simulation_raises():
    system = ss.ControlAffineSystem(lambda x: jnp.zeros(1), lambda x: jnp.ones((1, 1)), 1)
    clf = ss.CLF(lambda x: (x[0] - 2.0) ** 2, lam=1.0)
    cbf = ss.CBF(lambda x: 1.0 - x[0], beta=1.0)
    ctrl = ss.UniversalController(system, clf, cbf, kappa=1.0, rho=0.0, phi=1.0, varphi=0.0)
    tr = simulate(ctrl, [0.5], t_final=1.0, dt=0.01)
    assert tr.infeasible_steps > 0  # recorded, not raised
    with pytest.raises(ss.InfeasibleError, match=r"infeasible steps"):
        simulate(ctrl, [0.5], t_final=1.0, dt=0.01, strict=True)
    with pytest.raises(ss.ParameterError, match=r"dt must be > 0.0"):
        simulate(ctrl, [0.5], t_final=1.0, dt=0.0)


def test_simulate_runs_a_safety_filter_like_a_hand_written_loop():
    # A robot (single integrator) among three discs, a CLF at the goal and input limits: the
    # trajectory of simulate equals an eager loop over filt.step (x_{k+1} = x_k + dt u_k, which
    # RK4 reproduces exactly for xdot = u), and it records every barrier's value.
    sys = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)
    centres = np.array([[1.5, 0.1], [2.5, -0.6], [3.0, 0.8]])
    cbfs = [
        ss.CBF(lambda x, c=jnp.asarray(c): jnp.sum((x - c) ** 2) - 0.25, beta=2.0) for c in centres
    ]
    goal = jnp.array([4.0, 0.0])
    clf = ss.CLF(lambda x: jnp.sum((x - goal) ** 2), lam=1.0)
    filt = ss.SafetyFilter(
        sys, cbfs, clfs=[clf], u_nom=lambda x: 0.8 * (goal - x), slack_weight=10.0,
        u_min=-1.0, u_max=1.0,
    )  # fmt: skip
    dt, n = 0.02, 150
    tr = simulate(filt, np.zeros(2), t_final=n * dt, dt=dt)
    assert tr.multi and tr.h.shape == (n + 1, 3) and tr.V.shape == (n + 1, 1)
    x = np.zeros(2)
    for k in range(n + 1):
        out = filt.step(x)
        np.testing.assert_allclose(np.asarray(tr.x)[k], x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(tr.u)[k], np.asarray(out.u), rtol=0, atol=1e-10)
        hs = [float(c.fn(jnp.asarray(x))) for c in cbfs]
        np.testing.assert_allclose(np.asarray(tr.h)[k], hs, rtol=0, atol=1e-12)
        assert int(tr.region[k]) == int(out.formula_status)
        x = x + dt * np.asarray(out.u)
    assert tr.ok and tr.infeasible_steps == 0 and np.all(np.asarray(tr.cbf_satisfied))
    assert float(np.min(tr.h)) >= 0.0
    batch = simulate(filt, np.zeros((2, 2)), t_final=n * dt, dt=dt)
    assert batch.h.shape == (2, n + 1, 3)
    np.testing.assert_array_equal(np.asarray(batch.x[1]), np.asarray(tr.x))


def test_simulate_refuses_what_is_not_a_controller():
    with pytest.raises(
        ss.InputTypeError, match="UniversalController, a SafetyFilter or a PolicyController"
    ):
        simulate(lambda x: x, np.zeros(2), t_final=1.0)


@pytest.mark.parametrize("kind", ["formula", "filter"])
def test_a_simulation_traces_the_recorded_row_once_and_reuses_the_step(kind):
    """The closed loop records a row per step and one for the final state, and calls the
    controller before the loop and in its body: each is traced once per simulation. Counted
    by the CBF's function: once the controller's step has been traced (by ``eval_shape``),
    a simulation evaluates ``h`` at trace time only for the recorded row, once (it was twice
    when the row of the final state was traced apart from the steps')."""
    calls = {"h": 0, "f": 0}

    def f(x):
        calls["f"] += 1
        return jnp.zeros(2)

    def h(x):
        calls["h"] += 1
        return jnp.sum((x - jnp.array([2.0, 0.1])) ** 2) - 0.25

    sys = ss.ControlAffineSystem(f, lambda x: jnp.eye(2), 2)
    clf = ss.CLF(lambda x: jnp.sum((x - jnp.array([4.0, 0.0])) ** 2), lam=1.0)
    cbf = ss.CBF(h, beta=2.0)
    if kind == "formula":
        ctrl = ss.UniversalController(
            sys, clf, cbf, kappa=1.0, rho=0.0, phi=1.0, varphi=0.0, slack_weight=10.0
        )
    else:
        ctrl = ss.SafetyFilter(sys, [cbf], clfs=[clf], slack_weight=10.0, u_min=-1.0, u_max=1.0)
    jax.eval_shape(ctrl.step_fn, jnp.zeros(2))
    assert calls["h"] > 0  # the step evaluates h (its Lie terms)
    calls.update(h=0, f=0)
    tr = simulate(ctrl, np.zeros((2, 2)), t_final=0.1, dt=0.01)
    assert tr.ok and tr.x.shape == (2, 11, 2)
    # h: the recorded row only; f: the plant's four RK4 stages (the step's trace is reused)
    assert calls == {"h": 1, "f": 4}, calls


def test_the_closed_loop_program_holds_one_copy_of_the_controller():
    """XLA inlines every call: a controller called before the loop (for x_0) and in its body
    was compiled twice. Counted by an operation only the step uses (cbrt) in the compiled
    program, whose records are checked against a plain Python loop of the same scheme."""

    class Rec:
        def init(self, x0, data):
            return jnp.asarray(0.0)

        def update(self, s, k, t, x, out, data):
            return s + out[0] * (k + 1), (x, out, t)

        def finish(self, s, ys, x_final, out_final, t_final, data):
            return s, ys, x_final, out_final

    def step(t, x, data):
        return jax.lax.cbrt(x) * (1.0 + t)

    def rhs(t, x, out, data):
        return -out + 0.5 * x

    run = ss.closed_loop(step, rhs, Rec(), n_steps=5, dt=0.1)
    x0 = jnp.array([1.0, -2.0])
    assert jax.jit(run).lower(x0, None).compile().as_text().count("cbrt(") == 1
    s, (xs, outs, ts), x_final, out_final = jax.jit(run)(x0, None)
    # the reference: the same zero-order hold and RK4 step, one call at a time
    x, acc = x0, 0.0
    for k in range(5):
        t = k * 0.1
        out = step(t, x, None)
        np.testing.assert_allclose(xs[k], x, rtol=1e-14)
        np.testing.assert_allclose(outs[k], out, rtol=1e-14)
        assert ts[k] == pytest.approx(t, abs=1e-15)
        acc += float(out[0]) * (k + 1)
        x = rk4_step(lambda tt, z: rhs(tt, z, out, None), t, x, 0.1)
    np.testing.assert_allclose(x_final, x, rtol=1e-14)
    np.testing.assert_allclose(out_final, step(0.5, x, None), rtol=1e-14)
    assert float(s) == pytest.approx(acc, rel=1e-14)


class _SmallBand:
    """A hand-made uncertainty model: zero mean, a constant standard deviation."""

    n_states = 2

    def mean_std(self, x):
        return jnp.zeros(2), jnp.full(2, 0.01)


def test_simulate_reuses_the_loop_of_an_equal_controller_and_only_that():
    """The loop takes the controller as its argument: controllers of one tree structure
    (built alike, or replace() with new numbers, or another uncertainty model of the same
    kind) run one compiled program, with the same bits as a run of their own; another
    step, another plant object, or a controller traced under a user's jit trace again."""
    calls = {"f": 0}

    def f(x, p):
        calls["f"] += 1
        return p["a"] * x

    sys = ss.ControlAffineSystem(f, lambda x, p: jnp.eye(2), 2, params={"a": 0.0})
    clf = ss.CLF(lambda x: jnp.sum((x - jnp.array([1.0, 0.5])) ** 2), lam=1.0)
    cbf = ss.CBF(lambda x: 4.0 - jnp.sum(x**2), beta=1.0)
    opts = dict(kappa=1.0, rho=0.0, phi=1.0, varphi=0.0, slack_weight=10.0)
    ctrl = ss.UniversalController(sys, clf, cbf, **opts)
    twin = ss.UniversalController(sys, clf, cbf, **opts)
    x0 = np.array([[0.2, -0.1], [-0.5, 0.3]])
    run = dict(t_final=0.5, dt=0.01)

    alone = simulate(twin, x0, params={"a": -0.3}, **run)  # traced for the twin
    traced = calls["f"]
    assert traced > 0
    first = simulate(ctrl, x0, params={"a": 0.1}, **run)
    reused = simulate(ctrl, x0, params={"a": -0.3}, **run)
    assert calls["f"] == traced  # neither traced again
    for a, b in ((reused.x, alone.x), (reused.u, alone.u), (reused.h, alone.h)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.array_equal(np.asarray(first.x), np.asarray(reused.x))  # the params count

    other = simulate(ctrl.replace(kappa=2.0), x0, params={"a": -0.3}, **run)
    assert calls["f"] == traced  # another kappa: the same program, other numbers
    assert not np.array_equal(np.asarray(other.u), np.asarray(alone.u))

    # another step or another plant object (the same functions): traced
    twin_plant = ss.ControlAffineSystem(f, lambda x, p: jnp.eye(2), 2, params={"a": 0.0})
    for kwargs in ({"t_final": 0.5, "dt": 0.02}, {**run, "plant": twin_plant}):
        traced = calls["f"]
        simulate(ctrl, x0, params={"a": -0.3}, **kwargs)
        assert calls["f"] > traced, kwargs

    # an uncertainty model that is not a pytree is the controller's static part: one
    # program for that model object, reused
    gp_ctrl = ctrl.replace(uncertainty=_SmallBand(), gp_beta=1.0)
    traced = calls["f"]
    simulate(gp_ctrl, x0, params={"a": -0.3}, **run)
    assert calls["f"] > traced
    traced = calls["f"]
    simulate(gp_ctrl.replace(gp_beta=2.0), x0, params={"a": -0.3}, **run)
    assert calls["f"] == traced

    # a controller that is an argument of a user's jit: traced leaves, a program of its own
    xs = jax.jit(lambda c: simulate(c, x0, params={"a": -0.3}, **run).x)(twin)
    np.testing.assert_allclose(np.asarray(xs), np.asarray(alone.x), rtol=1e-12, atol=1e-14)


def test_twenty_controllers_that_differ_in_numbers_compile_one_loop():
    """The issue's count: simulate of 20 controllers that differ only in their numbers (and
    a filter's) compiles one closed loop, counted from JAX's compilation events."""
    events = []

    def listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            events.append(event)

    system = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)
    clf = ss.CLF(lambda x: jnp.sum((x - jnp.array([1.0, 0.5])) ** 2), lam=1.0)
    cbf = ss.CBF(lambda x: 4.0 - jnp.sum(x**2), beta=1.0)
    base = ss.UniversalController(
        system, clf, cbf, kappa=0.1, rho=0.0, phi=1.0, varphi=0.0, slack_weight=10.0
    )
    filt = ss.SafetyFilter(system, cbf, clfs=clf, slack_weight=10.0, u_min=-1.0, u_max=1.0)
    x0 = np.array([0.2, -0.1])
    for first in (base, filt):
        simulate(first, x0, t_final=0.3, dt=0.01)  # compiled here (or cached)
        jax.monitoring.register_event_duration_secs_listener(listen)
        try:
            runs = [
                simulate(first.replace(kappa=0.05 * k, rho=0.01 * k), x0, t_final=0.3, dt=0.01)
                for k in range(20)
            ]
        finally:
            jax.monitoring.unregister_event_duration_listener(listen)
        assert events == []  # no compilation at all for the 20
        assert len({np.asarray(r.u).tobytes() for r in runs}) == 20  # 20 different runs
