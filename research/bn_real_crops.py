"""BatchNorm statistics re-estimated on real crops only: does a DetNet trained on batches that
mix renders, real crops and negatives read the held-back people better when its BN layers
normalise with real crops' statistics? (issue 46: "measure BN re-estimated on real crops").

    python research/bn_real_crops.py runs/detnet/s35_lite0/last.pt [--n 2048] [--out runs/s35/bn_real.onnx]

The checkpoint's network is run in training mode (BN cumulative averages, momentum None) over
`--n` real training crops cut as training cuts them (detnet_batches.BatchMaker with every crop
real: the training people's, never the held-back ones; no negatives, no renders), then both
networks, as trained and re-estimated, are scored on the held-out sets (detnet_eval.validate:
the held-back people's crops `people_wild_*` / `people_11k_*`, howiema 001, the training
videos' tails). Frozen (pretrained) blocks are re-estimated too. Needs the data pack.
"""
import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from handmocap.training.pose_data import SHARED_DATA  # noqa: E402


def main():
    import torch

    from handmocap.training.detnet import DetNet, export_onnx
    from handmocap.training.detnet_batches import BatchMaker, to_torch
    from handmocap.training.detnet_data import load_real, load_synth, synth_dirs
    from handmocap.training.detnet_eval import real_val_set, validate
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=Path, help="a `handtrain detnet` checkpoint (last.pt)")
    p.add_argument("--n", type=int, default=2048, help="real training crops to re-estimate over")
    p.add_argument("--out", type=Path, default=None, help="also export the re-estimated network here")
    p.add_argument("--seed", type=int, default=35)
    p.add_argument("--data", default="runs/detnet_data/synth_train_*", help="synthetic shards (BatchMaker needs some)")
    args = p.parse_args()
    real = load_real(SHARED_DATA)
    if real is None:
        raise SystemExit(f"this study needs the data pack's real crops ({SHARED_DATA})")
    ckpt = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
    net = DetNet(ckpt.get("backbone", "fast"), fine=bool(ckpt.get("fine")))
    net.load_state_dict(ckpt["model"])
    refine = ckpt.get("refine", "softmax")
    synth = load_synth(synth_dirs([args.data]), 64)          # BatchMaker wants some; every crop drawn is real
    if synth is None:
        raise SystemExit(f"no synthetic shards match {args.data}")
    maker = BatchMaker(synth, real, share_real=1.0, share_neg=0.0, share_left=0.5, upright=60)
    again = copy.deepcopy(net).train()
    for m in again.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.reset_running_stats()
            m.momentum = None                       # a cumulative mean over every batch
    with torch.no_grad():
        for i in range(-(-args.n // 64)):
            again(to_torch(maker.make(64, np.random.default_rng([args.seed, i])))["image"])
    again.eval()
    rval = real_val_set(real)
    for name, model in (("as trained", net.eval()), ("BN on real crops", again)):
        m = validate(model, None, rval, refines=(refine,))
        keep = {k: round(v, 4) for k, v in m.items() if k.startswith(("people_", "howiema", "video", "real_hand"))}
        print(json.dumps({"network": name, **keep}))
    if args.out:
        export_onnx(again, args.out, refine)
        print(f"exported {args.out}")


if __name__ == "__main__":
    main()
