"""Per held-back crop, which handedness head reads the side better: the int8 (fast-deep)
network's, lite0's, or the mean of their logits? (session 37: 72.1% / 72.7% / 74.4% single,
74.4% / 73.9% / 74.6% as a pair, upright: the heads are about equally good per crop, so the
tracked side's difference comes from how their errors fall over a clip.)

    python research/side_heads_per_crop.py [--upright]

The held-back clips' crops cut around MediaPipe's label (quantize_detnet.heldout_sets), each
read as it is (the side shown) and flipped (the other side): "single" scores both readings
against the side shown, "pair" whether the two readings' logits order the right way (the
detector's mirror vote). Needs the data pack.
"""
import argparse

import numpy as np

from handmocap.perception.detnet_runner import DETNET_INT8, DETNET_LITE0
from handmocap.perception.tracks import logit
from handmocap.training.detnet_eval import HELD_BACK_SOURCE
from handmocap.training.quantize_detnet import OnnxNet, heldout_sets


def accuracy(right_logit, flipped_logit):
    """(single, pair) side accuracy of readings of the crops (N,) and of the crops flipped (N,)."""
    return np.mean([(right_logit > 0).mean(), (flipped_logit < 0).mean()]), ((right_logit - flipped_logit) > 0).mean()


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--upright", action="store_true", help="crops turned upright as the detector turns them")
    args = p.parse_args()
    _, rval = heldout_sets(upright=args.upright)
    source = rval["source"].astype(str)
    clips = np.char.startswith(source, HELD_BACK_SOURCE) & ~np.char.startswith(source, HELD_BACK_SOURCE + "11k/")
    images = rval["image"][clips]
    reads = {}
    for name, path in (("int8", DETNET_INT8), ("lite0", DETNET_LITE0)):
        net = OnnxNet(path)
        reads[name] = (logit(net.predict(images)[2]), logit(net.predict(images[:, :, ::-1])[2]))
    reads["mean of both"] = tuple((a + b) / 2 for a, b in zip(reads["int8"], reads["lite0"]))
    print(f"{clips.sum()} held-back clips' crops{' (upright)' if args.upright else ''}")
    print("| head | single | pair |\n|---|---|---|")
    for name, (r, f) in reads.items():
        print("| %s | %.1f%% | %.1f%% |" % (name, *(100 * a for a in accuracy(r, f))))


if __name__ == "__main__":
    main()
