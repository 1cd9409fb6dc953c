"""Output helpers: checked folders, atomic and all-or-none writes, strict JSON, figures."""

import json
import os
import stat
import sys

import matplotlib.pyplot as plt
import numpy as np
import pytest

from safestab import NonFiniteError, OutputError
from safestab._io import (
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    bytes_writer,
    ensure_writable_dir,
    figure_writer,
    replace_non_finite,
    save_figure,
    strict_json_dumps,
    text_writer,
    write_all,
)

IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


def _listing(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _fail_probe(monkeypatch, errno=13, message="Permission denied"):
    """Make creating the writability probe fail, as in a folder root cannot write either.

    Root ignores permission bits (chmod cannot make a folder unwritable for it), so the
    refusal is simulated where it happens: at the exclusive creation of the probe file.
    """
    real_open = os.open

    def fake_open(path, flags, *args, **kwargs):
        if ".safestab-probe-" in os.fspath(path):
            raise OSError(errno, message)
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", fake_open)


# -- ensure_writable_dir ----------------------------------------------------------------


def test_ensure_writable_dir_creates_nested_folders_and_leaves_no_probe(tmp_path):
    out = ensure_writable_dir(tmp_path / "a" / "b")
    assert out.is_dir() and list(out.iterdir()) == []


def test_folder_that_is_a_regular_file(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(
        OutputError, match=r"--out must be a writable folder .*, got '.*f': it is not"
    ):
        ensure_writable_dir(tmp_path / "f", name="--out")


def test_folder_below_a_regular_file(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match=r"out must be .*: its parent '.*f' is not a folder"):
        ensure_writable_dir(tmp_path / "f" / "sub" / "deeper")
    assert (tmp_path / "f").read_text() == "x"


def test_folder_that_cannot_be_created(tmp_path, monkeypatch):
    def refuse(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(type(tmp_path), "mkdir", refuse)
    with pytest.raises(OutputError, match=r"cannot create it \(Permission denied\)"):
        ensure_writable_dir(tmp_path / "new")


@pytest.mark.parametrize(
    "errno, message", [(13, "Permission denied"), (30, "Read-only file system")]
)
def test_unwritable_folder_found_by_the_probe(tmp_path, monkeypatch, errno, message):
    _fail_probe(monkeypatch, errno, message)
    with pytest.raises(OutputError, match=rf"cannot create a file in it \({message}\)"):
        ensure_writable_dir(tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(IS_ROOT or sys.platform == "win32", reason="root ignores permission bits")
def test_unwritable_folder_by_mode(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        with pytest.raises(OutputError, match=r"cannot create a file in it"):
            ensure_writable_dir(ro)
    finally:
        ro.chmod(stat.S_IRWXU)


# -- write_all --------------------------------------------------------------------------


def test_write_all_writes_every_file_with_ordinary_permissions(tmp_path):
    paths = write_all(
        {tmp_path / "a.txt": text_writer("é\n"), tmp_path / "b.bin": bytes_writer(b"\0")}
    )
    assert paths == [tmp_path / "a.txt", tmp_path / "b.bin"]
    assert _listing(tmp_path) == {"a.txt": "é\n".encode(), "b.bin": b"\0"}
    # same mode as a file made the ordinary way (umask applied), not mkstemp's 0o600
    (tmp_path / "plain").write_bytes(b"")
    assert (tmp_path / "a.txt").stat().st_mode == (tmp_path / "plain").stat().st_mode


def test_writer_failure_leaves_folder_as_it_was(tmp_path):
    (tmp_path / "a.txt").write_text("old a")
    before = _listing(tmp_path)

    def boom(fh):
        fh.write(b"half of it")
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError, match="disk on fire"):
        write_all({tmp_path / "a.txt": text_writer("new a"), tmp_path / "b.txt": boom})
    assert _listing(tmp_path) == before  # no new b, a not replaced, no temporaries


@pytest.mark.parametrize("with_old_files", [True, False])
@pytest.mark.parametrize("hard_links", [True, False])
def test_rename_failure_rolls_back(tmp_path, monkeypatch, with_old_files, hard_links):
    names = ["a.txt", "b.txt", "c.txt"]
    if with_old_files:
        for n in names:
            (tmp_path / n).write_text(f"old {n}")
    before = _listing(tmp_path)
    real_replace = os.replace
    calls = []

    def flaky_replace(src, dst):
        calls.append(dst)
        if len(calls) == 2:  # the second file's rename fails, after the first succeeded
            raise OSError(5, "Input/output error")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", flaky_replace)
    if not hard_links:

        def no_link(*args, **kwargs):
            raise OSError(1, "Operation not permitted")

        monkeypatch.setattr(os, "link", no_link)
    with pytest.raises(OutputError, match=r"cannot write '.*b\.txt' \(Input/output error\)"):
        write_all({tmp_path / n: text_writer(f"new {n}") for n in names})
    assert _listing(tmp_path) == before


def test_write_failure_at_flush_is_an_output_error(tmp_path, monkeypatch):
    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OutputError, match=r"cannot write '.*a\.txt' \(No space left on device\)"):
        atomic_write_text(tmp_path / "a.txt", "x")
    assert list(tmp_path.iterdir()) == []


def test_missing_folder_and_duplicates(tmp_path):
    with pytest.raises(OutputError, match=r"cannot create '.*nope/a\.txt' \(No such file"):
        atomic_write_text(tmp_path / "nope" / "a.txt", "x")
    with pytest.raises(OutputError, match=r"outputs must name distinct files, got '.*a\.txt' more"):
        write_all(
            {tmp_path / "a.txt": text_writer("1"), str(tmp_path / "." / "a.txt"): text_writer("2")}
        )
    assert list(tmp_path.iterdir()) == []


def test_atomic_single_files_round_trip(tmp_path):
    atomic_write_bytes(tmp_path / "b", b"\x00\xff")
    atomic_write_text(tmp_path / "t", "line\n")
    atomic_write_json(tmp_path / "j.json", {"x": np.float64(1.5), "v": np.arange(3)})
    assert (tmp_path / "b").read_bytes() == b"\x00\xff"
    assert (tmp_path / "t").read_text() == "line\n"
    assert json.loads((tmp_path / "j.json").read_text()) == {"x": 1.5, "v": [0, 1, 2]}


# -- strict JSON ------------------------------------------------------------------------


def test_replace_non_finite_reports_json_pointers():
    doc = {
        "a/b": [1.0, float("nan"), {"c~d": float("-inf")}],
        "ok": np.array([1.0, np.inf]),
        "n": np.float32("nan"),
        "i": 3,
        "s": "nan",
        "t": True,
        "z": None,
    }
    clean, found = replace_non_finite(doc)
    assert clean == {"a/b": [1.0, None, {"c~d": None}], "ok": [1.0, None], "n": None,
                     "i": 3, "s": "nan", "t": True, "z": None}  # fmt: skip
    # RFC 6901: '/' is written '~1' and '~' is written '~0'
    assert found == {"/a~1b/1": "nan", "/a~1b/2/c~0d": "-inf", "/ok/1": "inf", "/n": "nan"}
    assert replace_non_finite(float("inf")) == (None, {"/": "inf"})
    # JAX arrays and scalars become Python values too (a study's settings may hold them)
    import jax.numpy as jnp

    clean, found = replace_non_finite({"u": jnp.array([1.0, jnp.nan]), "k": jnp.int32(2)})
    assert clean == {"u": [1.0, None], "k": 2} and found == {"/u/1": "nan"}


def test_strict_json_refuses_non_finite():
    with pytest.raises(NonFiniteError, match=r"JSON output must be finite .*, got /x/0 = nan"):
        strict_json_dumps({"x": [float("nan")]})
    text = strict_json_dumps({"x": [1e308, -0.0]})
    assert "NaN" not in text and json.loads(text) == {"x": [1e308, -0.0]}


def test_atomic_write_json_with_nan_writes_nothing(tmp_path):
    with pytest.raises(NonFiniteError, match=r"/m = inf"):
        atomic_write_json(tmp_path / "m.json", {"m": float("inf")})
    assert list(tmp_path.iterdir()) == []


# -- figures ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "suffix, magic", [(".png", b"\x89PNG"), (".pdf", b"%PDF"), (".svg", b"<?xml")]
)
def test_save_figure_format_from_suffix(tmp_path, suffix, magic):
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    try:
        path = save_figure(fig, tmp_path / f"f{suffix}", dpi=50)
    finally:
        plt.close(fig)
    assert path.read_bytes().startswith(magic)
    assert [p.name for p in tmp_path.iterdir()] == [f"f{suffix}"]


def test_figure_writer_errors(tmp_path):
    fig = plt.figure()
    try:
        with pytest.raises(
            OutputError, match=r"figure path must end in one of .*'png'.*, got '.*f\.xyz'"
        ):
            figure_writer(fig, tmp_path / "f.xyz")
        with pytest.raises(OutputError, match=r"takes the format from the path's suffix"):
            figure_writer(fig, tmp_path / "f.png", format="pdf")
    finally:
        plt.close(fig)
