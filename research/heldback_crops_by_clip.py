"""DetNet files side by side on the held-back people's held-out crops, clip by clip: the median
2D error / joint-box side of each crop cut around its label, upright and shown as a right
hand (detnet_eval.real_val_set, a perfect finder, tracker and side), so a change aimed
at some clips' conditions (two hands touching, a sink from above, hands foreshortened) shows
where it lands.

    python research/heldback_crops_by_clip.py models/detnet_int8.onnx runs/detnet/X/final_int8.onnx ...
    python research/heldback_crops_by_clip.py --as-cut ...     (unturned: the crops `quantize_detnet --compare` reads)
"""
import argparse

import numpy as np
from read_fusion import relative_error          # research/ is on the path when run as a script

from handmocap.training.quantize_detnet import OnnxNet, heldout_sets
from handmocap.training.detnet_data import HELD_BACK_SOURCE
from handmocap.training.detnet_eval import heldout_groups
from handmocap.training.real_data import foreshortened


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("detnet", nargs="+", help="exported DetNet files (ONNX)")
    p.add_argument("--as-cut", action="store_true",
                   help="the crops as cut around the label, not turned upright (the hands at any angle, as "
                        "`python -m handmocap.training.quantize_detnet --compare` and a run's own log read them)")
    args = p.parse_args()
    _, crops = heldout_sets(upright=not args.as_cut)
    held = heldout_groups(crops["source"])
    clips, source = held["held-back clips"], crops["source"].astype(str)      # a clip's crops: heldback/<clip>
    groups = {name[len(HELD_BACK_SOURCE):]: clips & (source == name) for name in sorted(set(source[clips]))}
    groups["11K Hands photos"], groups["all held-back clips"] = held["held-back photos"], clips
    short = foreshortened(crops["uv"])      # palm to the camera, fingers first (session 52)
    groups["held-back clips, foreshortened"], groups["held-back clips, the others"] = clips & short, clips & ~short
    errors = [relative_error(OnnxNet(path).predict(crops["image"])[0][0], crops["uv"]) for path in args.detnet]
    print("| held-back crops | n | " + " | ".join(args.detnet) + " |")
    print("|---|---|" + "---|" * len(args.detnet))
    for name, mask in groups.items():
        print(f"| {name} | {mask.sum()} | " + " | ".join(f"{np.median(e[mask]):.4f}" for e in errors) + " |")


if __name__ == "__main__":
    main()
