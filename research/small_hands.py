"""Small hands in large frames: how often the detector finds a hand that covers only a small
part of the frame, and how large the finder's box is against the hand's.

    python research/small_hands.py [--finder models/finder.onnx ...] [--shared ../shared/data]

Frames: howiema 001 L8 and R8 (256 px, the sequences every model keeps out of training),
each scaled so that its hand's joint box spans a given fraction of a 640x480 frame's
width, and placed in that frame with its edge pixels repeated outwards (cv2.BORDER_REPLICATE:
no second hand, no hard seam). Per finder and fraction: the share of frames where
the detector in photo mode (PHOTO_SETTINGS) reads a hand within half the hand's size of its
labels (mean joint distance), the median of that distance / hand size, and the median
finder box side / hand side for boxes on the hand.
"""
import argparse
import glob
import json
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.detector import PHOTO_SETTINGS, HandDetector
from handmocap.perception.hand_finder import HandFinder
from handmocap.training.pose_data import SHARED_DATA
from handmocap.training.real_data import HOWIEMA_HELD_OUT, HOWIEMA_TRAIN_SUBJECT

W, H = 640, 480
FRACTIONS = (0.05, 0.07, 0.1, 0.15, 0.2, 0.3)


def held_out_frames(shared: Path):
    """(BGR 256 px frame, (21,2) labels) of howiema 001's held-out sequences."""
    root = shared / "labelled2d" / "howiema_lstm_pm"
    for seq in sorted(HOWIEMA_HELD_OUT):
        labels = json.loads((root / "label" / HOWIEMA_TRAIN_SUBJECT / f"{seq}.json").read_text())
        for f in sorted(glob.glob(str(root / "frames" / HOWIEMA_TRAIN_SUBJECT / seq / "*.jpg"))):
            key = Path(f).stem[len(seq[0]):]
            if key in labels:
                yield cv2.imread(f), np.asarray(labels[key], np.float64)


def placed(image, uv, fraction, rng):
    """The frame scaled so its hand spans `fraction` of W, at a random place in a W x H frame
    (edges repeated outwards), and the labels moved with it."""
    side = np.max(uv.max(0) - uv.min(0))
    s = fraction * W / side
    small = cv2.resize(image, None, fx=s, fy=s, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    h, w = small.shape[:2]
    if h > H or w > W:
        return None, None
    x0, y0 = int(rng.integers(0, W - w + 1)), int(rng.integers(0, H - h + 1))
    frame = cv2.copyMakeBorder(small, y0, H - h - y0, x0, W - w - x0, cv2.BORDER_REPLICATE)
    return frame, uv * s + (x0, y0)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--finder", nargs="+", default=[None])
    p.add_argument("--shared", type=Path, default=SHARED_DATA)
    args = p.parse_args()
    frames = list(held_out_frames(args.shared))
    if not frames:
        raise SystemExit(f"no howiema 001 {sorted(HOWIEMA_HELD_OUT)} frames under {args.shared}")
    print("| finder | hand / frame width | frames | hand read | distance / hand size, median | finder box / hand, median |")
    print("|---|---|---|---|---|---|")
    for finder_path in args.finder:
        finder = HandFinder.load(finder_path)
        det = HandDetector.load(finder=finder_path, **PHOTO_SETTINGS)
        for fraction in FRACTIONS:
            rng = np.random.default_rng(0)
            read, dist, ratio, n = 0, [], [], 0
            for image, uv in frames:
                frame, labels = placed(image, uv, fraction, rng)
                if frame is None:
                    continue
                n += 1
                side, centre = np.max(labels.max(0) - labels.min(0)), labels.mean(0)
                det.reset()
                d = min((np.linalg.norm(h["uv"] - labels, axis=1).mean() / side for h in det.process(frame)),
                        default=np.inf)
                read += d < 0.5
                dist.append(d)
                on = [f for f in finder.find(frame) if f.box[0] <= centre[0] <= f.box[2] and f.box[1] <= centre[1] <= f.box[3]]
                if on:
                    ratio.append((on[0].box[2] - on[0].box[0]) / side)
            print(f"| {finder_path or 'models/finder.onnx'} | {fraction:.2f} | {n} | {read / n:.1%} | {np.median(dist):.3f} | "
                  f"{np.median(ratio) if ratio else float('nan'):.2f} ({len(ratio)} on the hand) |")


if __name__ == "__main__":
    main()
