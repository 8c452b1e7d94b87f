#!/usr/bin/env bash
# Source me. Creates .venv in the repository root when it is missing and (re)installs the project with its
# pinned dependencies when pyproject.toml changed since the last install; otherwise reuses it as it is.
set -euo pipefail
NBVH_ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VENV="$NBVH_ROOT/.venv"
PY=${PYTHON:-python3}
stamp="$VENV/.nbvh-installed"
want=$(sha256sum "$NBVH_ROOT/pyproject.toml" | cut -d' ' -f1)
if [ ! -x "$VENV/bin/python" ]; then
  echo "creating virtual environment $VENV" >&2
  "$PY" -m venv "$VENV"
fi
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "installing nbvh_core and its pinned dependencies into $VENV (torch 2.13.0 CPU build)" >&2
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -e "$NBVH_ROOT[dev]"
  echo "$want" > "$stamp"
fi
# The fused C++ kernels of the fast path (seconds; cached per source and CPU; a machine without g++ gets a
# warning and the reference path).
"$VENV/bin/python" -m nbvh_core.kernels build >/dev/null
export NBVH_PY="$VENV/bin/python"
