#!/usr/bin/env bash
# Create .venv with Python 3.12 and install lerobot-murm with its dev (tests and ruff) and ray
# extras (the suite runs a grid on a real local Ray cluster).
#
# pybullet 3.2.7 has no wheel for Python 3.12 and compiles from source (about 6 minutes
# on 2 cores). It is built once, with NumPy present so that getCameraImage returns
# arrays (about 35% faster rendering than the tuples a plain `pip install` build gives),
# and kept in ~/.cache/lerobot-murm/wheels for later installs and fresh clones.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3.12}
PYBULLET_VERSION=3.2.7
WHEELS="${XDG_CACHE_HOME:-$HOME/.cache}/lerobot-murm/wheels"

if ! command -v "$PYTHON" >/dev/null 2>&1 || ! "$PYTHON" -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null; then
    echo "error: Python 3.12 is required (LeRobot 0.6.1 needs >= 3.12; tried '$PYTHON')." >&2
    echo "       With pyenv: 'pyenv install 3.12' (this repo's .python-version selects it), or set PYTHON=/path/to/python3.12." >&2
    exit 1
fi

[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip setuptools wheel numpy

if ! ls "$WHEELS"/pybullet-"$PYBULLET_VERSION"-*.whl >/dev/null 2>&1; then
    echo "building pybullet $PYBULLET_VERSION with NumPy support (once, about 6 minutes)..."
    mkdir -p "$WHEELS"
    .venv/bin/python -m pip wheel --no-deps --no-cache-dir --no-binary pybullet --no-build-isolation \
        --wheel-dir "$WHEELS" "pybullet==$PYBULLET_VERSION"
fi
.venv/bin/python -m pip install --quiet --no-index --find-links "$WHEELS" "pybullet==$PYBULLET_VERSION"
.venv/bin/python -m pip install --quiet --find-links "$WHEELS" -e ".[dev,ray]"
.venv/bin/python -c 'import pybullet, lerobot_murm; assert pybullet.isNumpyEnabled(), "pybullet built without NumPy"'
echo "installed: $(.venv/bin/python -c 'import lerobot, lerobot_murm; print("lerobot", lerobot.__version__, "lerobot-murm", lerobot_murm.__version__)')"
