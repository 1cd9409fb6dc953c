"""The filter's solver on the CPU: one custom call into its written C, the XLA loop as fallback.

Oracles: the lowered program's text (which kernel runs), the 60-digit reference of
``tests/test_dual_active_set.py`` for the XLA loop (the rest of the suite runs the custom
call, the default), and a child process whose compilers do not exist (the fallback's warning
and its answers against the custom call's).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from safestab.export._dual_qp_ffi import ENV, TARGET, enabled, ensure
from safestab.formulas._dual_active_set import solve_dual

from .test_dual_active_set import review_cases

G = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
R = np.array([-1.0, -1.0, -3.0])


def _w(G):
    return solve_dual(G, R, np.zeros(2), np.ones(3, bool), 20).w


def test_the_cpu_step_calls_the_written_solver_and_the_switch_turns_it_off(monkeypatch):
    text = jax.jit(_w).lower(G).as_text()
    assert f"@{TARGET}" in text and "stablehlo.while" not in text
    monkeypatch.setenv(ENV, "off")
    text = jax.jit(lambda g: _w(g)).lower(G).as_text()  # a new function: lowered afresh
    assert f"@{TARGET}" not in text and "stablehlo.while" in text


def test_the_custom_call_batches_and_agrees_with_the_xla_loop(monkeypatch):
    rng = np.random.default_rng(1)
    Gs = rng.normal(size=(64, 7, 3))
    rs = rng.normal(size=(64, 7))

    def solve(G, r):
        return solve_dual(G, r, np.zeros(3), np.ones(7, bool), 50)

    native = jax.jit(jax.vmap(solve))(Gs, rs)
    one = [jax.jit(solve)(Gs[i], rs[i]) for i in (0, 31)]
    monkeypatch.setenv(ENV, "off")
    loop = jax.jit(jax.vmap(lambda G, r: solve(G, r)))(Gs, rs)
    np.testing.assert_array_equal(native.status, loop.status)
    np.testing.assert_array_equal(native.active, loop.active)
    np.testing.assert_allclose(native.w, loop.w, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(native.multipliers, loop.multipliers, rtol=1e-10, atol=1e-12)
    for i, sol in zip((0, 31), one, strict=True):  # one problem: the batch's bits
        np.testing.assert_array_equal(sol.w, native.w[i])


def test_the_xla_loop_against_the_50_digit_reference(monkeypatch):
    """The fallback and other backends' solver, judged as the default one is."""
    monkeypatch.setenv(ENV, "off")
    jax.clear_caches()  # programs compiled with the custom call are not reused
    try:
        counts, faults = review_cases(240, seed=3)
    finally:
        jax.clear_caches()
    assert faults == []
    assert sum(counts.values()) == 240


_CHILD = """
import json, warnings
import numpy as np
import safestab
from safestab.formulas._dual_active_set import solve_dual
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    sol = solve_dual(np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]), np.array([-1.0, -1.0, -3.0]),
                     np.zeros(2), np.ones(3, bool), 20)
print(json.dumps({"w": np.asarray(sol.w).tolist(), "status": int(sol.status),
                  "warnings": [str(w.message) for w in caught]}))
"""


def test_without_compilers_a_warning_names_why_and_the_xla_loop_answers(tmp_path):
    # no compiler on the PATH, and none where CC and CXX point
    env = {**os.environ, "CC": str(tmp_path / "no-cc"), "CXX": str(tmp_path / "no-cxx"),
           "PATH": str(tmp_path), "SAFESTAB_COMPILATION_CACHE": str(tmp_path / "c")}  # fmt: skip
    env.pop(ENV, None)
    run = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True,
                         text=True, check=True)  # fmt: skip
    got = json.loads(run.stdout.strip().splitlines()[-1])
    (message,) = [m for m in got["warnings"] if "native solver" in m]
    assert "could not be built" in message and "no-cc" in message
    assert got["status"] == 0
    np.testing.assert_array_equal(got["w"], np.asarray(_w(G)))


@pytest.mark.parametrize("value", ["off", "0", "false", "NO"])
def test_the_switch_reads_its_values(monkeypatch, value):
    monkeypatch.setenv(ENV, value)
    assert not enabled() and ensure() is None
    monkeypatch.setenv(ENV, "on")
    assert enabled()
