#!/usr/bin/env bash
# Pre-training that a 2-core CPU cannot afford, on a lent GPU machine (issue 35 item 9): the
# eighth checkpoint's recipe (scripts/pretrain_real.sh) for many more steps, three variants side by
# side on the one GPU, each for $MINUTES of training.
#
# Here (the machine with the pairs), once; what travels is capped at 64 MiB, so the pairs are
# packed (every 2nd training view, JPEG q90, float16 depths: scripts/pack_pairs.py prints the cost):
#   C=~/.cache/roguenerf/pairs
#   python scripts/pack_pairs.py $C/{cup,dtu_scan24,coke_can,beer,bird_figurine,blowtorch,dancing_robot,doraemon}/coarse_x3 \
#       ../shared/data/lego --out .gpu/pairs --every 2 --quality 90
#   git show b611814:roguenerf/weights/default.safetensors > .gpu/sixth.safetensors   # START
#   pip download --no-deps kornia==0.9.0 kornia_rs==0.2.0 (cp312 manylinux x86_64) -d .whl
# There (device tool: carry .gpu and .whl), from the repository root:
#   MINUTES=6 ROGUENERF_THREADS=5 OUT_DIR=$OUT scripts/gpu_pretrain.sh   # 385 s on an H100, 2026-11-27
# It writes OUT_DIR/{A,B,C}.safetensors (the trained weights) and {A,B,C}.log. Then, here, blend and
# measure on the leave-one-kind-out figure as for the eighth (docs/kinds.md, *Pre-training on a GPU*:
# none beat the eighth):
#   python -c 'from roguenerf.checkpoint import blend_checkpoints as b; b(".gpu/sixth.safetensors", "A.safetensors", 0.5, "A_half.safetensors")'
set -euo pipefail
cd "$(dirname "$0")/.."
PACK=${PACK:-.gpu/pairs}
START=${START:-.gpu/sixth.safetensors}
MINUTES=${MINUTES:-6}
OUT_DIR=${OUT_DIR:?set OUT_DIR}
PY=${PY:-python3}
if ! "$PY" -c 'import kornia' 2> /dev/null; then  # the device image lacks kornia: carried wheels
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1 ROGUENERF_THREADS=${ROGUENERF_THREADS:-6}
nvidia-smi -L || true
if [ "${REQUIRE_CUDA:-1}" = 1 ]; then  # REQUIRE_CUDA=0: a dry run on the CPU (MINUTES=0.1)
  "$PY" -c 'import torch; assert torch.cuda.is_available(), "no CUDA device"; print(torch.__version__, torch.cuda.get_device_name())'
fi

# The eighth's recipe: from the sixth, lr 2.5e-4 cosine over the budget, seed 7, each neighbour's
# pose off by up to 0.5 deg / 5 %, 2 neighbours, micro.
common=(--checkpoint "$START" --variant micro --neighbours 2 --lr 2.5e-4 --lr-schedule cosine --seed 7
        --neighbour-pose-noise 0.5,0.05 --minutes "$MINUTES")
run() {  # NAME ARGS...: train into /tmp/NAME, keep the weights and the log
  local name=$1; shift
  "$PY" -m roguecli pretrain "$PACK"/* --output "/tmp/$name" "${common[@]}" "$@" > "$OUT_DIR/$name.log" 2>&1 \
    && cp "/tmp/$name/model.safetensors" "$OUT_DIR/$name.safetensors"
}
run A --crop 64 --batch 4 &     # the CPU recipe, many more steps
run B --crop 128 --batch 16 &   # 16x the pixels per step: wider context for flow and attention
run C --crop 128 --batch 16 --depth-noise 0.3 &  # B, with half the target depths off (fall back on the render)
wait
grep -H "^saved\|Error" "$OUT_DIR"/*.log
