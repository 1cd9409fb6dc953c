#!/usr/bin/env bash
# Set up .venv (if needed), rerun the studies behind the docs' result tables and figures and
# rewrite them in place (scripts/reproduce_docs.py: --long, --only STEP..., --check).
source "$(dirname "$0")/_venv.sh" test
exec .venv/bin/python scripts/reproduce_docs.py "$@"
