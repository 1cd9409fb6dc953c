"""The ACC's braking-distance barrier: invariance under the limits, the margin's bound, the
statuses of the GP-robust controllers against a direct check of the limits, the schema."""

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.errors import ParameterError, ScenarioError
from safestab.scenarios import load_scenario
from safestab.scenarios.acc_braking import braking_ddh_bound
from safestab.scenarios.trial_studies import ACCTrials

G = 9.81


@pytest.fixture(scope="module")
def sc():
    return load_scenario("stress-limited")


def _h(sc, x):
    a_f, a_l = sc.input_limit * sc.gravity, sc.lead_decel * sc.gravity
    vf, vl, D = x[..., 0], x[..., 1], x[..., 2]
    return D - sc.tau * vf - vf**2 / (2 * a_f) + vl**2 / (2 * a_l)


def _rhs(sc, x, force, a_lead):
    """The true plant written out by hand: force in N, the lead's acceleration in m/s^2."""
    d = sc.drag_true
    vf, vl = x[..., 0], x[..., 1]
    fr = d.f0 + d.f1 * vf + d.f2 * vf**2
    a_l = np.where((vl <= 0) & (a_lead < 0), 0.0, a_lead)  # a stopped lead stays stopped
    return np.stack([(-fr + force) / sc.mass, a_l, vl - vf], -1)


def test_full_braking_keeps_h_rising_against_the_worst_lead(sc):
    """Along the true plant with full braking and the lead braking at its bound, h' >= tau a_f
    at random states (v_f, v_l >= 0), by finite differences of h along the hand-written flow."""
    rng = np.random.default_rng(0)
    x = rng.uniform([0, 0, 0], [40, 40, 200], size=(5000, 3))
    force = -sc.input_limit * sc.mass * sc.gravity
    for a_lead in (-sc.lead_decel * G, 0.0, 0.15 * G):
        eps = 1e-6
        dh = (_h(sc, x + eps * _rhs(sc, x, force, a_lead)) - _h(sc, x)) / eps
        assert np.all(dh >= sc.tau * sc.input_limit * G - 1e-3)


def test_full_braking_from_the_boundary_stays_safe(sc):
    """Dense RK4 runs from states on h = 0, braking fully while the lead brakes at 0.3 g until
    it stops: h never goes below 0 (the barrier is control invariant under the limit)."""
    rng = np.random.default_rng(1)
    vf, vl = rng.uniform(0, 35, 200), rng.uniform(0, 35, 200)
    x = np.stack([vf, vl, np.zeros(200)], -1)
    x[:, 2] = -_h(sc, x)  # D with h = 0
    keep = x[:, 2] >= 0
    x = x[keep]
    force, a_lead, dt = -sc.input_limit * sc.mass * sc.gravity, -sc.lead_decel * G, 1e-3
    least = np.inf
    for _ in range(8000):  # 8 s: both stopped
        stopped = x[:, 0] <= 0
        f = np.where(stopped, 0.0, force)  # a brake holds a stopped car, it does not reverse it
        k1 = _rhs(sc, x, f, a_lead)
        k2 = _rhs(sc, x + dt / 2 * k1, f, a_lead)
        k3 = _rhs(sc, x + dt / 2 * k2, f, a_lead)
        k4 = _rhs(sc, x + dt * k3, f, a_lead)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        x[:, 0] = np.maximum(x[:, 0], 0.0)
        x[:, 1] = np.maximum(x[:, 1], 0.0)
        least = min(least, _h(sc, x).min())
    assert least >= -1e-6


def test_ddh_bound_is_sound_and_tight(sc):
    """braking_ddh_bound >= the dense max of -d/dt h'_w over v_f in [0, 40], u in the limits
    (h'_w's derivative by finite differences of the hand formula), and within 1 % of it."""
    a_f, k, M, tau = sc.input_limit * G, sc.input_scale, sc.mass, sc.tau
    d = sc.drag_true
    lim = sc.input_limit * M * sc.gravity / k

    def phi(v, u):
        return (k * u - (d.f0 + d.f1 * v + d.f2 * v**2)) / M

    def rate(v, u):  # h'_w = -v_f - (tau + v_f / a_f) phi
        return -v - (tau + v / a_f) * phi(v, u)

    v, u = np.meshgrid(np.linspace(0, 40, 801), np.linspace(-lim, lim, 201), indexing="ij")
    eps = 1e-6
    ddt = (rate(v + eps * phi(v, u), u) - rate(v, u)) / eps  # along v_f' = phi
    bound = braking_ddh_bound(d, M, tau, a_f, 40.0)
    assert bound >= np.max(-ddt) - 1e-6
    assert bound <= 1.01 * np.max(-ddt)
    assert sc.montecarlo.ddh_bound >= bound  # the preset's M is the proven one


class _Band:
    """A stub GP: mean and std of omega growing with v_f (so the band conflicts somewhere)."""

    n_states = 3

    def __init__(self, scale):
        self.scale = scale

    def mean_std(self, x):
        mean = jnp.array([-0.05 * x[0] / 20, 0.0, 0.0])
        return mean, self.scale * jnp.array([0.02, 0.01, 0.005]) * (1 + x[0] / 10)


@pytest.mark.parametrize("gp_beta", [2.0, 40.0, 400.0])
def test_robust_statuses_match_a_direct_check_of_the_limits(sc, gp_beta):
    """The GP-robust controller of the Monte Carlo (on the worst-lead model, the margin of
    the preset) at sampled states with h >= 0: its status is CBF_INFEASIBLE exactly where the
    hand-written robust condition fails at full braking (no input in the limits meets it),
    OK elsewhere, and never OK where the condition fails."""
    study = ACCTrials(sc, sc.montecarlo)
    _, nominal = study.systems()
    clf, cbf = study.certificates()
    band = _Band(1.0)
    ctrl = study.build_controller(nominal, clf, cbf, uncertainty=band, gp_beta=gp_beta,
                                  **study.controller_options())  # fmt: skip
    rng = np.random.default_rng(2)
    x = rng.uniform([0, 0, 0], [35, 35, 250], size=(4000, 3))
    x = x[_h(sc, x) >= 0]
    out = ctrl.step(jnp.asarray(x))
    status, u = np.asarray(out.status), np.asarray(out.u)[:, 0]
    # the direct check, by hand
    a_f, a_l = sc.input_limit * G, sc.lead_decel * G
    vf, vl = x[:, 0], x[:, 1]
    dn = sc.drag_nominal
    fr = dn.f0 + dn.f1 * vf + dn.f2 * vf**2
    slope = sc.tau + vf / a_f
    h = _h(sc, x)
    mean, std = (np.asarray(v) for v in jax_vmap_mean_std(band, x))
    grad = np.stack([-slope, vl / a_l, np.ones_like(vf)], -1)
    c = (slope * fr / sc.mass - vf + sc.beta * h + np.sum(grad * mean, -1)
         - gp_beta * np.sum(np.abs(grad) * std, -1))  # fmt: skip
    T, M = sc.dt, sc.montecarlo.ddh_bound
    c = c - (M * T / 2 + np.maximum(0.0, sc.beta * h - h / T))
    d = -slope * sc.input_scale / sc.mass
    lim = sc.input_limit
    assert sc.varphi == 0.0  # Gamma = |c~|
    slack_best = c + d * (-lim) - sc.rho * np.abs(c)
    scale = np.abs(c) + np.abs(d) * lim
    clear = np.abs(slack_best) > 1e-9 * scale
    feasible = slack_best > 0
    assert np.all(np.abs(u[np.isfinite(u)]) <= lim * (1 + 1e-12))
    S = ss.StepStatus
    assert np.all(status[clear & ~feasible] == S.CBF_INFEASIBLE)
    assert np.all(status[clear & feasible] == S.OK)
    if gp_beta >= 40.0:  # the wide bands conflict with the limit somewhere, named
        assert np.sum(clear & ~feasible) > 0
    else:
        assert np.sum(~feasible) == 0  # a narrow band never does at these states


def jax_vmap_mean_std(model, x):
    import jax

    return jax.vmap(model.mean_std)(jnp.asarray(x))


def test_hand_lie_terms_match_autodiff_on_the_worst_lead_model(sc):
    x = jnp.asarray(np.random.default_rng(3).uniform([0, 0, 0], [35, 35, 200], size=(50, 3)))
    clf, cbf = sc.certificates()
    for which in ("true", "nominal"):
        ctrl = ss.UniversalController(
            sc.controller_system(sc.system(which)),
            clf,
            cbf,
            kappa=0.2,
            rho=0.1,
            phi=0.0,
            varphi=0.0,
        )
        auto = ctrl.step(x).terms
        hand = sc.hand_lie_terms(x, which)
        for a, b in zip(auto, hand, strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)


def _doc(tmp_path, **edits):
    text = (Path(__file__).parent.parent / "src" / "safestab" / "scenarios"
            / "stress-limited.toml").read_text()  # fmt: skip
    for old, new in edits.items():
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            'barrier = "braking"',
            'barrier = "distance"',
            r"certificates\.barrier must be one of 'headway', 'braking', got 'distance'",
        ),
        (
            "input_limit = 0.3 ",
            "input_limit = false ",
            r"controller\.input_limit must be a number \(the braking limit",
        ),
        ("lead_decel = 0.3 ", "# ", r"certificates\.lead_decel must be a number in \(0, 10\]"),
        (
            "lead_decel = 0.3 ",
            "lead_decel = 0.01 ",
            r"certificates\.lead_decel must be >= the lead profile's largest deceleration, 0\.4",
        ),
        (
            "decel_max = 0.3 ",
            "decel_max = 0.5 ",
            r"montecarlo\.lead\.decel_max must be <= certificates\.lead_decel = 0\.3",
        ),
        (
            'barrier = "braking"',
            'barrier = "headway"',
            r"certificates\.lead_decel must be absent with certificates\.barrier = 'headway'",
        ),
    ],
)
def test_schema_names_the_braking_barrier_errors(tmp_path, old, new, message):
    with pytest.raises(ScenarioError, match=message):
        load_scenario(_doc(tmp_path, **{old: new}))


def test_a_passed_spec_must_keep_the_lead_bound(sc):
    with pytest.raises(ParameterError, match=r"montecarlo\.lead\.decel_max must be <="):
        ACCTrials(sc, sc.montecarlo.replace(lead_decel_max=0.4))
    assert load_scenario("stress").barrier == "headway"  # the paper's default
