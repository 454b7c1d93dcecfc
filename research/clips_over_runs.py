"""Which held-back clips move `handeval people --jitter N`'s figures: each video/wild clip read as it
is and with its frames moved by -1/0/+1 (seeds 0..N-1, as `--jitter` moves them), per clip the mean
and range over the runs of hands found and side right, and the false hands a frame.

    python research/clips_over_runs.py [--detnet F --side-detnet int8] [--seeds 9] [--json OUT.json]

Session 44 (experiment log, "Which clips move the held-back figures"): over ten runs the default's
side spread (72-89% for all clips) comes from four clips whose tracks settle on a side early, and
session 42's polished network's found gap is one clip of touching hands (Kirichovka__want)."""
import argparse
import json

import numpy as np

from handmocap.perception.detector import HandDetector
from handmocap.training import eval_people, real_data
from handmocap.training.pose_data import SHARED_DATA


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--detnet", default=None, help="as handeval's --detnet (default: the default pair)")
    ap.add_argument("--side-detnet", default=None, help="as handeval's --side-detnet")
    ap.add_argument("--seeds", type=int, default=9, help="runs with the frames moved, after the one as they are")
    ap.add_argument("--json", help="write every run's figures per clip here")
    args = ap.parse_args()
    detector = HandDetector.load(detnet=args.detnet, side_detnet=args.side_detnet)
    out = {}
    print("| clip | labelled hands | found % mean (range) | side % mean (range) | false hands a frame |")
    print("|---|---|---|---|---|")
    for video in real_data.wild_clips(SHARED_DATA, held_back=True, drops=("wild",)):
        runs = [eval_people.summary(eval_people.score_frames(detector, eval_people.frames_of_clip(video, seed),
                                                             fps=eval_people.clip_fps(video)))
                for seed in [None, *range(args.seeds)]]
        out[video.stem] = runs
        found = 100 * np.array([r["found"] for r in runs])
        side = 100 * np.array([r["side"] for r in runs], float)
        print(f"| {video.stem} | {runs[0]['labelled']} | {found.mean():.1f} ({found.min():.1f}-{found.max():.1f}) | "
              f"{np.nanmean(side):.1f} ({np.nanmin(side):.1f}-{np.nanmax(side):.1f}) | "
              f"{np.mean([r['false_per_frame'] for r in runs]):.3f} |", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, default=float)


if __name__ == "__main__":
    main()
