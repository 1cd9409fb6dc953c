"""Writing outputs safely: checked folders, atomic files, all-or-none sets, strict JSON.

Internal module shared by everything that writes results (the command line, the ACC study,
later Monte Carlo and export). The rules it enforces:

* **Check before work.** :func:`ensure_writable_dir` creates the output folder if needed and
  proves it writable by creating and removing a probe file, so a run that cannot save its
  results fails before it starts. Permission bits are not consulted: root ignores them, a
  read-only mount or a full quota does not show in them, and the probe sees all of these.
* **Atomic files.** Every file is written under a temporary name in its own folder (same
  filesystem), flushed and ``fsync``-ed, then moved over its final name with ``os.replace``
  (atomic on POSIX and Windows). A reader sees the old file or the new one, never half of one.
* **All or none.** :func:`write_all` writes every file of a set to temporaries first; only when
  all succeeded are they renamed, one ``os.replace`` each. A failure while writing removes the
  temporaries and leaves the folder as it was. A failure during the renames (an I/O error of
  the filesystem: a rename within a folder needs no space) rolls back the renames already done,
  restoring each previous file from a hard link (or copy) taken just before it was replaced.
  So a failed run never leaves new files beside stale ones.
* **Strict JSON.** No ``NaN``/``Infinity`` tokens, which are not JSON: :func:`replace_non_finite`
  turns non-finite numbers into ``null`` and reports where they were (so the caller can add a
  status field), and :func:`strict_json_dumps` refuses any that remain
  (``json.dumps(..., allow_nan=False)`` as the last guard).
"""

from __future__ import annotations

import json
import math
import os
import secrets
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from .errors import NonFiniteError, OutputError

__all__ = [
    "Writer",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_text",
    "bytes_writer",
    "ensure_writable_dir",
    "figure_writer",
    "json_writer",
    "replace_non_finite",
    "save_figure",
    "strict_json_dumps",
    "text_writer",
    "with_finite_status",
    "write_all",
]

#: Writes one file's content to an open binary file object.
Writer = Callable[[BinaryIO], object]


# -- folders ----------------------------------------------------------------------------


def ensure_writable_dir(path: str | os.PathLike[str], name: str = "out") -> Path:
    """Create the folder ``path`` if needed and prove that files can be created in it.

    Parameters
    ----------
    path : str or path-like
        The output folder; missing parents are created.
    name : str
        The argument's name for error messages (``"--out"`` on the command line).

    Returns
    -------
    Path
        ``path`` made absolute against the current working folder, once: a subprocess run in
        another folder, or a later change of folder, then finds the same folder. Error
        messages name ``path`` as given.

    Raises
    ------
    OutputError
        If ``path`` or one of its parents is not a folder, the folder cannot be created, or a
        file cannot be created and removed in it.

    Notes
    -----
    Writability is tested by creating (exclusively) and removing a hidden probe file, not by
    ``os.access``: root passes every permission check, and read-only mounts or quotas are not
    visible in permission bits.
    """
    path = Path(path)
    expected = "a writable folder (created if missing)"
    for parent in (path, *path.parents):
        if os.path.lexists(parent):
            if not parent.is_dir():
                where = "it is" if parent == path else f"its parent {str(parent)!r} is"
                raise OutputError(
                    f"{name} must be {expected}, got {str(path)!r}: {where} not a folder"
                )
            break
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(
            f"{name} must be {expected}, got {str(path)!r}: cannot create it ({_reason(exc)})"
        ) from None
    probe = path / f".safestab-probe-{secrets.token_hex(6)}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, b"probe")
        finally:
            os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        _remove_quietly(probe)
        raise OutputError(
            f"{name} must be {expected}, got {str(path)!r}: cannot create a file in it "
            f"({_reason(exc)})"
        ) from None
    return path.absolute()


# -- all-or-none writes -----------------------------------------------------------------


def write_all(outputs: Mapping[str | os.PathLike[str], Writer]) -> list[Path]:
    """Write a set of files all or none, each atomically.

    Parameters
    ----------
    outputs : mapping of path to writer
        Final path of each file and a callable that writes its content to an open binary
        file object (see :func:`bytes_writer`, :func:`text_writer`, :func:`json_writer`,
        :func:`figure_writer`). The folders must exist.

    Returns
    -------
    list of Path
        The final paths, in the order given.

    Raises
    ------
    OutputError
        If two entries name the same file, or a file cannot be created or renamed (the
        underlying ``OSError`` is chained).
    Exception
        Whatever a writer raises, unchanged.

    Notes
    -----
    Phase 1 writes every file to a hidden temporary beside its final name (created with
    ``O_EXCL`` and mode ``0o666`` less the umask, as an ordinary file), flushes and fsyncs it.
    Phase 2 renames each temporary over its final name with ``os.replace``, first keeping a
    hard link (or, where links are not supported, a copy) of any previous file. If anything
    fails, the renames done so far are undone from those backups, and all temporaries and
    backups are removed: the folder is left as it was. The undo is best effort: it can only
    fail if the filesystem itself fails during it.
    """
    targets = [Path(p) for p in outputs]
    keys = [os.path.normcase(os.path.abspath(p)) for p in targets]
    if len(set(keys)) != len(keys):
        dup = next(str(p) for p, k in zip(targets, keys, strict=True) if keys.count(k) > 1)
        raise OutputError(f"outputs must name distinct files, got {dup!r} more than once")
    temps: dict[Path, Path] = {}
    try:
        for target, writer in zip(targets, outputs.values(), strict=True):
            tmp = _temporary_name(target, "tmp")
            temps[target] = tmp
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _O_BINARY, 0o666)
            except OSError as exc:
                raise OutputError(f"cannot create {str(target)!r} ({_reason(exc)})") from exc
            with os.fdopen(fd, "wb") as fh:
                writer(fh)
                try:
                    fh.flush()
                    os.fsync(fh.fileno())
                except OSError as exc:
                    raise OutputError(f"cannot write {str(target)!r} ({_reason(exc)})") from exc
        _commit(temps)
    finally:
        for tmp in temps.values():
            _remove_quietly(tmp)  # renamed ones are gone already
    for folder in {t.parent for t in targets}:
        _fsync_dir(folder)
    return targets


def _commit(temps: dict[Path, Path]) -> None:
    """Rename each temporary over its target; undo them all if one fails."""
    backups: dict[Path, Path | None] = {}
    done: list[Path] = []
    try:
        for target, tmp in temps.items():
            backups[target] = None
            try:
                if os.path.lexists(target) and not target.is_dir():
                    bak = _temporary_name(target, "bak")
                    backups[target] = bak
                    try:
                        os.link(target, bak)
                    except OSError:
                        shutil.copy2(target, bak)  # no hard links on this filesystem
                os.replace(tmp, target)
            except OSError as exc:
                raise OutputError(f"cannot write {str(target)!r} ({_reason(exc)})") from exc
            done.append(target)
    except BaseException:
        for target in reversed(done):
            saved = backups[target]
            try:
                if saved is None:
                    os.unlink(target)
                else:
                    os.replace(saved, target)
            except OSError:
                pass  # the filesystem failed during the undo; nothing more can be done here
        raise
    finally:
        for maybe_bak in backups.values():
            if maybe_bak is not None:
                _remove_quietly(maybe_bak)


# -- writers ----------------------------------------------------------------------------


def bytes_writer(data: bytes) -> Writer:
    """A writer for fixed bytes."""
    data = bytes(data)
    return lambda fh: fh.write(data)


def text_writer(text: str, encoding: str = "utf-8") -> Writer:
    """A writer for text (encoded now, so an encoding error comes before any file exists)."""
    return bytes_writer(text.encode(encoding))


def json_writer(obj: Any, *, indent: int | None = 2) -> Writer:
    """A writer for strict JSON (serialised now; see :func:`strict_json_dumps`)."""
    return text_writer(strict_json_dumps(obj, indent=indent) + "\n")


def figure_writer(fig: Any, path: str | os.PathLike[str], **savefig_kwargs: Any) -> Writer:
    """A writer that saves a matplotlib figure in the format named by ``path``'s suffix.

    Raises
    ------
    OutputError
        If the suffix is not a format the figure's canvas can write.
    """
    fmt = Path(path).suffix.lstrip(".").lower()
    supported = fig.canvas.get_supported_filetypes()
    if fmt not in supported:
        raise OutputError(f"figure path must end in one of {sorted(supported)}, got {str(path)!r}")
    if "format" in savefig_kwargs:
        raise OutputError("figure_writer takes the format from the path's suffix, not format=")
    return lambda fh: fig.savefig(fh, format=fmt, **savefig_kwargs)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write bytes to ``path`` atomically (see :func:`write_all`)."""
    return write_all({path: bytes_writer(data)})[0]


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> Path:
    """Write text to ``path`` atomically (see :func:`write_all`)."""
    return write_all({path: text_writer(text, encoding)})[0]


def atomic_write_json(path: str | os.PathLike[str], obj: Any, *, indent: int | None = 2) -> Path:
    """Write strict JSON to ``path`` atomically.

    Raises
    ------
    NonFiniteError
        If ``obj`` holds NaN or infinity (replace them first with :func:`replace_non_finite`).
    """
    return write_all({path: json_writer(obj, indent=indent)})[0]


def save_figure(fig: Any, path: str | os.PathLike[str], **savefig_kwargs: Any) -> Path:
    """Save a matplotlib figure atomically, in the format of ``path``'s suffix."""
    return write_all({path: figure_writer(fig, path, **savefig_kwargs)})[0]


# -- strict JSON ------------------------------------------------------------------------


def replace_non_finite(obj: Any) -> tuple[Any, dict[str, str]]:
    """Copy of ``obj`` with every NaN or infinity replaced by ``None`` (JSON ``null``).

    Parameters
    ----------
    obj : JSON-like
        Nested dicts (string keys), lists, tuples, numbers, strings, booleans, ``None``, and
        NumPy or JAX scalars and arrays (converted to Python values).

    Returns
    -------
    clean : JSON-like
        The copy (tuples and arrays become lists).
    found : dict of str to str
        For each replaced value, its JSON Pointer (RFC 6901, e.g. ``"/controllers/GP/min_h_m"``)
        and what it was: ``"nan"``, ``"inf"`` or ``"-inf"``. Empty if all values were finite.
    """
    found: dict[str, str] = {}

    def walk(value: Any, pointer: str) -> Any:
        if isinstance(value, np.ndarray | np.generic) or hasattr(value, "__array__"):
            value = np.asarray(value).tolist()  # JAX arrays too
        if isinstance(value, dict):
            return {k: walk(v, f"{pointer}/{_escape(str(k))}") for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [walk(v, f"{pointer}/{i}") for i, v in enumerate(value)]
        if isinstance(value, float) and not math.isfinite(value):
            found[pointer or "/"] = repr(value)
            return None
        return value

    return walk(obj, ""), found


def strict_json_dumps(obj: Any, *, indent: int | None = 2) -> str:
    """``json.dumps`` that never writes ``NaN`` or ``Infinity`` (not JSON).

    NumPy scalars and arrays are converted to Python values.

    Raises
    ------
    NonFiniteError
        Naming the JSON Pointer of every non-finite value.
    """
    clean, found = replace_non_finite(obj)
    if found:
        raise NonFiniteError(
            "JSON output must be finite (write null plus a status instead), got "
            + ", ".join(f"{p} = {v}" for p, v in found.items())
        )
    return json.dumps(clean, indent=indent, allow_nan=False)


# -- helpers ----------------------------------------------------------------------------

_O_BINARY = getattr(os, "O_BINARY", 0)  # Windows only


def _escape(key: str) -> str:
    return key.replace("~", "~0").replace("/", "~1")


def _temporary_name(target: Path, kind: str) -> Path:
    return target.with_name(f".{target.name}.{secrets.token_hex(6)}.{kind}")


def _reason(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def _remove_quietly(path: Path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def _fsync_dir(folder: Path) -> None:
    """Make the renames durable (POSIX); a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def with_finite_status(doc: dict[str, Any]) -> dict[str, Any]:
    """A metrics document made strict: non-finite numbers become ``None``, listed by path.

    Returns ``{"status": "ok" | "non-finite", "non_finite": {...}, **doc}`` with the numbers
    replaced as :func:`replace_non_finite` does.
    """
    clean, found = replace_non_finite(doc)
    return {"status": "non-finite" if found else "ok", "non_finite": found, **clean}
