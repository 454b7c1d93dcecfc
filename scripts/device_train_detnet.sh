#!/usr/bin/env bash
# One complete DetNet training job on a lent GPU machine (issue 27, point 4), in about
# MINUTES + 2 minutes (default 6: with the machine's start, one run fits the 15 minutes of
# device time a session gets): train from the carried pack, export ONNX, log validation.
#
# Here, first (once; about 2 minutes, needs ../shared and runs/detnet_data):
#     handtrain detnet --write-pack runs/device/pack --pack-mb 24
# (session 25's lead, hard negatives: --pack-mb 29 --arm-neg 0.2 --near-neg 0.3 there, 23.4 MB; the
# job below as "ARM_NEG=0.2 NEAR_NEG=0.3 bash scripts/device_train_detnet.sh")
# Then the device tool's run: command "bash scripts/device_train_detnet.sh", carry
# ["runs/device/pack"], timeout_s 600 (the tool sets $OUT there; its files come back).
# What comes back under $OUT: detnet.onnx, last.pt (the checkpoint, for --resume or
# --init-from here) and train.log. Here, after it: int8 copy and the held-back people,
#     python -m handmocap.training.quantize_detnet --src F.onnx --out F_int8.onnx
#     handeval people --detnet F_int8.onnx
# and ship it only if it measures better (model card, "DetNet").
#
# The machine has python3 with torch, numpy, opencv, onnx and onnxruntime, and no registry:
# the repository runs from the checkout (PYTHONPATH), nothing is installed. The same script
# runs on a CPU for a check (DEVICE=cpu MINUTES=0.2 WORKERS=0 BATCH=8). EXTRA adds trainer
# options, e.g. EXTRA="--motion-blur 0.3" (session 30's augmentation).
set -euo pipefail
cd "$(dirname "$0")/.."
PACK=${PACK:-runs/device/pack}
OUT=${OUT:-runs/device/out}
MINUTES=${MINUTES:-6}
DEVICE=${DEVICE:-cuda}
WORKERS=${WORKERS:-14}
BATCH=${BATCH:-256}
BACKBONE=${BACKBONE:-fast-deep}
INIT=${INIT:-models/detnet.onnx}
LR=${LR:-1e-3}
# shares of the negatives that are arms without their hand and the scene beside a hand
# (--arm-neg, --near-neg: the pack must be written with the same options to carry them)
ARM_NEG=${ARM_NEG:-0}
NEAR_NEG=${NEAR_NEG:-0}
# more handtrain detnet options, as words (e.g. EXTRA="--motion-blur 0.3")
read -r -a EXTRA_ARGS <<< "${EXTRA:-}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
python3 - <<'EOF'
import torch
print("torch", torch.__version__, "cuda", torch.cuda.is_available(),
      torch.cuda.get_device_name() if torch.cuda.is_available() else "")
EOF
# the loader processes hand batches over in shared memory: 4 batches ahead each, 192 kB a crop
# (float32); keep them within half of /dev/shm, which a container may keep small
shm_kb=$(df -k --output=avail /dev/shm 2>/dev/null | tail -1 || echo 0)
fit=$(( ${shm_kb:-0} / 2 / (4 * BATCH * 192) ))
if [ "$WORKERS" -gt "$fit" ]; then
  echo "note: /dev/shm has ${shm_kb} kB free: $fit loader processes instead of $WORKERS"; WORKERS=$fit
fi
AMP=(); [ "$DEVICE" = cuda ] && AMP=(--amp)
python3 -m handmocap.training.train_cli detnet --pack "$PACK" --device "$DEVICE" "${AMP[@]}" \
    --workers "$WORKERS" --batch "$BATCH" --backbone "$BACKBONE" --init-from "$INIT" --lr "$LR" \
    --iters 1000000 --minutes "$MINUTES" --val-every 2000 --ckpt-every 1000000 \
    --share-real 0.5 --share-neg 0.12 --upright 60 --real-3d 0.5 --arm-neg "$ARM_NEG" --near-neg "$NEAR_NEG" \
    --run-dir "$OUT/run" --export "$OUT/detnet.onnx" ${EXTRA_ARGS[@]+"${EXTRA_ARGS[@]}"} 2>&1 | tee "$OUT/train.log"
cp "$OUT/run/last.pt" "$OUT/last.pt"
rm -rf "$OUT/run"           # only 2 folder levels come back; detnet.onnx and last.pt are what matter
ls -l "$OUT"
