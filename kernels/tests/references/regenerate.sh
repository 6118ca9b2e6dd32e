#!/usr/bin/env bash
# Regenerates robots.json from Pinocchio and MuJoCo, in a venv with pinned versions.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="${ADFLEX_REFERENCE_VENV:-$HOME/.cache/adflex-reference-venv}"
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/pip" install -q -r "$here/requirements.txt"
"$venv/bin/python" "$here/robots.py"
