"""Which part of the tracked 2D error a better crop could remove (session 51).

    python research/tracked_error_parts.py [--drops wild]

The held-back clips tracked as `handeval people` tracks them. For every scored hand (on a
reliable MediaPipe hand), its error / hand size four ways: the published joints (after the One
Euro filter), the reading before the filter, DetNet again on the crop re-cut from that reading
(a refine pass), and DetNet on the crop cut around MediaPipe's own joints at their quarter turn
(a perfect tracker: the bound for crop placement). Session 51, video/wild (2,294 hands): medians
0.1097, 0.1086, 0.1078 and 0.0873.
"""
from __future__ import annotations

import argparse

import numpy as np

from handmocap.perception.crops import crop_for_joints
from handmocap.perception.detector import HandDetector
from handmocap.training import eval_people as ep
from handmocap.training import real_data

WAYS = ("published", "before the filter", "refined", "cut around the label")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--drops", default="wild", help="comma-separated: wild, wild3")
    args = p.parse_args()
    detector = HandDetector.load()
    raw = {}                                    # track id -> this frame's joints before the filter
    smoothed = detector._smoothed

    def keep_raw(track, uv):
        raw[track.track_id] = uv.copy()
        return smoothed(track, uv)
    detector._smoothed = keep_raw
    errors = []
    recut = lambda uv, left: crop_for_joints(uv, left, detector.crop_scale, detector.upright_step,   # noqa: E731
                                             detector.crop_size)
    for video in real_data.wild_clips(real_data.SHARED_DATA, held_back=True, drops=tuple(args.drops.split(","))):
        for image, hands in ep.scored_hands(detector, video):     # keep_raw fills raw as each frame is read
            scored = []
            for h, label, _, _ in hands:
                left = h["handedness"] == "left"
                scored.append((label, h["uv"], raw[h["track_id"]], recut(raw[h["track_id"]], left), recut(label, left)))
            raw.clear()
            if not scored:
                continue
            crops = [s[3] for s in scored] + [s[4] for s in scored]
            out = detector._run(image, crops, read_side=False)
            for i, (label, published, before, refined, ideal) in enumerate(scored):
                reads = (published, before, refined.to_frame(out["uv"][i]), ideal.to_frame(out["uv"][len(scored) + i]))
                errors.append([np.linalg.norm(uv - label, axis=-1).mean() / real_data.hand_size(label) for uv in reads])
    errors = np.asarray(errors)
    print(f"{len(errors)} hands")
    for way, column in zip(WAYS, errors.T):
        print(f"{way}: median {np.median(column):.4f}, mean {column.mean():.4f}")


if __name__ == "__main__":
    main()
