"""Built shared objects kept on disk, so that a later process loads instead of compiling.

:func:`~safestab.export.jax_function` (and so :func:`~safestab.export.native_step`) compiles
the exported C and XLA's C++ handler into a shared object: 10 to 15 s for a filter with 8
discs. The object is a deterministic function of what built it, so it is stored under a key
of all of that and loaded by the next process that asks for the same build:

* the key is a SHA-256 of the C source and header, the handler's C++ source, the compilers
  (their paths, and the size and modification time of the files they resolve to: no compiler
  is run to identify it), the flags requested of each, JAX's and jaxlib's versions (the
  handler is built against ``jax.ffi.include_dir()``), and the machine (architecture and CPU
  flags: the code is compiled with ``-march=native``);
* the objects live in ``native/`` under the compilation cache's folder
  (:func:`safestab.compilation_cache_dir`), and the cache is on and off with it:
  ``SAFESTAB_COMPILATION_CACHE=off`` (or ``safestab --no-compilation-cache``) builds in a
  temporary folder every time, as without a cache;
* each object is written to a temporary file and renamed into place, so that a process
  finds it whole or not at all; two processes building the same object at once both build
  and the second rename wins (the same object); one that cannot be loaded is built again and
  replaced;
* at most :data:`MAX_ENTRIES` objects are kept, the least recently used go first. The folder
  is safe to delete at any time.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any

__all__ = [
    "MAX_ENTRIES", "SUBFOLDER", "build_key", "load_or_build", "lookup", "native_cache_dir",
    "store",
]  # fmt: skip

#: The folder under the compilation cache's that holds the objects.
SUBFOLDER = "native"
#: Most objects kept (each about 0.1 to 1 MB); beyond it the least recently used are removed.
MAX_ENTRIES = 256
#: Version of the key's layout: a change here makes every stored object a miss.
_FORMAT = "1"
_SUFFIX = ".so"
_WRITING = "-writing"
#: A temporary file older than this was left by a process that died writing it.
_STALE_SECONDS = 3600.0


def native_cache_dir() -> Path | None:
    """``<compilation cache>/native``, or None when the compilation cache is off."""
    from .._cache import compilation_cache_dir

    folder = compilation_cache_dir()
    return None if folder is None else folder / SUBFOLDER


def _tool(path: str) -> str:
    real = os.path.realpath(path)
    try:
        st = os.stat(real)
        return f"{path}|{real}|{st.st_size}|{st.st_mtime_ns}"
    except OSError:
        return f"{path}|{real}"


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "none"


def _machine() -> str:
    flags = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                flags = line
                break
    except OSError:
        pass
    return f"{platform.system()}|{platform.machine()}|{flags}"


def build_key(sources: list[str], tools: list[str], flags: list[str]) -> str:
    """The SHA-256 (hex) naming the object built from ``sources`` by ``tools`` with ``flags``.

    ``tools`` are the compilers' paths (identified by the files they resolve to, without
    running them); JAX's and jaxlib's versions and the machine are added.
    """
    import jax

    parts = [_FORMAT, *sources, *map(_tool, tools), *flags, jax.__version__, _version("jaxlib"),
             _machine()]  # fmt: skip
    h = hashlib.sha256()
    for part in parts:
        data = part.encode()
        h.update(len(data).to_bytes(8, "little") + data)
    return h.hexdigest()


def lookup(folder: Path, key: str) -> Path | None:
    """The stored object of ``key`` (its use time updated), or None."""
    path = folder / f"{key}{_SUFFIX}"
    try:
        os.utime(path)  # least recently used goes first when pruning
    except OSError:
        return None
    return path


def store(folder: Path, key: str, built: Path) -> Path | None:
    """Copy ``built`` into ``folder`` as ``key``'s object, atomically; None if it cannot.

    The cache is an optimisation: a folder that cannot be written is skipped.
    """
    final = folder / f"{key}{_SUFFIX}"
    temporary = folder / f".{uuid.uuid4().hex[:20]}{_WRITING}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(built, temporary)
        os.replace(temporary, final)
    except OSError:
        return None
    finally:
        temporary.unlink(missing_ok=True)  # only if the rename did not happen
    _prune(folder)
    return final


def load_or_build(key: str, symbol: str, build: Callable[[Path], Path]) -> Any:
    """The loaded library of ``key`` that has ``symbol``: from the cache, else built and stored.

    ``build(folder)`` writes the shared object in a temporary folder and returns its path. An
    object in the cache that cannot be loaded, or lacks ``symbol``, is built again. A built
    object stays mapped after its temporary file is removed (where the cache is off or its
    folder cannot be written).

    Raises
    ------
    AttributeError
        If the built object lacks ``symbol``.
    CompilationError, OSError
        From ``build``, or if the built object cannot be loaded.
    """
    folder = native_cache_dir()
    cached = None if folder is None else lookup(folder, key)
    lib = None if cached is None else _open(cached, symbol)
    if lib is not None:
        return lib
    with tempfile.TemporaryDirectory(prefix="safestab-native-") as tmp:
        built = build(Path(tmp))
        stored = None if folder is None else store(folder, key, built)
        lib = None if stored is None else _open(stored, symbol)
        if lib is None:
            lib = ctypes.CDLL(str(built))
            getattr(lib, symbol)
        return lib


def _open(path: Path, symbol: str) -> Any:
    """The library at ``path`` if it loads and has ``symbol``, else None."""
    try:
        lib = ctypes.CDLL(str(path))
        getattr(lib, symbol)
    except (OSError, AttributeError):
        return None
    return lib


def _prune(folder: Path, max_entries: int = MAX_ENTRIES) -> int:
    """Remove the least recently used objects beyond ``max_entries``, and stale temporaries."""
    found: list[tuple[float, str]] = []
    stale = time.time() - _STALE_SECONDS
    try:
        with os.scandir(folder) as entries:
            for entry in entries:
                try:
                    st = entry.stat(follow_symlinks=False)
                except OSError:
                    continue
                if entry.name.endswith(_WRITING):
                    if st.st_mtime < stale:
                        Path(entry.path).unlink(missing_ok=True)
                elif entry.name.endswith(_SUFFIX):
                    found.append((max(st.st_atime, st.st_mtime), entry.name))
    except OSError:
        return 0
    removed = 0
    for _, name in sorted(found)[: max(0, len(found) - max_entries)]:
        try:
            (folder / name).unlink()
            removed += 1
        except OSError:
            continue  # another process removed it, or it cannot be: the cache is optional
    return removed
