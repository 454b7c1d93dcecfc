"""DetNet's handedness head on the training side's held-out real crops: alone, on the crop
flipped, and with the detector's mirror vote (both readings averaged in logit space).

    python research/handedness_heldout.py [--detnet int8|float32|F.onnx] [--shared ../shared/data]

The crops are those train_detnet keeps out of training (the real cache's `held` hands: the
last 15% of every training video, howiema 001 L8/R8), cut as the detector cuts a tracked
hand (its joint box x CROP_SCALE, turned upright by quarter turns) and as filmed, not
mirrored. "Right" means the head's answer says the side of the cache's label (MediaPipe's
for the videos, human for howiema). The evaluation splits are never read: this is where
the detector's `mirror_vote_every` was chosen. Prints one row per source clip and a total.
"""
import argparse
from pathlib import Path

import numpy as np

from handmocap.training import real_data
from handmocap.perception.crops import hand_angle
from handmocap.perception.tracks import logit
from handmocap.training.pose_data import SHARED_DATA
from handmocap.training.quantize_detnet import OnnxNet
from handmocap.training.detnet_data import CTX, CTX_CROP_SIDE, load_real


def heldout_crops(real):
    """(crops (N,128,128,3) RGB as filmed, the same flipped, right (N,) bool, source (N,) str)."""
    idx = np.flatnonzero(real["held"])
    side, centre = CTX_CROP_SIDE, (CTX - 1) / 2     # the detector's crop in context px
    quarter = np.pi / 2
    crops, flipped = [], []
    for i in idx:
        angle = float(np.degrees(np.round(hand_angle(real["uv"][i]) / quarter) * quarter))
        for mirror, out in ((False, crops), (True, flipped)):
            out.append(real_data.warp(real["image"][i], real_data.crop_affine(centre, centre, side, 128, angle, mirror)))
    source = np.array([s.split("/")[0] for s in real["source"][idx].astype(str)])
    return np.asarray(crops), np.asarray(flipped), real["right"][idx].astype(bool), source


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--detnet", default=None)
    p.add_argument("--shared", type=Path, default=SHARED_DATA)
    args = p.parse_args()
    real = load_real(args.shared)
    if real is None:
        raise SystemExit(f"no real data pack at {args.shared}: nothing held out to measure")
    crops, flipped, right, source = heldout_crops(real)
    detnet = OnnxNet(args.detnet)
    as_filmed, on_flipped = detnet.predict(crops)[2], detnet.predict(flipped)[2]
    answers = {"head alone": as_filmed > 0.5, "flipped crop alone": on_flipped < 0.5,
               "mirror vote": logit(as_filmed) - logit(on_flipped) > 0}
    print("| source | crops | right hands | " + " | ".join(answers) + " |")
    print("|---|---|---|" + "---|" * len(answers))
    for name in [*np.unique(source), "all"]:
        k = np.ones(len(source), bool) if name == "all" else source == name
        shares = " | ".join(f"{np.mean(a[k] == right[k]):.1%}" for a in answers.values())
        print(f"| {name} | {k.sum()} | {right[k].mean():.0%} | {shares} |")


if __name__ == "__main__":
    main()
