#!/usr/bin/env bash
# Set up .venv (if needed) and run the test suite: tests marked slow are left out unless
# asked for (pyproject.toml's addopts; `-m slow` runs them, see the README).
# The test files run in parallel worker processes (pytest-xdist, one file per worker at a
# time so that a file's fixtures are built once): up to 4 workers, at most one per CPU;
# SAFESTAB_TEST_WORKERS=1 runs everything in this process (as does `-n 0` among the
# arguments, which are passed to pytest).
source "$(dirname "$0")/_venv.sh" test,docs  # docs: tests of the docs tooling, and the CI site build
cpus='import os; print(min(4, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1))'
workers="${SAFESTAB_TEST_WORKERS:-$(.venv/bin/python -c "$cpus")}"
parallel=()
if [ "$workers" -gt 1 ]; then parallel=(-n "$workers" --dist loadfile); fi
exec .venv/bin/python -m pytest "${parallel[@]}" "$@"
