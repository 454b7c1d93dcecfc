"""Which way is "up" for a tracked crop: the quarter turn each definition of a hand's angle
picks, read one frame at a time (session 58).

    python research/turn_definitions.py [--drops wild] [--training-clips]

The clips are tracked as `handeval people` tracks them. Every scored hand's crop is read again
at its four quarter turns (same centre, side and mirroring), and each definition of the hand's
angle, taken from MediaPipe's label or from this frame's reading, picks one of the four; printed:
the median and mean error / hand size at the picked turn, and the share where it is the best
turn. A one-frame proxy: in tracking the reading turns the *next* crop, and what a turn does to
that reading is not here (`handeval people --set turn_by=palm` measures that).

Session 58, shipped networks. video/wild held back (2,273 hands), from the reading: wrist ->
middle knuckle (today's) 0.0953, the knuckle line's normal 0.0924, their sum in px
(crops.palm_angle) 0.0878 (mean 0.1447 against 0.1468); best of four 0.0802. Training people's
clips of both drops (6,744 hands): 0.0345 today's, 0.0350 the sum. Tracked (10 runs) the sum read
the held-back median 0.097 against 0.099 and found 87.5% against 88.7 (not the default).
"""
from __future__ import annotations

import argparse
import math
from dataclasses import replace

import numpy as np

from handmocap.perception.crops import hand_angle, knuckle_line_normal, palm_angle, rounded_turn
from handmocap.perception.detector import HandDetector
from handmocap.training import eval_people as ep
from handmocap.training import real_data


def unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def angle_of(v):
    """(N,) angle (radians, as hand_angle) of direction vectors v (N,2) px."""
    return np.arctan2(v[:, 0], -v[:, 1])


DEFINITIONS = {   # name: (N,21,2) joints -> (N,) angles
    "wrist -> middle knuckle (today's)": hand_angle,
    "knuckle line's normal": lambda uv: angle_of(knuckle_line_normal(uv)),
    "sum of the two, unit vectors": lambda uv: angle_of(unit(uv[:, 9] - uv[:, 0]) + unit(knuckle_line_normal(uv))),
    "sum of the two, px (palm_angle)": palm_angle,
    "wrist -> mean of the knuckles": lambda uv: angle_of(uv[:, [5, 9, 13, 17]].mean(axis=1) - uv[:, 0]),
}


def picked_turn(angle, base):
    """(N,) which of the four quarter turns base + k pi/2 the angles (N,) round to."""
    turn = np.round(angle / (np.pi / 2)) * np.pi / 2
    return np.round((np.remainder(turn - base + np.pi, 2 * np.pi) - np.pi) / (np.pi / 2)).astype(int) % 4


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--drops", default="wild", help="comma-separated: wild, wild3")
    p.add_argument("--training-clips", action="store_true", help="the training people's clips instead")
    args = p.parse_args()
    detector = HandDetector.load()
    errors, labels, readings, bases = [], [], [], []
    for video in real_data.wild_clips(real_data.SHARED_DATA, held_back=not args.training_clips,
                                      drops=tuple(args.drops.split(","))):
        for image, scored in ep.scored_hands(detector, video):
            for hand, label, crop, _ in scored:
                if crop is None:
                    continue
                base = rounded_turn(crop.angle, 90)
                crops = [replace(crop, angle=base + k * math.pi / 2) for k in range(4)]
                out = detector._run(image, crops, read_side=False)
                size = real_data.hand_size(label)
                errors.append([np.linalg.norm(c.to_frame(out["uv"][k]) - label, axis=-1).mean() / size
                               for k, c in enumerate(crops)])
                labels.append(label)
                readings.append(hand["uv"])
                bases.append(base)
    errors, bases, n = np.asarray(errors), np.asarray(bases), np.arange(len(errors))
    print(f"{len(errors)} hands; best of the four turns: median {np.median(errors.min(axis=1)):.4f}")
    for source, uv in (("label", np.asarray(labels)), ("reading", np.asarray(readings))):
        for name, angle in DEFINITIONS.items():
            k = picked_turn(angle(uv), bases)
            e = errors[n, k]
            print(f"from the {source:7s} {name:36s} median {np.median(e):.4f}  mean {e.mean():.4f}  "
                  f"best turn {100 * np.mean(k == errors.argmin(axis=1)):.1f}%")


if __name__ == "__main__":
    main()
