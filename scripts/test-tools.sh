#!/usr/bin/env bash
# Third-party readers the tests check dla's files with (each test skips, saying why, without its
# tool): headless Chromium for `dla view`, PlayCanvas splat-transform for .ply/.spz/.splat, and
# Blender's Python module bpy for the USD files. bpy 5.0 pins numpy < 2, which the project's own
# environment cannot share, so it gets its own venv, .venv-bpy (tests/blender/conftest.py finds it;
# DLA_BPY_PYTHON points elsewhere). It also installs MediaPipe's lite and heavy landmark models
# into .venv the way users do (scripts/install-landmarks.sh), for the --landmarks tests. Run from
# the repository root.
set -euo pipefail
if ! command -v chromium >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get install -y -q chromium >/dev/null 2>&1 \
      || { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q chromium >/dev/null 2>&1; } \
      || echo "test-tools: apt-get could not install chromium; the browser tests will skip" >&2
  else
    echo "test-tools: no chromium (Debian: sudo apt-get install chromium); the browser tests will skip" >&2
  fi
fi
if ! command -v splat-transform >/dev/null; then
  if command -v npm >/dev/null; then
    npm install -g --silent @playcanvas/splat-transform@2.7.1 >/dev/null 2>&1 \
      || echo "test-tools: npm could not install splat-transform; its round trips will skip" >&2
  else
    echo "test-tools: no npm; the splat-transform round trips will skip" >&2
  fi
fi
if [ -x .venv/bin/python ]; then
  bash scripts/install-landmarks.sh .venv/bin/python \
    || echo "test-tools: the lite and heavy landmark models did not install; their tests will skip" >&2
fi
if [ ! -x .venv-bpy/bin/python ]; then
  python3 -m venv .venv-bpy && .venv-bpy/bin/pip install -q "bpy==5.0.1" \
    || echo "test-tools: bpy did not install (it needs CPython 3.11); the Blender tests will skip" >&2
fi
