"""`HandTracker.process` CPU ms per frame with two or more DetNet files, interleaved in one
process pass by pass, so that a machine whose speed drifts (a shared CPU) hits them alike.

    python benchmarks/bench_detnet_files.py A.onnx B.onnx [--video data/demo/hand_clip.mp4] [--passes 8]

Each file gets its own HandTracker (one tracked hand, 640x480 frames, onnxruntime 1 thread);
one warm-up pass each, then `--passes` passes over the clip in turn. Prints the median,
mean and p90 of CPU time (time.process_time) per frame for each file.
"""
import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from handmocap.runtime.frames import read_video
from handmocap.perception.tracker import HandTracker

ROOT = Path(__file__).resolve().parent.parent


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("files", nargs="+")
    p.add_argument("--video", default=str(ROOT / "data" / "demo" / "hand_clip.mp4"))
    p.add_argument("--passes", type=int, default=8)
    args = p.parse_args()
    try:
        frames = [cv2.resize(f, (640, 480)) for f in read_video(args.video)]
    except ValueError as e:                     # missing, unreadable or cut short: one line
        raise SystemExit(str(e)) from None
    if not frames:
        raise SystemExit(f"{args.video}: no frames could be read")
    trackers = [HandTracker(max_hands=1, threads=1, detnet=f) for f in args.files]
    for tracker in trackers:
        for frame in frames:
            tracker.process(frame)
    spent = {f: [] for f in args.files}
    for _ in range(args.passes):
        for f, tracker in zip(args.files, trackers):
            for frame in frames:
                c = time.process_time()
                tracker.process(frame)
                spent[f].append(time.process_time() - c)
    for f in args.files:
        ms = np.array(spent[f]) * 1e3
        print(f"{f}: median {np.median(ms):.2f} ms CPU per frame, mean {ms.mean():.2f}, p90 {np.percentile(ms, 90):.2f}")


if __name__ == "__main__":
    main()
