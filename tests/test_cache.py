"""JAX's persistent compilation cache: on by default, where it is told, off when told.

Each case runs in a fresh interpreter (the setting is made at import, for the whole process).
"""

from __future__ import annotations

import os
import subprocess
import sys

PROBE = (
    "import jax, safestab as ss; "
    "print('DIR', ss.compilation_cache_dir()); "
    "print('ON', jax.config.jax_enable_compilation_cache)"
)


def _run(code: str, **env: str) -> str:
    full = {k: v for k, v in os.environ.items() if k != "SAFESTAB_COMPILATION_CACHE"}
    full.update(env)
    proc = subprocess.run(
        [sys.executable, "-c", code], env=full, capture_output=True, text=True, check=True
    )
    return proc.stdout


def test_on_by_default_in_the_user_cache_folder(tmp_path):
    out = _run(PROBE, XDG_CACHE_HOME=str(tmp_path))
    assert f"DIR {tmp_path / 'safestab' / 'jax'}" in out
    assert (tmp_path / "safestab" / "jax").is_dir()


def test_a_second_process_reuses_the_first_ones_programs(tmp_path):
    code = (
        "import jax, jax.numpy as jnp, safestab; "
        "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0); "
        "f = jax.jit(lambda x: jnp.linalg.solve(x @ x.T + jnp.eye(40), x).sum()); "
        "print(f(jnp.ones((40, 40))))"
    )
    cache = tmp_path / "cache"
    first = _run(code, SAFESTAB_COMPILATION_CACHE=str(cache))
    stored = sorted(p.name for p in cache.iterdir())
    assert stored  # the compiled program was written
    second = _run(code, SAFESTAB_COMPILATION_CACHE=str(cache))
    assert second == first and sorted(p.name for p in cache.iterdir()) == stored


def test_off_by_environment_variable_and_by_option(tmp_path):
    out = _run(PROBE, SAFESTAB_COMPILATION_CACHE="off", XDG_CACHE_HOME=str(tmp_path))
    assert "DIR None" in out and "ON False" in out
    assert not (tmp_path / "safestab").exists()
    cli = (
        "import sys, jax; from safestab.cli import app; "
        "sys.argv = ['safestab', '--no-compilation-cache', 'run', '--help']\n"
        "try:\n    app()\nexcept SystemExit:\n    pass\n"
        "print('ON', jax.config.jax_enable_compilation_cache)"
    )
    assert "ON False" in _run(cli, XDG_CACHE_HOME=str(tmp_path))


def test_a_folder_given_to_jax_is_kept(tmp_path):
    code = (
        f"import jax; jax.config.update('jax_compilation_cache_dir', {str(tmp_path / 'mine')!r})\n"
        + PROBE
    )
    assert f"DIR {tmp_path / 'mine'}" in _run(code, XDG_CACHE_HOME=str(tmp_path))


def test_pruning_removes_the_least_recently_used_programs_only_past_the_limit(tmp_path):
    from safestab._cache import PRUNE_TO, prune_compilation_cache

    # ten 100-byte programs, used at times 0..9 (the access time is what JAX's reads move)
    for i in range(10):
        program = tmp_path / f"k{i}-cache"
        program.write_bytes(b"x" * 100)
        os.utime(program, (1_000_000 + i, 1_000_000 + i))
        (tmp_path / f"k{i}-atime").write_bytes(b"t" * 8)  # JAX's record under its own limit
    (tmp_path / "other-file").write_bytes(b"y" * 10_000)  # not a program: never counted
    assert prune_compilation_cache(tmp_path, max_bytes=1000) == 0  # at the limit: nothing
    assert len(list(tmp_path.glob("*-cache"))) == 10
    removed = prune_compilation_cache(tmp_path, max_bytes=999)
    # down to PRUNE_TO of the limit (799 bytes: 7 programs), oldest first, with their records
    assert removed == 10 - int(PRUNE_TO * 999) // 100
    left = sorted(int(p.name[1:-6]) for p in tmp_path.glob("*-cache"))
    assert left == list(range(removed, 10))
    assert sorted(int(p.name[1:-6]) for p in tmp_path.glob("*-atime")) == left
    assert (tmp_path / "other-file").exists()
    assert prune_compilation_cache(tmp_path / "missing") == 0  # no folder: nothing to do


def test_jax_does_not_scan_the_folder_on_every_write(tmp_path):
    # JAX's own size limit lists and reads the whole folder before each write (0.16 s per
    # program with 6,400 stored): safestab keeps it off and prunes once at import instead
    out = _run(
        "import jax, safestab; print('MAX', jax.config.jax_compilation_cache_max_size)",
        SAFESTAB_COMPILATION_CACHE=str(tmp_path / "c"),
    )
    assert "MAX -1" in out


def test_pruning_counts_a_program_another_process_removed_first(tmp_path, monkeypatch):
    from pathlib import Path

    from safestab._cache import prune_compilation_cache

    for i in range(4):
        program = tmp_path / f"k{i}-cache"
        program.write_bytes(b"x" * 100)
        os.utime(program, (1_000 + i, 1_000 + i))
    (tmp_path / "d-cache").mkdir()  # not a file: never counted nor removed
    real_unlink = Path.unlink

    def raced(self, *args, **kwargs):
        if self.name == "k0-cache":  # another process pruned it between listing and removal
            real_unlink(self, *args, **kwargs)
            raise FileNotFoundError(self)
        return real_unlink(self, *args, **kwargs)

    monkeypatch.setattr(Path, "unlink", raced)
    # 400 bytes over a limit of 399: down to 0.8 * 399 = 319 bytes, so only the oldest goes;
    # its removal by the other process counts, and k1 is not removed as well
    assert prune_compilation_cache(tmp_path, max_bytes=399) == 1
    assert sorted(p.name for p in tmp_path.glob("*-cache")) == [
        "d-cache",
        "k1-cache",
        "k2-cache",
        "k3-cache",
    ]


def test_programs_are_written_whole_then_renamed_into_place(tmp_path, monkeypatch):
    """A reader in another process finds a program whole or not at all."""
    from pathlib import Path

    from jax._src.lru_cache import LRUCache

    from safestab._cache import install_atomic_writes

    assert install_atomic_writes()  # on since the import
    wrapped = LRUCache.put
    assert install_atomic_writes() and LRUCache.put is wrapped  # idempotent: not wrapped twice
    cache = LRUCache(str(tmp_path), max_size=-1)
    renames = []
    real_replace = os.replace

    def replace(src, dst):
        # at the rename the final name does not exist yet and the whole value is written
        assert not Path(dst).exists() and Path(src).read_bytes() == b"program bytes"
        renames.append((Path(src).name, Path(dst).name))
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    cache.put("k1", b"program bytes")
    ((src, dst),) = renames
    assert src.startswith(".") and src.endswith("-writing") and dst == "k1-cache"
    assert cache.get("k1") == b"program bytes"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["k1-cache"]
    cache.put("k1", b"other bytes")  # as JAX: a stored entry is kept
    assert cache.get("k1") == b"program bytes" and len(renames) == 1

    # a failed write leaves neither the program nor its temporary file
    def full_disk(self, data):
        with Path.open(self, "wb") as fh:
            fh.write(data[:3])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full_disk)
    try:
        cache.put("k2", b"program bytes")
    except OSError:
        pass
    else:
        raise AssertionError("the write error was swallowed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["k1-cache"]


def test_pruning_removes_writes_left_by_a_dead_process(tmp_path):
    from safestab._cache import STALE_WRITE_SECONDS, prune_compilation_cache

    old, new = tmp_path / ".a.1.ff-writing", tmp_path / ".b.2.ee-writing"
    for f in (old, new):
        f.write_bytes(b"half")
    long_ago = os.path.getmtime(new) - STALE_WRITE_SECONDS - 60
    os.utime(old, (long_ago, long_ago))
    (tmp_path / "k-cache").write_bytes(b"x")
    assert prune_compilation_cache(tmp_path) == 0  # no program removed
    assert sorted(p.name for p in tmp_path.iterdir()) == [new.name, "k-cache"]
