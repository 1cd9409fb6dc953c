#!/usr/bin/env bash
# Set up .venv (if needed) with the lint extra (a pinned ruff, so that a new ruff release
# cannot fail CI on its own) and check the code: ruff's lint rules and its formatting.
source "$(dirname "$0")/_venv.sh" lint
.venv/bin/ruff check src tests benchmarks scripts
.venv/bin/ruff format --check src tests benchmarks scripts
