"""DetNet files compared on the training-side stills, each hand read with its labelled side:
cut around the label, and cut from a box like a finder's then refined once. This separates
a network's keypoints from the detector's decisions (births, side, turns).

    python research/finder_like_reads.py [F.onnx ...]      # default: the bundled int8 DetNet

The hands are every 4th frame of scripts/detector_thresholds.py's held-out clips (its
stills; never the evaluation splits). Each is read (1) on the crop cut around its labelled
joints, mirrored for its labelled side and turned upright as the detector turns a track,
and (2) on a crop of that side x0.7-1.4 with its centre moved up to 20% of the side (fixed
seed: the same boxes for every file), then again on the crop cut from that first read's
heatmap peaks. Prints the mean and median 2D error over the hand's joint-box side.
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "scripts"))   # detector_thresholds, a tool
from detector_thresholds import clips  # noqa: E402
from handmocap.perception.crops import CropTransform, crop_for_joints
from handmocap.perception.detnet_runner import DetNetRunner
from handmocap.training.pose_data import SHARED_DATA


def errors(detnet, hands, boxes):
    """(label-placed, first read from the box, refined) errors / hand size, each (n,)."""
    out = {"label": [], "first": [], "refined": []}

    def read(crop, image, key="uv"):
        return crop.to_frame(detnet(crop.cut(image)[None, ..., ::-1].copy())[key][0])

    for (image, uv, side), (scale, shift) in zip(hands, boxes):
        mirrored, size = side == "left", np.max(uv.max(0) - uv.min(0))
        err = lambda joints: np.linalg.norm(joints - uv, axis=1).mean() / size   # noqa: E731
        crop = crop_for_joints(uv, mirrored=mirrored, upright_step=90.0)
        out["label"].append(err(read(crop, image)))
        box = CropTransform.around(crop.centre + shift * crop.side, crop.side * scale, mirrored=mirrored,
                                   angle=crop.angle)
        out["first"].append(err(read(box, image)))
        again = crop_for_joints(read(box, image, "uv_peak"), mirrored=mirrored, upright_step=90.0)
        out["refined"].append(err(read(again, image)))
    return {k: np.array(v) for k, v in out.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("detnet", nargs="*", default=["int8"], help="DetNet files (default: the bundled int8 one)")
    args = ap.parse_args()
    if not SHARED_DATA.is_dir():
        raise SystemExit(f"needs the shared data pack at {SHARED_DATA}")
    hands = [(image, uv, side) for _, frames in clips(SHARED_DATA) for image, labels, sides in frames[::4]
             for uv, side in zip(labels, sides)]
    rng = np.random.default_rng(0)
    boxes = [(rng.uniform(0.7, 1.4), rng.uniform(-0.2, 0.2, 2)) for _ in hands]
    print(f"| DetNet ({len(hands)} hands) | around the label: mean / median | from a finder-like box: first read "
          f"| refined once |\n|---|---|---|---|")
    for path in args.detnet:
        e = errors(DetNetRunner.load(path), hands, boxes)
        print(f"| {path} | " + " | ".join(f"{np.mean(e[k]):.4f} / {np.median(e[k]):.4f}"
                                          for k in ("label", "first", "refined")) + " |", flush=True)


if __name__ == "__main__":
    main()
