#!/usr/bin/env bash
# Install bonecap from this checkout: a virtual environment in .venv with the
# package (editable, so generic_skeleton/ and marker_sets/ are found beside it)
# and its test extra, plus the Node tools the tests use (the Khronos glTF
# validator, pinned in package.json / package-lock.json).
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e '.[test]'
if command -v npm >/dev/null 2>&1; then
  npm ci --no-audit --no-fund --silent
else
  echo "install.sh: npm not found; the glTF validator tests will be skipped" >&2
fi
echo "install.sh: bonecap installed in .venv ($(.venv/bin/bonecap --version))" >&2
