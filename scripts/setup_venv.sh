#!/usr/bin/env bash
# Create (or reuse) the project's venv in .venv and install everything into it. Idempotent.
set -euo pipefail
cd "$(dirname "$(readlink -f "$0")")/.."
VENV=${PIEZO_VENV:-.venv}
if [ ! -x "$VENV/bin/python" ]; then
  python3 -m venv "$VENV"
fi
stamp="$VENV/.installed-$(cat requirements.txt setup.py | sha1sum | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -r requirements.txt
  "$VENV/bin/python" -m pip install -q -e .
  touch "$stamp"
fi
