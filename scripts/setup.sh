#!/usr/bin/env bash
# One-time set-up: Debian libraries that Blender's Cycles loads, a Python 3.11 venv in .venv,
# and the pinned project (CPU torch, bpy 5.0.1). Safe to re-run; does nothing when up to date.
set -euo pipefail
cd "$(dirname "$0")/.."

libs="libx11-6 libxext6 libxi6 libxrender1 libxfixes3 libxkbcommon0 libsm6 libice6 libgl1"
missing=""
for l in $libs; do dpkg -s "$l" >/dev/null 2>&1 || missing="$missing $l"; done
if [ -n "$missing" ]; then
  echo "setup: installing Debian libraries for bpy:$missing"
  sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
  $sudo apt-get update -qq && $sudo apt-get install -y -qq --no-install-recommends $missing
fi

py=$(command -v python3.11 || command -v python3)
"$py" -c 'import sys; assert sys.version_info[:2] == (3, 11), "bpy 5.0.x needs Python 3.11, found %s" % sys.version.split()[0]'
stamp=.venv/.installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  [ -x .venv/bin/python ] || "$py" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test,bench]'
  touch "$stamp"
fi
# `make repro` and `make test` put .venv/bin first on PATH themselves; a shell needs it once
[ "$(command -v rpod || true)" = "$PWD/.venv/bin/rpod" ] || echo "setup: done; run \`source .venv/bin/activate\` to put rpod and dvc on PATH (or call .venv/bin/rpod)"
