"""How the tracker's crops sit on the labelled hands of the video/wild clips: crop side / (label's joint
box x CROP_SCALE), centre offset / crop side, and the error inside and outside the range DetNet's real
training crops cover by default (x 0.9-1.1, 0.1).

    python research/tracked_crop_fit.py train|held
"""
import sys
import numpy as np
from handmocap.training import real_data, eval_people
from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.crops import CROP_SCALE
from handmocap.perception.detector import HandDetector
held = sys.argv[1] == "held"
det = HandDetector.load()
ratio, off, err = [], [], []
for video in real_data.wild_clips(SHARED_DATA, held_back=held):
    det.reset()
    for f, (img, hands, rel, sides) in enumerate(eval_people.frames_of_clip(video)):
        for h in det.process(img):
            k, d = eval_people.nearest_label(h["uv"], hands)
            if d >= eval_people.ON_HAND or not rel[k]:
                continue
            lab = hands[k]; b = np.asarray(h["bbox"], float)
            side_l = np.ptp(lab, 0).max() * CROP_SCALE
            side_c = np.mean(b[2:] - b[:2])
            ratio.append(side_c / side_l)
            off.append(np.abs(((b[:2] + b[2:]) / 2 - (lab.min(0) + lab.max(0)) / 2) / side_c).max())
            err.append(np.linalg.norm(h["uv"] - lab, axis=-1).mean() / real_data.hand_size(lab))
ratio, off, err = map(np.array, (ratio, off, err))
print("n", len(ratio))
print("side ratio pct 5/25/50/75/95:", np.percentile(ratio, [5, 25, 50, 75, 95]).round(3))
print("centre offset (max axis)/side pct 50/75/90/95:", np.percentile(off, [50, 75, 90, 95]).round(3))
inside = (ratio > 0.9) & (ratio < 1.1) & (off < 0.1)
print("share within training jitter (0.9-1.1, 0.1):", inside.mean().round(3), "median err inside", np.median(err[inside]).round(3), "outside", np.median(err[~inside]).round(3))
