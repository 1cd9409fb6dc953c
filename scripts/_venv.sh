# Shared by the run-*.sh scripts: create .venv with Python >= 3.11 and install safestab into it.
# Usage: source scripts/_venv.sh EXTRAS   (EXTRAS like "test" or "bench,test")
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY="${PYTHON:-}"
if [ -z "$PY" ]; then
  for cand in python3.11 python3.12 python3.13 python3; do
    if command -v "$cand" >/dev/null 2>&1; then PY="$cand"; break; fi
  done
fi
# safestab.export compiles C: install a compiler where there is none (CI machines run as root
# with apt; elsewhere say what is missing and go on, the rest of safestab works without one)
if ! command -v cc >/dev/null 2>&1 && ! command -v gcc >/dev/null 2>&1; then
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq gcc libc6-dev >/dev/null \
      || echo "warning: could not install a C compiler; safestab.export will not compile" >&2
  else
    echo "warning: no C compiler (cc) found; install gcc to use safestab.export" >&2
  fi
fi
"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "safestab needs Python >= 3.11")'
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[$1]"
