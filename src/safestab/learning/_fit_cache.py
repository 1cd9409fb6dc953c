"""The GP fit cache: the marginal-likelihood optimisations of earlier runs, kept on disk.

A study's GP fit spends most of its time in L-BFGS-B (several starts per component, hundreds
of likelihood evaluations). The optimisation is a deterministic function of its problem: the
standardised inputs, the targets, the kernel and its settings, the starts and the bounds. When
a later run poses the same problem (the same data, with a controller or a plotting option
changed), the results of the first are read back instead of recomputed: the same optima, the
same iteration counts and messages, so the fitted model, its warnings and every number built
from it are those of a fresh fit on the same machine with the same settings.

* The key is a SHA-256 of the whole problem (every array's bytes, every setting) and of
  what computes it: the source of the likelihood and kernel modules; the versions of
  safestab, JAX, jaxlib, NumPy and SciPy; the machine (architecture, CPU flags, JAX backend
  and device); the BLAS thread pools (library, kernels, thread count, read at each fit: the
  thread count changes the summation order), ``XLA_FLAGS`` and ``jax_enable_x64``. Change any
  of them and the entry is not found. Do not share the folder between machines of different
  kinds (a network home directory on a cluster): the key would not see every difference.
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
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from .._cache import OFF_VALUES, cache_root

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
_FORMAT = 1
_state: dict[str, Path | None] = {"dir": None}


def enable_fit_cache(path: str | Path | None = None) -> Path:
    """Read and write the fit cache in ``path`` (default ``~/.cache/safestab/fits``)."""
    folder = Path(path).expanduser() if path is not None else cache_root() / "fits"
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
    if value.lower() in OFF_VALUES:
        disable_fit_cache()
        return None
    return enable_fit_cache(value or None)


@functools.lru_cache(maxsize=1)
def _versions() -> str:
    """What computes the optimisation and does not change within a process."""
    import jax
    import jaxlib
    import scipy

    from .._version import __version__

    here = Path(__file__).parent
    sources = b"".join((here / name).read_bytes() for name in ("_likelihood.py", "_posterior.py"))
    try:  # the instruction set XLA compiles for and the BLAS kernels pick
        flags = next(
            line for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("flags")
        )  # fmt: skip
    except (OSError, StopIteration):
        flags = platform.processor()
    return "|".join([
        __version__, jax.__version__, jaxlib.__version__, np.__version__, scipy.__version__,
        platform.machine(), hashlib.sha256(flags.encode()).hexdigest(),
        jax.default_backend(), jax.devices()[0].device_kind,
        hashlib.sha256(sources).hexdigest(),
    ])  # fmt: skip


def _environment() -> str:
    """What can change between calls: BLAS threads (they change the summation order), x64."""
    import jax
    from threadpoolctl import threadpool_info

    pools = sorted(
        f"{p.get('internal_api')}:{p.get('version')}:{p.get('architecture')}:{p.get('num_threads')}"
        for p in threadpool_info()
    )
    return "|".join([*pools, os.environ.get("XLA_FLAGS", ""), str(jax.config.jax_enable_x64)])


def problem_key(settings: dict[str, Any], arrays: dict[str, Any]) -> str:
    """SHA-256 of an optimisation problem: ``settings`` (JSON-able) and ``arrays``' bytes."""
    h = hashlib.sha256()
    h.update(f"format {_FORMAT}|{_versions()}|{_environment()}|".encode())
    h.update(json.dumps(settings, sort_keys=True).encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(np.asarray(arrays[name], dtype=float))
        h.update(f"|{name}:{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _hex(v: float) -> str:
    return float(v).hex()


def load(
    key: str, n_starts: int, n_theta: int
) -> list[tuple[float, np.ndarray, int, bool, str]] | None:
    """The stored results ``(value, theta, nit, ok, message)`` of ``n_starts`` starts, or None.

    None also for an entry that is unreadable or not of that shape (``theta`` of
    ``n_theta`` entries): the fit then runs afresh and overwrites it.
    """
    folder = fit_cache_dir()
    if folder is None:
        return None
    try:
        doc = json.loads((folder / f"{key}.json").read_text())
        if not isinstance(doc, dict) or doc.get("format") != _FORMAT or doc.get("key") != key:
            return None
        results = [
            (float.fromhex(r["value"]), np.array([float.fromhex(t) for t in r["theta"]]),
             int(r["nit"]), bool(r["ok"]), str(r["message"]))
            for r in doc["results"]
        ]  # fmt: skip
    except Exception:  # noqa: BLE001 -- any unreadable entry: fit afresh
        return None
    if len(results) != n_starts or any(r[1].shape != (n_theta,) for r in results):
        return None
    return results


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
    tmp = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / f".{key}.{uuid.uuid4().hex}.tmp"  # one per writer, any host
        tmp.write_text(json.dumps(doc))
        tmp.replace(folder / f"{key}.json")
        _prune(folder)
    except OSError:
        # the cache is an optimisation: without it everything works, only slower
        if tmp is not None:
            tmp.unlink(missing_ok=True)


def _prune(folder: Path) -> None:
    entries = list(folder.glob("*.json"))
    if len(entries) <= MAX_ENTRIES:
        return
    entries.sort(key=lambda p: p.stat().st_mtime)
    for old in entries[: len(entries) - MAX_ENTRIES]:
        old.unlink(missing_ok=True)
