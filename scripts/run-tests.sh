#!/usr/bin/env bash
# Set up .venv (if needed) and run the test suite: tests marked slow are left out unless
# asked for (pyproject.toml's addopts; `-m slow` runs them, see the README).
# The test files run in parallel worker processes (pytest-xdist, one file per worker at a
# time so that a file's fixtures are built once): one worker per CPU, at most 4. Each worker
# gives BLAS one thread, since the workers already fill the CPUs (tests/conftest.py).
# SAFESTAB_TEST_WORKERS=N sets the count; 1 runs everything in this process, as `-n 0` among
# the arguments (passed to pytest) does: use it for --pdb or -s.
source "$(dirname "$0")/_venv.sh" test,docs  # docs: tests of the docs tooling, and the CI site build
# The embedded tests' ARM toolchain (arm-none-eabi-gcc, newlib, qemu-system-arm) is set up here,
# with the rest of the installation, not while the tests run (about 100 s of apt-get on a fresh
# machine): installed where this process may (root, apt-get); elsewhere those tests skip,
# naming what is missing.
if ! command -v arm-none-eabi-gcc >/dev/null 2>&1 || ! command -v qemu-system-arm >/dev/null 2>&1; then
  .venv/bin/python -c 'from safestab.export import embedded; embedded.find_toolchain(install=True)' \
    >/dev/null 2>&1 || echo "note: no ARM toolchain; the embedded tests will be skipped" >&2
fi
cpus='import os; print(min(4, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1))'
workers="${SAFESTAB_TEST_WORKERS:-$(.venv/bin/python -c "$cpus")}"
case "$workers" in
  ''|*[!0-9]*) echo "SAFESTAB_TEST_WORKERS must be a whole number >= 1, got '$workers'" >&2; exit 2 ;;
esac
if [ "$workers" -gt 1 ]; then
  exec .venv/bin/python -m pytest -n "$workers" --dist loadfile "$@"
fi
exec .venv/bin/python -m pytest "$@"
