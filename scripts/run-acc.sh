#!/usr/bin/env bash
# Set up .venv (if needed) and run the main job.
source "$(dirname "$0")/_venv.sh" test
exec .venv/bin/python examples/quickstart.py "$@"
