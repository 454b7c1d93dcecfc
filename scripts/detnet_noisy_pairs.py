"""DetNet's 3D on rendered crops of known poses, paired with the truth: IKNet's noisy input
as the paper trains it (Sec. 3.3: positional supervision through FK on detector output).

    handsynth generate -n 8192 -o runs/iknet_data/synth_ik_0 --seed 1500      # (and _1, _2, ...)
    python scripts/detnet_noisy_pairs.py --data 'runs/iknet_data/synth_ik_*' --out runs/iknet_data/detnet_pairs.npz
    handtrain iknet --noisy-source runs/iknet_data/detnet_pairs.npz

Each crop is shown to DetNet as the detector shows it (left hands mirrored to the right,
turned upright by quarter turns: quantize_detnet.quarter_turned), run by default as the
shipped int8 copy. Writes `pred` (N,21,3) DetNet's xyz, `target` (N,21,3) the rendered
hand's joints in the same axes, `rest` (N,21,3) the hand model's rest joints at the
rendered β (all root-relative and scale-normalized: pose_data.PositionPairs.from_npz).
Render new shards for this (not DetNet's training shards, whose errors DetNet has learnt
away) and keep the held-out synthetic validation shard out of it.
"""
import argparse
import glob
from pathlib import Path

import numpy as np

from handmocap.perception.hand_model import HandModel
from handmocap.training.quantize_detnet import OnnxNet, quarter_turned
from handmocap.perception.skeleton import normalize_joints
from handmocap.training.synth.dataset import SynthDataset
from handmocap.training.detnet_eval import shown_as_right


def pairs(detnet, shard, model, batch=128):
    """(pred, target, rest) of one shard dict (SynthDataset.shard); detnet: a quantize_detnet.OnnxNet."""
    image, uv, xyz = shown_as_right(shard["image"], shard["uv"], shard["xyz_rel"].astype(np.float64),
                                    shard["handedness"] == 1)
    shown = quarter_turned({"image": image, "uv": uv, "xyz": xyz})
    pred = detnet.predict(shown["image"], batch)[0][1]
    rest = model.rest_joints(shard["beta"].astype(np.float64))
    return normalize_joints(pred), normalize_joints(shown["xyz"]), normalize_joints(rest)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", nargs="+", required=True, help="handsynth crop shard directories (globs)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--detnet", default=None, help="int8 (default), float32 or an ONNX path")
    args = p.parse_args()
    dirs = sorted({d for pat in args.data for d in glob.glob(pat) if (Path(d) / "meta.json").exists()})
    if not dirs:
        raise SystemExit(f"no complete shard directory matches {args.data}: render some with handsynth generate")
    detnet, model = OnnxNet(args.detnet), HandModel.load()
    out = {"pred": [], "target": [], "rest": []}
    for d in dirs:
        ds = SynthDataset(d)
        for k in range(len(ds.counts)):
            for key, value in zip(out, pairs(detnet, ds.shard(k), model)):
                out[key].append(value.astype(np.float32))
        print(f"{d}: {sum(len(v) for v in out['pred'])} pairs so far")
    arrays = {k: np.concatenate(v) for k, v in out.items()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(args.out, **arrays)
    err = np.linalg.norm(arrays["pred"] - arrays["target"], axis=-1).mean()
    print(f"wrote {args.out}: {len(arrays['pred'])} pairs; DetNet's mean joint error {err:.3f} reference bones")


if __name__ == "__main__":
    main()
