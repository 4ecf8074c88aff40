#!/usr/bin/env bash
# Pre-train the shipped default checkpoint (roguenerf/weights/default.safetensors).
#
# Pre-training data: N generated toy scenes with NeRF-like degradations plus the TRAIN views of
# the real scenes given (lego by default; its test views are never used). Resumable: run it
# again with the same OUT to continue an interrupted run.
#
#   scripts/train_default.sh                    # 60 min, nano, lego + 8 toy scenes
#   MINUTES=240 VARIANT=nano TOY=16 scripts/train_default.sh /path/to/sceneA /path/to/sceneB
set -euo pipefail
cd "$(dirname "$0")/.."
MINUTES=${MINUTES:-60}
VARIANT=${VARIANT:-nano}
TOY=${TOY:-8}
OUT=${OUT:-runs/pretrain_default}
DEST=${DEST:-roguenerf/weights/default.safetensors}
SHARED=${ROGUENERF_SHARED_DATA:-../shared/data}
if [ "$#" -gt 0 ]; then scenes=("$@"); else scenes=("$SHARED/lego"); fi
extra=()
if [ -n "${VGG_WEIGHTS:-}" ]; then extra+=(--vgg-weights "$VGG_WEIGHTS"); fi

.venv/bin/roguenerf pretrain "${scenes[@]}" --toy "$TOY" --minutes "$MINUTES" --variant "$VARIANT" \
  --output "$OUT" "${extra[@]}"
mkdir -p "$(dirname "$DEST")"
cp "$OUT/model.safetensors" "$DEST"
if [ -f "$OUT/model.json" ]; then cp "$OUT/model.json" "${DEST%.safetensors}.json"; fi
echo "default checkpoint: $DEST" >&2
.venv/bin/roguenerf evaluate "$SHARED/lego" --checkpoint "$DEST"
