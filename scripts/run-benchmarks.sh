#!/usr/bin/env bash
# Set up .venv (if needed) and run the speed benchmarks; writes docs/performance.{json,md}.
# Pass --no-full-fit to skip the slow full-data GP fit.
source "$(dirname "$0")/_venv.sh" "test,bench"
exec .venv/bin/python benchmarks/run.py "$@"
