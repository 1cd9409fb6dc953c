"""C export: the native step against the JAX step, the primitive table, harness and errors.

Each controller is exported and compiled once per module (fixtures with module scope). The
reference is always the JAX step (``controller.step_fn``), compared leaf by leaf: integer and
boolean leaves (regions, flags) must be identical, real leaves must satisfy
``|native - jax| <= rtol (|jax| + scale)`` with the scales of
:func:`safestab.export.harness.comparison_scales` (docs/export.md explains them).
"""

import shutil
import subprocess
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

import safestab as ss
from safestab.errors import (
    CompilationError,
    ConvergenceWarning,
    DimensionError,
    InfeasibleError,
    NonFiniteError,
    ParameterError,
    UnsupportedPrimitiveError,
)
from safestab.export import NativeController, compile_native, export_c, export_function
from safestab.export.harness import HARNESS_FLAGS, compare, comparison_scales
from safestab.learning import FastGP, GaussianProcessModel
from safestab.scenarios import load_scenario
from safestab.scenarios.export_study import export_scenario

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler")

N_STATES = 100_000
#: XLA fuses a*b + c into FMAs and sums in its own order, the C code does neither (it is
#: compiled with -ffp-contract=off so that it gives the same numbers on every platform):
#: the two agree to rounding, measured at most 2.2e-14 of the scales (docs/export.md).
RTOL = 1e-12


@pytest.fixture(scope="module")
def acc():
    sc = load_scenario("stress")
    clf, cbf = sc.certificates()
    p = dict(kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi)
    # A GP on omega_1 with enough noise that its posterior variance is not a cancellation of
    # prior and explained variance (where it is, XLA is reproducible only to ~1e-5 of sigma
    # between its batched and single-state steps, docs/export.md)
    rng = np.random.default_rng(0)
    lo, hi = np.array(sc.x0_low), np.array(sc.x0_high)
    xt = rng.uniform(lo, hi, size=(40, 3))
    yt = np.asarray(sc.omega(xt)) + 0.3 * rng.standard_normal((40, 3))
    # any fitted GP serves here (the test is about the export, not the fit): 50 iterations keep
    # the fixture fast, and the fit's ConvergenceWarning for stopping there is expected
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        gp = GaussianProcessModel(kernel="se", max_iter=50).fit(xt, yt, components=[0], seed=0)
    fast = FastGP(gp, n_inducing=16)
    # states beyond the learning box, so that every region of the formula occurs
    states = rng.uniform([0.0, 0.0, -50.0], [40.0, 40.0, 250.0], size=(N_STATES, 3))
    return dict(sc=sc, clf=clf, cbf=cbf, p=p, fast=fast, states=states)


def _acc_controller(acc, *, gp, relaxed, saturation):
    sc = acc["sc"]
    extra = dict(uncertainty=acc["fast"], gp_beta=sc.gp_beta) if gp else {}
    return ss.UniversalController(
        sc.system("nominal"),
        acc["clf"],
        acc["cbf"],
        slack_weight=sc.slack_weight if relaxed else None,
        u_min=[-0.3],
        u_max=[0.3],
        saturation=saturation,
        **acc["p"],
        **extra,
    )


def zoo_system():
    """n = 3, m = 2; f, g, V, h with sin, cos, exp, tanh and matrix products."""
    a = jnp.array([[0.0, 1.0, 0.0], [-1.0, -0.3, 0.2], [0.1, 0.0, -0.5]])
    p = jnp.array([[2.0, 0.3, 0.0], [0.3, 1.0, 0.1], [0.0, 0.1, 1.5]])
    q = jnp.array([[1.0, 0.2, 0.0], [0.2, 0.5, 0.0], [0.0, 0.0, 0.8]])

    def f(x):
        return a @ jnp.tanh(x) + jnp.array(
            [jnp.sin(x[1]), 0.3 * jnp.cos(x[0]), jnp.exp(-(x[2] ** 2))]
        )

    def g(x):
        return jnp.array(
            [[1.0, 0.2 * jnp.sin(x[0])], [0.1 * jnp.cos(x[2]), 1.0], [0.3, jnp.tanh(x[1])]]
        )

    system = ss.ControlAffineSystem(f, g, 3, name="zoo")
    clf = ss.CLF(lambda x: x @ p @ x + 0.1 * jnp.sin(x[0]) ** 2, lam=1.0)
    cbf = ss.CBF(lambda x: 4.0 - x @ q @ x - 0.2 * jnp.exp(0.5 * x[1]), beta=2.0)
    return system, clf, cbf


def _zoo_controller(*, relaxed):
    system, clf, cbf = zoo_system()
    limits = dict(u_min=[-2.0, -1.5], u_max=[2.0, 1.5]) if relaxed else {}
    return ss.UniversalController(
        system,
        clf,
        cbf,
        kappa=0.5,
        rho=0.2,
        phi=0.1,
        varphi=0.05,
        slack_weight=5.0 if relaxed else None,
        **limits,
    )


VARIANTS = {
    "acc nominal, relaxed, projection": ("acc", dict(gp=False, relaxed=True, saturation="project")),
    "acc nominal, hard, safety-first": (
        "acc",
        dict(gp=False, relaxed=False, saturation="safety_first"),
    ),
    "acc GP-robust, relaxed, safety-first": (
        "acc",
        dict(gp=True, relaxed=True, saturation="safety_first"),
    ),
    "acc GP-robust, hard, projection": ("acc", dict(gp=True, relaxed=False, saturation="project")),
    "zoo, relaxed, projection": ("zoo", dict(relaxed=True)),
    "zoo, hard, no limits": ("zoo", dict(relaxed=False)),
}


@pytest.fixture(scope="module")
def built(acc):
    cache = {}

    def get(variant):
        if variant not in cache:
            kind, kw = VARIANTS[variant]
            ctrl = _acc_controller(acc, **kw) if kind == "acc" else _zoo_controller(**kw)
            name = "c" + str(list(VARIANTS).index(variant))
            cache[variant] = (ctrl, NativeController(ctrl, name=name))
        return cache[variant]

    return get


def _states(acc, variant):
    if VARIANTS[variant][0] == "acc":
        return acc["states"]
    return 1.5 * np.random.default_rng(1).standard_normal((N_STATES, 3))


@pytest.mark.parametrize("variant", VARIANTS)
def test_native_equals_jax_step(acc, built, variant):
    ctrl, native = built(variant)
    x = _states(acc, variant)
    ref = ctrl.step_fn(jnp.asarray(x))
    out = native.step(x)
    ref_leaves = [np.asarray(v) for v in jax.tree_util.tree_leaves(ref)]
    out_leaves = jax.tree_util.tree_leaves(out)
    assert jax.tree_util.tree_structure(out) == jax.tree_util.tree_structure(ref)
    for got, want in zip(out_leaves, ref_leaves, strict=True):
        assert got.shape == want.shape and got.dtype == want.dtype
    bad = compare(out_leaves, ref_leaves, comparison_scales(ctrl, ref, x), RTOL)
    assert bad == {}, {native.exported.leaves[i].path: n for i, n in bad.items()}
    # the states exercise the formula: several regions, both flags' values
    assert len(np.unique(np.asarray(ref.region))) >= 3
    assert 0 < np.mean(np.asarray(ref.cbf_satisfied)) <= 1


def test_call_and_single_state(acc, built):
    ctrl, native = built("acc GP-robust, relaxed, safety-first")
    for x in acc["states"][:20]:
        u = native(x)
        assert u.shape == (1,) and u.dtype == np.float64
        np.testing.assert_allclose(u, np.asarray(ctrl(x)), rtol=1e-12, atol=1e-15)
        one = native.step(x)
        assert np.shape(one.region) == () and np.shape(one.u) == (1,)
        np.testing.assert_array_equal(native.step(x).u, u)
    # lists and jax arrays are accepted like UniversalController accepts them
    np.testing.assert_array_equal(native(list(acc["states"][0])), native(acc["states"][0]))
    np.testing.assert_array_equal(native(jnp.asarray(acc["states"][0])), native(acc["states"][0]))


def test_one_state_paths_give_the_batch_bits(acc, built):
    """input_fn's paths for one state (the state as C arguments for a float64 array, the
    bound buffer for anything else) give the bits of the batch loop, in double and float;
    each call returns a fresh array."""
    ctrl, native = built("acc GP-robust, relaxed, safety-first")
    assert native.function.step_args is not None  # the api-mode build has the glue
    x = acc["states"][:200]
    batch = native.step(x).u
    f32 = NativeController(ctrl, name="f32one", precision="float")
    batch32 = f32.step(x.astype(np.float32)).u
    first = native.input_fn(x[0])
    for i, xi in enumerate(x):
        for got in (native.input_fn(xi), native(xi), native(list(xi)), native(xi.astype(">f8"))):
            np.testing.assert_array_equal(got, batch[i])
        np.testing.assert_array_equal(f32.input_fn(xi), batch32[i])  # rounded in C
        np.testing.assert_array_equal(f32(xi.astype(np.float32)), batch32[i])
    np.testing.assert_array_equal(first, batch[0])  # not overwritten by the later calls
    with pytest.raises(NonFiniteError, match="x must be finite"):
        native.input_fn(np.array([1.0, np.nan, 3.0]))


def test_batch_shapes(acc, built):
    ctrl, native = built("acc nominal, relaxed, projection")
    x = acc["states"][:30].reshape(2, 5, 3, 3)
    out = native.step(x)
    assert out.u.shape == (2, 5, 3, 1) and out.region.shape == (2, 5, 3)
    np.testing.assert_array_equal(native(x), out.u)
    np.testing.assert_array_equal(out.region, np.asarray(ctrl.step_fn(jnp.asarray(x)).region))


def test_step_errors(acc, built):
    ctrl, native = built("acc nominal, hard, safety-first")
    with pytest.raises(DimensionError, match=r"x must have shape \(\.\.\., 3\), got shape \(2,\)"):
        native.step([1.0, 2.0])
    with pytest.raises(DimensionError, match="x must have shape"):
        native(np.zeros((4, 2)))
    with pytest.raises(NonFiniteError, match="x must be finite, got"):
        native.step([1.0, np.nan, 3.0])
    with pytest.raises(NonFiniteError, match="x must be finite"):
        native([1.0, np.inf, 3.0])
    with pytest.raises(NonFiniteError, match="x must be finite"):
        native(np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0]]))
    # strict: the hard formula with input limits cannot keep the CBF condition at a state
    # far inside the unsafe set (the same states make UniversalController raise)
    some = acc["states"][:2000]
    x = some[~np.asarray(ctrl.step_fn(jnp.asarray(some)).cbf_satisfied)]
    assert len(x) > 0
    with pytest.raises(InfeasibleError, match="the CBF condition cannot be met at state index"):
        ctrl.step(x[:3], strict=True)
    with pytest.raises(InfeasibleError, match="the CBF condition cannot be met at state index"):
        native.step(x[:3], strict=True)


def test_float_precision_where_well_conditioned(acc):
    """The float build agrees with float64 JAX to 1e-5 (unit roundoff 6e-8 times the few
    dozen operations of a step) where u is not a cancellation of large terms."""
    for ctrl, x in [
        (_acc_controller(acc, gp=False, relaxed=True, saturation="project"), acc["states"][:20000]),
        (_zoo_controller(relaxed=True), _states(acc, "zoo, relaxed, projection")[:20000]),
    ]:
        native = NativeController(ctrl, name="f32", precision="float")
        x = x.astype(np.float32)  # the float build's input; the reference gets the same numbers
        out = native.step(x)
        assert out.u.dtype == np.float32
        ref = ctrl.step_fn(jnp.asarray(x, dtype=jnp.float64))
        u_ref, u = np.asarray(ref.u), out.u.astype(float)
        scale = comparison_scales(ctrl, ref, x)[0]
        # well conditioned: |u| is at least a tenth of the terms it is formed from
        well = np.all(np.abs(u_ref) >= 0.1 * scale, axis=-1) & np.all(np.abs(u_ref) > 0, axis=-1)
        assert np.mean(well) > 0.1  # the ACC states are mostly in P3, where u cancels
        rel = np.abs(u - u_ref)[well] / np.abs(u_ref)[well]
        assert rel.max() <= 1e-5
        for name in ("slack",):
            a, b = np.asarray(getattr(ref, name)), getattr(out, name).astype(float)
            assert np.max(np.abs(a - b)) <= 1e-5 * np.max(np.abs(a))


# ------------------------------------------------------------------------------------------
# the primitive table on its own


def _special_values():
    vals = np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 1.0, -2.5, 3.0])
    a, b = np.meshgrid(vals, vals)
    return np.stack([a.ravel(), b.ravel()], -1)


def test_nan_and_signed_zero_semantics_match_xla():
    def fn(x):
        a, b = x[0], x[1]
        return dict(
            max=jnp.maximum(a, b),
            min=jnp.minimum(a, b),
            sign=jnp.sign(a),
            clamp=lax.clamp(-1.0, a, 1.0),
            lt=a < b,
            ge=a >= b,
            ne=a != b,
            to_int=a.astype(jnp.int32),
            to_bool=a.astype(bool),
            argmax=jnp.argmax(x),
            argmin=jnp.argmin(x),
            reduce_max=jnp.max(x),
            where=jnp.where(a > b, a, b),
            isfinite=jnp.isfinite(a),
        )

    xs = _special_values()
    ex = export_function(fn, 2, "nan_sem")
    native = compile_native(ex, march_native=False)
    got, _ = native.columns(np.ascontiguousarray(xs))
    want = [np.asarray(v) for v in jax.tree_util.tree_leaves(jax.vmap(fn)(jnp.asarray(xs)))]
    for leaf, g, w in zip(ex.leaves, got, want, strict=True):
        if w.dtype.kind == "f":
            same = (g == w) & (np.signbit(g) == np.signbit(w)) | (np.isnan(g) & np.isnan(w))
        else:
            same = g == w
        assert same.all(), (leaf.path, xs[~same], g[~same], w[~same])


def _correctly_rounded_exp(a: np.ndarray, dtype: type) -> np.ndarray:
    """exp rounded to ``dtype`` from a 60-digit mpmath value (the reference)."""
    import mpmath

    with mpmath.workdps(60):
        out = []
        for v in a.astype(float):
            if np.isnan(v):
                out.append(np.nan)
            elif np.isinf(v):
                out.append(np.inf if v > 0 else 0.0)
            else:
                e = mpmath.exp(mpmath.mpf(float(v)))
                big = mpmath.mpf(np.finfo(float).max) * (1 + mpmath.mpf(2) ** -54)
                out.append(float(e) if e < big else np.inf)  # rounds to +inf from there
        with np.errstate(over="ignore"):
            return np.asarray(out).astype(dtype)


@pytest.mark.parametrize("precision", ["double", "float"])
def test_exp_helper_within_one_ulp_of_correct_rounding(precision):
    # the generated exp (a polynomial, so that loops over it vectorise) against mpmath, over
    # the whole range: normal, subnormal and overflowing results, and the special values
    dt = np.float64 if precision == "double" else np.float32
    hi, lo = (712.0, -750.0) if precision == "double" else (90.0, -106.0)
    rng = np.random.default_rng(11)
    a = np.concatenate([
        rng.uniform(lo, hi, 3000), rng.uniform(-1.0, 1.0, 1000), np.linspace(lo, hi, 1001),
        [0.0, -0.0, np.inf, -np.inf, np.nan, 1e-300, -1e-300, np.log(np.finfo(dt).max)],
    ]).astype(dt)  # fmt: skip
    ex = export_function(lambda x: jnp.exp(x), 1, f"exp_{precision}", precision=precision)
    native = compile_native(ex)
    (got,), _ = native.columns(np.ascontiguousarray(a[:, None]))
    got = got.reshape(-1)
    want = _correctly_rounded_exp(a, dt)
    assert np.array_equal(np.isnan(got), np.isnan(want))
    fin = np.isfinite(want) & ~np.isnan(got)
    assert np.array_equal(got[~fin & ~np.isnan(want)], want[~fin & ~np.isnan(want)])  # +inf
    tiny = np.finfo(dt).tiny
    normal = fin & (want >= tiny)
    ulps = np.abs(got[normal].astype(float) - want[normal]) / np.spacing(want[normal]).astype(float)
    assert ulps.max() <= 1.0, a[normal][np.argmax(ulps)]
    # subnormal results: within one unit of the smallest subnormal
    sub = fin & (want < tiny)
    smallest = np.finfo(dt).smallest_subnormal
    assert np.all(np.abs(got[sub].astype(float) - want[sub]) <= smallest)
    assert np.signbit(got).sum() == 0  # never -0


@jax.custom_jvp
def _softclip(x):
    return jnp.tanh(x) * 2.0


_softclip.defjvp(lambda p, t: (_softclip(p[0]), 2.0 * (1 - jnp.tanh(p[0]) ** 2) * t[0]))


@jax.custom_vjp
def _scaled(x):
    return 3.0 * x


_scaled.defvjp(lambda x: (_scaled(x), None), lambda r, t: (3.0 * t,))


def _table_fn(x):
    m = jnp.arange(12.0).reshape(3, 4) * 0.1  # iota
    y = jnp.concatenate([x, x[::-1] * 0.5])  # concatenate, rev, slice
    batch = jnp.stack([m, m * x[0]], 0)  # (2, 3, 4)
    bd = jnp.einsum("bij,bj->bi", batch, jnp.stack([y[:4], y[1:5]]))  # batch dims
    t = jnp.transpose(batch, (2, 0, 1)).reshape(4, 6)
    inner = jax.jit(lambda v: jnp.log1p(jnp.abs(v)) + jnp.expm1(-jnp.abs(v)))(y)  # nested jit
    return dict(
        elementwise=jnp.stack(
            [
                jnp.exp(x[0]),
                jnp.log(jnp.abs(x[1]) + 1.0),
                jnp.sin(x[2]) * jnp.cos(x[0]) + jnp.tan(0.3 * x[1]),
                jnp.arctan2(x[0], x[1]),
                jnp.sqrt(jnp.abs(x[2])) + lax.rsqrt(x[0] ** 2 + 1.0),
                jnp.power(jnp.abs(x[0]) + 0.5, x[1]),
                x[1] ** 3 + (x[0] ** 2 + 1.0) ** -2,
                jnp.sign(x[2]) * jnp.abs(x[1]),
                jnp.clip(x[0], -0.5, 0.5),
                jax.nn.relu(x[1]) + _softclip(x[2]) + _scaled(x[0]),  # custom_jvp, custom_vjp
                jax.nn.sigmoid(x[2]),
            ]
        ),
        dot=m @ y[:4] + bd.sum(),
        reductions=jnp.stack([t.sum(0).max(), t.min(1).sum(), jnp.prod(x)]),
        argmax=jnp.argmax(t, axis=1),
        expand=jnp.expand_dims(inner, 0).squeeze(),
        cond=lax.cond(x[0] > 0, lambda v: v * 2.0, lambda v: v - 1.0, x),
        ints=(x * 10).astype(jnp.int32) % 7 + jnp.int32(3),
        gathered=x[jnp.array([2, 0, 2])],
        scattered=jnp.zeros(5).at[jnp.array([1, 3])].set(x[:2]),
        padded=jnp.pad(x, (1, 2)),
    )


def test_primitive_table_matches_jax():
    x = np.random.default_rng(2).normal(size=(500, 3)) * 2.0
    ex = export_function(_table_fn, 3, "table")
    native = compile_native(ex)
    got, status = native.columns(np.ascontiguousarray(x))
    want = [np.asarray(v) for v in jax.tree_util.tree_leaves(jax.vmap(_table_fn)(jnp.asarray(x)))]
    for leaf, g, w in zip(ex.leaves, got, want, strict=True):
        assert g.dtype == w.dtype, leaf.path
        if w.dtype.kind == "f":
            # elementwise functions and short sums: libm and XLA's math differ by a few ulp
            np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-14, err_msg=leaf.path)
        else:
            np.testing.assert_array_equal(g, w, err_msg=leaf.path)
    assert "double c" in ex.source or "static const" in ex.source  # constants became tables


_MOVES = {
    "broadcast_in_dim": lambda x: lax.broadcast_in_dim(x[:, :1], (2, 4, 1, 3), (1, 2)),
    "broadcast of size-1 axes, int": (
        lambda x: lax.broadcast_in_dim(x[:1].astype(jnp.int32), (2, 4, 3), (0, 2))
    ),
    "pad, bool": lambda x: lax.pad(x > 3.0, False, [(1, 1, 1), (0, -1, 0)]),
    "reshape": lambda x: x.reshape(6, 2),
    "reshape, transposed first": lambda x: lax.reshape(x, (3, 4), dimensions=(1, 0)),
    "squeeze": lambda x: lax.squeeze(x[:1, None], (0, 1)),
    "squeeze to a scalar": lambda x: lax.squeeze(x[0, :1], (0,)),
    "transpose": lambda x: x.T,
    "rev": lambda x: lax.rev(x, (0, 1)),
    "slice with strides": lambda x: lax.slice(x, (1, 0), (4, 3), (2, 2)),
    "concatenate": lambda x: jnp.concatenate([x, 2 * x[:2]], axis=0),
    "split": lambda x: jnp.split(x, [1, 2], axis=1),
    "pad, cropped and interior": lambda x: lax.pad(x, -1.0, [(2, -1, 1), (-1, 3, 2)]),
    "dynamic_slice, clamped": lambda x: lax.dynamic_slice(x, (3, -2), (2, 2)),
    "dynamic_update_slice, clamped": (lambda x: lax.dynamic_update_slice(x, -x[:2, :2], (7, -1))),
}


@pytest.mark.parametrize("case", _MOVES)
def test_data_movement_in_numpy_is_the_primitive(case):
    """Export finds where each element comes from with NumPy versions of the movement
    primitives (no XLA program per shape); each gives exactly what JAX's primitive gives."""
    from safestab.export._primitives import move

    x = np.arange(12.0).reshape(4, 3) + 0.5
    closed = jax.make_jaxpr(_MOVES[case])(x)
    env = {v: c for v, c in zip(closed.jaxpr.constvars, closed.consts, strict=True)}
    env[closed.jaxpr.invars[0]] = x
    read = lambda a: a.val if isinstance(a, jax.extend.core.Literal) else env[a]  # noqa: E731
    moved = 0
    for eqn in closed.jaxpr.eqns:
        args = [np.asarray(read(a)) for a in eqn.invars]
        want = eqn.primitive.bind(*args, **eqn.params)
        want = want if eqn.primitive.multiple_results else [want]
        got = move(eqn.primitive.name, args, eqn.params)
        if got is not None:
            moved += 1
            assert len(got) == len(want)
            for g, w in zip(got, want, strict=True):
                assert g.shape == w.shape and g.dtype == w.dtype
                np.testing.assert_array_equal(g, np.asarray(w))
        for var, val in zip(eqn.outvars, want, strict=True):
            env[var] = np.asarray(val)
    assert moved >= 1  # the case reached the NumPy version
    assert move("gather", [x], {}) is None  # others run through JAX


def test_unsupported_primitive_names_it_and_the_source_line(acc):
    sc = acc["sc"]
    system = sc.system("nominal")

    def h_sorted(x):  # a sort has no C translation
        return jnp.sort(x)[0] + 1.0

    ctrl = ss.UniversalController(system, acc["clf"], ss.CBF(h_sorted, beta=1.0), **acc["p"])
    with pytest.raises(UnsupportedPrimitiveError, match=r"'sort' \(from .*test_export\.py:\d+"):
        export_c(ctrl, "bad")

    def h_scan(x):  # a scan over an array (loops over a count are exported)
        return lax.scan(lambda s, xi: (s + xi, None), 0.0, x)[0]

    ctrl = ss.UniversalController(system, acc["clf"], ss.CBF(h_scan, beta=1.0), **acc["p"])
    with pytest.raises(UnsupportedPrimitiveError, match=r"'scan'.*scanned inputs .* not exported"):
        export_c(ctrl, "bad")


def test_option_errors(acc, tmp_path):
    ctrl = _acc_controller(acc, gp=False, relaxed=True, saturation="project")
    with pytest.raises(ParameterError, match="name must be a C identifier"):
        export_c(ctrl, "9lives")
    with pytest.raises(ParameterError, match="precision must be 'double' or 'float', got 'half'"):
        export_c(ctrl, "ok", precision="half")
    with pytest.raises(DimensionError, match="n_states must be a positive integer"):
        export_function(lambda x: x, 0, "f")
    with pytest.raises(CompilationError, match="no C compiler found"):
        NativeController(ctrl, compiler="/nonexistent/cc")
    with pytest.raises(ParameterError, match="controller must be one of"):
        export_scenario("stress", tmp_path, controller="exact")
    with pytest.raises(ParameterError, match="cases must be >= 1"):
        export_scenario("stress", tmp_path, controller="nominal", cases=0)


# ------------------------------------------------------------------------------------------
# the command line and the C harness


def _run_export_command(out, *extra):
    from typer.testing import CliRunner

    from safestab.cli import app

    return CliRunner().invoke(
        app, ["export", "--scenario", "stress", "--out", str(out), "--cases", "64", *extra]
    )


def _check_written_files(out, gp):
    header = (out / "acc.h").read_text()
    assert "int acc_step(const double x[ACC_N_STATES], double u[ACC_N_OUT], acc_info *info);" in (
        header
    )
    assert "D gap, m" in header and ("GP-robust Lie terms" in header) == gp
    source = (out / "acc.c").read_text()
    assert "malloc" not in source
    # <stdint.h> (type definitions only) comes with the generated exp, which the GP uses
    assert [ln for ln in source.splitlines() if ln.startswith("#include")] == [
        "#include <math.h>",
        *(["#include <stdint.h>"] if gp else []),
        '#include "acc.h"',
    ]


def test_export_command_harness_compiles_and_passes(tmp_path):
    res = _run_export_command(tmp_path / "build", "--controller", "nominal")
    assert res.exit_code == 0, res.output
    assert "acc_harness: 64 states, 0 mismatches" in res.output
    _check_written_files(tmp_path / "build", gp=False)


@pytest.mark.slow
# Q = 60 keeps the test short; on so few samples the fit rightly warns that the targets' offset
# dwarfs their spread (DataWarning); the warning is the GP's concern, tested in test_learning
@pytest.mark.filterwarnings("ignore::safestab.errors.DataWarning")
def test_export_command_gp_controller(tmp_path):
    # the default controller: data collection, GP fit and fast cache as in the study (small Q)
    res = _run_export_command(tmp_path / "build", "--n-samples", "60", "--n-inducing", "8")
    assert res.exit_code == 0, res.output
    assert "acc_harness: 64 states, 0 mismatches" in res.output
    _check_written_files(tmp_path / "build", gp=True)


def test_export_command_bad_scenario(tmp_path):
    res = _run_export_command(tmp_path / "build", "--controller", "nominal", "--precision", "half")
    assert res.exit_code == 2 and "precision must be 'double' or 'float'" in res.output


def test_harness_fails_on_a_mismatch(tmp_path):
    rep = export_scenario("stress", tmp_path, controller="nominal", cases=16, check=True)
    assert rep.passed and "0 mismatches" in rep.harness_output
    harness = tmp_path / "acc_harness.c"
    text = harness.read_text()
    # change the first expected input: the harness must notice and exit 1
    head, rest = text.split("static const double want_0[16] = {\n    ", 1)
    first, tail = rest.split(",", 1)
    changed = head + "static const double want_0[16] = {\n    " + first + " + 1e-6," + tail
    harness.write_text(changed)
    cmd = ["cc", *HARNESS_FLAGS, "acc.c", "acc_harness.c", "-lm", "-o", "h"]
    subprocess.run(cmd, cwd=tmp_path, check=True)
    run = subprocess.run(["./h"], cwd=tmp_path, capture_output=True, text=True)
    assert run.returncode == 1
    assert "state 0: u[0]" in run.stdout and "1 mismatches" in run.stdout
