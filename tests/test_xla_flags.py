"""The XLA flag set at import (safestab/_xla_flags.py): when it is added, when it is not, and
that it reaches XLA. The process-wide cases each run in a fresh interpreter."""

from __future__ import annotations

import os
import subprocess
import sys

import jaxlib
import pytest

from safestab._xla_flags import ENV_VAR, FLAG, KNOWN_JAXLIB, flags_with_ours, xla_flag_environment

KNOWN = ".".join(map(str, KNOWN_JAXLIB[0]))
THIS_JAXLIB_KNOWN = flags_with_ours({}, jaxlib.__version__) is not None


def test_added_to_what_the_user_set():
    assert flags_with_ours({}, KNOWN) == FLAG
    user = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert flags_with_ours(user, KNOWN) == f"--xla_force_host_platform_device_count=2 {FLAG}"
    assert flags_with_ours({ENV_VAR: "on"}, KNOWN) == FLAG  # only off values turn it off


@pytest.mark.parametrize("off", ["off", "0", "no", "false", "None", " OFF "])
def test_left_alone_when_turned_off(off):
    assert flags_with_ours({ENV_VAR: off}, KNOWN) is None


def test_left_alone_when_the_user_chose():
    user = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}
    assert flags_with_ours(user, KNOWN) is None
    assert flags_with_ours({"XLA_FLAGS": "--flagfile=/etc/xla.flags"}, KNOWN) is None


@pytest.mark.parametrize(
    ("version", "added"),
    [("0.5.0", False), ("0.5.2", False), ("0.5.3", True), ("0.10.2", True), ("0.10.3", False),
     ("0.11.0", False), ("1.0.0", False), ("0.9.0.dev20260101", True), ("unknown", False)],
)  # fmt: skip
def test_only_on_a_jaxlib_known_to_have_the_flag(version, added):
    # XLA aborts the whole process on a flag it does not know; a later release may drop it
    assert (flags_with_ours({}, version) is not None) is added


def test_processes_that_do_not_inherit_the_environment_are_told_what_to_do():
    assert xla_flag_environment({"XLA_FLAGS": f"--xla_dump_to=x {FLAG}"}) == {}
    for flags in ("", "--xla_cpu_use_fusion_emitters=true", "--xla_dump_to=x"):
        assert xla_flag_environment({"XLA_FLAGS": flags}) == {ENV_VAR: "off"}
    assert xla_flag_environment({}) == {ENV_VAR: "off"}


# arctan is one of the operations whose last bits differ between XLA's two CPU emitters (16
# of these 100,000 values with jaxlib 0.10.2, all with |x| < 0.5)
PROBE = (
    "import os, sys; import safestab, jax.numpy as jnp, numpy as np; "
    "x = np.random.default_rng(0).normal(size=100_000) * 5; "
    "sys.stdout.write(os.environ.get('XLA_FLAGS', '') + '|' + "
    "os.environ.get('SAFESTAB_XLA_FLAGS', '') + '|' + "
    "np.asarray(jnp.arctan(jnp.asarray(x))).tobytes().hex())"
)


def _probe(code: str = PROBE, **env: str) -> tuple[str, str, str]:
    full = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", ENV_VAR)}
    full.update(env, SAFESTAB_COMPILATION_CACHE="off")
    proc = subprocess.run(
        [sys.executable, "-c", code], env=full, capture_output=True, text=True, check=True
    )
    flags, ours, bits = proc.stdout.split("|")
    return flags, ours, bits


@pytest.mark.skipif(not THIS_JAXLIB_KNOWN, reason="this jaxlib is left alone")
def test_the_import_sets_the_flag_and_xla_uses_it():
    flags, _, ours = _probe()
    assert flags == FLAG
    explicit_flags, _, explicit = _probe(XLA_FLAGS=FLAG)  # the user's own, kept, not doubled
    assert explicit_flags == FLAG and ours == explicit
    off_flags, _, off = _probe(**{ENV_VAR: "off"})
    assert off_flags == ""
    _, _, newer = _probe(XLA_FLAGS="--xla_cpu_use_fusion_emitters=true")
    if newer == ours:
        pytest.skip("the two emitters round this probe alike on this machine")
    assert off == newer  # off: XLA's default emitters
    assert off != ours  # the setting reaches XLA: another emitter, other last bits


@pytest.mark.skipif(not THIS_JAXLIB_KNOWN, reason="this jaxlib is left alone")
def test_after_jax_has_run_something_the_children_are_told_to_leave_it_out():
    code = "import jax.numpy as jnp; jnp.zeros(3).block_until_ready(); " + PROBE
    flags, told, bits = _probe(code)
    assert flags == "" and told == "off"  # children compile as this process does
    _, _, off = _probe(**{ENV_VAR: "off"})
    assert bits == off
