"""The C export of safety filters (several barriers, a CLF, limits) and of loops and branches.

The exported filter is compared with the JAX step it was traced from: the recorded harness
(compiled with -Wall -Wextra -Werror -pedantic) and the native controller must agree to
rounding, with identical statuses and active sets, on states that reach every phase of the
solver (solved, CLF dropped, CBF rows relaxed).
"""

from __future__ import annotations

import shutil
import subprocess
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from safestab.errors import InfeasibleError, UnsupportedPrimitiveError
from safestab.export import NativeController, compile_native, export_c, export_function
from safestab.export.harness import HARNESS_FLAGS, compare, comparison_scales, write_harness
from safestab.formulas import MultiStatus

from .systems_zoo import disc_filter, disc_states

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")


@pytest.fixture(scope="module")
def case():
    filt = disc_filter()
    x = disc_states()
    out = filt.step_fn(jnp.asarray(x))
    return filt, x, out


def test_the_states_reach_every_phase(case):
    _, _, out = case
    kinds = set(np.asarray(out.formula_status).tolist())
    assert {MultiStatus.SOLVED, MultiStatus.CLF_DROPPED, MultiStatus.CBF_RELAXED} <= kinds


def test_filter_harness_passes(case, tmp_path):
    filt, x, out = case
    ex = export_c(filt, "robot", tmp_path)
    # the solver is one written C function (its loop a loop), called by each phase
    assert ex.source.count("static void ss_dual_qp(") == 1
    assert "while (status < 0 && it < max_iter)" in ex.source
    assert ex.source.count("ss_dual_qp(") >= 3
    write_harness(ex, x, out, tmp_path, scales=comparison_scales(filt, out, x))
    cmd = ["cc", *HARNESS_FLAGS, "robot.c", "robot_harness.c", "-lm", "-o", "h"]
    subprocess.run(cmd, cwd=tmp_path, check=True, capture_output=True)
    run = subprocess.run(["./h"], cwd=tmp_path, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-2000:]
    assert f"{len(x)} states, 0 mismatches" in run.stdout


@pytest.fixture(scope="module")
def native(case):
    return NativeController(case[0], name="robot")


def test_native_filter_equals_jax(case, native):
    filt, x, out = case
    got = native.step(x)
    want = jax.tree_util.tree_leaves(out)
    scales = comparison_scales(filt, out, x)
    assert compare(jax.tree_util.tree_leaves(got), want, scales, 1e-12) == {}
    np.testing.assert_array_equal(got.formula_status, np.asarray(out.formula_status))
    np.testing.assert_array_equal(got.active, np.asarray(out.active))
    # one state through the fast path: the same bits as the batch
    for k in (0, 160, len(x) - 1):
        np.testing.assert_array_equal(native(x[k]), got.u[k])


def test_native_filter_strict_names_the_failing_state(case, native):
    _, x, out = case
    fstat = np.asarray(out.formula_status)
    solved = np.flatnonzero(fstat == MultiStatus.SOLVED)
    native.step(x[solved], strict=True)  # certified states pass
    first = int(np.flatnonzero(fstat != MultiStatus.SOLVED)[0])
    with pytest.raises(InfeasibleError, match=f"state index {first}"):
        native.step(x, strict=True)


def test_float_filter_close_to_double(case):
    filt, x, out = case
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a compiler retried without a flag
        nat = NativeController(filt, name="robot_f", precision="float")
    got = nat.step(x)
    ok = np.asarray(out.formula_status) == MultiStatus.SOLVED
    # float rounding (6e-8) grows by the solver's few dozen operations; |u| <= 1
    np.testing.assert_allclose(got.u[ok], np.asarray(out.u)[ok], rtol=0, atol=1e-5)


# ------------------------------------------------------------------------------------------
# the control-flow and linear-algebra rules, on their own


def _loops(x):
    # a data-dependent while loop (Newton for sqrt), a fori_loop with a static count (a scan)
    # and one with a count from the state (a while), nested; a three-way switch
    target = 1.0 + x[0] ** 2

    def newton(c):
        y, it = c
        return 0.5 * (y + target / y), it + 1

    root, its = lax.while_loop(
        lambda c: (jnp.abs(c[0] * c[0] - target) > 1e-12 * target) & (c[1] < 50),
        newton,
        (target, 0),
    )
    powers = lax.fori_loop(  # sum of x1^i, i < 5 (indices inside loops must be constants)
        0, 5, lambda i, c: (c[0] * x[1], c[1] + c[0]), (jnp.ones(()), jnp.zeros(()))
    )
    n = jnp.clip(jnp.floor(jnp.abs(x[2])), 0, 6).astype(jnp.int32)
    inner = lax.fori_loop(
        0, n, lambda i, s: s + lax.fori_loop(0, 3, lambda j, t: t + i * j * x[0], 0.0), 0.0
    )
    branch = lax.switch(
        jnp.clip(jnp.floor(x[1]), -1, 3).astype(jnp.int32),
        [lambda v: v * 2.0, lambda v: v - 1.0, lambda v: jnp.sin(v)],
        x,
    )
    return dict(root=root, iterations=its, powers=powers, inner=inner, branch=branch)


def _linalg(x):
    A = jnp.outer(jnp.cos(jnp.arange(10.0) * x[0]), jnp.sin(jnp.arange(10.0) + x[1]))
    A = A + jnp.diag(2.0 + x[2] ** 2 + jnp.arange(10.0))
    Q, R = jnp.linalg.qr(A)
    b = jnp.arange(10.0) - x[0]
    upper = jax.scipy.linalg.solve_triangular(R, b, lower=False)
    lower_t = jax.scipy.linalg.solve_triangular(R.T, b, lower=True, trans=1)
    return dict(Q=Q, R=R, upper=upper, lower_t=lower_t)


@pytest.mark.parametrize("fn", [_loops, _linalg], ids=["loops", "linalg"])
def test_control_flow_and_linear_algebra_match_jax(fn):
    x = np.random.default_rng(5).normal(size=(200, 3)) * 2.0
    ex = export_function(fn, 3, fn.__name__.strip("_"))
    got, status = compile_native(ex).columns(np.ascontiguousarray(x))
    assert status == 0
    want = [np.asarray(v) for v in jax.tree_util.tree_leaves(jax.vmap(fn)(jnp.asarray(x)))]
    for leaf, g, w in zip(ex.leaves, got, want, strict=True):
        if w.dtype.kind == "f":
            scale = np.max(np.abs(w))  # QR and the solves: rounding relative to the matrix
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-12 * scale, err_msg=leaf.path)
        else:
            np.testing.assert_array_equal(g, w, err_msg=leaf.path)


def test_scan_over_arrays_is_named_as_unsupported():
    def fn(x):
        return lax.scan(lambda c, xi: (c + xi, c), 0.0, x)[1]

    with pytest.raises(UnsupportedPrimitiveError, match=r"'scan'.*scanned inputs"):
        export_function(fn, 3, "scan")
