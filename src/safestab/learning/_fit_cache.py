"""The GP fit cache: the marginal-likelihood optimisations of earlier runs, kept on disk.

A study's GP fit spends most of its time in L-BFGS-B (several starts per component, hundreds
of likelihood evaluations). The optimisation is a deterministic function of its problem: the
standardised inputs, the targets, the kernel and its settings, the starts and the bounds. When
a later run poses the same problem (the same data, with a controller or a plotting option
changed), the results of the first are read back instead of recomputed: the same optima, the
same iteration counts and messages, so the fitted model, its warnings and every number built
from it are those of a fresh fit.

* The key is a SHA-256 of the whole problem (every array's bytes, every setting) and of
  what computes it: the source of the likelihood and kernel modules, and the versions of
  safestab, JAX, jaxlib, NumPy and SciPy, and the machine. Change any of them and the entry is
  not found: nothing stale is read.
* Entries are small JSON files (floats written exactly, as hexadecimal), written atomically
  in ``$XDG_CACHE_HOME/safestab/fits`` (``~/.cache/safestab/fits``); an unreadable entry is
  ignored and overwritten. At most :data:`MAX_ENTRIES` are kept (the oldest go first). The
  folder is safe to delete at any time.
* ``SAFESTAB_FIT_CACHE=off`` (or ``0``, ``no``, ``false``) turns it off,
  ``SAFESTAB_FIT_CACHE=/some/folder`` puts it elsewhere; ``safestab --no-fit-cache <command>``
  and :func:`disable_fit_cache` turn it off for one command or process.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import threading
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "FIT_ENV_VAR",
    "MAX_ENTRIES",
    "disable_fit_cache",
    "enable_fit_cache",
    "fit_cache_dir",
    "load",
    "problem_key",
    "store",
]

#: The environment variable read at import: ``off`` (``0``, ``no``, ``false``) or a folder.
FIT_ENV_VAR = "SAFESTAB_FIT_CACHE"
#: Most entries kept; beyond it the least recently written are removed.
MAX_ENTRIES = 4000
_OFF = frozenset({"0", "off", "no", "false", "none"})
_FORMAT = 1
_state: dict[str, Path | None] = {"dir": None}


def _default_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "safestab" / "fits"


def enable_fit_cache(path: str | Path | None = None) -> Path:
    """Read and write the fit cache in ``path`` (default ``~/.cache/safestab/fits``)."""
    folder = Path(path).expanduser() if path is not None else _default_dir()
    _state["dir"] = folder
    return folder


def disable_fit_cache() -> None:
    """Fit every GP afresh and write nothing (this process)."""
    _state["dir"] = None


def fit_cache_dir() -> Path | None:
    """The fit cache's folder, or None when it is off."""
    return _state["dir"]


def configure_fit_cache_from_environment() -> Path | None:
    """What the import does: on in the default folder unless ``SAFESTAB_FIT_CACHE`` says."""
    value = os.environ.get(FIT_ENV_VAR, "").strip()
    if value.lower() in _OFF:
        disable_fit_cache()
        return None
    return enable_fit_cache(value or None)


@functools.lru_cache(maxsize=1)
def _versions() -> str:
    import jax
    import jaxlib
    import scipy

    from .._version import __version__

    here = Path(__file__).parent
    sources = b"".join((here / name).read_bytes() for name in ("_likelihood.py", "_posterior.py"))
    return "|".join([
        __version__, jax.__version__, jaxlib.__version__, np.__version__, scipy.__version__,
        platform.machine(), platform.processor(), hashlib.sha256(sources).hexdigest(),
    ])  # fmt: skip


def problem_key(settings: dict[str, Any], arrays: dict[str, Any]) -> str:
    """SHA-256 of an optimisation problem: ``settings`` (JSON-able) and ``arrays``' bytes."""
    h = hashlib.sha256()
    h.update(f"format {_FORMAT}|{_versions()}|".encode())
    h.update(json.dumps(settings, sort_keys=True).encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(np.asarray(arrays[name], dtype=float))
        h.update(f"|{name}:{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _hex(v: float) -> str:
    return float(v).hex()


def load(key: str) -> list[tuple[float, np.ndarray, int, bool, str]] | None:
    """The stored starts' results ``(value, theta, nit, ok, message)``, or None."""
    folder = fit_cache_dir()
    if folder is None:
        return None
    try:
        doc = json.loads((folder / f"{key}.json").read_text())
        if doc.get("format") != _FORMAT or doc.get("key") != key:
            return None
        return [
            (float.fromhex(r["value"]), np.array([float.fromhex(t) for t in r["theta"]]),
             int(r["nit"]), bool(r["ok"]), str(r["message"]))
            for r in doc["results"]
        ]  # fmt: skip
    except (OSError, ValueError, KeyError, TypeError):
        return None  # missing or unreadable: fit afresh (and overwrite it)


def store(key: str, results: list[tuple[float, Any, int, bool, str]]) -> None:
    """Write ``results`` under ``key`` atomically; a cache that cannot be written is skipped."""
    folder = fit_cache_dir()
    if folder is None:
        return
    doc = {
        "format": _FORMAT,
        "key": key,
        "results": [
            {"value": _hex(v), "theta": [_hex(t) for t in np.asarray(theta, float)],
             "nit": int(nit), "ok": bool(ok), "message": str(message)}
            for v, theta, nit, ok, message in results
        ],
    }  # fmt: skip
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / f".{key}.{os.getpid()}.{threading.get_ident()}.tmp"  # one per writer
        tmp.write_text(json.dumps(doc))
        tmp.replace(folder / f"{key}.json")
        _prune(folder)
    except OSError:
        return  # the cache is an optimisation: without it everything works, only slower


def _prune(folder: Path) -> None:
    entries = list(folder.glob("*.json"))
    if len(entries) <= MAX_ENTRIES:
        return
    entries.sort(key=lambda p: p.stat().st_mtime)
    for old in entries[: len(entries) - MAX_ENTRIES]:
        old.unlink(missing_ok=True)
