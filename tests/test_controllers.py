"""Controllers against the solver-based reference, input limits and their flags."""

import numpy as np
import pytest

from safestab import InfeasibleError, Region, UniversalController, lie_terms
from safestab.reference import ReferenceController

from .systems_zoo import pendulum_two_inputs, unicycle_obstacle

PARAMS = {"kappa": 0.5, "rho": 0.2, "phi": 1.0, "varphi": 0.5}


@pytest.mark.parametrize("solver", ["clarabel", "osqp"])
@pytest.mark.parametrize("slack_weight", [None, 10.0])
def test_controller_matches_reference(solver, slack_weight):
    system, clf, cbf = unicycle_obstacle()
    ctrl = UniversalController(system, clf, cbf, slack_weight=slack_weight, **PARAMS)
    ref = ReferenceController(ctrl, solver=solver)
    xs = np.random.default_rng(5).normal(size=(40, 3))
    out = ctrl.step(xs)
    # OSQP is first-order: even polished, 1e-6 relative is what it reaches on these problems.
    tol = 1e-6 if solver == "clarabel" else 1e-4
    checked = 0
    for i, x in enumerate(xs):
        u_ref = ref(x)
        if np.all(np.isfinite(u_ref)) and int(out.region[i]) != Region.INCOMPATIBLE:
            assert np.linalg.norm(out.u[i] - u_ref) <= tol * max(1.0, np.linalg.norm(u_ref))
            checked += 1
    assert checked >= 30


def test_batched_step_equals_single_steps():
    system, clf, cbf = pendulum_two_inputs()
    ctrl = UniversalController(system, clf, cbf, **PARAMS)
    xs = np.random.default_rng(1).normal(size=(10, 2))
    batch = ctrl(xs)
    for i in range(10):
        np.testing.assert_allclose(batch[i], ctrl(xs[i]), rtol=1e-14, atol=1e-300)


def test_projection_flags_lost_cbf():
    system, clf, cbf = unicycle_obstacle()
    ctrl = UniversalController(system, clf, cbf, u_min=[-0.01, -0.01], u_max=[0.01, 0.01], **PARAMS)
    xs = np.random.default_rng(2).normal(size=(200, 3))
    out = ctrl.step(xs)
    assert np.all(np.abs(out.u) <= 0.01)
    t = lie_terms(system, clf, cbf, xs)
    B = PARAMS["rho"] * np.sqrt(t.c**2 + PARAMS["varphi"] * np.sum(t.d**2, -1) ** 2) - t.c
    holds = np.sum(t.d * out.u, -1) >= B - 1e-9 * (np.abs(B) + 1)
    np.testing.assert_array_equal(np.asarray(out.cbf_satisfied), holds)
    assert (~holds).any() and holds.any()  # the tight box breaks the CBF at some states


def _wall_system():
    import jax.numpy as jnp

    from safestab import CBF, CLF, ControlAffineSystem

    # double integrator heading for x = 5 with a wall: h = 1 - x - v
    system = ControlAffineSystem(
        lambda x: jnp.array([x[1], 0.0]), lambda x: jnp.array([[0.0], [1.0]]), 2
    )
    clf = CLF(lambda x: (x[0] - 5.0) ** 2 + (x[1]) ** 2 + x[1] * (x[0] - 5.0), lam=1.0)
    cbf = CBF(lambda x: 1.0 - x[0] - x[1], beta=1.0)
    return system, clf, cbf


def test_safety_first_equals_projection_for_formula_output():
    # In 1-D, clipping an input that meets the CBF keeps it whenever the box allows
    # (docs/theory.md), so both saturations agree on the formula's own output.
    system, clf, cbf = _wall_system()
    kw = dict(kappa=0.2, rho=0.1, phi=1.0, varphi=0.0, slack_weight=1.0, u_min=[-1.0], u_max=[1.0])
    proj = UniversalController(system, clf, cbf, **kw)
    safe = UniversalController(system, clf, cbf, saturation="safety_first", **kw)
    xs = np.random.default_rng(0).uniform([-2, -2], [1, 2], size=(500, 2))
    np.testing.assert_allclose(proj(xs), safe(xs), rtol=0, atol=1e-12)


def test_safety_first_rescues_a_cbf_blind_input():
    from safestab import clf_sontag, project_box, saturate_safety_first

    system, clf, cbf = _wall_system()
    xs = np.random.default_rng(0).uniform([-2, -2], [1, 2], size=(500, 2))
    t = lie_terms(system, clf, cbf, xs)
    u_clf = clf_sontag(t.a, t.b, kappa=0.2, phi=1.0).u  # ignores the barrier
    rho, varphi, lo, hi = 0.1, 0.0, -1.0, 1.0
    u_safe, feasible = saturate_safety_first(
        u_clf, t.c, t.d, rho=rho, varphi=varphi, u_min=[lo], u_max=[hi]
    )
    u_proj = project_box(u_clf, [lo], [hi])
    B = rho * np.abs(t.c) - t.c
    # feasibility by brute force: the best box input for the barrier is an endpoint
    brute = np.maximum(t.d[:, 0] * lo, t.d[:, 0] * hi) >= B
    np.testing.assert_array_equal(np.asarray(feasible), brute)
    tol = 1e-9 * (np.abs(B) + 1.0)
    assert np.all((t.d[:, 0] * u_safe[:, 0] >= B - tol)[brute])
    lost = (t.d[:, 0] * u_proj[:, 0] < B - tol)[brute]
    assert lost.any()  # plain projection of the CBF-blind input breaks the barrier somewhere


def test_strict_raises_on_incompatible():
    import jax.numpy as jnp

    from safestab import CBF, CLF, ControlAffineSystem

    system = ControlAffineSystem(lambda x: jnp.zeros(1), lambda x: jnp.ones((1, 1)), 1)
    clf = CLF(lambda x: (x[0] - 2.0) ** 2, lam=1.0)  # wants x -> 2
    cbf = CBF(lambda x: 1.0 - x[0], beta=1.0)  # keeps x <= 1
    ctrl = UniversalController(system, clf, cbf, kappa=1.0, rho=0.0, phi=1.0, varphi=0.0)
    out = ctrl.step([0.99])
    assert int(out.region) == Region.INCOMPATIBLE and not bool(out.compatible)
    assert bool(out.cbf_satisfied)  # the safety-first fallback keeps h
    with pytest.raises(InfeasibleError, match="CBF condition cannot be met"):
        ctrl.step([0.99], strict=True)


def test_on_device_keeps_the_numbers_and_never_a_stale_copy():
    """``step`` passes ``on_device()`` (the leaves as device arrays, kept on the object) to the
    compiled step: the same numbers, a new copy for every new value, none inside a trace."""
    import jax

    sys, clf, cbf = unicycle_obstacle()
    ctrl = UniversalController(sys, clf, cbf, kappa=0.5, rho=0.1, phi=0.0, varphi=0.0)
    dev = ctrl.on_device()
    assert dev is ctrl.on_device()  # made once
    got = jax.tree_util.tree_leaves(dev)
    want = jax.tree_util.tree_leaves(ctrl)
    assert all(isinstance(v, jax.Array) for v in got)
    np.testing.assert_array_equal(np.concatenate([np.ravel(v) for v in got]),
                                  np.concatenate([np.ravel(v) for v in want]))  # fmt: skip
    # values rebuilt from this one (replace, tree_map, a jitted function's output) have their
    # own numbers, not the cached copy's
    assert float(ctrl.replace(kappa=2.0).on_device().tunables()["kappa"]) == 2.0
    doubled = jax.tree_util.tree_map(lambda v: 2 * np.asarray(v), ctrl)
    assert float(doubled.on_device().tunables()["kappa"]) == 1.0
    x = np.array([2.0, 0.5, 0.1])
    np.testing.assert_array_equal(ctrl.step(x).u, np.asarray(ctrl.step_fn(x).u))
    # inside a trace: no traced copy is kept (it would leak out of the trace)
    fresh = ctrl.replace(kappa=1.0)
    jax.jit(lambda z: z + fresh.on_device().tunables()["kappa"])(1.0)
    kept = fresh.__dict__.get("_device_copy")
    leaves = [] if kept is None else jax.tree_util.tree_leaves(kept)
    assert not any(isinstance(v, jax.core.Tracer) for v in leaves)
    np.testing.assert_array_equal(fresh.step(x).u, np.asarray(fresh.step_fn(x).u))
