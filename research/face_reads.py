"""How each DetNet reads faces of people it never trained on: crops of the faces in the
held-back clips (both drops; OpenCV's stock Haar cascade, `detnet_data.face_boxes`, cut as
`handtrain detnet --face-neg` cuts the training people's, `detnet_data.face_crop`: a hand's
crop side, no hand in the crop), read by each network given. Prints, per network, the mean
heatmap peak (the tracker's confidence: a track is born at `birth_confidence` 0.3 and kept
down to `min_confidence` 0.1), the share of face crops at or over each, the share the presence
head calls a hand (over `presence_threshold` 0.5), and the share that would start a track (both
bounds passed); the bounds are DetectorSettings' defaults. Session 60: the face-negative
network against the default and session 58's palm network.

    python research/face_reads.py models/detnet_lite0_int8.onnx models/detnet_lite0_palm_int8.onnx [more.onnx]
           [--every 5] [--montage runs/s60/held_faces.png]
"""
import argparse

import cv2
import numpy as np

from handmocap.perception.detector import DetectorSettings
from handmocap.perception.detnet_runner import DetNetRunner
from handmocap.training import real_data
from handmocap.training.detnet_data import face_boxes, face_crop
from handmocap.training.pose_data import SHARED_DATA


def held_back_face_crops(every, seed=0):
    """(n,128,128,3) uint8 face crops of every `every`th frame of the held-back clips whose
    every hand MediaPipe found is reliable (as the training cache is cut), and (n,) clip names."""
    rng = np.random.default_rng(seed)
    crops, names = [], []
    for clip in real_data.wild_clips(SHARED_DATA, held_back=True, drops=real_data.WILD_DROPS):
        lab = real_data.load_pseudo_labels(clip)
        reliable = real_data.reliable_hands(lab)
        frames = set(range(0, len(lab["found"]), every))
        for f, image in real_data.read_video(clip, frames=frames):
            if f >= len(lab["found"]) or not reliable[f].any() or not np.array_equal(reliable[f], lab["found"][f]):
                continue
            for face in face_boxes(image):
                for _ in range(3):
                    crop = face_crop(image, face, lab["uv"][f][reliable[f]], rng)
                    if crop is not None:
                        crops.append(crop)
                        names.append(clip.stem)
                        break
    return np.asarray(crops, np.uint8).reshape(-1, 128, 128, 3), np.asarray(names)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("detnets", nargs="+", help="DetNet ONNX files")
    p.add_argument("--every", type=int, default=5, help="every Nth frame of each held-back clip")
    p.add_argument("--montage", default=None, help="draw up to 48 of the face crops here (PNG)")
    args = p.parse_args()
    crops, names = held_back_face_crops(args.every)
    clips, counts = np.unique(names, return_counts=True)
    print(f"{len(crops)} face crops from {len(clips)} held-back clips: "
          + ", ".join(f"{c} {n}" for c, n in zip(clips, counts)))
    if not len(crops):
        raise SystemExit("no face found in the held-back clips")
    if args.montage:
        pick = crops[np.linspace(0, len(crops) - 1, min(48, len(crops))).astype(int)]
        pick = np.concatenate([pick, np.zeros((-len(pick) % 8, 128, 128, 3), np.uint8)])
        rows = [np.concatenate(list(pick[r * 8:(r + 1) * 8]), 1) for r in range(len(pick) // 8)]
        cv2.imwrite(args.montage, cv2.cvtColor(np.concatenate(rows, 0), cv2.COLOR_RGB2BGR))
    bounds = DetectorSettings()
    born, kept, present = bounds.birth_confidence, bounds.min_confidence, bounds.presence_threshold
    print(f"| network | mean peak | peak >= {born} | peak >= {kept} (kept) | presence > {present} | "
          f"born (peak >= {born}, presence > {present}) | " + " | ".join(f"{c} mean peak" for c in clips) + " |")
    print("|---|---|---|---|---|---|" + "---|" * len(clips))
    for path in args.detnets:
        out = DetNetRunner.load(path, side_path="none")(crops, read_side=False)
        peak = out["confidence"].mean(axis=1)
        is_hand = out["presence"] > present
        print(f"| {path} | {peak.mean():.3f} | {(peak >= born).mean():.3f} | {(peak >= kept).mean():.3f} | "
              f"{is_hand.mean():.3f} | {((peak >= born) & is_hand).mean():.3f} | "
              + " | ".join(f"{peak[names == c].mean():.3f}" for c in clips) + " |")


if __name__ == "__main__":
    main()
