"""JAX's persistent compilation cache, on by default in a user cache folder.

Most of the time of a first run is compilation, not arithmetic (a preset's closed loops, GP
fits and Monte Carlo batches each compile in seconds and run in fractions of one). JAX can
keep compiled programs on disk and reuse them in later processes; safestab turns that on when
it is imported, in ``$XDG_CACHE_HOME/safestab/jax`` (``~/.cache/safestab/jax`` when the
variable is unset), so that a second run of the same study skips the compilations of the
first.

* ``SAFESTAB_COMPILATION_CACHE=off`` (or ``0``, ``no``, ``false``) before the import turns it
  off; ``SAFESTAB_COMPILATION_CACHE=/some/folder`` puts it elsewhere;
* ``safestab --no-compilation-cache <command>`` turns it off for one command;
* :func:`disable_compilation_cache` and :func:`enable_compilation_cache` do the same from
  Python (before the first compilation);
* a folder the user already gave JAX (``jax_compilation_cache_dir``) is left alone.

The folder only holds compiled code keyed by the program, JAX's version and the machine, at
most :data:`MAX_BYTES` (the least recently used programs go first): it is safe to delete at any
time (the next run compiles again), and nothing else reads it.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = [
    "ENV_VAR",
    "OFF_VALUES",
    "cache_root",
    "compilation_cache_dir",
    "default_cache_dir",
    "disable_compilation_cache",
    "enable_compilation_cache",
]

#: The environment variable read at import: ``off`` (``0``, ``no``, ``false``) or a folder.
ENV_VAR = "SAFESTAB_COMPILATION_CACHE"
#: Compilations shorter than this are not stored. 0: every program is stored. A study compiles
#: about 140 programs of 10 to 30 ms each besides its few large ones; read back they save
#: about 3 s of a second obstacle run (21.4 s with 0.1 against 18.2 s with 0) and 1.7 s of a
#: paper run, and writing them costs a first run 1.5 to 4 s (2 CPUs, 2026-11-27).
MIN_COMPILE_SECONDS = 0.0
#: Size limit of the folder: beyond it JAX removes the least recently used programs.
MAX_BYTES = 2 * 2**30
#: Values of a cache's environment variable that turn it off (lower case; also the fit cache's).
OFF_VALUES = frozenset({"0", "off", "no", "false", "none"})


def cache_root() -> Path:
    """``$XDG_CACHE_HOME/safestab``, or ``~/.cache/safestab``: the folder of safestab's caches."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "safestab"


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/safestab/jax``, or ``~/.cache/safestab/jax``."""
    return cache_root() / "jax"


def enable_compilation_cache(path: str | Path | None = None) -> Path | None:
    """Keep JAX's compiled programs in ``path`` (default :func:`default_cache_dir`).

    Returns
    -------
    Path or None
        The folder in use, or None if it cannot be created (the cache is an optimisation:
        without it everything works, only slower to start).
    """
    folder = Path(path).expanduser() if path is not None else default_cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    jax.config.update("jax_enable_compilation_cache", True)
    return folder


def disable_compilation_cache() -> None:
    """Stop reading and writing the persistent cache (call before the first compilation)."""
    jax.config.update("jax_enable_compilation_cache", False)


def compilation_cache_dir() -> Path | None:
    """The folder of the persistent cache, or None when it is off."""
    folder = jax.config.jax_compilation_cache_dir
    if not folder or not jax.config.jax_enable_compilation_cache:
        return None
    return Path(folder)


def configure_from_environment() -> Path | None:
    """What the import does: turn the cache on, unless told otherwise.

    The folder is ``$SAFESTAB_COMPILATION_CACHE`` or the default; the cache stays off when that
    variable says so, and a folder the user already gave JAX is kept.
    """
    value = os.environ.get(ENV_VAR, "").strip()
    if value.lower() in OFF_VALUES:
        disable_compilation_cache()
        return None
    if jax.config.jax_compilation_cache_dir:  # the user's own choice
        return compilation_cache_dir()
    return enable_compilation_cache(value or None)
