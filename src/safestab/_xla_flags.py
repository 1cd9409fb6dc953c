"""The one XLA flag safestab sets at import: XLA's older fusion emitters on CPU.

Most of a first run's time, and of a cold test run's, is XLA compiling programs on the CPU.
XLA's CPU compiler now generates each fusion's code with its newer emitters (the default of
jaxlib 0.10), which take 1.5 to 2.3 times as long to compile safestab's solver as the older
ones (``--xla_cpu_use_fusion_emitters=false``), for code that runs about as fast and gives
every output of the solver bit for bit the same (``python benchmarks/xla_flags.py``, the
"XLA's fusion emitters" table in ``docs/performance.md``). The two emitters differ in the
last bits of a few operations (``arctan``; a multiply-add that one fuses and the other does
not), which moves the studies' results by rounding.

So the import adds ``--xla_cpu_use_fusion_emitters=false`` to the ``XLA_FLAGS`` environment
variable, which XLA reads once, when JAX first compiles. It does nothing when:

* ``SAFESTAB_XLA_FLAGS`` is ``off`` (``0``, ``no``, ``false``, ``none``) before the import;
* ``XLA_FLAGS`` already names the flag, or gives a ``--flagfile`` (the user's choice is
  kept);
* JAX has already started in this process (compiled, run or listed devices): XLA has read
  its flags, so the flag would reach only child processes (Ray workers, ``safestab run``'s
  other processes), whose results would then differ by rounding from this process's. The
  import sets ``SAFESTAB_XLA_FLAGS=off`` instead, so that the children compile as this
  process does;
* the installed jaxlib is outside :data:`KNOWN_JAXLIB`: XLA aborts the process on a flag it
  does not know (jaxlib 0.5.0 has none of this name), so a version not checked is left alone.

Child processes inherit the variable, so all of a run's processes compile alike. Ray
workers reached through a cluster's address do not inherit this process's environment:
:func:`~safestab.montecarlo.start_ray` gives them ``SAFESTAB_XLA_FLAGS=off`` when this process
runs without the flag. Anything else in the process that reads ``XLA_FLAGS`` sees the flag
too (another framework's XLA; a subprocess with another jaxlib, which may not know it): set
``SAFESTAB_XLA_FLAGS=off`` for such a process. The persistent compilation cache and the GP
fit cache key their entries on ``XLA_FLAGS``, so entries made with and without the flag
never mix.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping

from ._cache import OFF_VALUES

__all__ = [
    "ENV_VAR",
    "FLAG",
    "KNOWN_JAXLIB",
    "configure_from_environment",
    "flags_with_ours",
    "xla_flag_environment",
]

#: The environment variable read at import: ``off`` leaves ``XLA_FLAGS`` as it is.
ENV_VAR = "SAFESTAB_XLA_FLAGS"
#: The flag added to ``XLA_FLAGS``.
FLAG = "--xla_cpu_use_fusion_emitters=false"
_NAME = "xla_cpu_use_fusion_emitters"
#: jaxlib versions known to have the flag, half-open, as (major, minor, patch): from 0.5.3
#: (0.5.0 has not) to 0.10.2, the last checked (0.5.3, 0.6.0, 0.7.0 and 0.10.2 by the names in
#: their XLA library, 0.10.2 by use). XLA may drop the flag in any later release, patch
#: releases included, so each newer one is left alone until it has been checked.
KNOWN_JAXLIB = ((0, 5, 3), (0, 10, 3))


def _version_tuple(text: str) -> tuple[int, ...] | None:
    match = re.match(r"(\d+)\.(\d+)\.(\d+)", text)
    return tuple(int(g) for g in match.groups()) if match else None


def flags_with_ours(environ: Mapping[str, str], jaxlib_version: str) -> str | None:
    """The ``XLA_FLAGS`` value a fresh process sets, or None to leave it as it is.

    Parameters
    ----------
    environ : mapping
        The environment (``SAFESTAB_XLA_FLAGS``, ``XLA_FLAGS``); only read.
    jaxlib_version : str
        The installed jaxlib's version, e.g. ``"0.10.2"``.
    """
    if environ.get(ENV_VAR, "").strip().lower() in OFF_VALUES:
        return None
    current = environ.get("XLA_FLAGS", "")
    if _NAME in current or "--flagfile" in current:  # a flag file may name it: not read here
        return None
    version = _version_tuple(jaxlib_version)
    if version is None or not KNOWN_JAXLIB[0] <= version < KNOWN_JAXLIB[1]:
        return None
    return f"{current} {FLAG}".strip()


def xla_flag_environment(environ: Mapping[str, str]) -> dict[str, str]:
    """What a process that does not inherit ``environ`` needs to compile as this one does.

    ``{"SAFESTAB_XLA_FLAGS": "off"}`` where ``XLA_FLAGS`` lacks :data:`FLAG` (safestab's
    import did not add it, or the user chose otherwise); otherwise nothing, as that
    process's own import adds the flag (given the same jaxlib).
    """
    return {} if FLAG in environ.get("XLA_FLAGS", "").split() else {ENV_VAR: "off"}


def _jax_started() -> bool:
    """Whether JAX has started its backends (compiled, run or listed devices)."""
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except Exception:  # pragma: no cover - another JAX layout: assume the worst
        return True


def configure_from_environment() -> str | None:
    """What the import does: add :data:`FLAG` to ``XLA_FLAGS`` unless told otherwise.

    Where JAX has already run something, the flag would reach only child processes, which
    would then round otherwise than this one: ``SAFESTAB_XLA_FLAGS=off`` is set instead, so
    that the children leave ``XLA_FLAGS`` as this process has it.

    Returns
    -------
    str or None
        The new ``XLA_FLAGS``, or None where it was left alone.
    """
    import jaxlib

    value = flags_with_ours(os.environ, getattr(jaxlib, "__version__", ""))
    if value is None:
        return None
    if _jax_started():
        os.environ[ENV_VAR] = "off"  # too late here: the children compile as this process
        return None
    os.environ["XLA_FLAGS"] = value
    return value
