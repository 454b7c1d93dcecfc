"""The hand finder on whole frames of prepared evaluation splits (`handeval splits --work W`).

    python scripts/eval_finder.py --work /tmp/handeval [--finder models/finder.onnx] [--threshold 0.3]

Per split: recall (the best found box has IoU >= 0.3 with the square around the labelled
21-joint box), false boxes per frame (found boxes matching no labelled hand), median centre
error / box side of matched hands, and handedness of matched hands where the split has it.
Frames whose label is missing are skipped. Only one labelled hand per frame.
"""
import argparse
import glob
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.crops import square_box
from handmocap.perception.hand_finder import HandFinder, box_iou


def evaluate(finder, split_dir, threshold):
    gt = np.load(split_dir / "gt.npz")
    files = sorted(glob.glob(str(split_dir / "images" / "*")))
    hits = n = false = hand_ok = hand_n = 0
    centre_err = []
    for i, f in enumerate(files):
        uv = gt["uv"][i]
        if not np.all(np.isfinite(uv)):
            continue
        n += 1
        box = square_box(uv)
        found = finder.find(cv2.imread(f), threshold)
        ious = [box_iou(h.box, box)[0, 0] for h in found]
        best = int(np.argmax(ious)) if ious else -1
        if best >= 0 and ious[best] >= 0.3:
            hits += 1
            h = found[best]
            centre_err.append(np.linalg.norm((h.box[:2] + h.box[2:]) / 2 - (box[:2] + box[2:]) / 2) / (box[2] - box[0]))
            if "handedness" in gt.files and gt["handedness"][i] in ("left", "right"):
                hand_n += 1
                hand_ok += (h.right_prob >= 0.5) == (gt["handedness"][i] == "right")
            false += len(found) - 1
        else:
            false += len(found)
    return {"frames": n, "recall": hits / max(n, 1), "false_per_frame": false / max(n, 1),
            "centre_err": float(np.median(centre_err)) if centre_err else float("nan"),
            "handedness": hand_ok / hand_n if hand_n else float("nan")}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=Path("/tmp/handeval"))
    p.add_argument("--finder", type=Path, default=None)
    p.add_argument("--threshold", type=float, default=0.3)
    p.add_argument("--splits", nargs="+", default=["temugeb_cam0", "temugeb_cam1", "howiema_040", "cmu_sample"])
    args = p.parse_args()
    finder = HandFinder.load(args.finder)
    print("| split | frames | recall | false / frame | centre error / side | handedness |\n|---|---|---|---|---|---|")
    for s in args.splits:
        r = evaluate(finder, args.work / s, args.threshold)
        print(f"| {s} | {r['frames']} | {r['recall']:.3f} | {r['false_per_frame']:.2f} | {r['centre_err']:.3f} | "
              f"{r['handedness']:.2f} |")


if __name__ == "__main__":
    main()
