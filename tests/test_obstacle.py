"""The obstacle scenario (the paper's Fig. 2): model, file validation, study claims, maps, CLI.

Fast tests check the model against hand derivations and simulate small batches directly; the
tests marked slow run the whole preset study once (module fixture) and check its claims.
"""

import json
import warnings
from importlib import resources

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
import pytest

import safestab as ss
from safestab import ScenarioError
from safestab.errors import InducingPointsWarning
from safestab.scenarios import ObstacleScenario, load, load_obstacle_scenario, scenario_kind
from safestab.scenarios.obstacle_study import (
    CONTROLLERS,
    LIMIT_SETTINGS,
    calibrate_beta,
    classify_outcomes,
    compatibility_maps,
    doa_level,
    run_obstacle_study,
)

matplotlib.use("Agg")


@pytest.fixture(scope="module")
def sc():
    return load_obstacle_scenario("obstacle")


def _params(sc):
    return {"kappa": sc.kappa, "rho": sc.rho, "phi": sc.phi, "varphi": sc.varphi}


def _hand_margins(sc, a, b, c, d):
    """``A = a + kappa zeta``, ``B = rho Gamma - c`` written out (eq. (8))."""
    nb2, nd2 = np.sum(b * b, -1), np.sum(d * d, -1)
    A = a + sc.kappa * np.sqrt(a**2 + sc.phi * nb2**2)
    B = sc.rho * np.sqrt(c**2 + sc.varphi * nd2**2) - c
    return A, B


# -- the model ----------------------------------------------------------------------------


def test_lie_terms_match_hand_derivation(sc):
    x = np.random.default_rng(0).uniform([-9, -4], [3, 4], (200, 2))
    clf, cbf = sc.certificates()
    for which in ("true", "nominal"):
        auto = ss.lie_terms(sc.system(which), clf, cbf, x)
        hand = sc.hand_lie_terms(x, which)
        for got, want in zip(auto, hand, strict=True):
            # autodiff and the closed form differ only by float64 rounding of O(100) values
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12, atol=1e-12)


def test_omega_is_the_drift_difference_and_symmetric(sc):
    x = np.random.default_rng(1).uniform([-9, -4], [3, 4], (100, 2))
    f_true = jax.vmap(sc.system("true").f)(jnp.asarray(x))
    f_nom = jax.vmap(sc.system("nominal").f)(jnp.asarray(x))
    np.testing.assert_array_equal(np.asarray(sc.omega(x)), np.asarray(f_true - f_nom))
    mirrored = np.asarray(sc.omega(x * [1, -1]))  # mirror image about the x1 axis
    np.testing.assert_array_equal(mirrored, np.asarray(sc.omega(x)) * [1, -1])


def test_parallel_set_is_where_b_and_d_point_the_same_way(sc):
    pts = sc.parallel_set()
    _, b, _, d = (np.asarray(t) for t in sc.hand_lie_terms(pts))
    cross = b[:, 0] * d[:, 1] - b[:, 1] * d[:, 0]
    scale = np.linalg.norm(b, axis=1) * np.linalg.norm(d, axis=1)
    # sin of the angle: rounding of products of O(10) numbers, a few eps
    assert np.all(np.abs(cross) <= 1e-13 * scale)
    assert np.all(np.sum(b * d, 1) > 0)
    # and off the set, b and d are not parallel: random points have a clear angle
    x = np.random.default_rng(2).uniform([-9, 0.1], [3, 4], (500, 2))
    x = x[np.abs(x[:, 0] - sc.P[1] * sc.obstacle_x1 / (sc.P[1] - sc.P[0])) > 0.1]
    _, b, _, d = (np.asarray(t) for t in sc.hand_lie_terms(x))
    cross = b[:, 0] * d[:, 1] - b[:, 1] * d[:, 0]
    assert np.all(np.abs(cross) > 1e-6 * np.linalg.norm(b, axis=1) * np.linalg.norm(d, axis=1))


def test_doa_level_matches_the_hand_lemma1_on_the_axis(sc):
    # On the axis behind the obstacle d = t b with t = |d|/|b| > 0, so Lemma 1 (corrected)
    # says incompatible iff t A + B > 0. c* is the least V there with h >= 0.
    xo, r = sc.obstacle_x1, sc.radius
    x1 = np.linspace(xo - r, sc.map_x1[0], 200001)
    pts = np.stack([x1, 0 * x1], -1)
    for controller, which in (("true model", "true"), ("mismatched model", "nominal")):
        a, b, c, d = (np.asarray(t) for t in sc.hand_lie_terms(pts, which))
        A, B = _hand_margins(sc, a, b, c, d)
        t = np.linalg.norm(d, axis=1) / np.linalg.norm(b, axis=1)
        bad = t * A + B > 0
        c_hand = np.min(np.asarray(sc.V(pts[bad])))
        got = doa_level(sc, controller)
        # parallel_set samples the axis with 2001 points over 6 m: V varies by < 0.03 m^2
        # between samples near x1 = -4, and the boundary point (the minimiser here) is exact
        assert got == pytest.approx(c_hand, abs=0.03), controller
    # the line x1 = p2 x1_o / (p2 - p1) is compatible in the preset: far from the obstacle
    line = sc.parallel_set()[sc.parallel_set()[:, 1] != 0]
    a, b, c, d = (np.asarray(t) for t in sc.hand_lie_terms(line, "nominal"))
    A, B = _hand_margins(sc, a, b, c, d)
    t = np.linalg.norm(d, axis=1) / np.linalg.norm(b, axis=1)
    assert np.all(t * A + B <= 0)


def test_verdict_rejects_unknown_controller_and_missing_model(sc):
    from safestab import ParameterError
    from safestab.scenarios.obstacle_study import verdict

    with pytest.raises(ParameterError, match=r"controller must be one of .*got 'exact'"):
        verdict(sc, "exact", np.zeros((1, 2)))
    with pytest.raises(ParameterError, match=r"'GP-robust' verdict needs uncertainty="):
        verdict(sc, "GP-robust", np.zeros((1, 2)))


def test_classify_outcomes_by_hand():
    t = np.linspace(0, 1, 3)[None, :, None]
    x = np.concatenate(
        [
            np.zeros((1, 3, 2)),  # at the goal
            np.ones((1, 3, 2)) * [2.0, 0.0],  # at rest away from it
            t * [1.0, 0.0] + [2.0, 0.0],  # still moving
            np.zeros((1, 3, 2)),  # at the goal, but h < 0 on the way
        ]
    )
    h = np.ones((4, 3))
    h[3, 1] = -1e-12
    out = classify_outcomes(x, h, dt=0.5, ball_radius=0.05, rest_speed=1e-3)
    assert out.tolist() == ["converged", "stuck", "moving", "unsafe"]
    h[0, 2] = np.nan
    assert classify_outcomes(x, h, 0.5, 0.05, 1e-3)[0] == "unsafe"


# -- the claims, with direct simulations (fast) ------------------------------------------


def test_input_variation_and_converge_time_by_hand():
    from safestab.scenarios.obstacle_study import ObstacleRun

    t = np.arange(5) * 0.5  # T = 2 s
    x = np.array([[[1, 0], [0.5, 0], [0.04, 0], [0.06, 0], [0.01, 0]],  # back out once
                  [[1, 0], [0.5, 0], [0.3, 0], [0.2, 0], [0.1, 0]],  # never inside
                  [[0.01, 0]] * 5], float)  # fmt: skip
    u = np.zeros((3, 5, 2))
    u[0, :, 0] = [0, 3, -1, -1, 0]  # jumps 3, 4, 0, 1: 8 m/s over 2 s
    u[1, :, 1] = [0, 0, 0, 0, 0.5]
    u[2, :, 0] = [0, 0, 0, 0.2, 0]  # jumps 0.2, 0.2, all inside the ball
    n = np.zeros((3, 5))
    run = ObstacleRun(
        controller="true model", limits="no limits", x0=x[:, 0], compatible_formula=n[:, 0] > 0,
        t=t, x=x, u=u, V=n, h=n + 1, compatible=n > 0, status=n.astype(int),
        outcome=np.array(["converged", "moving", "converged"]), end_verdict=n[:, 0] > 0,
    )  # fmt: skip
    np.testing.assert_allclose(run.input_variation(), [4.0, 0.25, 0.2])
    ct = run.converge_time(0.05)
    assert ct[0] == 2.0 and np.isnan(ct[1]) and ct[2] == 0.0
    # jumps made inside the ball: run 0's third (0 of its 8), run 1 none (0.5), run 2 all 0.4
    assert run.variation_in_ball_share(0.05) == pytest.approx(0.4 / 8.9)
    doc = run.summary(0.05)
    assert doc["median_input_variation_mps2"] == 0.25 and doc["median_converge_time_s"] == 1.0
    assert doc["input_variation_in_ball_share"] == pytest.approx(0.4 / 8.9)
    # per run, per second of the 2 s horizon: run 0 none, run 1 none, run 2 0.4 m/s
    np.testing.assert_allclose(run.variation_in_ball(0.05), [0.0, 0.0, 0.2])
    assert doc["max_input_variation_in_ball_mps2"] == pytest.approx(0.2)
    assert "median_converge_time_s" not in run.summary()


def test_true_model_from_documented_compatible_region_converges_safely(sc):
    # docs/obstacle.md: the compatible region is {V < doa_fraction c*} ∩ C, c* of the true model
    level = sc.doa_fraction * doa_level(sc, "true model")
    rng = np.random.default_rng(3)
    x = rng.uniform([-4.0, -3.0], [4.0, 3.0], (4000, 2))
    x = x[(np.asarray(sc.V(x)) < level) & (np.asarray(sc.h(x)) > 0)][:40]
    assert len(x) == 40
    clf, cbf = sc.certificates()
    ctrl = ss.UniversalController(sc.system("true"), clf, cbf, **_params(sc))  # Theorem 1
    tr = ss.simulate(ctrl, x, t_final=sc.t_final, dt=sc.dt)
    h = np.asarray(tr.h)
    assert np.all(h >= 0)
    assert np.all(np.linalg.norm(np.asarray(tr.x)[:, -1], axis=1) <= sc.ball_radius)
    assert np.all(np.asarray(tr.compatible))  # Theorem 1's hypothesis held along the way


@pytest.mark.parametrize("limits", [False, True])
def test_model_family_is_each_model_to_the_last_bit_and_gives_the_models_own_loops(sc, limits):
    """The study runs the true-model and mismatched-model controllers on one parametric
    model (one program, other data). Its drift and input matrix are each model's (equal
    values), and the study's way of running them (every start, then its selection) gives the
    trajectories of controllers on the models themselves run from the selection alone, bit
    for bit: with the projection-free formula and with the safety filter (the preset's
    limits)."""
    from safestab.scenarios.obstacle_study import obstacle_controller, study_controller

    family = sc.model_family()
    x = np.random.default_rng(5).uniform([-4.0, -3.0], [4.0, 3.0], (64, 2))
    starts = sc.start_states()[::6]
    sel = np.arange(len(starts)) % 3 != 1
    kw = {"t_final": 0.5, "dt": sc.dt, "plant": sc.system("true")}
    for name, which in (("true model", "true"), ("mismatched model", "nominal")):
        p = sc.model_params(which)
        model = sc.system(which)
        for got, want in ((family.f_of, model.f), (family.g_of, model.g)):
            a = np.asarray(jax.vmap(lambda z: got(z, p))(jnp.asarray(x)))  # noqa: B023
            assert np.array_equal(a, np.asarray(jax.vmap(want)(jnp.asarray(x))))
        shared, params = study_controller(sc, name, limits=limits, hard=False)
        assert params == p
        own = obstacle_controller(sc, name, limits=limits)
        a = ss.simulate(shared, starts, params=params, **kw)
        b = ss.simulate(own, starts[sel], **kw)
        assert np.array_equal(np.asarray(a.x)[sel], np.asarray(b.x))
        assert np.array_equal(np.asarray(a.u)[sel], np.asarray(b.u))
    with pytest.raises(ss.ParameterError, match="controller must be one of"):
        study_controller(sc, "nominal", limits=False, hard=False)


def test_stuck_trajectories_end_incompatible(sc):
    # starts on the axis behind the obstacle: by symmetry x2 stays exactly 0
    x0 = np.array([[-8.0, 0.0], [-6.0, 0.0], [-5.0, 0.0]])
    clf, cbf = sc.certificates()
    true = sc.system("true")
    ctrl = ss.UniversalController(true, clf, cbf, slack_weight=sc.slack_weight, **_params(sc))
    tr = ss.simulate(ctrl, x0, t_final=sc.t_final, dt=sc.dt)
    out = classify_outcomes(tr.x, tr.h, sc.dt, sc.ball_radius, sc.rest_speed)
    assert out.tolist() == ["stuck"] * 3
    assert not np.any(np.asarray(tr.compatible)[:, -1])  # the controller's own flag
    end = np.asarray(tr.x)[:, -1]
    a, b, c, d = (np.asarray(t) for t in sc.hand_lie_terms(end, "true"))
    assert not np.any(np.asarray(ss.compatibility(a, b, c, d, **_params(sc)).compatible))
    # independently: d = t b with t > 0 and t A + B > 0 (Lemma 1, corrected)
    A, B = _hand_margins(sc, a, b, c, d)
    t = np.linalg.norm(d, axis=1) / np.linalg.norm(b, axis=1)
    assert np.all(t * A + B > 0)
    assert np.all(np.asarray(sc.h(end)) >= 0)


class _Band:
    """An analytic uncertainty model: mean 0.8 w(x), std 0.05 + 0.1 |w(x)| (m/s)."""

    n_states = 2

    def __init__(self, sc):
        self.sc = sc

    def mean_std(self, x):
        w = self.sc.current(x)
        return 0.8 * w, 0.05 + 0.1 * jnp.abs(w)


def test_maps_agree_pointwise_with_the_public_verdicts(sc):
    small = sc.replace(map_n_x1=41, map_n_x2=21)
    band = _Band(small)
    maps = compatibility_maps(small, band)
    x1, x2 = small.map_axes()
    grid = np.stack(np.meshgrid(x1, x2, indexing="ij"), -1).reshape(-1, 2)
    a, b, c, d = (np.asarray(t) for t in small.hand_lie_terms(grid, "nominal"))
    comp = ss.compatibility(a, b, c, d, **_params(small))
    np.testing.assert_array_equal(maps.nominal_compatible.reshape(-1), np.asarray(comp.compatible))
    np.testing.assert_array_equal(
        maps.nominal_region.reshape(-1), np.asarray(ss.clf_cbf(a, b, c, d, **_params(small)).region)
    )
    # the robust margins by hand: Delta_V = gradV.m + sum |dV/dx_i| beta s_i, likewise Delta_h
    w = np.asarray(small.current(grid))
    mean, std = 0.8 * w, 0.05 + 0.1 * np.abs(w)
    gV = 2 * grid * np.asarray(small.P)
    gh = 2 * (grid - small.obstacle_center)
    beta = small.gp_beta
    # the preset's boundary layer on the CLF term: times |gV| / sqrt(|gV|^2 + eps^2)
    norm = np.linalg.norm(gV, axis=1)
    shrink = norm / np.hypot(norm, small.robust_clf_layer)
    dV = np.sum(gV * mean, 1) + shrink * np.sum(np.abs(gV) * beta * std, 1)
    dh = np.sum(gh * mean, 1) - np.sum(np.abs(gh) * beta * std, 1)
    pc = ss.probabilistic_compatibility(
        ss.LieTerms(a, b, c, d), ss.RobustMargins(dV, dh), **_params(small)
    )
    np.testing.assert_array_equal(maps.robust_updated.reshape(-1), np.asarray(pc.updated))
    np.testing.assert_array_equal(maps.robust_lemma4.reshape(-1), np.asarray(pc.lemma4))
    # a beta not calibrated (the preset's gp_beta = 2 as it stands) states Lemma 2's
    # (1 - delta)^2; a calibrated one holds for both components at once: 1 - delta
    assert maps.probability == pytest.approx((1 - small.delta) ** 2, rel=1e-15)
    calibrated = compatibility_maps(small, band, calibrated=True)
    assert calibrated.probability == pytest.approx(1 - small.delta, rel=1e-15)
    np.testing.assert_array_equal(calibrated.robust_updated, maps.robust_updated)
    # the grid holds the axis, so the maps do show incompatible points behind the obstacle
    axis = np.isclose(x2, 0.0, atol=0)
    assert axis.sum() == 1
    assert not np.all(maps.nominal_compatible[:, axis])
    assert np.all(maps.nominal_compatible[:, ~axis])  # elsewhere b, d are not parallel


# -- the scenario file ------------------------------------------------------------------


def _preset_text():
    return resources.files("safestab.scenarios").joinpath("obstacle.toml").read_text()


def _edited(tmp_path, old, new):
    text = _preset_text()
    assert old in text, old  # the edit must apply, or the test proves nothing
    path = tmp_path / "case.toml"
    path.write_text(text.replace(old, new, 1))
    return path


BAD = [
    ("gain_true = 1.1", "gain_true = 0.0", r"vehicle\.gain_true must be a finite number in \[1e-9"),
    ("gain_true = 1.1", "gain_true = nan", r"vehicle\.gain_true must be .*, got nan"),
    ("speed = 0.7", "speed = -0.7", r"current\.speed must be .*\[0, 1e9\], got -0\.7"),
    ("width = 1.5", 'width = "wide"', r"current\.width must be .*, got 'wide' \(a string\)"),
    ("radius = 1.0", "radius = inf", r"obstacle\.radius must be .*, got inf"),
    ("radius = 1.0", "radius = 3.0", r"obstacle\.radius must be < \|obstacle\.x1\| = 3\.0"),
    ("P = [1.0, 2.0]", "P = [1.0]", r"certificates\.P must be an array of 2 finite numbers"),
    ("P = [1.0, 2.0]", "P = [1.0, -2.0]", r"certificates\.P\[1\] must be .*, got -2\.0"),
    ("lam = 0.5", "lam = -1", r"certificates\.lam must be .*, got -1"),
    ("slack_weight = 100.0", "slack_weight = 0", r"controller\.slack_weight must be"),
    ("input_limit = 1.5", "input_limit = false", r"controller\.input_limit must be .*false"),
    ("doa_fraction = 0.9", "doa_fraction = 1.0", r"controller\.doa_fraction must be a number in"),
    ("x1 = [-8.0, 2.0]", "x1 = [2.0, -8.0]", r"starts\.x1\[0\] must be < starts\.x1\[1\]"),
    ("n_x1 = 11", "n_x1 = 0", r"starts\.n_x1 must be an integer in \[1, 1000\], got 0"),
    ("n_x1 = 121", "n_x1 = 12.5", r"map\.n_x1 must be an integer in \[1, 1000\], got 12\.5"),
    ("t_final = 25.0", "t_final = 1e12", r"simulation\.t_final must be .*, got 1000000000000\.0"),
    ("dt = 0.02", "dt = 1e-8", r"simulation\.t_final / simulation\.dt must give between"),
    ("ball_radius = 0.05", "ball_radius = 0", r"simulation\.ball_radius must be"),
    ("n_samples = 400", "n_samples = 5", r"learning\.n_samples must be an integer in \[10, "),
    ("delta = 0.01", "delta = 0.0", r"learning\.delta must be a number in the open interval"),
    ('kernel = "se"', 'kernel = "rbf"', r"learning\.kernel must be one of 'se', 'matern52'"),
    ("x0_low = [-9.0, -4.0]", "x0_low = [9.0, -4.0]", r"learning\.x0_low\[0\] must be <="),
    ("seed = 0", "seed = -1", r"learning\.seed must be an integer in \[0, 4294967295\]"),
    ("n_inducing = 256", "n_inducing = -1", r"learning\.n_inducing must be an integer"),
    (
        "robust_clf_layer = 0.2",
        "robust_clf_layer = -0.1",
        r"controller\.robust_clf_layer must be .*, got -0\.1",
    ),
    (
        'beta_method = "conformal"',
        'beta_method = "lemma2"',
        r"learning\.beta_method must be one of 'chosen', 'conformal', got 'lemma2'",
    ),
    ('name = "obstacle"', 'name = "../x"', r"name must be a string of 1 to 64"),
    ("[map]", "[mapp]\nx = 1\n\n[map]", r"unknown key 'mapp'; expected one of certificates"),
    ("rest_speed = 0.001", "rest_speed = 0.001\nextra = 1", r"unknown key 'simulation\.extra'"),
    ("n_x2 = 81\n", "", r"missing key map\.n_x2"),
]


@pytest.mark.parametrize("old, new, message", BAD)
def test_bad_fields_are_rejected_at_load_naming_the_key(tmp_path, old, new, message):
    path = _edited(tmp_path, old, new)
    with pytest.raises(ScenarioError, match=message):
        load_obstacle_scenario(path)
    with pytest.raises(ScenarioError, match=message):  # the dispatching loader too
        load(path)


def test_beta_method_is_optional_and_defaults_to_chosen(tmp_path, sc):
    assert sc.beta_method == "conformal"  # the preset
    old = _edited(tmp_path, 'beta_method = "conformal"  #', "#")  # a file from before the key
    assert load_obstacle_scenario(old).beta_method == "chosen"
    with pytest.raises(ScenarioError, match=r"learning\.beta_method must be one of"):
        sc.replace(beta_method="Conformal")


def test_robust_clf_layer_is_optional_and_reaches_the_gp_robust_controller(tmp_path, sc):
    from safestab.scenarios.obstacle_study import obstacle_controller

    assert sc.robust_clf_layer == 0.2  # the preset
    old = _edited(tmp_path, "robust_clf_layer = 0.2 #", "#")  # a file from before the key
    assert load_obstacle_scenario(old).robust_clf_layer == 0.0

    class Band:
        n_states = 2

        def mean_std(self, x):
            return jnp.zeros(2), jnp.full(2, 0.1)

    layered = obstacle_controller(sc, "GP-robust", Band())
    plain = obstacle_controller(sc.replace(robust_clf_layer=0.0), "GP-robust", Band())
    assert float(layered.robust_clf_layer) == 0.2 and plain.robust_clf_layer is None
    assert obstacle_controller(sc, "true model").uncertainty is None  # no layer without a band


def test_limit_method_is_optional_and_the_filter_keeps_the_box_as_constraints(tmp_path, sc):
    from safestab.scenarios.obstacle_study import obstacle_controller

    assert sc.limit_method == "filter"  # the preset
    old = _edited(tmp_path, 'limit_method = "filter"', "#")  # a file from before the key
    base = load_obstacle_scenario(old)
    assert base.limit_method == "projection"
    with pytest.raises(ScenarioError, match=r"controller\.limit_method must be one of"):
        sc.replace(limit_method="clip")
    free = obstacle_controller(base, "true model")
    proj = obstacle_controller(base, "true model", limits=True)
    filt = obstacle_controller(base.replace(limit_method="filter"), "true model", limits=True)
    assert isinstance(proj, ss.UniversalController) and isinstance(filt, ss.SafetyFilter)
    assert isinstance(obstacle_controller(sc, "true model"), ss.UniversalController)
    lim = sc.input_limit
    rng = np.random.default_rng(3)
    x = rng.uniform([-9.0, -4.0], [3.0, 4.0], (400, 2))
    x = x[np.asarray(sc.h(x)) > 0.05]  # states in the safe set
    u_free = np.asarray(free.step(x).u)
    out = filt.step(x)
    u_filt, u_proj = np.asarray(out.u), np.asarray(proj.step(x).u)
    # where the relaxed formula's input is inside the box, the box is inactive: the same QP
    inside = np.all(np.abs(u_free) <= lim, -1)
    assert 20 < inside.sum() < len(x)  # both cases occur
    np.testing.assert_allclose(u_filt[inside], u_free[inside], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(u_proj[inside], u_free[inside], rtol=0, atol=0)
    # elsewhere the filter's input keeps the box and the CBF condition (certified)
    assert np.all(np.abs(u_filt) <= lim * (1 + 1e-12))
    assert np.all(np.asarray(out.safety_certified))
    # the CBF condition at the projected input, by hand: it fails at some of these states
    a, b, c, d = (np.asarray(t) for t in sc.hand_lie_terms(x, "true"))
    _, B = _hand_margins(sc, a, b, c, d)
    assert np.any(np.sum(d * u_proj, -1) < B - 1e-9)
    assert np.all(np.sum(d * u_filt, -1) >= B - 1e-9 * (np.abs(B) + 1))
    # 1 mm off the axis behind the obstacle the projection leaves the safe set, the filter not
    x0 = np.array([[-8.0, 1e-3]])
    h_proj = ss.simulate(proj, x0, t_final=sc.t_final, dt=sc.dt, plant=sc.system("true")).h
    h_filt = ss.simulate(filt, x0, t_final=sc.t_final, dt=sc.dt, plant=sc.system("true")).h
    assert np.min(h_proj) < 0 < np.min(h_filt)


def test_calibrate_beta_is_the_conformal_quantile_of_trajectory_scores(sc):
    from safestab.scenarios.obstacle_study import fit_obstacle_gp

    small = sc.replace(n_samples=60, hyper_subset=60, n_inducing=16, delta=0.05)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InducingPointsWarning)  # Q = 60, M = 16: wide, valid
        _, _, model, _ = fit_obstacle_gp(small)
    rep = calibrate_beta(small, model)
    assert rep["n_trajectories"] == 100 and rep["states_per_trajectory"] == 2
    assert rep["chosen_beta"] == sc.gp_beta and rep["probability"] == pytest.approx(0.95)
    # the same draw, scored by hand: the largest |omega - m| / sigma over a trajectory's
    # states and both components, then the ceil((N + 1)(1 - delta))-th smallest
    cal_seed = int(np.random.SeedSequence([small.seed, 1]).generate_state(1)[0])
    cal = small.trial_study().collect(100 * 20, cal_seed)
    cal = cal.take(np.arange(0, len(cal), 10))  # 20 rows per trajectory: rows 0 and 10 of each
    mean, std = model.predict(cal.x, return_std=True)
    score = np.abs(np.asarray(small.omega(cal.x)) - mean) / std
    per_traj = np.array([score[cal.trajectory == t].max() for t in np.unique(cal.trajectory)])
    k = int(np.ceil((len(per_traj) + 1) * (1 - small.delta)))
    assert rep["beta"] == pytest.approx(np.sort(per_traj)[k - 1], rel=1e-12)


def test_kind_dispatch_and_errors(tmp_path):
    assert scenario_kind("obstacle") == "obstacle"
    assert scenario_kind("paper") == "acc"
    assert isinstance(load(_edited(tmp_path, "x1 = -3.0", "x1 = -3.5")), ObstacleScenario)
    path = _edited(tmp_path, 'kind = "obstacle"', 'kind = "boat"')
    with pytest.raises(
        ScenarioError, match=r"kind must be one of 'acc', 'obstacle', 'swarm' .*got 'boat'"
    ):
        load(path)
    # without the kind key a file is an ACC file, and the ACC schema names the first problem
    path = _edited(tmp_path, 'kind = "obstacle"\n', "")
    with pytest.raises(ScenarioError, match=r"unknown key 'certificates\.P'|unknown key"):
        load(path)
    with pytest.raises(ScenarioError, match=r"missing key kind"):
        load_obstacle_scenario(path)


def test_overrides_are_checked_like_the_file(sc):
    from safestab.scenarios import parse_override

    assert parse_override("learning.kernel=se") == ("learning.kernel", "se")  # bare string
    assert parse_override(" starts.x1 = [-8.0, -7] ") == ("starts.x1", [-8.0, -7])
    assert parse_override("learning.seed=3") == ("learning.seed", 3)
    with pytest.raises(ScenarioError, match=r"--set must be KEY=VALUE .*got '=3'"):
        parse_override("=3")
    got = load_obstacle_scenario("obstacle", overrides={"starts.n_x1": 3, "learning.seed": 4})
    assert (got.starts_n_x1, got.seed) == (3, 4)
    with pytest.raises(ScenarioError, match=r"with overrides starts\.n_x1: starts\.n_x1 must be"):
        load_obstacle_scenario("obstacle", overrides={"starts.n_x1": 0})
    with pytest.raises(ScenarioError, match=r"unknown key 'starts\.nx1'"):
        load_obstacle_scenario("obstacle", overrides={"starts.nx1": 3})
    with pytest.raises(ScenarioError, match=r"cannot set 'name\.x': name is a value"):
        load_obstacle_scenario("obstacle", overrides={"name.x": 3})
    with pytest.raises(ScenarioError, match=r"simulation\.dt must be"):
        sc.replace(dt=-1.0)


def test_an_error_in_the_study_does_not_wait_for_its_model_based_thread(sc, monkeypatch):
    """The true and mismatched models' part runs in a thread beside the GP-robust part; an
    error in the latter is raised at once, not after that thread (which finishes on its own).
    Here the thread waits on an event the test sets only after the study has raised."""
    import threading

    from safestab.scenarios import obstacle_study

    release, finished = threading.Event(), threading.Event()

    def held_verdict(*args, **kwargs):  # the model-based thread's first call
        release.wait(60)
        finished.set()
        raise RuntimeError("released")

    def boom(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(obstacle_study, "fit_obstacle_gp", lambda sc, **kw: (None,) * 4)
    monkeypatch.setattr(obstacle_study, "verdict", held_verdict)
    monkeypatch.setattr(obstacle_study, "calibrate_beta", boom)
    monkeypatch.setattr(obstacle_study, "_coverage", boom)
    try:
        with pytest.raises(RuntimeError, match="boom"):
            run_obstacle_study(sc)
        assert not finished.is_set()  # raised while the model-based thread still waited
    finally:
        release.set()


# -- the whole study (slow) --------------------------------------------------------------


@pytest.fixture(scope="module")
def study(sc):
    """The preset study (a coarser map grid): about 1.5 to 5 minutes on 2 shared cores."""
    # the preset's cache (up to 256 inducing points; at seed 0 the pivot rules take 84 and
    # 254) is tight at the training inputs (docs/obstacle.md's obstacle-gp table): no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", InducingPointsWarning)
        return run_obstacle_study(sc.replace(map_n_x1=61, map_n_x2=41))


@pytest.mark.slow
def test_study_mismatched_leaves_the_safe_set_and_gp_robust_does_not(study):
    for limits in LIMIT_SETTINGS:
        mismatched = study.runs[("mismatched model", limits)]
        robust = study.runs[("GP-robust", limits)]
        true = study.runs[("true model", limits)]
        assert np.any(np.min(mismatched.h, axis=1) < 0), limits
        assert np.all(robust.h >= 0), limits
        assert np.all(true.h >= 0), limits
    assert study.coverage["joint"] >= 0.95  # the GP band covers the true current held out
    # the model at the goal, as recorded: the controller's own mean_std and the true current
    goal = study.coverage["at_goal"]
    mean, std = study.uncertainty.mean_std(jnp.zeros(2))
    np.testing.assert_array_equal(goal["mean_mps"], np.asarray(mean))
    np.testing.assert_array_equal(goal["std_mps"], np.asarray(std))
    np.testing.assert_allclose(goal["omega_mps"], [0.7 * np.exp(-(4.5**2) / (2 * 1.5**2)), 0])


@pytest.mark.slow
def test_study_stuck_runs_end_on_the_incompatible_set(study):
    n_stuck = 0
    for (name, limits), run in study.runs.items():
        stuck = run.outcome == "stuck"
        n_stuck += int(stuck.sum())
        assert not np.any(run.compatible[stuck, -1]), (name, limits)
        assert not np.any(run.end_verdict[stuck]), (name, limits)
    assert n_stuck > 0
    # with the true model, by Lemma 1 on the hand terms
    run = study.runs[("true model", "no limits")]
    end = run.x[run.outcome == "stuck", -1]
    a, b, c, d = (np.asarray(t) for t in study.scenario.hand_lie_terms(end, "true"))
    verdict = ss.compatibility(a, b, c, d, **_params(study.scenario)).compatible
    assert not np.any(np.asarray(verdict))


@pytest.mark.slow
def test_study_maps_agree_with_the_public_verdicts_for_the_fitted_gp(study):
    sc, maps = study.scenario, study.maps
    grid = np.stack(np.meshgrid(maps.x1, maps.x2, indexing="ij"), -1).reshape(-1, 2)
    a, b, c, d = (np.asarray(t) for t in sc.hand_lie_terms(grid, "nominal"))
    comp = ss.compatibility(a, b, c, d, **_params(sc))
    np.testing.assert_array_equal(maps.nominal_compatible.reshape(-1), np.asarray(comp.compatible))
    mean, std = jax.vmap(study.uncertainty.mean_std)(jnp.asarray(grid))
    gV = 2 * grid * np.asarray(sc.P)
    gh = 2 * (grid - sc.obstacle_center)
    beta = sc.gp_beta
    mean, std = np.asarray(mean), np.asarray(std)
    dV = np.sum(gV * mean, 1) + np.sum(np.abs(gV) * beta * std, 1)
    dh = np.sum(gh * mean, 1) - np.sum(np.abs(gh) * beta * std, 1)
    pc = ss.probabilistic_compatibility(
        ss.LieTerms(a, b, c, d), ss.RobustMargins(dV, dh), **_params(sc)
    )
    # the hand margins and autodiff ones agree to rounding; a grid point exactly on the
    # verdict's boundary could flip, so count disagreements instead of requiring none
    assert np.sum(maps.robust_updated.reshape(-1) != np.asarray(pc.updated)) == 0
    doc = json.loads(json.dumps(study.metrics_document(), allow_nan=False))
    assert doc["status"] == "ok"
    assert set(doc["runs"]) == {f"{c} / {lim}" for c in CONTROLLERS for lim in LIMIT_SETTINGS}


# -- the command line -------------------------------------------------------------------

# Reduced sizes; the starts lie outside every certified domain of attraction (V >= 49 m^2),
# so no compatible-formula runs are compiled: 6 closed loops instead of 9. The run's cost is
# almost all XLA compilation (about 4 to 12 s per closed loop on 2 shared cores), not sizes.
SMALL = [
    "--n-samples", "30", "--t-final", "2.0",
    "--set", "learning.hyper_subset=30", "--set", "learning.n_inducing=8",
    "--set", "starts.x1=[-8.0, -7.0]", "--set", "starts.n_x1=2", "--set", "starts.n_x2=3",
    "--set", "map.n_x1=11", "--set", "map.n_x2=5",
]  # fmt: skip


def _run(*args):
    from typer.testing import CliRunner

    from safestab.cli import app

    return CliRunner().invoke(app, ["run", *map(str, args)])


@pytest.mark.slow
# at Q = 30 with 8 inducing points the cache rightly warns that its band is needlessly wide
@pytest.mark.filterwarnings("default::safestab.errors.InducingPointsWarning")
def test_cli_run_obstacle_smoke(tmp_path):
    res = _run("--scenario", "obstacle", "--out", tmp_path, *SMALL)
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == [
        "obstacle_obstacle.pdf",
        "obstacle_obstacle.png",
        "obstacle_obstacle_maps.pdf",
        "obstacle_obstacle_maps.png",
        "obstacle_obstacle_metrics.json",
        "obstacle_obstacle_run.json",
    ]
    doc = json.loads((tmp_path / "obstacle_obstacle_metrics.json").read_text())
    assert doc["status"] == "ok"
    assert doc["settings"]["n_samples"] == 30 and doc["settings"]["t_final_s"] == 2.0
    assert doc["maps"]["grid"] == [11, 5]
    assert len(doc["runs"]) == 6
    assert all(r["n_starts"] == doc["settings"]["n_starts"] == 6 for r in doc["runs"].values())
    assert all(r["compatible_formula_starts"] == 0 for r in doc["runs"].values())
    assert "Obstacle study 'obstacle'" in res.output and "GP-robust" in res.output
    # the preset calibrates beta: the controller, the coverage and the maps all use it
    gp = doc["gp"]
    assert gp["beta_method"] == "conformal" and gp["calibration"]["chosen_beta"] == 2.0
    assert gp["beta"] == gp["calibration"]["beta"] != 2.0
    assert gp["stated_probability"] == doc["maps"]["stated_probability"] == pytest.approx(0.99)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--set", "starts.n_x1=0"], r"starts\.n_x1 must be an integer in \[1, 1000\], got 0"),
        (["--set", "starts.nx1=3"], r"unknown key 'starts\.nx1'"),
        (["--set", "seed"], r"--set must be KEY=VALUE"),
        (["--n-samples", "5"], r"learning\.n_samples must be an integer in \[10, "),
        (["--t-final", "-1"], r"simulation\.t_final must be"),
    ],
)
def test_cli_run_rejects_bad_input_before_work(tmp_path, args, message):
    import re

    out = tmp_path / "out"
    res = _run("--scenario", "obstacle", "--out", out, *args)
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ScenarioError: ")
    assert re.search(message, lines[0])
    assert not out.exists() or not any(out.iterdir())


def test_cli_run_dispatches_acc_presets(tmp_path, monkeypatch):
    from types import SimpleNamespace

    import matplotlib.pyplot as plt

    import safestab.plotting
    from safestab.scenarios import acc_study

    seen = []

    def fake_run_study(scenario, **kwargs):
        seen.append(scenario.name)
        return SimpleNamespace(
            scenario=scenario,
            dataset=[None] * scenario.n_samples,
            metrics={
                "true model": {
                    "min_h_m": 1.0,
                    "time_h_negative_s": 0.0,
                    "rms_speed_error_mps": 1.0,
                    "incompatible_steps": 0,
                }
            },
            calibration=SimpleNamespace(per_component=[1.0], joint=1.0, rmse=[0.0]),
            uncertainty=None,  # StudyResult's default: the summary prints no cache line
            metrics_document=lambda: {"status": "ok"},
        )

    def fake_plot(result):
        fig, ax = plt.subplots()
        ax.plot([0, 1], [0, 1])
        return fig

    monkeypatch.setattr(acc_study, "run_study", fake_run_study)
    monkeypatch.setattr(safestab.plotting, "plot_acc_study", fake_plot)
    res = _run("--scenario", "stress", "--out", tmp_path, "--set", "learning.seed=3")
    assert res.exit_code == 0, res.output
    assert seen == ["stress"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "acc_stress.pdf",
        "acc_stress.png",
        "acc_stress_metrics.json",
        "acc_stress_run.json",
    ]


def test_an_error_of_the_model_based_thread_is_named_on_the_studys_error(monkeypatch):
    """The model-based runs' thread failed first, then the GP-robust part: the error raised
    names both (the thread's error was dropped before)."""
    import types
    from concurrent.futures import Future

    from safestab.scenarios import obstacle_study as study_module

    class InThisThread:  # the "background" runs at submit: its error is set before the rest
        def __init__(self, max_workers):
            pass

        def submit(self, fn, *args):
            future: Future = Future()
            try:
                future.set_result(fn(*args))
            except Exception as exc:  # noqa: BLE001  (the future holds it)
                future.set_exception(exc)
            return future

        def shutdown(self, wait=True, cancel_futures=False):
            pass

    def fit(sc, timings, report):  # held-out data, GP, uncertainty model, input gain
        return types.SimpleNamespace(x=None), None, None, None

    def failing_verdict(*args, **kwargs):
        raise FloatingPointError("model-based verdicts failed")

    def progress(message, fraction):  # the GP-robust part fails at its first step
        if message.startswith("calibrating"):
            raise ValueError("calibration failed")

    monkeypatch.setattr(study_module, "ThreadPoolExecutor", InThisThread)
    monkeypatch.setattr(study_module, "fit_obstacle_gp", fit)
    monkeypatch.setattr(study_module, "verdict", failing_verdict)
    sc = load_obstacle_scenario("obstacle").replace(beta_method="conformal")
    with pytest.raises(ValueError, match="calibration failed") as info:
        study_module.run_obstacle_study(sc, progress=progress)
    assert any(
        "FloatingPointError: model-based verdicts failed" in note
        for note in getattr(info.value, "__notes__", [])
    )
