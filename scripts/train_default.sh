#!/usr/bin/env bash
# Pre-train the lego + toy checkpoint: the shipped default before real-scene pre-training, and the
# START of scripts/pretrain_real.sh (roguenerf/weights/default.safetensors is its DEST here).
#
# Pre-training data: N generated toy scenes with NeRF-like degradations plus the TRAIN views of
# the real scenes given (lego by default; its test views are never used). Resumable: run it
# again with the same OUT to continue an interrupted run.
#
#   scripts/train_default.sh                    # 50 min, micro, constant lr 5e-4, lego + 4 toy scenes
#   MINUTES=240 VARIANT=nano TOY=16 scripts/train_default.sh /path/to/sceneA /path/to/sceneB
#
# The shipped weights came from the defaults below, run as
#   OMP_NUM_THREADS=1 nice -n 5 .venv/bin/roguenerf pretrain ../shared/data/lego --toy 4 \
#       --variant micro --crop 64 --lr 5e-4 --minutes 50 --output runs/pretrain_default
# on a 2-core CPU shared with other jobs (time-budgeted, so the step count depends on load).
set -euo pipefail
cd "$(dirname "$0")/.."
MINUTES=${MINUTES:-50}
VARIANT=${VARIANT:-micro}
TOY=${TOY:-4}
CROP=${CROP:-64}
LR=${LR:-5e-4}
LR_SCHEDULE=${LR_SCHEDULE:-constant}  # as the previous default was trained (cosine: decay to 0)
OUT=${OUT:-runs/pretrain_default}
DEST=${DEST:-roguenerf/weights/default.safetensors}
SHARED=${ROGUENERF_SHARED_DATA:-../shared/data}
if [ "$#" -gt 0 ]; then scenes=("$@"); else scenes=("$SHARED/lego"); fi
extra=()
if [ -n "${VGG_WEIGHTS:-}" ]; then extra+=(--vgg-weights "$VGG_WEIGHTS"); fi

.venv/bin/roguenerf pretrain "${scenes[@]}" --toy "$TOY" --minutes "$MINUTES" --variant "$VARIANT" \
  --crop "$CROP" --lr "$LR" --lr-schedule "$LR_SCHEDULE" --output "$OUT" "${extra[@]}"
mkdir -p "$(dirname "$DEST")"
cp "$OUT/model.safetensors" "$DEST"
if [ -f "$OUT/model.json" ]; then cp "$OUT/model.json" "${DEST%.safetensors}.json"; fi
echo "default checkpoint: $DEST" >&2
.venv/bin/roguenerf evaluate "$SHARED/lego" --checkpoint "$DEST"
