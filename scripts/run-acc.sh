#!/usr/bin/env bash
# Set up .venv (if needed) and run the main job into results/: the ACC study (presets "paper"
# and "stress"), the obstacle scenario (preset "obstacle", the paper's Fig. 2) and the swarm
# (preset "swarm", the safety filter with a barrier per pair).
# Extra arguments go to every run, e.g. --seed 3.
source "$(dirname "$0")/_venv.sh" test
# one command for the three learning studies: the two ACC studies share a process (it
# imports once and traces the programs they share once); with two CPUs or more the obstacle
# study runs in a second process beside it (--jobs, default one per CPU)
.venv/bin/safestab run --scenario paper --scenario stress --scenario obstacle --out results "$@"
# the swarm learns nothing (no --n-samples) and its file has other keys (no --set): it takes
# --seed and --t-final of the extra arguments
swarm_args=()
while [ $# -gt 0 ]; do
  case "$1" in
    --seed|--t-final) swarm_args+=("$1" "$2"); shift 2 ;;
    --seed=*|--t-final=*) swarm_args+=("$1"); shift ;;
    *) shift ;;
  esac
done
.venv/bin/safestab run --scenario swarm --out results "${swarm_args[@]}"
