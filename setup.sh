#!/usr/bin/env bash
# One-command set-up: a .venv with the pinned dependencies (requirements.lock) and UniPixie installed in it.
#   ./setup.sh            # create or update .venv
#   PYTHON=/path/to/python3.11 ./setup.sh
set -euo pipefail
cd "$(dirname "$0")"

PY="${PYTHON:-}"
if [ -z "$PY" ]; then
  for cand in python3.11 python3; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
      PY="$cand"; break
    fi
  done
fi
if [ -z "$PY" ]; then
  echo "setup.sh: error: Python 3.11 is required (bpy 5.0.1 exists for 3.11 only); set PYTHON=/path/to/python3.11" >&2
  exit 2
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup.sh: creating .venv with $("$PY" --version)"
  "$PY" -m venv .venv
fi
echo "setup.sh: installing pinned dependencies from requirements.lock (about 7 GB; a few minutes)"
.venv/bin/python -m pip install --quiet --disable-pip-version-check -r requirements.lock
echo "setup.sh: installing unipixie (editable)"
.venv/bin/python -m pip install --quiet --disable-pip-version-check --no-build-isolation --no-deps -e .
.venv/bin/unipixie --version
.venv/bin/python -c "import unipixie; print('setup.sh: ok - activate with: source .venv/bin/activate')"
