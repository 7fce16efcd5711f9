#!/usr/bin/env bash
# Create the isolated Blender-as-a-module venv used by the data generator.
# Idempotent: re-running only checks the pinned versions in tools/datagen/requirements.txt.
# bpy pins numpy<2, so it must never be installed into the project's main environment.
set -euo pipefail
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
VENV="${DATAGEN_VENV:-$REPO_ROOT/.venv-datagen}"
PY="${DATAGEN_PYTHON:-python3.11}"

if [ ! -x "$VENV/bin/python" ]; then
    echo "[setup_env] creating $VENV with $PY"
    "$PY" -m venv "$VENV"
fi

REQ="$REPO_ROOT/tools/datagen/requirements.txt"
if "$VENV/bin/python" - "$REQ" <<'PYEOF' 2>/dev/null
import importlib.metadata as m, sys
reqs = [l.split("#")[0].strip() for l in open(sys.argv[1])]
reqs = [r.split("==") for r in reqs if r]
sys.exit(0 if all(m.version(n) == v for n, v in reqs) else 1)
PYEOF
then
    echo "[setup_env] requirements already satisfied in $VENV"
else
    echo "[setup_env] installing $(grep -v '^#' "$REQ" | xargs) into $VENV"
    "$VENV/bin/python" -m pip install --quiet --upgrade pip
    "$VENV/bin/python" -m pip install --quiet -r "$REQ"
fi

# Debian package with the CMU motion-capture BVH used by the articulated sequence.
if [ ! -f /usr/share/assimp/models/BVH/01_01.bvh ]; then
    if command -v apt-get >/dev/null && [ "$(id -u)" = "0" ]; then
        echo "[setup_env] installing Debian package assimp-testmodels"
        apt-get update -qq && apt-get install -y -qq assimp-testmodels >/dev/null
    else
        echo "[setup_env] WARNING: /usr/share/assimp/models/BVH/01_01.bvh missing;" \
             "install Debian package assimp-testmodels (needed for the articulated sequence)" >&2
    fi
fi
echo "[setup_env] ok: $("$VENV/bin/python" -c 'import bpy, numpy; print("bpy", bpy.app.version_string, "numpy", numpy.__version__)')"
