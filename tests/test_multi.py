"""Several CLFs/CBFs, limits inside the problem and weighted objectives (issue 10, point 1-2).

Oracles: the 80-digit active-set enumeration of tests/mpref.py, the KKT certificate computed
here from the returned multipliers, and Clarabel on well-conditioned problems.
"""

import warnings

import numpy as np
import pytest

import safestab as ss
from safestab import (
    DimensionError,
    MultiStatus,
    NonFiniteError,
    ParameterError,
    clf_cbf,
    clf_cbf_multi,
    clf_cbf_relaxed,
)

from . import mpref

P = {"kappa": 0.5, "rho": 0.2, "phi": 1.0, "varphi": 0.5}
# The enumerated solve is backward stable for the well-separated random rows drawn here
# (condition numbers below 1e4): 1e-9 relative leaves room above eps * cond.
RTOL = 1e-9


def _rows(a, b, c, d, sw, lim, u_nom=None):
    """The reference's rows G z <= r (z = (u - u_nom, sqrt(m) chi)) for one problem."""
    p, m = b.shape
    k = d.shape[0]
    A = [mpref.margins(a[j], b[j], 0.0, b[j], P["kappa"], 0.0, P["phi"], 0.0)[0] for j in range(p)]
    B = [mpref.margins(0.0, d[i], c[i], d[i], 0.0, P["rho"], 0.0, P["varphi"])[1] for i in range(k)]
    un = np.zeros(m) if u_nom is None else u_nom
    ns = p if sw is not None else 0
    G, r = [], []
    for j in range(p):
        slack = [(-1 / np.sqrt(sw) if t == j else 0.0) for t in range(ns)]
        G.append(list(b[j]) + slack)
        r.append(-A[j] - float(np.dot(b[j], un)))
    for i in range(k):
        G.append(list(-d[i]) + [0.0] * ns)
        r.append(-B[i] + float(np.dot(d[i], un)))
    if lim is not None:
        for sign, bound in ((1.0, lim[1]), (-1.0, lim[0])):
            for t in range(m):
                e = [0.0] * (m + ns)
                e[t] = sign
                G.append(e)
                r.append(sign * (bound[t] - un[t]))
    return G, r


def _problems(rng, n, p, k, m):
    a = rng.standard_normal((n, p)) * 3
    b = rng.standard_normal((n, p, m))
    c = rng.standard_normal((n, k)) * 3
    d = rng.standard_normal((n, k, m))
    return a, b, c, d


@pytest.mark.parametrize("slack_weight", [None, 10.0])
def test_one_clf_one_cbf_no_limits_is_the_universal_formula_bit_for_bit(slack_weight):
    rng = np.random.default_rng(1)
    a, b, c, d = _problems(rng, 300, 1, 1, 3)
    multi = clf_cbf_multi(a, b, c, d, slack_weight=slack_weight, **P)
    if slack_weight is None:
        ref = clf_cbf(a[:, 0], b[:, 0], c[:, 0], d[:, 0], **P)
    else:
        ref = clf_cbf_relaxed(a[:, 0], b[:, 0], c[:, 0], d[:, 0], slack_weight=slack_weight, **P)
    assert np.array_equal(np.asarray(multi.u), np.asarray(ref.u))
    assert np.array_equal(np.asarray(multi.slack[:, 0]), np.asarray(ref.slack))


CASES = [
    # (p CLFs, k CBFs, m inputs, limits, slack weight)
    (1, 2, 2, False, None),
    (1, 2, 2, True, 10.0),
    (0, 3, 2, True, None),
    (2, 2, 3, False, 5.0),
    (1, 4, 2, True, 100.0),
    (1, 1, 2, True, None),
]


@pytest.mark.parametrize("p, k, m, limits, sw", CASES)
def test_matches_the_high_precision_active_set_reference(p, k, m, limits, sw):
    rng = np.random.default_rng(10 * p + k + m)
    n = 40
    a, b, c, d = _problems(rng, n, p, k, m)
    lim = (-1.5 * np.ones(m), 1.5 * np.ones(m)) if limits else None
    kw = {"u_min": lim[0], "u_max": lim[1]} if limits else {}
    res = clf_cbf_multi(a, b, c, d, slack_weight=sw, **P, **kw)
    status = np.asarray(res.status)
    for i in range(n):
        G, r = _rows(a[i], b[i], c[i], d[i], sw, lim)
        z, found = mpref.solve_rows(G, r)
        assert found == (status[i] == MultiStatus.SOLVED), i
        if found:
            assert mpref.rel_error(np.asarray(res.u[i]), z[:m]) <= RTOL, i
            _assert_kkt(G, r, np.asarray(res.u[i]), np.asarray(res.slack[i]), sw, res, i)


def _assert_kkt(G, r, u, slack, sw, res, i):
    """Stationarity, dual feasibility, complementarity and primal feasibility in z-space."""
    G = np.asarray(G, float)
    r = np.asarray(r, float)
    z = np.concatenate([u, np.sqrt(sw) * slack]) if sw is not None else u
    lam = np.asarray(res.multipliers[i])
    # multipliers are those of the original rows, whose z-space versions are the rows of G
    # except for the slack columns, where the original variable is chi = z_s / sqrt(m)
    scale = np.abs(G) @ np.abs(z) + np.abs(r)
    assert np.all(G @ z - r <= 1e-9 * scale)
    assert np.all(lam >= 0)
    assert np.all(np.abs(lam * (G @ z - r)) <= 1e-9 * (lam * scale + 1e-300))
    stat = z + G.T @ lam
    assert np.linalg.norm(stat) <= 1e-9 * (np.linalg.norm(z) + np.abs(G.T) @ np.abs(lam)).max()


def test_safety_filter_passes_a_safe_nominal_input_through_and_weights_matter():
    rng = np.random.default_rng(3)
    m = 2
    a, b, c, d = _problems(rng, 30, 1, 2, m)
    c = np.abs(c) + 50.0  # every CBF holds with a wide margin near u = 0
    a = -np.abs(a) - 50.0  # and the CLF too
    u_nom = 0.1 * rng.standard_normal((30, m))
    res = clf_cbf_multi(a, b, c, d, u_nom=u_nom, **P)
    assert np.allclose(np.asarray(res.u), u_nom, rtol=0, atol=1e-14)
    # a weighted objective against the reference with the rows in whitened coordinates
    H = np.array([[4.0, 1.0], [1.0, 2.0]])
    a, b, c, d = _problems(rng, 20, 1, 2, m)
    u_nom = rng.standard_normal((20, m))
    res = clf_cbf_multi(a, b, c, d, u_nom=u_nom, H=H, **P)
    L = np.linalg.cholesky(H)
    for i in range(20):
        if int(res.status[i]) != MultiStatus.SOLVED:
            continue
        G, r = _rows(a[i], b[i], c[i], d[i], None, None, u_nom=u_nom[i])
        Gw = np.linalg.solve(L, np.asarray(G).T).T  # rows L^{-1} g
        z, found = mpref.solve_rows(Gw.tolist(), r)
        assert found
        u_ref = u_nom[i] + np.linalg.solve(L.T, np.array([float(x) for x in z]))
        assert np.linalg.norm(np.asarray(res.u[i]) - u_ref) <= 1e-8 * max(
            1.0, np.linalg.norm(u_ref)
        )


def test_limits_inside_the_problem_beat_projection():
    """With a limit active, projecting the unlimited optimum can break the CBF; the in-problem
    solution keeps it whenever some admissible input can."""
    b = np.array([[[1.0, 0.0]]])
    a = np.array([[5.0]])  # the CLF wants u0 <= -5
    d = np.array([[[1.0, 1.0]]])
    c = np.array([[0.0]])  # the CBF wants u0 + u1 >= rho Gamma
    res = clf_cbf_multi(a, b, c, d, slack_weight=1.0, u_min=-1.0, u_max=1.0, **P)
    u = np.asarray(res.u[0])
    assert int(res.status[0]) == MultiStatus.SOLVED
    assert np.all(u >= -1 - 1e-12) and np.all(u <= 1 + 1e-12)
    B = mpref.margins(0.0, d[0, 0], c[0, 0], d[0, 0], 0.0, P["rho"], 0.0, P["varphi"])[1]
    assert float(np.dot(d[0, 0], u)) >= float(B) - 1e-12


def test_fallbacks_are_named_and_keep_what_can_be_kept():
    # two CBFs that cannot both hold (u >= 1 and u <= -1) with limits: CBF_RELAXED
    d = np.array([[[1.0], [-1.0]]])
    c = np.array([[-1.0, -1.0]])  # with rho = 0: u >= 1 and -u >= 1
    params = {**P, "rho": 0.0}
    res = clf_cbf_multi(
        np.zeros((1, 0)), np.zeros((1, 0, 1)), c, d, u_min=-5.0, u_max=5.0, **params
    )
    assert int(res.status[0]) == MultiStatus.CBF_RELAXED
    assert np.all(np.isfinite(np.asarray(res.u))) and abs(float(res.u[0, 0])) <= 5.0
    # a hard CLF against a CBF (u <= -1 and u >= 1): CLF_DROPPED, the CBF holds
    res = clf_cbf_multi(
        np.array([[1.0]]),
        np.array([[[1.0]]]),
        np.array([[-1.0]]),
        np.array([[[1.0]]]),
        u_min=-5.0,
        u_max=5.0,
        **params,
    )
    assert int(res.status[0]) == MultiStatus.CLF_DROPPED
    assert float(res.u[0, 0]) >= 1.0 - 1e-12


def test_matches_clarabel_on_well_conditioned_problems():
    qpsolvers = pytest.importorskip("qpsolvers")
    sparse = pytest.importorskip("scipy.sparse")
    rng = np.random.default_rng(5)
    m, p, k = 2, 1, 3
    a, b, c, d = _problems(rng, 30, p, k, m)
    res = clf_cbf_multi(a, b, c, d, slack_weight=10.0, u_min=-2.0, u_max=2.0, **P)
    compared = 0
    for i in range(30):
        if int(res.status[i]) != MultiStatus.SOLVED:
            continue  # infeasible draws: the solver's verdict is not the oracle there
        G, r = _rows(a[i], b[i], c[i], d[i], 10.0, (-2 * np.ones(m), 2 * np.ones(m)))
        G = np.asarray(G, float)
        r = np.asarray([float(x) for x in r])
        n = G.shape[1]
        P_ = sparse.csc_matrix(np.eye(n))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # solver status chatter; the answer is checked
            z = qpsolvers.solve_qp(P_, np.zeros(n), sparse.csc_matrix(G), r, solver="clarabel")
        assert z is not None
        # Clarabel's default tolerances (1e-8) bound its error: 1e-6 relative is a second opinion
        assert np.linalg.norm(np.asarray(res.u[i]) - z[:m]) <= 1e-6 * max(1.0, np.linalg.norm(z))
        compared += 1
    assert compared >= 10


def test_argument_errors():
    one = (np.zeros(1), np.ones((1, 2)), np.zeros(1), np.ones((1, 2)))
    with pytest.raises(DimensionError, match=r"b must have shape \(\.\.\., rows, m\)"):
        clf_cbf_multi(np.zeros(()), np.ones(2), np.zeros(1), np.ones((1, 2)), **P)
    with pytest.raises(DimensionError, match=r"a must have shape \(1,\)"):
        clf_cbf_multi(np.zeros(2), np.ones((1, 2)), np.zeros(1), np.ones((1, 2)), **P)
    with pytest.raises(ParameterError, match=r"max_iter must be an integer >= 1, got 2.5"):
        clf_cbf_multi(*one, max_iter=2.5, **P)
    with pytest.raises(ParameterError, match=r"H must be positive definite"):
        clf_cbf_multi(*one, H=-np.eye(2), **P)
    with pytest.raises(NonFiniteError, match=r"u_min must be a number, or -inf where"):
        clf_cbf_multi(*one, u_min=[np.nan, 0.0], u_max=1.0, **P)
    with pytest.raises(DimensionError, match=r"u_nom must have shape \(2,\)"):
        clf_cbf_multi(*one, u_nom=np.zeros(3), **P)


def test_safety_filter_matches_the_formula_and_keeps_every_barrier():
    import jax.numpy as jnp

    from safestab import CBF, CLF, ControlAffineSystem, SafetyFilter, lie_terms

    # a planar single integrator with two disc obstacles and a nominal go-to-goal input
    system = ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2, name="si")
    cbfs = [
        CBF(lambda x: jnp.sum((x - jnp.array([1.0, 0.2])) ** 2) - 0.25, beta=1.0),
        CBF(lambda x: jnp.sum((x - jnp.array([1.0, -0.6])) ** 2) - 0.16, beta=1.0),
    ]
    goal = jnp.array([2.5, 0.0])
    filt = SafetyFilter(
        system, cbfs, u_nom=lambda x: goal - x, u_min=-1.0, u_max=1.0, rho=0.0, varphi=0.0
    )
    x = np.random.default_rng(4).uniform([-1.0, -1.5], [0.3, 1.5], (40, 2))
    out = filt.step(x)
    terms = [lie_terms(system, CLF(lambda x: x @ x, lam=0.0), cb, x) for cb in cbfs]
    c = np.stack([np.asarray(t.c) for t in terms], -1)
    d = np.stack([np.asarray(t.d) for t in terms], -2)
    ref = clf_cbf_multi(
        np.zeros((40, 0)), np.zeros((40, 0, 2)), c, d, u_min=-1.0, u_max=1.0,
        u_nom=np.asarray(goal) - x, kappa=0.0, rho=0.0, phi=0.0, varphi=0.0,
    )  # fmt: skip
    assert np.allclose(np.asarray(out.u), np.asarray(ref.u), rtol=1e-13, atol=1e-14)
    solved = np.asarray(out.formula_status) == MultiStatus.SOLVED
    assert solved.sum() >= 30 and np.all(np.asarray(out.cbf_satisfied)[solved])


def test_status_names_where_the_box_and_the_cbf_conflict():
    """Where the input box and the CBF conflict the status says so (it said OK). The
    filter's ``safety_certified`` must be False exactly where no input in the box meets the
    CBF condition, computed here by hand: c + d u >= rho Gamma, Gamma = sqrt(c^2 + varphi
    d^4), for the one-input ACC at the box's two ends."""
    from safestab.scenarios import load_scenario

    sc = load_scenario("paper")
    system = sc.system("true")
    clf, cbf = sc.certificates()
    mg = sc.mass * sc.gravity / sc.input_scale
    lo, hi = -0.3 * mg, 0.25 * mg
    filt = ss.SafetyFilter(
        system, cbf, clfs=clf, u_min=lo, u_max=hi, kappa=sc.kappa, rho=sc.rho, phi=sc.phi,
        varphi=sc.varphi,
    )  # fmt: skip
    x = np.random.default_rng(0).uniform([5, 5, 1], [35, 35, 150], size=(2000, 3))
    out = filt.step(x)
    terms = ss.lie_terms(system, clf, cbf, x)
    c, d = np.asarray(terms.c), np.asarray(terms.d)[:, 0]
    need = sc.rho * np.sqrt(c**2 + sc.varphi * d**4)
    best = np.maximum(c + d * lo, c + d * hi)  # the best CBF value the box allows
    scale = np.abs(c) + np.abs(d) * hi + need  # the condition's own magnitudes
    clear = np.abs(best - need) > 1e-9 * scale  # away from the feasibility boundary
    feasible = best >= need
    status = np.asarray(out.status)
    assert np.all(np.isfinite(np.asarray(out.u)))  # an input everywhere
    assert 100 < np.sum(~feasible) < 1900  # both kinds of state are drawn
    certified = np.asarray(out.safety_certified)
    np.testing.assert_array_equal(certified[clear], feasible[clear])
    # the status says it too: OK exactly where certified, CBF_INFEASIBLE where the box and
    # the barrier conflict
    np.testing.assert_array_equal(status == ss.StepStatus.OK, certified)
    assert np.all(status[clear & ~feasible] == ss.StepStatus.CBF_INFEASIBLE)
    fstat = np.asarray(out.formula_status)
    assert np.all(fstat[clear & ~feasible] == MultiStatus.CBF_RELAXED)
    # the single-pair controller with the same box says the same
    ctrl = ss.UniversalController(
        system, clf, cbf, kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi,
        slack_weight=10.0, u_min=lo, u_max=hi,
    )  # fmt: skip
    cout = ctrl.step(x)
    np.testing.assert_array_equal(np.asarray(cout.safety_certified)[clear], feasible[clear])
    cstatus = np.asarray(cout.status)
    np.testing.assert_array_equal(cstatus == ss.StepStatus.OK, np.asarray(cout.safety_certified))
    assert np.all(cstatus[clear & ~feasible] == ss.StepStatus.CBF_INFEASIBLE)
