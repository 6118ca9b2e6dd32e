#!/usr/bin/env bash
# Regenerates robots.json (Pinocchio, MuJoCo) and mpm99.json (Taichi), in a venv with pinned
# versions.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="${ADFLEX_REFERENCE_VENV:-$HOME/.cache/adflex-reference-venv}"
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/pip" install -q -r "$here/requirements.txt"
"$venv/bin/python" "$here/robots.py"
"$venv/bin/python" "$here/taichi_mpm99.py"
