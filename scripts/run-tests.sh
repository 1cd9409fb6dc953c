#!/usr/bin/env bash
# Set up .venv (if needed) and run the test suite: tests marked slow are left out unless
# asked for (pyproject.toml's addopts; `-m slow` runs them, see the README).
source "$(dirname "$0")/_venv.sh" test,docs  # docs: tests of the docs tooling, and the CI site build
exec .venv/bin/python -m pytest "$@"
