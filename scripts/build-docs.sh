#!/usr/bin/env bash
# Set up .venv (if needed) with the docs extra, build the site into site/ with
# `mkdocs build --strict` (broken links, missing API references or malformed docstrings fail)
# and check that the built pages load nothing from the internet. Needs no network after setup.
source "$(dirname "$0")/_venv.sh" docs
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict "$@"
.venv/bin/python scripts/check_site_offline.py site
