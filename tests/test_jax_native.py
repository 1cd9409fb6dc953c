"""The public formulas, controllers, filters and simulate under jit, vmap, grad and jacfwd.

Values under a transformation are compared with the eager call; derivatives with central
finite differences of the high-precision (mpmath) references in ``tests/mpref.py``, computed
in 80 digits with a step of 1e-25 (so the differences are exact to far beyond float64), in
the interior of each region P1 to P4 and of the filter's active sets; at a region boundary
with the documented one-sided choice.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest

import safestab as ss
from safestab.errors import ParameterError

from . import mpref
from .jax_events import traces_while

K = dict(kappa=0.5, rho=0.2, phi=1.0, varphi=0.5)
B_ = jnp.array([1.0, 0.5])
D_ = jnp.array([0.2, 1.0])


def _u(out):
    return out.u if hasattr(out, "u") else (out[0] if isinstance(out, tuple) else out)


# every public function, as a function of one scalar that enters its arguments
PUBLIC = {
    "zeta": lambda s: ss.zeta(s, B_, 1.0 + s),
    "clf_sontag": lambda s: ss.clf_sontag(s, B_ * s, kappa=0.5 * s, phi=1.0).u,
    "cbf_universal": lambda s: ss.cbf_universal(s, D_, rho=0.2 * s, varphi=0.5).u,
    "clf_cbf": lambda s: ss.clf_cbf(s, B_, 0.3 * s, D_, **K).u,
    "clf_cbf_relaxed": lambda s: ss.clf_cbf_relaxed(s, B_, 0.3, D_, slack_weight=2 * s, **K).u,
    "compatibility": lambda s: jnp.where(
        ss.compatibility(s, B_, 0.3, D_, **K).compatible, s * s, -s
    ),
    "project_box": lambda s: ss.project_box(s * B_, -0.7, 0.7 * s),
    "saturate_safety_first": lambda s: ss.saturate_safety_first(
        s * jnp.ones(1), 0.3, jnp.ones(1), rho=0.2, varphi=0.5, u_min=-1.0, u_max=s
    )[0],
    "clf_cbf_multi": lambda s: (
        ss.clf_cbf_multi(
            s[None],
            B_[None],
            jnp.array([0.3, 0.1]) * s,
            jnp.stack([D_, -B_]),
            **K,
            u_min=-3.0,
            u_max=3.0,
            u_nom=s * D_,
            H=jnp.eye(2) * (1 + s),
            slack_weight=s,
        ).u
    ),  # fmt: skip
    "kkt_residuals": lambda s: (
        ss.kkt_residuals(s, B_ * s, 0.3, D_, ss.clf_cbf(1.0, B_, 0.3, D_, **K), **K).stationarity
    ),
    "conditions_satisfied": lambda s: jnp.where(
        ss.conditions_satisfied(s, B_, 0.3, D_, s * B_, **K).cbf_satisfied, s, 2 * s
    ),
    "robust_lie_terms": lambda s: jnp.stack(
        ss.robust_lie_terms(ss.LieTerms(s, B_, 0.3, D_), B_ * s, D_, 0.1 * B_, s * D_, 2.0)[::2]
    ),
    "robust_margins": lambda s: jnp.stack(ss.robust_margins(B_, D_ * s, 0.1 * B_, D_, s)),
    "probabilistic_compatibility": lambda s: jnp.where(
        ss.probabilistic_compatibility(
            ss.LieTerms(s, B_, 0.3, D_), ss.RobustMargins(0.1 * s, -0.2), **K
        ).lemma4,
        s * s,
        -s,
    ),
}


@pytest.mark.parametrize("name", sorted(PUBLIC))
def test_every_public_function_composes(name):
    fn = PUBLIC[name]
    s0 = jnp.asarray(0.8)
    eager = np.asarray(fn(s0))
    np.testing.assert_allclose(np.asarray(jax.jit(fn)(s0)), eager, rtol=1e-14, atol=1e-300)
    ss_ = jnp.array([0.8, 1.3, 2.0])
    batched = np.asarray(jax.vmap(fn)(ss_))
    each = np.stack([np.asarray(fn(v)) for v in ss_])
    np.testing.assert_allclose(batched, each, rtol=1e-14, atol=1e-300)
    rev = np.asarray(jax.grad(lambda s: jnp.sum(fn(s)))(s0))
    fwd = np.asarray(jax.jacfwd(fn)(s0))
    assert np.all(np.isfinite(fwd)) and np.isfinite(rev)
    np.testing.assert_allclose(rev, np.sum(fwd), rtol=1e-12, atol=1e-14)
    h = 1e-6  # smooth at s0 (away from every boundary): a float64 difference is enough
    fd = (np.asarray(fn(s0 + h), float) - np.asarray(fn(s0 - h), float)) / (2 * h)
    np.testing.assert_allclose(fwd, fd, rtol=1e-6, atol=1e-7)


def test_concrete_calls_keep_their_checks_and_traced_ones_check_shapes():
    with pytest.raises(ss.ParameterError):
        ss.clf_cbf(1.0, B_, 0.3, D_, kappa=-1.0, rho=0.2, phi=1.0, varphi=0.5)
    with pytest.raises(ss.NonFiniteError):
        ss.clf_sontag(jnp.nan, B_, kappa=0.5, phi=1.0)
    with pytest.raises(ss.DimensionError):
        jax.jit(lambda a: ss.clf_cbf(a, B_, 0.3, jnp.ones(3), **K).u)(1.0)
    with pytest.raises(ss.InputTypeError):
        jax.jit(lambda a: ss.clf_sontag(a, B_ > 0, kappa=0.5, phi=1.0))(1.0)
    # traced values are not inspected: a NaN passes through as NaN (the docs say so)
    out = jax.jit(lambda a: ss.clf_sontag(a, B_, kappa=0.5, phi=1.0).u)(jnp.nan)
    assert np.all(np.isnan(np.asarray(out)))
    with pytest.raises(ss.ParameterError):  # a non-PD H is still refused when concrete
        ss.clf_cbf_multi(
            jnp.ones(1), B_[None], jnp.ones(1), D_[None], **K, H=-jnp.eye(2), u_min=-1, u_max=1
        )


# -- derivatives against high-precision finite differences ---------------------------------

_NAMES = ("kappa", "rho", "phi", "varphi")


def _flat(a, b, c, d, params):
    return np.concatenate([[a], b, [c], d, params])


def _unflat(theta, m):
    a, b, c, d = theta[0], theta[1 : 1 + m], theta[1 + m], theta[2 + m : 2 + 2 * m]
    return a, b, c, d, theta[2 + 2 * m :]


def _mp_jacobian(theta, m, relaxed):
    """d u / d theta by central differences of the 80-digit reference, step 1e-25."""
    h = mp.mpf("1e-25")

    def u_of(th):
        a, b, c, d, prm = _unflat(th, m)
        kw = dict(zip(_NAMES, prm[:4], strict=True))
        if relaxed:
            kw["slack_weight"] = prm[4]
        return mpref.solve(a, list(b), c, list(d), **kw)[0]

    with mp.workdps(mpref.DPS):
        th = [mp.mpf(float(v)) for v in theta]
        cols = []
        for j in range(len(th)):
            up, dn = list(th), list(th)
            up[j] += h
            dn[j] -= h
            cols.append([(x - y) / (2 * h) for x, y in zip(u_of(up), u_of(dn), strict=True)])
        region = mpref.solve(
            *(lambda t: (t[0], list(t[1]), t[2], list(t[3])))(_unflat(th, m)[:4]),
            **dict(zip(_NAMES, _unflat(th, m)[4][:4], strict=True)),
            **({"slack_weight": _unflat(th, m)[4][4]} if relaxed else {}),
        )[2]
        return np.array([[float(v) for v in col] for col in cols]).T, region


@functools.partial(jax.jit, static_argnames=("m", "relaxed"))
def _jax_derivatives(th, m, relaxed):
    """Forward- and reverse-mode Jacobians of ``u`` and the region, in one program per
    shape: eager transformations traced the formula again at every call (about half of
    this test's time); the eager ones are tested in test_every_public_function_composes."""

    def u_of(th):
        a, b, c, d, prm = _unflat(th, m)
        kw = dict(zip(_NAMES, prm[:4], strict=True))
        if relaxed:
            return ss.clf_cbf_relaxed(a, b, c, d, slack_weight=prm[4], **kw)
        return ss.clf_cbf(a, b, c, d, **kw)

    return (
        jax.jacfwd(lambda t: u_of(t).u)(th),
        jax.jacrev(lambda t: u_of(t).u)(th),
        u_of(th).region,
    )


def _jax_jacobian(theta, m, relaxed):
    fwd, rev, region = _jax_derivatives(jnp.asarray(theta), m, relaxed)
    return np.asarray(fwd), np.asarray(rev), int(region)


@pytest.mark.parametrize("relaxed", [False, True])
def test_gradients_match_high_precision_differences_in_every_region(relaxed):
    rng = np.random.default_rng(7 + relaxed)
    seen: dict[int, int] = {}
    tries = 0
    while min(seen.get(r, 0) for r in (1, 2, 3, 4)) < 3 and tries < 400:
        tries += 1
        m = int(rng.integers(1, 4))
        params = list(rng.uniform(0.05, 2.0, size=2)) + list(rng.uniform(0.0, 1.5, size=2))
        params += [10 ** rng.uniform(-1, 2)] if relaxed else []
        a, c = rng.normal(size=2) * 2
        theta = _flat(a, rng.normal(size=m), c, rng.normal(size=m), params)
        fwd, rev, region = _jax_jacobian(theta, m, relaxed)
        if seen.get(region, 0) >= 3 and region != 0:
            continue
        ref, ref_region = _mp_jacobian(theta, m, relaxed)
        assert region == ref_region
        seen[region] = seen.get(region, 0) + 1
        scale = 1.0 + np.max(np.abs(ref))
        np.testing.assert_allclose(fwd, ref, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(rev, fwd, rtol=0, atol=1e-12 * scale)
    assert min(seen.get(r, 0) for r in (1, 2, 3, 4)) >= 3, seen


def test_boundary_derivative_is_that_of_the_region_picked_there():
    """On the P1/P3 boundary (v = 0) the formula picks P1 (the first matching row of its
    table), and the derivative is P1's: the one-sided derivative from the P1 side."""
    kw = dict(kappa=0.0, rho=0.0, phi=0.0, varphi=0.0)
    b, d = jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0])

    def u_of(c):  # B = -c; v = A b.d + B |b|^2 = -c: P1 for c >= 0, P3 for c < 0
        return ss.clf_cbf(1.0, b, c, d, **kw)

    assert int(u_of(0.0).region) == ss.Region.P1
    assert int(u_of(-1e-3).region) == ss.Region.P3
    g = np.asarray(jax.jacfwd(lambda c: u_of(c).u)(0.0))
    right = (np.asarray(u_of(1e-7).u) - np.asarray(u_of(0.0).u)) / 1e-7
    left = (np.asarray(u_of(0.0).u) - np.asarray(u_of(-1e-7).u)) / 1e-7
    np.testing.assert_allclose(g, right, atol=1e-12)
    assert np.max(np.abs(left - right)) > 0.5  # a real kink, and the choice is one side


@pytest.mark.parametrize(
    "a, b, c, d, phi, varphi",
    [
        (0.0, [0.0, 0.0], 0.0, [0.0, 0.0], 0.0, 0.0),  # everything zero
        (1.0, [0.0, 0.0], -1.0, [1.0, 0.0], 1.0, 0.0),  # b = 0
        (-1.0, [1.0, 0.5], 1.0, [0.0, 0.0], 0.0, 1.0),  # d = 0, phi = 0
        (0.0, [1.0, 0.0], 0.0, [0.0, 1.0], 0.0, 0.0),  # zeta = Gamma = 0
        (-1.0, [-1.0, 0.5], 0.0, [1.0, 0.0], 1.0, 0.0),  # varphi = 0 with c = 0
    ],
)
def test_no_nan_gradient_where_the_value_is_finite(a, b, c, d, phi, varphi):
    args = [jnp.asarray(v, float) for v in (a, b, c, d, 1.0, 0.5, phi, varphi)]
    fns = {
        "clf_cbf": lambda a, b, c, d, k, r, p, v: (
            ss.clf_cbf(a, b, c, d, kappa=k, rho=r, phi=p, varphi=v).u
        ),
        "relaxed": lambda a, b, c, d, k, r, p, v: (
            ss.clf_cbf_relaxed(a, b, c, d, kappa=k, rho=r, phi=p, varphi=v, slack_weight=3.0).u
        ),
        "sontag": lambda a, b, c, d, k, r, p, v: ss.clf_sontag(a, b, kappa=k, phi=p).u,
        "cbf": lambda a, b, c, d, k, r, p, v: ss.cbf_universal(c, d, rho=r, varphi=v).u,
        "multi": lambda a, b, c, d, k, r, p, v: (
            ss.clf_cbf_multi(
                a[None],
                b[None],
                c[None],
                d[None],
                kappa=k,
                rho=r,
                phi=p,
                varphi=v,
                u_min=-9.0,
                u_max=9.0,
            ).u
        ),  # fmt: skip
    }
    for name, fn in fns.items():
        assert np.all(np.isfinite(np.asarray(fn(*args)))), name
        grads = jax.grad(lambda *xs: jnp.sum(fn(*xs)), argnums=tuple(range(8)))(*args)
        for g in grads:
            assert np.all(np.isfinite(np.asarray(g))), name


def test_zeta_derivative_in_phi_at_zero_is_finite_and_right():
    """d zeta / d phi = |b|^4 / (2 zeta): finite at phi = 0 when a != 0 (the chain rule
    through phi^(1/4) would give NaN)."""
    b = jnp.array([1.0, 2.0])
    g = float(jax.grad(lambda p: ss.zeta(0.5, b, p))(0.0))
    assert g == pytest.approx(25.0 / (2 * 0.5), rel=1e-15)


# -- the filter's active sets ------------------------------------------------------------


def _mp_filter_u(clf, c, d, u_nom, rho, lo, hi, phase, hint):
    """The exact optimum of the filter's problem of ``phase`` in 60 digits.

    ``clf``: ``(a, b, kappa, phi)`` of one hard CLF row, or None. Phase 0 (``SOLVED``): every
    row; 1 (``CLF_DROPPED``): the CBFs and limits; 2 (``CBF_RELAXED``): the penalised problem
    of :class:`~safestab.MultiStatus` over the CBFs and limits.
    """
    k, m = len(c), len(u_nom)
    W = mp.mpf(ss.formulas.multi.FALLBACK_WEIGHT)
    B = [mpref.margins(0, [0] * m, ci, di, 0, rho, 0, 0)[1] for ci, di in zip(c, d, strict=True)]
    eye = [[mp.mpf(int(i == j)) for j in range(m)] for i in range(m)]
    slack = [0] * k if phase == 2 else []
    G = [[-x for x in di] + ([-mp.mpf(int(j == i)) for j in range(k)] if phase == 2 else [])
         for i, di in enumerate(d)]  # fmt: skip
    G += [row + slack for row in eye] + [[-x for x in row] + slack for row in eye]
    r = [-x for x in B] + list(hi) + [-x for x in lo]
    if clf is not None and phase == 0:
        a, b, kappa, phi = clf
        G = [list(b)] + G
        r = [-mpref.margins(a, b, 0, [0] * m, kappa, 0, phi, 0)[0]] + r
    dim = m + len(slack)
    Q = [[mp.mpf(int(i == j)) for j in range(dim)] for i in range(dim)]
    if phase == 2:
        for i, di in enumerate(d):
            Q[m + i][m + i] = W / mp.fsum(x * x for x in di)
    out = mpref.solve_qp(Q, list(u_nom) + slack, G, r, hint=hint, dps=60)
    assert out is not None
    return out[0][:m]


@functools.partial(jax.jit, static_argnums=(1, 2))
def _filter_jacobian(theta, k, p, kappa, rho, phi, lo, hi):
    """``d u / d theta`` (reverse mode: the pullback of each output direction) and the
    filter's answer at ``theta = (a, b, c, d, u_nom)``, in one program per shape (eager
    transformations compiled two and traced the solver again at every call)."""
    m = lo.shape[0]
    split = np.cumsum([p, p * m, k, k * m])

    def u_of(th):
        a, b, c, d, un = (th[i:j] for i, j in zip([0, *split], [*split, len(th)], strict=True))
        res = ss.clf_cbf_multi(
            a, b.reshape(p, m), c, d.reshape(k, m), kappa=kappa, rho=rho, phi=phi, varphi=0.0,
            u_min=lo, u_max=hi, u_nom=un,
        )  # fmt: skip
        return res.u, res

    _, pullback, res = jax.vjp(u_of, theta, has_aux=True)
    return jax.vmap(lambda e: pullback(e)[0])(jnp.eye(m)), res


def test_filter_gradients_match_high_precision_differences_on_its_active_sets():
    """Every phase of the filter's solver (SOLVED with and without a hard CLF, CLF_DROPPED,
    CBF_RELAXED): d u / d (a, b, c, d, u_nom) against 80-digit differences."""
    rng = np.random.default_rng(3)
    seen = {(0, 0): 0, (0, 1): 0, (1, 1): 0, (2, 0): 0}
    kappa, phi, rho, lim, m = 0.5, 1.0, 0.3, 1.5, 2
    lo, hi = -lim * np.ones(m), lim * np.ones(m)
    for _ in range(400):
        if min(seen.values()) >= 2:
            break
        k, p = int(rng.integers(2, 5)), int(rng.integers(0, 2))
        theta = np.concatenate(
            [rng.normal(size=p) * 2, rng.normal(size=p * m), rng.normal(size=k) * 2,
             rng.normal(size=k * m), rng.normal(size=m)]
        )  # fmt: skip
        split = np.cumsum([p, p * m, k, k * m])
        J, res = _filter_jacobian(jnp.asarray(theta), k, p, kappa, rho, phi, lo, hi)
        J = np.asarray(J)
        phase = int(res.status)
        if seen.get((phase, p), 2) >= 2:
            continue
        shift = p if phase > 0 else 0  # the CLF row is not in the fallback problems
        hint = [int(i) - shift for i in np.flatnonzero(np.asarray(res.active))]
        h = mp.mpf("1e-20")
        with mp.workdps(60):
            th = [mp.mpf(float(v)) for v in theta]
            cols = []
            for j in range(len(th)):
                vals = []
                for sgn in (1, -1):
                    t = list(th)
                    t[j] += sgn * h
                    a, b = t[:p], t[p : p + p * m]
                    c = t[split[1] : split[2]]
                    d = [t[split[2] + i * m : split[2] + (i + 1) * m] for i in range(k)]
                    clf = (a[0], b, kappa, phi) if p else None
                    vals.append(_mp_filter_u(clf, c, d, t[split[3] :], rho, lo, hi, phase, hint))
                cols.append([float((x - y) / (2 * h)) for x, y in zip(*vals, strict=True)])
        ref = np.array(cols).T
        # the derivative is the difference of dG^T mu and its projection: it carries the
        # rounding of the multipliers' size (about FALLBACK_WEIGHT in the last resort phase)
        mu = float(np.max(np.abs(np.asarray(res.multipliers))))
        tol = (1e-9 + 64 * np.finfo(float).eps * mu) * (1 + np.max(np.abs(ref)))
        np.testing.assert_allclose(J, ref, rtol=0, atol=tol)
        seen[(phase, p)] += 1
    assert min(seen.values()) >= 2, seen


# -- controllers and filters as values; simulate under transformations ---------------------


def _plant():
    def f(x):
        return jnp.array([x[1], -x[0] - 0.5 * x[1] + 0.1 * x[0] ** 3])

    def g(x):
        return jnp.array([[1.0 + 0.1 * x[1], 0.0], [0.2 * x[0], 1.0]])

    system = ss.ControlAffineSystem(f, g, 2)
    clf = ss.CLF(lambda x: x[0] ** 2 + x[0] * x[1] + x[1] ** 2, lam=0.5)
    cbf = ss.CBF(lambda x: 1.0 - (x[0] - 1.0) ** 2 - x[1] ** 2, beta=1.0)
    return system, clf, cbf


def test_controller_is_a_value_jit_vmap_grad():
    system, clf, cbf = _plant()
    ctrl = ss.UniversalController(system, clf, cbf, **K, u_min=-5.0, u_max=5.0)
    x = jnp.array([1.5, -0.5])
    assert set(ctrl.tunables()) == {"kappa", "rho", "phi", "varphi", "u_min", "u_max"}
    eager = np.asarray(ctrl.step(x).u)
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda c, x: c.step_fn(x).u)(ctrl, x)), eager)
    kappas = jnp.array([0.1, 0.5, 2.0])
    batched = jax.vmap(lambda k: ctrl.replace(kappa=k).input_fn(x))(kappas)
    for k, row in zip(kappas, np.asarray(batched), strict=True):
        np.testing.assert_allclose(row, ctrl.replace(kappa=float(k)).step(x).u, rtol=1e-14)
    for name in ("kappa", "rho", "phi", "varphi"):
        v = float(ctrl.tunables()[name])
        g = np.asarray(jax.jacfwd(lambda p, n=name: ctrl.replace(**{n: p}).input_fn(x))(v))
        h = 1e-6
        fd = (
            np.asarray(ctrl.replace(**{name: v + h}).step(x).u)
            - np.asarray(ctrl.replace(**{name: v - h}).step(x).u)
        ) / (2 * h)
        np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)
    # the gradient with respect to the whole controller is a controller of gradients
    grads = jax.grad(lambda c: jnp.sum(c.input_fn(x)))(ctrl)
    assert isinstance(grads, ss.UniversalController)
    assert set(grads.tunables()) == set(ctrl.tunables())
    with pytest.raises(ParameterError):  # replace checks as the constructor does
        ctrl.replace(kappa=-1.0)


def test_controllers_built_alike_share_one_compilation_and_others_do_not():
    """Equal static parts (system, certificates, formula, options) give equal tree structures:
    a user's jit compiles once for controllers built alike and for replace() with new numbers;
    a different static part (formula, saturation, system, a slack weight) compiles anew, and
    every output equals that controller's own eager step."""
    system, clf, cbf = _plant()
    traces = []

    @jax.jit
    def u_of(c, x):
        traces.append(1)
        return c.step_fn(x).u

    base = ss.UniversalController(system, clf, cbf, **K, u_min=-5.0, u_max=5.0)
    alike = [
        base,
        ss.UniversalController(system, clf, cbf, **K, u_min=-5.0, u_max=5.0),
        base.replace(kappa=2.0),
        base.replace(rho=0.9, u_min=-1.0, u_max=1.0),
    ]
    x = jnp.array([1.5, -0.5])
    for c in alike:
        np.testing.assert_array_equal(np.asarray(u_of(c, x)), np.asarray(c.step(x).u))
    assert len(traces) == 1
    other_system = ss.ControlAffineSystem(system.f, system.g, system.n_states)
    others = [
        base.replace(formula="sontag"),
        base.replace(saturation="safety_first")
        if system.n_inputs == 1
        else base.replace(u_min=None, u_max=None),
        ss.UniversalController(other_system, clf, cbf, **K, u_min=-5.0, u_max=5.0),
        base.replace(slack_weight=3.0),
    ]
    for c in others:
        np.testing.assert_array_equal(np.asarray(u_of(c, x)), np.asarray(c.step(x).u))
    assert len(traces) == 1 + len(others)
    # the outputs differ where the static parts say they should (the test can fail)
    assert not np.array_equal(np.asarray(u_of(others[0], x)), np.asarray(u_of(base, x)))

    # a value JAX rebuilt keeps its own numbers through replace(), though its tree structure
    # was first made from another controller
    ident = jax.jit(lambda c: c)
    ident(base)
    rebuilt = ident(base.replace(kappa=3.0))
    assert float(rebuilt.replace(rho=0.3).tunables()["kappa"]) == 3.0
    doubled = jax.tree_util.tree_map(lambda v: 2 * v, base)
    assert float(doubled.replace(rho=0.3).tunables()["kappa"]) == 2 * K["kappa"]

    # a subclass defined outside the package is keyed by identity (its own state is unknown)
    class Mine(ss.UniversalController):
        pass

    mine = [Mine(system, clf, cbf, **K), Mine(system, clf, cbf, **K)]
    assert jax.tree_util.tree_structure(mine[0]) != jax.tree_util.tree_structure(mine[1])


def test_a_filter_built_with_lists_and_its_replace_share_one_tree_structure():
    """``cbfs=[...]`` is kept as a tuple, which ``replace`` passes on: one structure, so a
    user's jit compiles once for both (a list and a tuple were two keys)."""
    system, clf, cbf = _plant()
    filt = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_min=-4.0, u_max=4.0)
    other = filt.replace(rho=0.31)
    assert jax.tree_util.tree_structure(filt) == jax.tree_util.tree_structure(other)
    traces = []

    @jax.jit
    def u_of(c, x):
        traces.append(1)
        return c.step_fn(x).u

    x = jnp.array([1.2, 0.7])
    for c in (filt, other):
        np.testing.assert_array_equal(np.asarray(u_of(c, x)), np.asarray(c.step(x).u))
    assert len(traces) == 1
    # another structure (a slack weight) is traced anew (the test can fail)
    u_of(filt.replace(slack_weight=2.0), x)
    assert len(traces) == 2


def test_the_eager_step_of_a_replaced_controller_is_not_traced_again():
    """An eager ``step`` runs one program per tree structure: new numbers (``replace``)
    reuse it, and its answer is the one of the controller passed to a user's jit."""
    system, clf, cbf = _plant()
    filt = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_min=-4.0, u_max=4.0)
    ctrl = ss.UniversalController(system, clf, cbf, **K, u_min=-5.0, u_max=5.0)
    x = jnp.array([1.2, 0.7])
    for base, others in (
        (filt, [filt.replace(rho=0.31), filt.replace(kappa=0.7, u_max=3.0)]),
        (ctrl, [ctrl.replace(rho=0.31), ctrl.replace(kappa=0.7, u_max=3.0)]),
    ):
        u_of = jax.jit(lambda c, x: c.step_fn(x).u)
        base.step(x), u_of(base, x)
        outs = []
        assert traces_while(lambda others=others: outs.extend(o.step(x).u for o in others)) == []
        for other, u in zip(others, outs, strict=True):
            np.testing.assert_array_equal(np.asarray(u), np.asarray(u_of(other, x)))
        # the numbers did reach the program (the test can fail)
        assert not np.array_equal(np.asarray(outs[1]), np.asarray(base.step(x).u))
    # another structure (a slack weight) is a program of its own
    assert traces_while(lambda: filt.replace(slack_weight=2.0).step(x)) != []


def test_a_copy_with_other_numbers_does_not_reuse_the_eager_arguments_of_its_template():
    """JAX rebuilds a controller by copying the first of its structure: the copy carries
    that one's kept device arguments, and must step with its own numbers."""
    system, clf, cbf = _plant()
    filt = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_min=-4.0, u_max=4.0)
    x = jnp.array([1.2, 0.7])
    u = np.asarray(filt.step(x).u)  # keeps its device arguments
    other = jax.tree_util.tree_map(lambda v: np.asarray(v) * 0.5, filt)
    got = np.asarray(other.step(x).u)
    # the numbers as arguments, as a user's jit passes them: the same program, the same bits
    np.testing.assert_array_equal(got, np.asarray(jax.jit(lambda c, x: c.step_fn(x).u)(other, x)))
    # step_fn holds them as constants, which XLA may fold in another order: the last bit
    np.testing.assert_allclose(got, np.asarray(other.step_fn(x).u), rtol=1e-14, atol=0)
    assert not np.allclose(got, u)
    np.testing.assert_array_equal(np.asarray(filt.step(x).u), u)


def test_a_traced_step_is_the_controllers_own_step_fn():
    """Inside a trace (a user's jit, a study's loop) and eagerly alike, ``step`` and
    ``__call__`` run the one jitted step, ``controller_step``, with the controller as its
    argument: a controller with new numbers is not traced again."""
    system, clf, cbf = _plant()
    filt = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_min=-4.0, u_max=4.0)
    x = jnp.array([1.2, 0.7])
    text = str(jax.make_jaxpr(lambda x: filt(x))(x))
    assert "controller_step" in text
    np.testing.assert_array_equal(
        np.asarray(jax.jit(lambda x: filt(x))(x)), np.asarray(filt.step_fn(x).u)
    )
    filt.step(x)
    # eagerly, new numbers: the program of the first (the test can fail: a new structure is
    # named in the trace, as another clfs spelling was before the certificates keyed it)
    assert "controller_step" not in traces_while(lambda: filt.replace(rho=0.29).step(x))
    assert "controller_step" in traces_while(lambda: filt.replace(H=np.eye(2)).step(x))


def test_state_gradient_through_f_g_v_h_matches_high_precision_differences():
    """du/dx of the controller (through f, g, V, h and their autodiff gradients) against
    central differences of the same controller written out by hand in 80 digits."""
    system, clf, cbf = _plant()
    ctrl = ss.UniversalController(system, clf, cbf, **K)

    def u_mp(x0, x1, lam=mp.mpf("0.5"), beta=mp.mpf(1)):
        f = [x1, -x0 - mp.mpf("0.5") * x1 + mp.mpf("0.1") * x0**3]
        g = [[1 + mp.mpf("0.1") * x1, 0], [mp.mpf("0.2") * x0, 1]]
        V = x0**2 + x0 * x1 + x1**2
        gV = [2 * x0 + x1, x0 + 2 * x1]
        h = 1 - (x0 - 1) ** 2 - x1**2
        gh = [-2 * (x0 - 1), -2 * x1]
        lie = lambda gr: [mp.fsum(gr[i] * g[i][j] for i in range(2)) for j in range(2)]  # noqa: E731
        a = mp.fsum(gV[i] * f[i] for i in range(2)) + lam * V
        c = mp.fsum(gh[i] * f[i] for i in range(2)) + beta * h
        return mpref.solve(a, lie(gV), c, lie(gh), **K)[0]

    rng = np.random.default_rng(11)
    regions = set()
    for _ in range(12):  # inside the safe set, some states near its edge (CBF active)
        r, angle = rng.uniform(0.3, 0.99), rng.uniform(0, 2 * np.pi)
        x = np.array([1.0 + r * np.cos(angle), r * np.sin(angle)])
        J = np.asarray(jax.jacrev(ctrl.input_fn)(jnp.asarray(x)))
        regions.add(int(ctrl.step(x).region))
        hh = mp.mpf("1e-25")
        with mp.workdps(mpref.DPS):
            xm = [mp.mpf(float(v)) for v in x]
            cols = []
            for j in range(2):
                up, dn = list(xm), list(xm)
                up[j] += hh
                dn[j] -= hh
                cols.append(
                    [float((p - q) / (2 * hh)) for p, q in zip(u_mp(*up), u_mp(*dn), strict=True)]
                )
            for name in ("lam", "beta"):  # the class-K rates of the certificates
                base = {"lam": mp.mpf("0.5"), "beta": mp.mpf(1)}
                up = u_mp(*xm, **{**base, name: base[name] + hh})
                dn = u_mp(*xm, **{**base, name: base[name] - hh})
                cols.append([float((p - q) / (2 * hh)) for p, q in zip(up, dn, strict=True)])
        ref = np.array(cols).T

        def u_rates(r, x=x):
            c = ctrl.replace(clf=clf.replace(lam=r[0]), cbf=cbf.replace(beta=r[1]))
            return c.input_fn(jnp.asarray(x))

        J = np.concatenate([J, np.asarray(jax.jacrev(u_rates)(jnp.array([0.5, 1.0])))], -1)
        np.testing.assert_allclose(J, ref, rtol=0, atol=1e-9 * (1 + np.max(np.abs(ref))))
    assert len(regions) >= 2, regions


def test_filter_is_a_value_and_differentiates():
    system, clf, cbf = _plant()
    cbf2 = ss.CBF(lambda x: 3.0 - x[0] - x[1], beta=0.5)
    filt = ss.SafetyFilter(
        system,
        [cbf, cbf2],
        clfs=[clf],
        **K,
        u_min=-4.0,
        u_max=4.0,
        H=jnp.diag(jnp.array([1.0, 2.0])),
    )
    x = jnp.array([1.2, 0.7])
    assert set(filt.tunables()) == {"kappa", "rho", "phi", "varphi", "u_min", "u_max", "H"}
    np.testing.assert_array_equal(
        np.asarray(jax.jit(lambda f, x: f.step_fn(x).u)(filt, x)), np.asarray(filt.step(x).u)
    )
    # every derivative from one reverse-mode program, with the filter as an argument: its
    # gradient is a filter of Jacobians (eager jacrev per parameter compiled two programs of
    # the whole step for each, half of this test's time). At the first state only the CLF
    # row is active (u depends on kappa and H, not on rho); at the second the CLF and the
    # first CBF are (u is fixed by the two rows: rho and kappa, not H). Each derivative is
    # compared where it is not zero, so that the comparison can fail.
    jac = jax.jit(jax.jacrev(lambda f, x: f.step_fn(x).u, argnums=(0, 1)))
    H0 = filt.tunables()["H"]
    for x, names in ((x, ("kappa", "H")), (jnp.array([0.3, 0.2]), ("rho", "kappa"))):
        dfilt, J = jac(filt, x)
        assert isinstance(dfilt, ss.SafetyFilter)
        grads = dfilt.tunables()
        for name in names:
            if name == "H":
                gH = np.asarray(grads["H"])
                for i, j in ((0, 0), (1, 1)):
                    E = np.zeros((2, 2))
                    E[i, j] = 1e-6
                    fdH = (
                        np.asarray(filt.replace(H=H0 + E).step(x).u)
                        - np.asarray(filt.replace(H=H0 - E).step(x).u)
                    ) / 2e-6
                    assert np.max(np.abs(gH[:, i, j])) > 1e-3  # far above the atol
                    np.testing.assert_allclose(gH[:, i, j], fdH, rtol=1e-6, atol=1e-8)
                continue
            v = float(filt.tunables()[name])
            g = np.asarray(grads[name])
            fd = (
                np.asarray(filt.replace(**{name: v + 1e-6}).step(x).u)
                - np.asarray(filt.replace(**{name: v - 1e-6}).step(x).u)
            ) / 2e-6
            assert np.max(np.abs(g)) > 1e-3, name  # far above the atol
            np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)
        J = np.asarray(J)
        fd = np.stack(
            [(np.asarray(filt.step(x + 1e-6 * e).u) - np.asarray(filt.step(x - 1e-6 * e).u)) / 2e-6
             for e in np.eye(2)], -1,
        )  # fmt: skip
        assert np.max(np.abs(J)) > 1e-3
        np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-8)


def test_a_controller_keeps_its_numbers_when_arrays_change_in_place():
    """A controller is a value: the caller's arrays changed after construction, or its own
    written in place, do not change its numbers behind its back (an eager step kept the
    device copies of the old ones and gave an input outside the limits it then reported)."""
    system, clf, cbf = _plant()
    lo, hi, H = np.full(2, -4.0), np.full(2, 4.0), np.diag([1.0, 2.0])
    x = jnp.array([3.0, 3.0])
    ctrls = [
        ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_min=lo, u_max=hi, H=H),
        ss.UniversalController(system, clf, cbf, **K, u_min=lo, u_max=hi),
    ]
    before = [np.asarray(c.step(x).u) for c in ctrls]
    lo[:], hi[:], H[:] = -0.5, 0.5, np.diag([5.0, 0.1])  # the caller's arrays
    for ctrl, u in zip(ctrls, before, strict=True):
        np.testing.assert_array_equal(np.asarray(ctrl.step(x).u), u)
        own = ctrl.tunables()
        np.testing.assert_array_equal(own["u_min"], [-4.0, -4.0])
        np.testing.assert_array_equal(own["u_max"], [4.0, 4.0])
        if "H" in own:
            np.testing.assert_array_equal(own["H"], np.diag([1.0, 2.0]))
        arrays = [v for v in ctrl.tunables().values() if isinstance(v, np.ndarray)]
        assert len(arrays) >= 2
        for value in arrays:
            with pytest.raises(ValueError, match="read-only"):
                value[...] = 0.0
        # the new numbers, as a new controller, do move the input into the new limits
        moved = np.asarray(ctrl.replace(u_min=lo, u_max=hi).step(x).u)
        assert np.all(np.abs(moved) <= 0.5) and not np.all(np.abs(u) <= 0.5)


def test_a_constant_nominal_input_changed_in_place_is_not_the_old_program():
    """A filter's constant ``u_nom`` is part of its tree structure by value: a second filter
    built from the same array, changed in place in between, does not reuse the first one's
    compiled step (it was keyed by the array's identity and answered for the old values);
    ``replace`` rebuilds from the values given at construction."""
    system, clf, cbf = _plant()
    u_nom = np.array([0.3, -0.2])
    first = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_nom=u_nom)
    x = jnp.array([0.2, 0.1])
    u_first = np.asarray(first.step(x).u)
    u_nom[:] = [-0.4, 0.25]
    second = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_nom=u_nom)
    fresh = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_nom=np.array([-0.4, 0.25]))
    np.testing.assert_array_equal(np.asarray(second.step(x).u), np.asarray(fresh.step(x).u))
    assert not np.array_equal(np.asarray(second.step(x).u), u_first)
    np.testing.assert_array_equal(np.asarray(first.replace().step(x).u), u_first)
    # built alike from equal values: one tree structure, one program
    again = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_nom=np.array([-0.4, 0.25]))
    assert jax.tree_util.tree_structure(again) == jax.tree_util.tree_structure(fresh)


def test_a_controller_rebuilt_from_numpy_leaves_holds_read_only_copies():
    system, clf, cbf = _plant()
    filt = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_min=-4.0, u_max=4.0)
    leaves = [np.array(v) for v in jax.tree_util.tree_leaves(filt)]
    rebuilt = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(filt), leaves)
    leaves[4][:] = 0.0  # u_min, the caller's array
    for value in rebuilt.tunables().values():
        if isinstance(value, np.ndarray):
            assert not value.flags.writeable
    np.testing.assert_array_equal(rebuilt.tunables()["u_min"], [-4.0, -4.0])


def test_simulate_under_jit_vmap_and_grad():
    system, clf, cbf = _plant()
    ctrl = ss.UniversalController(system, clf, cbf, **K)
    x0 = jnp.array([1.5, -0.5])

    def cost(c, x0):
        tr = ss.simulate(c, x0, t_final=1.0, dt=0.05)
        return jnp.sum(tr.V) * 0.05

    eager = float(cost(ctrl, x0))
    jcost = jax.jit(cost)  # the controller an argument: new numbers reuse its program
    assert float(jcost(ctrl, x0)) == pytest.approx(eager, rel=1e-13)
    xs = jnp.array([[1.5, -0.5], [0.8, 0.5]])
    np.testing.assert_allclose(
        np.asarray(jax.vmap(cost, in_axes=(None, 0))(ctrl, xs)),
        [float(cost(ctrl, x)) for x in xs],
        rtol=1e-13,
    )
    g = float(jax.grad(lambda k: cost(ctrl.replace(kappa=k), x0))(0.5))
    fd = (
        float(jcost(ctrl.replace(kappa=0.5 + 1e-6), x0))
        - float(jcost(ctrl.replace(kappa=0.5 - 1e-6), x0))
    ) / 2e-6
    assert g == pytest.approx(fd, rel=1e-5, abs=1e-9)
    gx = np.asarray(jax.grad(lambda x: cost(ctrl, x))(x0))
    fdx = [
        (float(cost(ctrl, x0 + 1e-6 * e)) - float(cost(ctrl, x0 - 1e-6 * e))) / 2e-6
        for e in np.eye(2)
    ]
    np.testing.assert_allclose(gx, fdx, rtol=1e-5, atol=1e-9)
    with pytest.raises(ParameterError, match="strict=True needs concrete"):
        jax.jit(lambda c: ss.simulate(c, x0, t_final=0.2, dt=0.05, strict=True).V)(ctrl)


def test_unflatten_takes_placeholders_as_jax_requires():
    system, clf, cbf = _plant()
    ctrl = ss.UniversalController(system, clf, cbf, **K, slack_weight=10.0)
    leaves, tree = jax.tree_util.tree_flatten(ctrl)
    again = jax.tree_util.tree_unflatten(tree, [object()] * len(leaves))
    assert isinstance(again, ss.UniversalController)
    doubled = jax.tree_util.tree_map(lambda v: 2 * v, ctrl)
    assert doubled.tunables()["slack_weight"] == 20.0
    assert jax.tree_util.tree_structure(doubled) == tree


def test_checked_steps_compose_and_refuse_strict_when_traced():
    system, clf, cbf = _plant()
    ctrl = ss.UniversalController(system, clf, cbf, **K)
    filt = ss.SafetyFilter(system, [cbf], clfs=[clf], **K)
    x = jnp.array([1.2, 0.3])
    for obj in (ctrl, filt):
        eager = np.asarray(obj.step(x).u)
        np.testing.assert_array_equal(np.asarray(jax.jit(lambda x, o=obj: o.step(x).u)(x)), eager)
        np.testing.assert_array_equal(np.asarray(jax.vmap(obj)(jnp.stack([x, x]))[0]), eager)
        g = np.asarray(jax.grad(lambda x, o=obj: o.step(x).u[0])(x))
        fd = [(float(obj(x + 1e-6 * e)[0]) - float(obj(x - 1e-6 * e)[0])) / 2e-6 for e in np.eye(2)]
        np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)
        with pytest.raises(ParameterError, match="strict=True needs concrete"):
            jax.jit(lambda x, o=obj: o.step(x, strict=True).u)(x)


def test_gp_robust_controllers_differentiate_without_nan():
    """The exact GP and its fast cache under jacfwd and jacrev: no NaN where a component's
    std is exactly 0 (a component the GP does not learn), and the derivative of u in the
    state and in gp_beta against central differences (step 1e-4: the std is small, and a
    smaller step would measure its rounding)."""
    from safestab.learning import FastGP, GaussianProcessModel

    system, clf, cbf = _plant()
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 2, (60, 2))
    Y = np.stack([0 * X[:, 0], -0.3 * X[:, 1]], -1) + 1e-3 * rng.normal(size=(60, 2))
    gp = GaussianProcessModel(kernel="se").fit(X, Y, components=[1])
    x = jnp.array([1.2, 0.3])
    for unc in (gp, FastGP(gp, n_inducing=16)):
        ctrl = ss.UniversalController(system, clf, cbf, **K, uncertainty=unc, gp_beta=2.0)
        fwd = np.asarray(jax.jacfwd(ctrl.input_fn)(x))
        rev = np.asarray(jax.jacrev(ctrl.input_fn)(x))
        assert np.all(np.isfinite(fwd))
        # the cache's weights c = Lj^-T Lj^-1 k carry cond(K_ZZ) u, which the two modes
        # accumulate in different orders
        rtol = 1e-12 if unc is gp else 1e-9
        np.testing.assert_allclose(fwd, rev, rtol=rtol, atol=1e-14)
        h = 1e-4
        fd = np.stack(
            [
                (np.asarray(ctrl(x + h * e)) - np.asarray(ctrl(x - h * e))) / (2 * h)
                for e in np.eye(2)
            ],
            -1,
        )
        np.testing.assert_allclose(fwd, fd, rtol=1e-5, atol=1e-6)
        gb = float(jax.grad(lambda b, c=ctrl: c.replace(gp_beta=b).input_fn(x)[0])(2.0))
        fdb = (
            float(ctrl.replace(gp_beta=2.0 + h)(x)[0]) - float(ctrl.replace(gp_beta=2.0 - h)(x)[0])
        ) / (2 * h)
        assert gb == pytest.approx(fdb, rel=1e-5, abs=1e-9)


def _objects():
    system, clf, cbf = _plant()
    ctrl = ss.UniversalController(system, clf, cbf, **K, u_min=-5.0, u_max=5.0)
    filt = ss.SafetyFilter(system, [cbf], clfs=[clf], **K, u_min=-5.0, u_max=5.0)
    return {
        "controller.step_fn": lambda x: ctrl.step_fn(x).u,
        "controller.step": lambda x: ctrl.step(x).u,
        "controller()": ctrl,
        "filter.step_fn": lambda x: filt.step_fn(x).u,
        "filter.step": lambda x: filt.step(x).u,
        "lie_terms": lambda x: jnp.stack(ss.lie_terms(system, clf, cbf, x)[::2]),
        "simulate": lambda x: ss.simulate(ctrl, x, t_final=0.2, dt=0.05).h,
    }


@pytest.mark.parametrize("name", sorted(_objects()))
def test_every_public_object_composes(name):
    fn = _objects()[name]
    x = jnp.array([1.2, 0.3])
    eager = np.asarray(fn(x))
    np.testing.assert_allclose(np.asarray(jax.jit(fn)(x)), eager, rtol=1e-13, atol=1e-15)
    xs = jnp.stack([x, x + 0.1])
    np.testing.assert_allclose(
        np.asarray(jax.vmap(fn)(xs)), np.stack([eager, np.asarray(fn(xs[1]))]), rtol=1e-13,
        atol=1e-15,
    )  # fmt: skip
    fwd = np.asarray(jax.jacfwd(fn)(x))
    rev = np.asarray(jax.jacrev(fn)(x))
    assert np.all(np.isfinite(fwd))
    np.testing.assert_allclose(rev, fwd, rtol=1e-10, atol=1e-12)
    g = np.asarray(jax.grad(lambda x: jnp.sum(fn(x)))(x))
    np.testing.assert_allclose(g, fwd.reshape(-1, 2).sum(0), rtol=1e-10, atol=1e-12)
    fd = np.stack(
        [(np.asarray(fn(x + 1e-6 * e)) - np.asarray(fn(x - 1e-6 * e))) / 2e-6 for e in np.eye(2)],
        -1,
    )
    np.testing.assert_allclose(fwd, fd, rtol=1e-6, atol=1e-7)


def test_class_k_gain_built_inside_the_traced_function_differentiates():
    """A class-K function whose gain is traced (built inside the differentiated function):
    its probe checks give way to shape checks, and d u / d gain matches differences."""
    system, clf, cbf = _plant()
    h = cbf.fn
    ctrl = ss.UniversalController(system, clf, cbf, **K)

    def u(gain, x):
        alpha = lambda s: gain * s**3 + s  # noqa: E731
        return ctrl.replace(cbf=ss.CBF(h, alpha=alpha)).input_fn(x)

    angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    states = [jnp.array([1 + 0.97 * np.cos(t), 0.97 * np.sin(t)]) for t in angles]
    active = [x for x in states if int(ctrl.step(x).region) in (ss.Region.P2, ss.Region.P3)]
    assert active  # the CBF binds somewhere on this circle
    for x in active[:3]:
        g = np.asarray(jax.jacfwd(u)(2.0, x))
        fd = (np.asarray(u(2.0 + 1e-6, x)) - np.asarray(u(2.0 - 1e-6, x))) / 2e-6
        assert np.max(np.abs(g)) > 0
        np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
    with pytest.raises(ParameterError):  # concrete class-K functions are still checked
        ss.CBF(h, alpha=lambda s: -s)
