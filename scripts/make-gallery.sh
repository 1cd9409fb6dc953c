#!/usr/bin/env bash
# Set up .venv (if needed) and remake the figures of docs/gallery/ from real runs (a few minutes).
# Arguments go to scripts/make_gallery.py, e.g. --only regions robot.
source "$(dirname "$0")/_venv.sh" test
exec .venv/bin/python scripts/make_gallery.py "$@"
