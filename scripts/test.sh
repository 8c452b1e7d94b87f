#!/usr/bin/env bash
# Every test: the nbvh_core unit tests (pytest). Extra arguments go to pytest.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/ensure_venv.sh"
cd "$NBVH_ROOT"
"$NBVH_PY" -m pytest tests "$@"
