"""Closed forms against a conic QP solver (Clarabel), their KKT certificates, hand values."""

import mpmath
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from safestab import (
    CompatibilityCase,
    Region,
    cbf_universal,
    clf_cbf,
    clf_cbf_relaxed,
    clf_sontag,
    compatibility,
    kkt_residuals,
    project_box,
    saturate_safety_first,
)
from safestab.reference import margins_numpy, solve_formula_qp

from .strategies import lie_cases

# Rounding in b.u, d.u and in the 2x2 solve is a few ulps of the magnitudes involved; 1e-9
# relative leaves six orders of magnitude of headroom above float64 epsilon (2.2e-16) while
# still catching any algebraic error (those are O(1) relative).
KKT_RTOL = 1e-9
# The agreement tolerance with the solver's optimum.
SOLVER_RTOL = 1e-6


def _assert_kkt(a, b, c, d, res, params, slack_weight=None):
    A, B = margins_numpy(a, b, c, d, **params)
    u = np.asarray(res.u)
    lam = np.asarray(res.multipliers)
    kkt = kkt_residuals(a, b, c, d, res, slack_weight=slack_weight, **params)
    # u = -lambda1 b + lambda2 d is rounded relative to its terms, which can be much larger
    # than |u| itself; that magnitude (times |b| or |d|) bounds the rounding of b.u and d.u.
    u_terms = np.linalg.norm(u) + lam[0] * np.linalg.norm(b) + lam[1] * np.linalg.norm(d)
    bu = float(np.linalg.norm(b) * u_terms)
    du = float(np.linalg.norm(d) * u_terms)
    chi = abs(float(res.slack))
    scale1 = abs(A) + bu + chi
    scale2 = abs(B) + du
    assert float(kkt.clf_violation) <= KKT_RTOL * scale1
    assert float(kkt.cbf_violation) <= KKT_RTOL * scale2
    assert float(kkt.dual_violation) == 0.0
    assert float(kkt.complementarity) <= KKT_RTOL * (lam[0] * scale1 + lam[1] * scale2)
    stat_scale = (
        np.linalg.norm(u)
        + lam[0] * np.linalg.norm(b)
        + lam[1] * np.linalg.norm(d)
        + (0.0 if slack_weight is None else slack_weight * chi + lam[0])
    )
    assert float(kkt.stationarity) <= KKT_RTOL * stat_scale


def _close(u, v):
    return np.linalg.norm(u - v) <= SOLVER_RTOL * max(1.0, np.linalg.norm(v))


@settings(max_examples=1000)
@given(lie_cases())
def test_clf_cbf_matches_solver_and_kkt(case):
    a, b, c, d, params = case
    res = clf_cbf(a, b, c, d, **params)
    comp = compatibility(a, b, c, d, **params)
    ref = solve_formula_qp(a, b, c, d, **params)
    region = int(res.region)
    assert np.all(np.isfinite(np.asarray(res.u)))
    assert bool(comp.compatible) == (region != Region.INCOMPATIBLE)
    if region != Region.INCOMPATIBLE:
        _assert_kkt(a, b, c, d, res, params)  # certifies optimality without the solver
        if ref.found:
            assert _close(np.asarray(res.u), ref.u), (res.u, ref.u, region)
        # A solver "infeasible" verdict on a certified point is the solver's error (NOTES.md 1).
    else:
        A, B = margins_numpy(a, b, c, d, **params)
        if ref.found:  # the solver's point may be feasible only within its own tolerance
            violation = max(float(np.dot(b, ref.u)) + A, B - float(np.dot(d, ref.u)))
            assert violation > 0, (res.u, ref.u, int(comp.case))
        dd = float(np.dot(d, d))
        if dd > 0:  # safety-first fallback: least-norm input meeting the CBF condition
            # B itself carries the reference's cancellation error (1e-19 |c| / |B|), so
            # compare at KKT_RTOL; a wrong fallback would differ at O(1).
            expected = max(B, 0.0) / dd * d
            assert np.linalg.norm(np.asarray(res.u) - expected) <= KKT_RTOL * np.linalg.norm(
                expected
            )


@settings(max_examples=750)
@given(lie_cases(), st.sampled_from([1e-3, 0.1, 10.0, 100.0, 1e4]))
def test_relaxed_matches_solver_and_kkt(case, slack_weight):
    a, b, c, d, params = case
    res = clf_cbf_relaxed(a, b, c, d, slack_weight=slack_weight, **params)
    ref = solve_formula_qp(a, b, c, d, slack_weight=slack_weight, **params)
    A, B = margins_numpy(a, b, c, d, **params)
    region = int(res.region)
    assert np.all(np.isfinite(np.asarray(res.u)))
    infeasible = float(np.dot(d, d)) == 0.0 and B > 0
    assert (region == Region.INCOMPATIBLE) == infeasible
    if not infeasible:
        _assert_kkt(a, b, c, d, res, params, slack_weight=slack_weight)
        if ref.found:
            # The QP's variable is (u, chi); its objective is |z|^2/2 in z = (u, sqrt(m) chi), so
            # a solver's duality gap bounds its error in z, not in u alone: compare in z.
            sq = np.sqrt(slack_weight)
            z_cf = np.append(np.asarray(res.u), sq * float(res.slack))
            z_ref = np.append(ref.u, sq * ref.slack)
            assert _close(z_cf, z_ref), (z_cf, z_ref)

            # The objective is flat in chi when slack_weight is small, so the solver's chi is
            # only as good as its duality gap: compare objective values, not chi itself.
            def objective(u, chi):
                return 0.5 * float(np.dot(u, u)) + 0.5 * slack_weight * chi * chi

            f_cf = objective(np.asarray(res.u), float(res.slack))
            f_ref = objective(ref.u, ref.slack)
            assert abs(f_cf - f_ref) <= SOLVER_RTOL * max(1.0, f_ref)
    else:
        assert not ref.found or B - float(np.dot(d, ref.u)) > 0


def test_batched_equals_pointwise():
    rng = np.random.default_rng(0)
    n, m = 200, 3
    a, c = rng.normal(size=n), rng.normal(size=n)
    b, d = rng.normal(size=(n, m)), rng.normal(size=(n, m))
    d[:20] = 2.0 * b[:20]  # parallel rows
    p = {"kappa": 0.5, "rho": 0.3, "phi": 1.0, "varphi": 0.5}
    batch = clf_cbf(a, b, c, d, **p)
    for i in range(0, n, 17):
        one = clf_cbf(a[i], b[i], c[i], d[i], **p)
        np.testing.assert_allclose(batch.u[i], one.u, rtol=1e-14, atol=0)
        assert int(batch.region[i]) == int(one.region)


def test_clf_cbf_unpacks_as_pair():
    u, region = clf_cbf(-1.0, [1.0], 1.0, [1.0], kappa=0.0, rho=0.0, phi=0.0, varphi=0.0)
    assert u.shape == (1,) and int(region) == Region.P4


# ---- hand-derived values ------------------------------------------------------------------


def test_sontag_scalar_integrator():
    # xdot = u, V = x^2/2, lambda = 0: a = 0 and b = x. Sontag with kappa = 1, phi = 1:
    # zeta = sqrt(0 + x^4) = x^2, u = -(0 + x^2)/x^2 * x = -x.
    for x in [-3.0, -0.5, 0.25, 2.0]:
        u = clf_sontag(0.0, [x], kappa=1.0, phi=1.0).u
        np.testing.assert_allclose(u, [-x], rtol=1e-15)
    # xdot = x + u, V = x^2/2: a = x^2, b = x, zeta = sqrt(x^4 + x^4) = sqrt(2) x^2,
    # u = -(1 + sqrt(2)) x: the classic Sontag feedback of the unstable scalar system.
    x = 1.7
    u = clf_sontag(x * x, [x], kappa=1.0, phi=1.0).u
    np.testing.assert_allclose(u, [-(1 + np.sqrt(2)) * x], rtol=1e-14)
    res = clf_sontag(1.0, [0.0], kappa=1.0, phi=1.0)
    assert float(res.u[0]) == 0.0  # b = 0 gives u = 0, in the formula's region P4
    assert int(res.region) == Region.P4


def test_cbf_universal_hand_value():
    # c = -1, d = (2, 0), rho = 0: u = (0 - (-1))/4 * d = (0.5, 0), so c + d.u = 0 = rho Gamma.
    res = cbf_universal(-1.0, [2.0, 0.0], rho=0.0, varphi=1.0)
    np.testing.assert_allclose(res.u, [0.5, 0.0], rtol=1e-15)
    # the same result kind as clf_cbf: u = lambda_2 d with lambda_2 = 1/4, region P2
    assert int(res.region) == Region.P2
    np.testing.assert_allclose(res.multipliers, [0.0, 0.25], rtol=1e-15)
    # rho = 1, varphi = 0: Gamma = |c|; with c = -1, B = 1 + 1 = 2 and u = 2/4 d = (1, 0).
    u = cbf_universal(-1.0, [2.0, 0.0], rho=1.0, varphi=0.0).u
    np.testing.assert_allclose(u, [1.0, 0.0], rtol=1e-15)


def test_single_active_constraint_by_hand():
    p = {"kappa": 0.0, "rho": 0.0, "phi": 0.0, "varphi": 0.0}
    # CLF active only: b = (1, 0), a = 2 -> u = (-2, 0); CBF c = 5, d = (0, 1) inactive.
    u, region = clf_cbf(2.0, [1.0, 0.0], 5.0, [0.0, 1.0], **p)
    np.testing.assert_allclose(u, [-2.0, 0.0], rtol=1e-15)
    assert int(region) == Region.P1
    # CBF active only: c = -3, d = (0, 2) -> u = (0, 1.5); CLF a = -1 inactive.
    u, region = clf_cbf(-1.0, [1.0, 0.0], -3.0, [0.0, 2.0], **p)
    np.testing.assert_allclose(u, [0.0, 1.5], rtol=1e-15)
    assert int(region) == Region.P2
    # Both active, orthogonal: u = (-2, 1.5).
    u, region = clf_cbf(2.0, [1.0, 0.0], -3.0, [0.0, 2.0], **p)
    np.testing.assert_allclose(u, [-2.0, 1.5], rtol=1e-15)
    assert int(region) == Region.P3


def test_relaxed_scalar_by_hand():
    # m = 1, b = 1, d = 1, A = 1 (a = 1, kappa = 0), B = 1 (c = -1, rho = 0): infeasible hard.
    # Relaxed with weight s: min u^2/2 + s chi^2/2, u - chi <= -1, u >= 1. CBF active: u = 1,
    # then chi >= 2; optimum chi = 2 (lambda1 = 2 s, lambda2 = 1 + 2 s).
    s = 10.0
    res = clf_cbf_relaxed(
        1.0, [1.0], -1.0, [1.0], kappa=0.0, rho=0.0, phi=0.0, varphi=0.0, slack_weight=s
    )
    np.testing.assert_allclose(res.u, [1.0], rtol=1e-14)
    np.testing.assert_allclose(res.slack, 2.0, rtol=1e-14)
    np.testing.assert_allclose(res.multipliers, [2 * s, 1 + 2 * s], rtol=1e-14)
    assert int(res.region) == Region.P3


def test_compatibility_cases_by_hand():
    p = {"kappa": 0.0, "rho": 0.0, "phi": 0.0, "varphi": 0.0}
    C = CompatibilityCase
    cases = [
        ((1.0, [1.0, 0.0], -1.0, [0.0, 1.0]), C.NOT_PARALLEL),
        ((1.0, [1.0], -1.0, [1.0]), C.INCOMPATIBLE_PARALLEL),  # u <= -1 and u >= 1
        ((-1.0, [1.0], 1.0, [1.0]), C.PARALLEL_ORDERED),  # u <= 1 and u >= -1
        ((1.0, [1.0], -1.0, [-1.0]), C.ANTIPARALLEL),  # u <= -1 and u <= -1
        ((1.0, [0.0], -1.0, [1.0]), C.INCOMPATIBLE_B_ZERO),
        ((-1.0, [0.0], -1.0, [1.0]), C.B_ZERO),
        ((-1.0, [1.0], -1.0, [0.0]), C.INCOMPATIBLE_D_ZERO),
        ((-1.0, [1.0], 1.0, [0.0]), C.D_ZERO),
    ]
    for (a, b, c, d), expected in cases:
        comp = compatibility(a, b, c, d, **p)
        assert int(comp.case) == expected, (a, b, c, d)
        assert bool(comp.compatible) == (expected > 0)


def test_parallel_tolerance_is_relative():
    # b and d parallel up to rounding at scales 1e-6 and 1e6: still detected as parallel.
    p = {"kappa": 0.0, "rho": 0.0, "phi": 0.0, "varphi": 0.0}
    b = np.array([0.3, -0.7, 0.1]) * 1e-6
    for scale in [1e-6, 1.0, 1e6]:
        d = b * 0.1 * scale * 3.0
        comp = compatibility(1.0, b, -1.0, d, **p)
        assert int(comp.case) == CompatibilityCase.INCOMPATIBLE_PARALLEL


def test_no_nan_for_extreme_finite_input():
    rng = np.random.default_rng(1)
    b = rng.normal(size=(50, 2)) * 10.0 ** rng.uniform(-6, 6, size=(50, 1))
    d = rng.normal(size=(50, 2)) * 10.0 ** rng.uniform(-6, 6, size=(50, 1))
    a = rng.normal(size=50) * 1e8
    c = rng.normal(size=50) * 1e8
    p = {"kappa": 1.0, "rho": 1.0, "phi": 1.0, "varphi": 1.0}
    for res in (clf_cbf(a, b, c, d, **p), clf_cbf_relaxed(a, b, c, d, slack_weight=10.0, **p)):
        assert np.all(np.isfinite(res.u))
        assert np.all(np.isfinite(res.multipliers))


# ---- input limits -----------------------------------------------------------------------


def test_project_box_is_clip():
    u = np.array([[-3.0, 0.5], [2.0, -0.1]])
    np.testing.assert_array_equal(
        project_box(u, [-1.0, -1.0], [1.0, 0.0]), [[-1.0, 0.0], [1.0, -0.1]]
    )


@settings(max_examples=300)
@given(
    st.floats(-10, 10),
    st.floats(-10, 10),
    st.floats(-5, 5),
    st.floats(0.05, 5),
    st.floats(-5, 5),
)
def test_saturate_safety_first_against_grid(u, c, d, width, center):
    """The safety-first input is the closest box point meeting the CBF, checked on a dense grid."""
    lo, hi = center - width, center + width
    rho, varphi = 0.5, 1.0
    u_sat, feasible = saturate_safety_first(
        [u], c, [d], rho=rho, varphi=varphi, u_min=[lo], u_max=[hi]
    )
    # XLA on CPU flushes subnormal inputs to zero (docs/theory.md): the reference does too
    c, d = (0.0 if abs(v) < np.finfo(float).tiny else v for v in (c, d))
    # in 50 digits: c**2 and d**4 underflow in float64 for |c|, |d| ~ 1e-245 (the library
    # scales them; a float64 reference would be the wrong one)
    with mpmath.workdps(50):
        mc, md = mpmath.mpf(c), mpmath.mpf(d)
        B = float(rho * mpmath.sqrt(mc**2 + varphi * md**4) - mc)
    grid = np.linspace(lo, hi, 20001)
    ok = d * grid >= B
    assert bool(feasible) == bool(ok.any()) or abs(d * (hi if d > 0 else lo) - B) < 1e-9
    us = float(u_sat[0])
    assert lo - 1e-12 <= us <= hi + 1e-12
    if ok.any():
        assert d * us >= B - 1e-9 * (1 + abs(B))
        best = grid[ok][np.argmin(np.abs(grid[ok] - u))]
        assert abs(us - best) <= (grid[1] - grid[0]) + 1e-12  # grid spacing bounds the error
    else:
        assert d * us >= max(d * lo, d * hi) - 1e-12
