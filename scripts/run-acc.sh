#!/usr/bin/env bash
# Set up .venv (if needed) and run the main job into results/: the ACC study (presets "paper"
# and "stress") and the obstacle scenario (preset "obstacle", the paper's Fig. 2).
# Extra arguments go to every run, e.g. --seed 3.
source "$(dirname "$0")/_venv.sh" test
.venv/bin/safestab run --scenario paper --out results "$@"
.venv/bin/safestab run --scenario stress --out results "$@"
.venv/bin/safestab run --scenario obstacle --out results "$@"
