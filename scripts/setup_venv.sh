#!/usr/bin/env bash
# Create (or reuse) the project's venv in .venv and install everything into it. Idempotent.
# The packages are installed with uv (from PyPI, as pip would; several times quicker than pip on a fresh
# machine) where uv can be installed and does the install; otherwise, or where uv fails, with pip.  Either way
# compiled to bytecode at install (pip does by default, uv when asked): a process that may not write bytecode
# (PYTHONDONTWRITEBYTECODE) would otherwise compile every module it imports at each start (each node and tool
# the tests start: twice the start-up).
# PIEZO_INSTALLER=pip skips uv.
set -euo pipefail
cd "$(dirname "$(readlink -f "$0")")/.."
VENV=${PIEZO_VENV:-.venv}
if [ ! -x "$VENV/bin/python" ]; then
  python3 -m venv "$VENV"
fi
stamp="$VENV/.installed-$(cat requirements.txt setup.py | sha1sum | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  installed=
  if [ "${PIEZO_INSTALLER:-uv}" = uv ] && "$VENV/bin/python" -m pip install -q uv >/dev/null 2>&1; then
    uv=("$VENV/bin/uv" pip install -q --compile-bytecode --python "$VENV/bin/python")
    if "${uv[@]}" -r requirements.txt && "${uv[@]}" -e .; then
      installed=uv
    else
      echo "setup_venv: uv could not install the packages; installing them with pip" >&2
    fi
  fi
  if [ -z "$installed" ]; then
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -r requirements.txt
    "$VENV/bin/python" -m pip install -q -e .
  fi
  touch "$stamp"
fi
