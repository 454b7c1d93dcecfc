"""Where a clip's false hands lie: every hand the detector outputs on none of MediaPipe's
hands (handeval people's rule: its joints' centre half the hand's size or more from every
label), with its frame, track, distance to the nearest label (hand sizes; -1: no label in
the frame), box side (px), side and presence; every 15th is drawn (labels green, the false
hand red, the frame's other outputs blue) as OUT/<clip>_<frame>.png.

    python research/false_hands.py Kirichovka__want [--out runs/false_hands] [--detnet F] [--set KEY=VALUE ...]

A clip of video/wild, held-back or training (by its stem).
"""
import argparse
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.detector import HandDetector
from handmocap.training import eval_people, real_data
from handmocap.training.eval_cli import add_model_arguments, detector_keywords, model_paths
from handmocap.training.pose_data import SHARED_DATA


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("clip", help="stem of a video/wild clip")
    p.add_argument("--shared", type=Path, default=SHARED_DATA)
    p.add_argument("--out", type=Path, default=Path("runs/false_hands"))
    add_model_arguments(p)
    args = p.parse_args()
    clips = [v for held in (True, False) for v in real_data.wild_clips(args.shared, held) if v.stem == args.clip]
    if not clips:
        raise SystemExit(f"no clip {args.clip} in {args.shared / 'video' / 'wild'}")
    args.out.mkdir(parents=True, exist_ok=True)
    detector = HandDetector.load(**detector_keywords(model_paths(args)))
    detector.reset()
    false = 0
    print("frame track distance box_px side presence")
    for f, (image, labels, _, _) in enumerate(eval_people.frames_of_clip(clips[0])):
        hands = detector.process(image)
        for hand in hands:
            _, dist = eval_people.nearest_label(hand["uv"], labels)
            if dist < eval_people.ON_HAND:
                continue
            false += 1
            print(f, hand["track_id"], round(dist, 2) if np.isfinite(dist) else -1,
                  round(float(np.ptp(hand["uv"], 0).max())), hand["handedness"], round(float(hand["score"]), 2))
            if false % 15 == 1:
                drawn = image.copy()
                for uv, colour in [(uv, (0, 255, 0)) for uv in labels] + \
                        [(h["uv"], (0, 0, 255) if h is hand else (255, 0, 0)) for h in hands]:
                    for x, y in uv:
                        cv2.circle(drawn, (int(x), int(y)), 2, colour, -1)
                cv2.imwrite(str(args.out / f"{args.clip}_{f}.png"), drawn)
    print(f"{false} false hands in {f + 1} frames")


if __name__ == "__main__":
    main()
