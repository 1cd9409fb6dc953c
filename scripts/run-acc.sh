#!/usr/bin/env bash
# Set up .venv (if needed) and run the ACC study (paper preset and stress preset) into results/.
# Extra arguments go to both runs, e.g. --seed 3.
source "$(dirname "$0")/_venv.sh" test
.venv/bin/safestab acc --scenario paper --out results "$@"
.venv/bin/safestab acc --scenario stress --out results "$@"
