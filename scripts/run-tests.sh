#!/usr/bin/env bash
# Set up .venv (if needed) and run the whole test suite, slow tests included.
source "$(dirname "$0")/_venv.sh" test,docs  # docs: tests of the docs tooling, and the CI site build
exec .venv/bin/python -m pytest "$@"
