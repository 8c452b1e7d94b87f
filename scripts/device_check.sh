#!/usr/bin/env bash
# On a lent card's machine (its python3 holds torch with CUDA and Triton; nothing can be fetched there): install
# what `python -m bench.device_check --prepare` carried in .device_assets/, build the fused CPU kernels, run the
# device check with the arguments given, and pack its results into $OUT/gpu_results.tgz (the device tool brings
# back a few files, not a folder tree).
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
CARRIED=.device_assets
if [ -d "$CARRIED/wheels" ]; then
  "$PY" -m pip install -q --no-index --no-deps "$CARRIED"/wheels/*.whl
  for src in "$CARRIED"/wheels/*.tar.gz; do
    [ -e "$src" ] && "$PY" -m pip install -q --no-index --no-deps --no-build-isolation "$src"
  done
fi
[ -f "$CARRIED/commit" ] && export NBVH_COMMIT="$(cat "$CARRIED/commit")"
"$PY" -m nbvh_core.kernels build >/dev/null
"$PY" -m bench.device_check "$@"
code=$?
if [ -n "${OUT:-}" ]; then
  tar czf "$OUT/gpu_results.tgz" --exclude='*.ply' --exclude='*.ply.gz' -C bench/results gpu
fi
exit $code
