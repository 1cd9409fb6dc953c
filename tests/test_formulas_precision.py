"""The formulas against an 80-digit active-set reference, at the widest scales (issue 8).

The oracle is tests/mpref.py (mpmath), not a QP solver: Clarabel, OSQP and qpax are wrong on
exactly these badly scaled and nearly parallel problems.
"""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from safestab import (
    SATISFIED_RTOL,
    Region,
    clf_cbf,
    clf_cbf_relaxed,
    compatibility,
    conditions_satisfied,
)

from . import mpref

EPS = np.finfo(float).eps
# The accuracy target: relative error <= 1e-9, or <= 1e3 cond eps where the problem
# itself is ill-conditioned (cond estimated in 80 digits by tests/mpref.py).
ACC_FLOOR = 1e-9
COND_FACTOR = 1e3
# Evaluating c + d.u - rho Gamma in float64 rounds by at most about (m + 10) eps of its scale
# (m products and sums, and B from a hypot); 32 eps covers m <= 6 with room.
EVAL_EPS = 32 * EPS


def _unit(rng_vals, m):
    v = np.asarray(rng_vals[:m], float)
    n = np.linalg.norm(v)
    if n < 1e-3:
        v = np.zeros(m)
        v[0] = 1.0
        n = 1.0
    return v / n


def _orth(v, w):
    """A unit vector orthogonal to unit v, from w (m >= 2)."""
    w = w - np.dot(w, v) * v
    n = np.linalg.norm(w)
    if n < 1e-3:
        w = np.zeros_like(v)
        w[np.argmin(np.abs(v))] = 1.0
        w = w - np.dot(w, v) * v
        n = np.linalg.norm(w)
    return w / n


KINDS = [
    "general",
    "parallel",
    "antiparallel",
    "near_parallel",
    "near_antiparallel",
    "b_zero",
    "d_zero",
    "both_zero",
]


@st.composite
def wide_cases(draw):
    """The ranges of issue 8, point 1: m 1..6, |b|, |d| 1e-6..1e6, |a|, |c| 1e-4..1e4, angles."""
    m = draw(st.integers(1, 6))
    kind = draw(st.sampled_from(KINDS))
    floats = st.floats(-1, 1, allow_subnormal=False)
    bu = _unit(draw(st.lists(floats, min_size=m, max_size=m)), m)
    du = _unit(draw(st.lists(floats, min_size=m, max_size=m)), m)
    nb = 10.0 ** draw(st.floats(-6, 6))
    nd = 10.0 ** draw(st.floats(-6, 6))
    if kind in ("parallel", "antiparallel"):
        du = bu if kind == "parallel" else -bu
    elif kind in ("near_parallel", "near_antiparallel") and m >= 2:
        theta = 10.0 ** draw(st.floats(-12, -2))
        e = _orth(bu, du)
        sign = 1.0 if kind == "near_parallel" else -1.0
        du = sign * np.cos(theta) * bu + np.sin(theta) * e
    b, d = nb * bu, nd * du
    if kind in ("b_zero", "both_zero"):
        b = np.zeros(m)
    if kind in ("d_zero", "both_zero"):
        d = np.zeros(m)

    def signed():
        if draw(st.integers(0, 9)) == 0:
            return 0.0
        return draw(st.sampled_from([-1.0, 1.0])) * 10.0 ** draw(st.floats(-4, 4))

    a, c = signed(), signed()
    params = {
        "kappa": draw(st.sampled_from([0.0, 0.2, 1.0, 2.0, 5.0])),
        "rho": draw(st.sampled_from([0.0, 0.1, 1.0, 3.0])),
        "phi": draw(st.sampled_from([0.0, 1e-3, 1.0, 10.0])),
        "varphi": draw(st.sampled_from([0.0, 1e-3, 1.0, 10.0])),
    }
    return a, b, c, d, params


def _on_tolerance_edge(ratio, rtol=1e-12):
    # the parallel decision flips where det/(|b|^2|d|^2) crosses rtol; the float det has a
    # relative error of about eps/angle = 2e-10 there, so cases within 1e-6 of it are skipped
    return abs(float(ratio) / rtol - 1.0) < 1e-6


def _check_accuracy(a, b, c, d, params, res, slack_weight=None):
    u_ref, chi_ref, region_ref, ratio = mpref.solve(a, b, c, d, slack_weight=slack_weight, **params)
    if slack_weight is None and _on_tolerance_edge(ratio):
        return
    u = np.asarray(res.u)
    assert np.all(np.isfinite(u))
    err = mpref.rel_error(u, u_ref)
    if err > ACC_FLOOR:
        cond = mpref.condition_estimate(a, b, c, d, params, slack_weight=slack_weight)
        assert err <= COND_FACTOR * cond * EPS, (err, cond, int(res.region), region_ref)
    if slack_weight is not None:
        chi = float(res.slack)
        scale = max(abs(float(chi_ref)), 1e-300)
        if abs(chi - float(chi_ref)) > ACC_FLOOR * scale:
            cond = mpref.condition_estimate(a, b, c, d, params, slack_weight=slack_weight)
            # chi = lambda1 / m inherits the conditioning of the multipliers, which is that of
            # u divided by the angle-free part; bound it like u, with the same factor
            assert abs(chi - float(chi_ref)) <= COND_FACTOR * cond * EPS * max(
                scale, float(np.linalg.norm(u)) * float(np.linalg.norm(b) + 1.0)
            ), (chi, float(chi_ref))


def _check_cbf_honest(a, b, c, d, params, u, must_hold):
    flags = conditions_satisfied(a, b, c, d, u, **params)
    res, scale = mpref.cbf_residual(c, d, u, params["rho"], params["varphi"])
    if must_hold:
        assert bool(flags.cbf_satisfied), (res, scale)
    if bool(flags.cbf_satisfied):  # a True flag never hides a violation
        assert res >= -(SATISFIED_RTOL + EVAL_EPS) * scale, (res, scale)
    else:  # and a False flag is not raised by rounding alone
        assert res < 0


@settings(max_examples=800, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(wide_cases())
def test_clf_cbf_matches_high_precision_reference(case):
    a, b, c, d, params = case
    res = clf_cbf(a, b, c, d, **params)
    _check_accuracy(a, b, c, d, params, res)
    comp = compatibility(a, b, c, d, **params)
    assert bool(comp.compatible) == (int(res.region) != Region.INCOMPATIBLE)
    _check_cbf_honest(a, b, c, d, params, np.asarray(res.u), int(res.region) != Region.INCOMPATIBLE)


@settings(max_examples=800, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(wide_cases(), st.floats(-2, 6))
def test_relaxed_matches_high_precision_reference(case, log_weight):
    a, b, c, d, params = case
    slack_weight = 10.0**log_weight
    res = clf_cbf_relaxed(a, b, c, d, slack_weight=slack_weight, **params)
    _check_accuracy(a, b, c, d, params, res, slack_weight)
    d_zero_infeasible = not np.any(d) and float(mpref.margins(a, b, c, d, **params)[1]) > 0
    assert (int(res.region) == Region.INCOMPATIBLE) == d_zero_infeasible
    _check_cbf_honest(a, b, c, d, params, np.asarray(res.u), not d_zero_infeasible)


@settings(max_examples=500, deadline=None)
@given(wide_cases(), st.floats(-14, -6), st.integers(0, 2**31 - 1))
def test_flags_never_lie_for_perturbed_inputs(case, log_step, seed):
    """For inputs near the boundary of each condition, a True flag means the condition holds."""
    a, b, c, d, params = case
    u0 = np.asarray(clf_cbf(a, b, c, d, **params).u)
    rng = np.random.default_rng(seed)
    u = u0 * (1.0 + 10.0**log_step * rng.standard_normal(u0.shape))
    flags = conditions_satisfied(a, b, c, d, u, **params)
    res, scale = mpref.cbf_residual(c, d, u, params["rho"], params["varphi"])
    if bool(flags.cbf_satisfied):
        assert res >= -(SATISFIED_RTOL + EVAL_EPS) * scale
    res, scale = mpref.clf_residual(a, b, u, params["kappa"], params["phi"])
    if bool(flags.clf_satisfied):
        assert res <= (SATISFIED_RTOL + EVAL_EPS) * scale


@settings(max_examples=800, deadline=None)
@given(wide_cases())
def test_compatibility_agrees_with_clf_cbf_everywhere(case):
    a, b, c, d, params = case
    res = clf_cbf(a, b, c, d, **params)
    comp = compatibility(a, b, c, d, **params)
    assert bool(comp.compatible) == (int(res.region) != Region.INCOMPATIBLE)
    assert (int(comp.case) > 0) == bool(comp.compatible)


# -- the reproducers ------------------------------------------------------------------


@pytest.mark.parametrize("slack_weight", [1e2, 1e6, 1e8])
def test_relaxed_one_input_p3_is_exact(slack_weight):
    """b, d parallel (one input): P3 gives u = B/d = 1e-3 exactly (was 0.0 at sw = 1e8)."""
    res = clf_cbf_relaxed(
        1e3, [1e3], -1e-3, [1.0], kappa=0, rho=0, phi=0, varphi=0, slack_weight=slack_weight
    )
    assert int(res.region) == Region.P3
    # u = B / d with B = -c = 1e-3 and d = 1: the same float, to the last bit
    assert float(res.u[0]) == 1e-3
    # chi = A + b u (the CLF row is active) = 1e3 + 1e3 * 1e-3 = 1001, to rounding of 1001
    assert abs(float(res.slack) - 1001.0) <= 4 * EPS * 1001.0


def test_nearly_parallel_hard_case_keeps_the_cbf_condition():
    """theta = 2e-6 above the parallel tolerance: was 3e-5 relative error, CBF violated."""
    theta = 2e-6
    b = np.array([0.28, 0.96])
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    d = rot @ b
    params = {"kappa": 0.0, "rho": 0.0, "phi": 0.0, "varphi": 0.0}
    res = clf_cbf(1.0, b, 1.0 - 1e-6, d, **params)
    assert int(res.region) == Region.P3
    u_ref, _, region_ref, _ = mpref.solve(1.0, b, 1.0 - 1e-6, d, **params)
    assert region_ref == Region.P3
    cond = mpref.condition_estimate(1.0, b, 1.0 - 1e-6, d, params)
    err = mpref.rel_error(np.asarray(res.u), u_ref)
    assert err <= max(ACC_FLOOR, COND_FACTOR * cond * EPS), (err, cond)
    _check_cbf_honest(1.0, b, 1.0 - 1e-6, d, params, np.asarray(res.u), True)


def test_badly_scaled_relaxed_cases_are_accurate():
    """|b| = 1e5, |d| = 1e-5 with slack weights 10 to 1e4: was 1e-3 to 1e-1 relative error."""
    rng = np.random.default_rng(8)
    params = {"kappa": 0.5, "rho": 0.2, "phi": 1.0, "varphi": 0.5}
    worst = 0.0
    for _ in range(200):
        m = int(rng.integers(2, 5))
        b = rng.standard_normal(m)
        d = rng.standard_normal(m)
        b *= 1e5 / np.linalg.norm(b)
        d *= 1e-5 / np.linalg.norm(d)
        a, c = rng.standard_normal(2) * 10.0 ** rng.uniform(-2, 2, 2)
        sw = 10.0 ** rng.uniform(1, 4)
        res = clf_cbf_relaxed(a, b, c, d, slack_weight=sw, **params)
        u_ref, _, _, _ = mpref.solve(a, b, c, d, slack_weight=sw, **params)
        worst = max(worst, mpref.rel_error(np.asarray(res.u), u_ref))
    assert worst <= ACC_FLOOR, worst


def test_near_antiparallel_inside_tolerance_is_compatible_and_consistent():
    """Anti-parallel within the parallel tolerance: always compatible, and clf_cbf agrees."""
    theta = 1e-8
    b = np.array([1.0, 0.0])
    d = -np.array([np.cos(theta), np.sin(theta)])
    params = {"kappa": 0.0, "rho": 0.0, "phi": 0.0, "varphi": 0.0}
    # A = 1 and B = 1: both conditions bound b.u from above (b.u <= -1, -d.u <= -1)
    for c in (-1.0, -1.0 + 1e-15, -1.0 - 1e-15):
        res = clf_cbf(1.0, b, c, d, **params)
        comp = compatibility(1.0, b, c, d, **params)
        assert bool(comp.compatible) and int(res.region) != Region.INCOMPATIBLE
        _check_cbf_honest(1.0, b, c, d, params, np.asarray(res.u), True)
