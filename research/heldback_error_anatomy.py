"""Where one held-back clip's error is: by hand size, joint and side, against labels a few
frames off (is it lag?), and the side our track says frame by frame.

    python research/heldback_error_anatomy.py CLIP [--set KEY=VALUE ...]   # e.g. Kirichovka__want

The shipped detector tracks the clip once (frames as decoded); each output hand on a
reliable MediaPipe hand (eval_people's matching) is scored as `handeval people` scores it
(mean joint distance / hand size). Prints the median by hand size (px, the side of the
label's joint box), by joint, for hands given the label's side and the other side, the
median against the labels of frames f-2 .. f+2, and the label's and our side per matched
hand in frame order (r / l). --trace-side N: also every handedness reading the tracks took
in the first N frames (p_right and its weight: 1 for DetNet's head, less for the finder's
side), the evidence behind the side they published.
"""
import argparse

import numpy as np

from handmocap.perception import tracks as detector_module
from handmocap.perception.detector import HandDetector
from handmocap.training import eval_people, real_data
from handmocap.training.eval_cli import detector_settings
from handmocap.training.pose_data import SHARED_DATA

SIZE_BINS = (0, 40, 60, 80, 120, 10_000)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("clip")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="HandDetector settings, as handeval's --set")
    p.add_argument("--trace-side", type=int, default=0, metavar="N", help="print the side readings of the first N frames")
    args = p.parse_args()
    readings, frame = [], [0]
    add_handedness = detector_module.Track.add_handedness

    def logged(track, p_right, weight=1.0):                 # every reading, as the track takes it
        readings.append((frame[0], track.track_id, float(p_right), weight))
        return add_handedness(track, p_right, weight)
    detector_module.Track.add_handedness = logged
    settings = detector_settings(args.set)
    video = next(v for v in real_data.wild_clips(SHARED_DATA, held_back=True) if v.stem == args.clip)
    det = HandDetector.load(**settings)
    det.reset()
    frames = list(eval_people.frames_of_clip(video))
    fps = eval_people.clip_fps(video)
    outs = []
    for f, (image, *_) in enumerate(frames):
        frame[0] = f
        outs.append(det.process(image, f / fps))

    def scored(lag=0):
        rows = []
        for f, out in enumerate(outs):
            if not 0 <= f + lag < len(frames):
                continue
            _, hands, reliable, sides = frames[f + lag]
            for h in out:
                k, dist = eval_people.nearest_label(h["uv"], hands)
                if dist < eval_people.ON_HAND and reliable[k]:
                    size = real_data.hand_size(hands[k])
                    rows.append((size, np.linalg.norm(h["uv"] - hands[k], axis=-1) / size,
                                 sides[k][0], h["handedness"][0]))
        return rows

    rows = scored()
    size = np.array([r[0] for r in rows])
    joint = np.array([r[1] for r in rows])
    err = joint.mean(1)
    same = np.array([r[2] == r[3] for r in rows])
    print(f"{args.clip}: {len(rows)} hands scored, median {np.median(err):.3f} of the hand's size "
          f"(hand size median {np.median(size):.0f} px)")
    for lo, hi in zip(SIZE_BINS[:-1], SIZE_BINS[1:]):
        m = (size >= lo) & (size < hi)
        if m.any():
            print(f"  hands of {lo}-{hi} px: {m.sum()}, median {np.median(err[m]):.3f}")
    for name, m in (("the label's side", same), ("the other side", ~same)):
        if m.any():
            print(f"  read as {name}: {m.sum()}, median {np.median(err[m]):.3f}")
    print("  median by joint (MP order):", " ".join(f"{v:.2f}" for v in np.median(joint, 0)))
    for lag in (-2, -1, 1, 2):
        print(f"  against the labels {lag:+d} frames: median {np.median([r[1].mean() for r in scored(lag)]):.3f}")
    print("  labels:", "".join(r[2] for r in rows))
    print("  ours:  ", "".join(r[3] for r in rows))
    for f in range(min(args.trace_side, len(frames))):
        print(f"  frame {f}: " + ", ".join(f"track {t} p_right {p:.2f} (weight {w:.2f})"
                                          for g, t, p, w in readings if g == f))


if __name__ == "__main__":
    main()
