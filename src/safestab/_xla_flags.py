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
* ``XLA_FLAGS`` already names the flag (the user's choice is kept);
* JAX has already compiled or run something in this process: XLA has read its flags, so the
  flag would reach only child processes (Ray workers, ``safestab run``'s other processes),
  whose results would then differ by rounding from this process's. The import sets
  ``SAFESTAB_XLA_FLAGS=off`` instead, so that the children compile as this process does;
* the installed jaxlib is outside :data:`KNOWN_JAXLIB`: XLA aborts the process on a flag it
  does not know (jaxlib 0.5.0 has none of this name), so a version not checked is left alone.

Child processes inherit the variable, so all of a run's processes compile alike. The
persistent compilation cache and the GP fit cache key their entries on ``XLA_FLAGS``, so
entries made with and without the flag never mix.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping

__all__ = ["ENV_VAR", "FLAG", "KNOWN_JAXLIB", "configure_from_environment", "flags_with_ours"]

#: The environment variable read at import: ``off`` leaves ``XLA_FLAGS`` as it is.
ENV_VAR = "SAFESTAB_XLA_FLAGS"
#: The flag added to ``XLA_FLAGS``.
FLAG = "--xla_cpu_use_fusion_emitters=false"
_NAME = "xla_cpu_use_fusion_emitters"
#: jaxlib versions known to have the flag: from 0.5.3 (0.5.0 has not) to the 0.10 series
#: (checked in 0.5.3, 0.6.0, 0.7.0 and 0.10.2); half-open, as (major, minor, patch).
KNOWN_JAXLIB = ((0, 5, 3), (0, 11, 0))
_OFF = frozenset({"0", "off", "no", "false", "none"})


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
    if environ.get(ENV_VAR, "").strip().lower() in _OFF:
        return None
    current = environ.get("XLA_FLAGS", "")
    if _NAME in current:
        return None
    version = _version_tuple(jaxlib_version)
    if version is None or not KNOWN_JAXLIB[0] <= version < KNOWN_JAXLIB[1]:
        return None
    return f"{current} {FLAG}".strip()


def _jax_started() -> bool:
    try:
        from jax._src import xla_bridge
    except ImportError:  # pragma: no cover - another JAX layout: assume the worst
        return True
    check = getattr(xla_bridge, "backends_are_initialized", None)
    return True if check is None else bool(check())


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
