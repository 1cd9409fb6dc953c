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
most about :data:`MAX_BYTES`: when the import finds it larger, the least recently used
programs go first (:func:`prune_compilation_cache`). It is safe to delete at any time (the
next run compiles again), and nothing else reads it.

Several processes may share the folder (``safestab run`` runs studies of different kinds in
parallel processes, Ray workers on one machine): JAX writes a program in place, so another
process could read it half written (JAX then warns and compiles again) or two could write
one at once. safestab writes each program to a temporary file and renames it into place
(:func:`install_atomic_writes`), so a reader finds a program whole or not at all.

JAX's own size limit (``jax_compilation_cache_max_size``) is not used: with it set, JAX lists
and reads the whole folder, under a file lock, before every program it writes, which costs
0.16 s per program with 6,400 programs stored (20 new programs in 3.7 s against 0.56 s
without the limit, 2 CPUs), so a first run slowed as the folder grew.
"""

from __future__ import annotations

import os
import time
import uuid
from pathlib import Path

import jax

__all__ = [
    "ENV_VAR",
    "OFF_VALUES",
    "cache_root",
    "child_cache_environment",
    "compilation_cache_dir",
    "default_cache_dir",
    "disable_compilation_cache",
    "enable_compilation_cache",
    "install_atomic_writes",
    "prune_compilation_cache",
]

#: The environment variable read at import: ``off`` (``0``, ``no``, ``false``) or a folder.
ENV_VAR = "SAFESTAB_COMPILATION_CACHE"
#: Compilations shorter than this are not stored. 0: every program is stored. A study compiles
#: about 140 programs of 10 to 30 ms each besides its few large ones; read back they save
#: about 3 s of a second obstacle run (21.4 s with 0.1 against 18.2 s with 0) and 1.7 s of a
#: paper run, and writing them costs a first run 1.5 to 4 s (2 CPUs).
MIN_COMPILE_SECONDS = 0.0
#: Size limit of the folder: beyond it the import removes the least recently used programs.
MAX_BYTES = 2 * 2**30
#: Pruning removes programs until the folder holds at most this share of :data:`MAX_BYTES`.
PRUNE_TO = 0.8
#: JAX's names of a stored program and of its access-time record (written only under JAX's
#: own size limit, which safestab does not set).
_PROGRAM, _ATIME = "-cache", "-atime"
#: Suffix of a program being written (:func:`install_atomic_writes`); pruning removes those
#: older than :data:`STALE_WRITE_SECONDS` (a process that died while writing).
_WRITING = "-writing"
STALE_WRITE_SECONDS = 3600.0
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
    jax.config.update("jax_compilation_cache_max_size", -1)  # no scan per write: see above
    jax.config.update("jax_enable_compilation_cache", True)
    install_atomic_writes()
    prune_compilation_cache(folder)
    return folder


def install_atomic_writes() -> bool:
    """Make JAX write each stored program whole: to a temporary file, then renamed.

    Applies to JAX's file cache without a size limit on a local folder (as safestab sets it);
    otherwise JAX's own write runs. Idempotent. The temporary file is not synced to disk
    before the rename: after a crash of the machine a program may be cut short, which JAX
    reports with a warning and compiles again.

    Returns
    -------
    bool
        Whether the writes are atomic now (False if this JAX has no such cache class).
    """
    try:
        from jax._src import lru_cache
    except ImportError:  # pragma: no cover - another JAX layout: JAX's own writes stay
        return False
    cls = getattr(lru_cache, "LRUCache", None)
    local = getattr(lru_cache, "_is_local_filesystem", None)
    if cls is None or local is None or not hasattr(cls, "put"):
        return False  # pragma: no cover
    if getattr(cls.put, "_safestab_atomic", False):
        return True
    original = cls.put

    # not _io.write_all: it fsyncs each file and its folder (hundreds of programs on a first
    # run) and names its temporary after the target (JAX's key is already long)
    def put(self: object, key: str, value: bytes) -> None:
        path = getattr(self, "path", None)
        plain = path is not None and local(str(path)) and "://" not in str(path)
        if getattr(self, "eviction_enabled", True) or not plain:
            return original(self, key, value)
        if not key:
            raise ValueError("key cannot be empty")
        final = Path(str(path)) / f"{key}{_PROGRAM}"
        if final.exists():  # as JAX: an entry, once written, is kept
            return None
        # a short name (JAX's key is long already): unique per writer, any process
        temporary = final.with_name(f".{uuid.uuid4().hex[:20]}{_WRITING}")
        try:
            temporary.write_bytes(value)
            os.replace(temporary, final)
        finally:
            temporary.unlink(missing_ok=True)  # only if the rename did not happen
        return None

    put._safestab_atomic = True  # type: ignore[attr-defined]
    cls.put = put
    return True


def prune_compilation_cache(folder: str | Path, max_bytes: int = MAX_BYTES) -> int:
    """Keep ``folder`` under ``max_bytes``: remove the least recently used programs.

    One listing of the folder (about 15 ms for 6,400 programs). Only when their total size
    exceeds ``max_bytes`` are programs removed, oldest access (or modification) time first,
    until at most :data:`PRUNE_TO` of ``max_bytes`` remains. A file that cannot be listed or
    removed (another process, permissions) is skipped: the cache is an optimisation.

    Returns
    -------
    int
        How many programs were removed.
    """
    folder = Path(folder)
    found: list[tuple[float, str, int]] = []
    total = 0
    stale = time.time() - STALE_WRITE_SECONDS
    try:
        with os.scandir(folder) as entries:
            for entry in entries:
                if entry.name.endswith(_WRITING):  # left by a process that died writing it
                    try:
                        if entry.stat(follow_symlinks=False).st_mtime < stale:
                            os.unlink(entry.path)
                    except OSError:
                        pass
                    continue
                if not entry.name.endswith(_PROGRAM):
                    continue
                try:
                    if not entry.is_file(follow_symlinks=False):
                        continue
                    st = entry.stat(follow_symlinks=False)
                except OSError:
                    continue
                total += st.st_size
                found.append((max(st.st_atime, st.st_mtime), entry.name, st.st_size))
    except OSError:
        return 0
    if total <= max_bytes:
        return 0
    removed = 0
    for _, name, size in sorted(found):
        if total <= PRUNE_TO * max_bytes:
            break
        try:
            (folder / name).unlink()
        except FileNotFoundError:
            pass  # another process pruned it first: it is gone all the same
        except OSError:
            continue
        try:
            (folder / (name[: -len(_PROGRAM)] + _ATIME)).unlink(missing_ok=True)
        except OSError:
            pass
        total -= size
        removed += 1
    return removed


def disable_compilation_cache() -> None:
    """Stop reading and writing the persistent cache (call before the first compilation)."""
    jax.config.update("jax_enable_compilation_cache", False)


def compilation_cache_dir() -> Path | None:
    """The folder of the persistent cache, or None when it is off."""
    folder = jax.config.jax_compilation_cache_dir
    if not folder or not jax.config.jax_enable_compilation_cache:
        return None
    return Path(folder)


def child_cache_environment(
    compilation_cache: Path | None, fit_cache: Path | None
) -> dict[str, str]:
    """The variables that give another process these caches (None: off).

    ``SAFESTAB_COMPILATION_CACHE`` and ``SAFESTAB_FIT_CACHE``, each a folder or ``off``. With
    this process's folders (:func:`compilation_cache_dir`,
    :func:`~safestab.learning._fit_cache.fit_cache_dir`) the other process uses its caches
    whatever set them (an option, the environment or Python): ``safestab run``'s other
    processes and a local Ray cluster's workers.
    """
    from .learning._fit_cache import FIT_ENV_VAR

    return {
        var: "off" if folder is None else str(folder)
        for var, folder in ((ENV_VAR, compilation_cache), (FIT_ENV_VAR, fit_cache))
    }


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
        install_atomic_writes()
        return compilation_cache_dir()
    return enable_compilation_cache(value or None)
