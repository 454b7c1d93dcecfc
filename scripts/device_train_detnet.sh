#!/usr/bin/env bash
# One complete DetNet training job on a lent GPU machine (issue 46: the lite0 backbone from its
# ImageNet weights), in about MINUTES + 1.5 minutes: train from the carried pack, export ONNX and
# the float16 weights, log validation.
#
# Here, first (once; about a minute, needs ../shared and runs/detnet_data):
#     handtrain detnet --backbone lite0 --write-pack runs/device/s42 --pack-mb 78 --pack-quality 75 \
#         --arm-neg 0.2 --near-neg 0.3 --data 'runs/detnet_data/synth_train_s35_*' --max-synth 24576
# (62 MB: every real training crop, 10,267 rendered ones and the trunk's ImageNet weights in float16).
# The device tool carries at most 64 MiB with the working tree, so the call is made from a
# checkout without the tracked weights and pictures (models/, data/, docs' images: 55 MB), e.g. a
# throwaway branch that `git rm`s them; `git checkout main` brings them back afterwards.
# Then the device tool's run: command "PACK=runs/device/s42 bash scripts/device_train_detnet.sh",
# carry ["runs/device/s42"], timeout_s MINUTES*60 + 150 (the tool sets $OUT; its files come back).
# What comes back under $OUT: detnet.onnx (float32), weights_fp16.pt (the network's weights, for
# `--init-from` here: the checkpoint with AdamW's state is 37 MB, over the 16 MiB a file may have)
# and train.log. Here, after it: the int8 copy and the held-back people,
#     python -m handmocap.training.quantize_detnet --src F.onnx --out F_int8.onnx
#     handeval people --jitter 9 --detnet F_int8.onnx --side-detnet int8
# and ship it only by the rule written before the run (model card, "DetNet"). Commit what came
# back (weights_fp16.pt, 6 MB) as models/candidates/<run>.pt in the same session, shipped or not:
# runs/ is git-ignored and goes with the machine (session 42's GPU run and its polished copy,
# the best keypoints measured on strangers, were lost that way before session 45).
#
# Session 42 on an H200 (15 minutes of device time): a cold start and the 65 MB transfer took
# 35-90 s a call; MINUTES=6.5 ran 419 s (6,564 iterations of 256 at 17-19 a second, validation
# and exports included). One call of MINUTES=8.5 with timeout_s 600 fits the lease with a
# minute to spare, but leaves no room for a second start (4 minutes needed).
# The machine has python3 with torch, numpy, opencv, onnx and onnxruntime, and no registry:
# the repository runs from the checkout (PYTHONPATH), nothing is installed. The same script
# runs on a CPU for a check (DEVICE=cpu MINUTES=0.2 WORKERS=0 BATCH=8). EXTRA adds trainer
# options, e.g. EXTRA="--motion-blur 0.3".
set -euo pipefail
cd "$(dirname "$0")/.."
PACK=${PACK:-runs/device/pack}
OUT=${OUT:-runs/device/out}
MINUTES=${MINUTES:-6}
DEVICE=${DEVICE:-cuda}
WORKERS=${WORKERS:-14}
BATCH=${BATCH:-256}
BACKBONE=${BACKBONE:-lite0}
INIT=${INIT:-}                  # a checkpoint to start from; empty: lite0 from the pack's ImageNet weights
LR=${LR:-2e-3}
VAL_EVERY=${VAL_EVERY:-1500}
# session 41's recipe (its CPU run's shares, negatives and side options)
ARM_NEG=${ARM_NEG:-0.2}
NEAR_NEG=${NEAR_NEG:-0.3}
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
if [ "$WORKERS" -gt "$fit" ] && [ "$(id -u)" = 0 ] && mount -o remount,size=16g /dev/shm 2>/dev/null; then
  shm_kb=$(df -k --output=avail /dev/shm | tail -1); fit=$(( shm_kb / 2 / (4 * BATCH * 192) ))   # root there: grow it
fi
if [ "$WORKERS" -gt "$fit" ]; then
  echo "note: /dev/shm has ${shm_kb} kB free: $fit loader processes instead of $WORKERS"; WORKERS=$fit
fi
AMP=(); [ "$DEVICE" = cuda ] && AMP=(--amp)
INIT_ARGS=(); [ -n "$INIT" ] && INIT_ARGS=(--init-from "$INIT")
python3 -m handmocap.training.train_cli detnet --pack "$PACK" --device "$DEVICE" "${AMP[@]}" \
    --workers "$WORKERS" --batch "$BATCH" --backbone "$BACKBONE" ${INIT_ARGS[@]+"${INIT_ARGS[@]}"} --lr "$LR" \
    --iters 1000000 --minutes "$MINUTES" --val-every "$VAL_EVERY" --ckpt-every 1000000 \
    --share-real 0.45 --share-neg 0.12 --upright 60 --real-3d 0.5 --left-2d 1.0 --share-left 0.5 \
    --arm-neg "$ARM_NEG" --near-neg "$NEAR_NEG" \
    --run-dir "$OUT/run" --export "$OUT/detnet.onnx" ${EXTRA_ARGS[@]+"${EXTRA_ARGS[@]}"} 2>&1 | tee "$OUT/train.log"
python3 -m handmocap.training.train_cli detnet --backbone "$BACKBONE" --device "$DEVICE" --run-dir "$OUT/run" \
    --export-only --export "$OUT/run/final.onnx" --weights-out "$OUT/weights_fp16.pt" 2>&1 | tail -2 | tee -a "$OUT/train.log"
rm -rf "$OUT/run"           # only 2 folder levels and 16 MiB a file come back: what matters is above
ls -l "$OUT"
