"""Handedness readings weighted by how open the hand is: a study on the dev split of strangers.

    python research/side_openness.py --detnet runs/detnet/lc_half/final_int8.onnx [--floor 0.1]

DetNet's handedness head is right on open hands and wrong on many fists and curled hands of
people it never saw (experiment log, session 32: a counting close-up's track turns "left"
on the fist). Here each head reading enters a track's running side with a weight from the
track's last joints (frame px): openness = mean over the five fingers of |tip - wrist| /
the side of the joints' box, mapped linearly from 0.6 (a fist or a pointing hand: weight `floor`) to 0.9 (an open hand: weight 1).
The finder's readings keep their weights. Runs `handeval people --training-clips` with
the DetNet given, with and without the weighting, and prints the side over the clips of
the uploaders in `people_learning_curve.HALF_OWNERS`' complement: the seven that
runs/detnet/lc_half never trained on (the finder did: its part is not a stranger's).
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from people_learning_curve import HALF_OWNERS  # noqa: E402

from handmocap.perception import detector, tracks  # noqa: E402
from handmocap.training import eval_people, real_data  # noqa: E402
from handmocap.training.pose_data import SHARED_DATA  # noqa: E402

TIPS = (4, 8, 12, 16, 20)


def openness(uv):
    """(21,2) joints -> mean fingertip distance from the wrist / the joint box's side."""
    return float(np.linalg.norm(uv[list(TIPS)] - uv[0], axis=1).mean() / max(real_data.hand_size(uv), 1e-6))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--detnet", required=True)
    p.add_argument("--floor", type=float, default=0.1)
    args = p.parse_args()
    plain = tracks.Track.add_head_reading

    def weighted(track, p_right_seen, mirrored):
        w = 1.0 if track.uv is None else float(np.clip((openness(track.uv) - 0.6) / 0.3, args.floor, 1.0))
        track.add_handedness(1.0 - p_right_seen if mirrored else p_right_seen, weight=w)

    for name, reading in (("as shipped", plain), (f"by openness (floor {args.floor})", weighted)):
        tracks.Track.add_head_reading = reading
        clips = []
        for video in real_data.wild_clips(SHARED_DATA):
            if video.stem.split("__")[0] in HALF_OWNERS:
                continue
            det = detector.HandDetector.load(detnet=args.detnet)
            clips.append(eval_people.score_frames(det, eval_people.frames_of_clip(video),
                                                  fps=eval_people.clip_fps(video)))
            s = eval_people.summary(clips[-1])
            print(f"  {name}: {video.stem}: side {s['side']:.1%}, median {s['median_err']:.3f}", flush=True)
        s = eval_people.summary(eval_people.merge(clips))
        print(f"{name}: side {s['side']:.1%} over {len(clips)} clips, median {s['median_err']:.3f}, "
              f"found {s['found']:.1%}", flush=True)


if __name__ == "__main__":
    main()
