"""The filter's exported C step called from JAX (an XLA custom call) against the JAX step.

Values: the same inputs to rounding (1e-12), identical statuses, active sets and flags, on
states that reach every phase of the solver (solved, CLF dropped, CBF rows relaxed), one
state, a batch, inside a user's jit and under vmap. Derivatives: the custom call's tangent
(the optimum's on its final active set) against the JAX step's jvp and against central
finite differences of the C step itself.
"""

from __future__ import annotations

import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.errors import CompilationError, DimensionError, ParameterError
from safestab.export import export_c, jax_function, native_step
from safestab.formulas import MultiStatus

from .systems_zoo import DISC_GOAL, disc_clf, disc_filter, disc_robot, disc_states

pytestmark = pytest.mark.skipif(
    shutil.which("cc") is None or shutil.which("c++") is None, reason="no C/C++ compiler"
)


def _soft_filter() -> ss.SafetyFilter:
    """A soft CLF, a weight H, phi and varphi, one-sided limits."""
    system, cbfs = disc_robot()
    return ss.SafetyFilter(
        system, cbfs, clfs=disc_clf(), u_nom=lambda x: 0.3 * (DISC_GOAL - x), slack_weight=3.0,
        H=np.array([[2.0, 0.3], [0.3, 1.0]]), phi=0.5, varphi=0.2, rho=0.1, u_max=1.2,
    )  # fmt: skip


@pytest.fixture(scope="module", params=["hard", "soft"])
def case(request):
    filt = disc_filter() if request.param == "hard" else _soft_filter()
    return request.param, filt, native_step(filt, name=f"ns_{request.param}")


def _assert_same(got, ref):
    for field in ("status", "formula_status", "active", "cbf_satisfied", "clf_satisfied"):
        np.testing.assert_array_equal(np.asarray(getattr(got, field)), getattr(ref, field), field)
    for field in ("u", "multipliers", "slack"):
        g, r = np.asarray(getattr(got, field)), np.asarray(getattr(ref, field))
        np.testing.assert_array_equal(np.isnan(g), np.isnan(r))
        scale = np.maximum(1.0, np.abs(np.nan_to_num(r)))
        assert np.nanmax(np.abs(g - r) / scale, initial=0.0) <= 1e-12, field


def test_the_states_reach_every_phase():
    out = disc_filter().step_fn(jnp.asarray(disc_states()))
    seen = set(np.asarray(out.formula_status).tolist())
    assert {MultiStatus.SOLVED, MultiStatus.CLF_DROPPED, MultiStatus.CBF_RELAXED} <= seen


def test_values_equal_the_jax_step(case):
    _, filt, step = case
    x = jnp.asarray(disc_states())
    ref = filt.step_fn(x)
    _assert_same(jax.jit(step)(x), ref)  # a batch: one loop in C
    _assert_same(jax.jit(jax.vmap(step))(x), ref)  # a user's vmap
    _assert_same(step(x.reshape(20, 11, 2)), jax.tree_util.tree_map(
        lambda v: v.reshape((20, 11) + v.shape[1:]), ref))  # fmt: skip
    for i in (0, 160, 200):  # one state, inside a user's jit
        one = jax.jit(lambda s: step(s))(x[i])
        _assert_same(one, jax.tree_util.tree_map(lambda v, i=i: v[i], ref))


def test_derivative_equals_the_jax_steps_jvp(case):
    kind, filt, step = case
    x = jnp.asarray(disc_states())
    dx = jnp.asarray(np.random.default_rng(1).normal(size=x.shape))
    ref_out, ref = jax.jvp(filt.step_fn, (x,), (dx,))
    _, got = jax.jit(lambda x, dx: jax.jvp(step, (x,), (dx,)))(x, dx)
    fs = np.asarray(ref_out.formula_status)
    solved = np.isin(fs, [MultiStatus.SOLVED, MultiStatus.CLF_DROPPED, MultiStatus.CBF_RELAXED])
    solved &= np.all(np.isfinite(np.asarray(ref_out.u)), -1)  # u is NaN where a step failed
    relaxed = fs == MultiStatus.CBF_RELAXED
    assert np.any(solved & relaxed) and np.any(solved & ~relaxed)
    # the last-resort phase weighs its slacks by 1e8: its KKT system is that much worse
    # conditioned, and the two ways of solving it (an SVD of the normalised rows in the JAX
    # step, an LU of the KKT matrix here) agree to about 1e-5 of the tangent's size
    for field in ("u", "multipliers", "slack"):
        g, r = np.asarray(getattr(got, field)), np.asarray(getattr(ref, field))
        for sel, tol in ((solved & ~relaxed, 1e-10), (solved & relaxed, 1e-4)):
            err = np.abs(g[sel] - r[sel]) / np.maximum(1.0, np.abs(r[sel]).max(-1, keepdims=True))
            assert np.max(err, initial=0.0) <= tol, (kind, field, tol)
    # reverse mode under vmap
    g = jax.jit(jax.vmap(jax.grad(lambda s: jnp.sum(step(s).u))))(x)
    g0 = jax.vmap(jax.grad(lambda s: jnp.sum(filt.step_fn(s).u)))(x)
    for sel, tol in ((solved & ~relaxed, 1e-10), (solved & relaxed, 1e-4)):
        np.testing.assert_allclose(np.asarray(g)[sel], np.asarray(g0)[sel], rtol=tol, atol=tol)


def test_derivative_equals_finite_differences_of_the_c_step(case):
    _, filt, step = case
    x = disc_states()
    out = filt.step_fn(jnp.asarray(x))
    # interior points of an active set: the set is the same at x +- h in both directions
    h = 1e-6
    call = jax.jit(step)
    checked = 0
    for i in range(0, len(x), 7):
        if int(out.formula_status[i]) == MultiStatus.UNCERTIFIED or np.any(np.isnan(out.u[i])):
            continue
        jac = np.asarray(jax.jacfwd(lambda s: step(s).u)(jnp.asarray(x[i])))
        for j in range(2):
            e = np.zeros(2)
            e[j] = h
            hi, lo = call(jnp.asarray(x[i] + e)), call(jnp.asarray(x[i] - e))
            if not (np.array_equal(hi.active, out.active[i])
                    and np.array_equal(lo.active, out.active[i])):  # fmt: skip
                continue
            fd = (np.asarray(hi.u) - np.asarray(lo.u)) / (2 * h)
            np.testing.assert_allclose(jac[:, j], fd, rtol=1e-5, atol=1e-6)
            checked += 1
    assert checked >= 20


def test_bad_arguments_are_named():
    filt = disc_filter()
    with pytest.raises(ParameterError, match="SafetyFilter"):
        native_step(object())
    with pytest.raises(ParameterError, match="double precision"):
        jax_function(export_c(filt, "flt", precision="float"))
    step = native_step(filt, name="ns_dims")
    with pytest.raises(DimensionError, match=r"\(\.\.\., 2\)"):
        step(jnp.zeros(3))


def test_a_missing_compiler_raises_or_falls_back():
    filt = disc_filter()
    with pytest.raises(CompilationError, match="no C\\+\\+ compiler"):
        native_step(filt, name="ns_nocxx", cxx_compiler="no-such-compiler++")
    with pytest.warns(RuntimeWarning, match="falls back on the JAX step"):
        step = native_step(filt, name="ns_nocxx", cxx_compiler="no-such-compiler++", fallback=True)
    x = jnp.asarray(disc_states()[:5])
    np.testing.assert_array_equal(step(x).u, filt.step_fn(x).u)


#: A child process: builds ``native_step`` of a three-disc filter with the compilers and cache
#: of its environment, and saves its outputs on 220 states.
_CHILD = """
import sys, time
import jax, jax.numpy as jnp, numpy as np
import safestab as ss
from safestab.export import native_step
o = np.array([[0.0, 0.0], [3.0, 0.0], [1.5, 2.0]])
sysm = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2, name="robot")
cbfs = [ss.CBF(lambda x, c=c: jnp.sum((x - c) ** 2) - 1.0, beta=1.0) for c in o]
clf = ss.CLF(lambda x: jnp.sum((x - jnp.array([6.0, 0.0])) ** 2), lam=0.2)
filt = ss.SafetyFilter(sysm, cbfs, clfs=clf, u_nom=lambda x: 0.3 * (jnp.array([6.0, 0.0]) - x),
                       u_min=-1.0, u_max=1.0)
t = time.perf_counter()
step = native_step(filt, name="ns_cached")
print("build", time.perf_counter() - t)
x = np.random.default_rng(3).uniform([-2.5, -2.5], [8.0, 4.0], (220, 2))
out = jax.jit(step)(jnp.asarray(x))
np.savez(sys.argv[1], u=out.u, multipliers=out.multipliers, active=out.active,
         status=out.status, formula_status=out.formula_status)
"""


def test_a_later_process_loads_the_build_from_the_disk_cache(tmp_path):
    import os
    import subprocess
    import sys

    log = tmp_path / "compiler-calls.log"
    tools = {}
    for var, real in (("CC", shutil.which("cc")), ("CXX", shutil.which("c++"))):
        wrapper = tmp_path / f"logged-{var.lower()}"
        wrapper.write_text(f'#!/bin/sh\necho "{var} $*" >> "{log}"\nexec "{real}" "$@"\n')
        wrapper.chmod(0o755)
        tools[var] = str(wrapper)
    cache = tmp_path / "cache"
    script = tmp_path / "child.py"
    script.write_text(_CHILD)

    def run(name, cache_setting):
        env = {**os.environ, **tools, "SAFESTAB_COMPILATION_CACHE": cache_setting}
        before = log.read_text().count("\n") if log.exists() else 0
        proc = subprocess.run([sys.executable, str(script), str(tmp_path / name)], env=env,
                              capture_output=True, text=True, timeout=600)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-3000:]
        calls = (log.read_text().count("\n") if log.exists() else 0) - before
        return dict(np.load(tmp_path / f"{name}.npz")), calls

    first, calls_first = run("first", str(cache))
    stored = sorted((cache / "native").glob("*.so"))
    assert len(stored) == 1 and calls_first >= 2  # the C step, the C++ handler (and probes)
    second, calls_second = run("second", str(cache))
    assert calls_second == 0  # loaded: neither compiler ran
    for key, value in first.items():  # the same object: the same bits
        np.testing.assert_array_equal(second[key], value, key)
    # an object that cannot be loaded is built again and replaced
    stored[0].write_bytes(b"not a shared object")
    third, calls_third = run("third", str(cache))
    assert calls_third >= 2 and stored[0].stat().st_size > 1000
    np.testing.assert_array_equal(third["u"], first["u"])
    # off: built in a temporary folder, nothing stored
    _, calls_off = run("off", "off")
    assert calls_off >= 2 and sorted((cache / "native").glob("*.so")) == stored
    assert not list((cache / "native").glob("*-writing"))
