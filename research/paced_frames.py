"""HandTracker.process paced at 30 fps, as a camera feeds it, and where each frame's wall time goes,
by frame index modulo the side period (`side_every` / `mirror_vote_every`: 6). On a one-hand clip
whose hand is found on the first frame and held, the index is the track's age, so the frames that
read the side (age % 6 == 0, phase 0) stand beside the others.

    python research/paced_frames.py [--video V] [--max-hands 1] [--detnet F ...] [--set KEY=VALUE ...]

Columns (ms, median over the frames of each phase): the whole frame (`HandTracker.process`: the
detector, then shape and pose), the detector alone, and the DetNet reads in it (`_run_voting`).
Back to back (benchmarks/bench_frame_events.py) a frame's work on the second thread overlaps the
next frame's; paced, it runs in the gap before it, beside whatever the first thread still does.

Session 45 (experiment log, "The detector's periodic work a frame late"): with the side read moved
off the frame's path (`research/late_side_and_finder.patch`, `--set side_late=true`), the keypoints
of those frames still took 11.3 ms against 7.3-8.2 on the others: the side network then runs on
the second thread at the same moment, and on a 2-core VM two busy threads slow each other.
"""
import argparse
import collections
import time

import numpy as np

from handmocap.perception.tracker import HandTracker
from handmocap.runtime.frames import read_video
from handmocap.training.eval_cli import add_model_arguments, model_paths
from handmocap.training.pose_data import SHARED_DATA

WARMUP, FPS, PERIOD = 60, 30.0, 6
STAGES = ("process", "_run_voting")


def paced_times(tracker, frames):
    """(F, 1 + len(STAGES)) ms per frame: the tracker's wall time and each detector stage's."""
    detector, spent = tracker.detector, collections.defaultdict(float)
    for name in STAGES:
        fn = getattr(detector, name)

        def timed(*a, _fn=fn, _name=name, **k):
            t = time.perf_counter()
            try:
                return _fn(*a, **k)
            finally:
                spent[_name] += time.perf_counter() - t
        setattr(detector, name, timed)
    rows, t0 = [], time.perf_counter()
    for i, frame in enumerate(frames):
        due = t0 + i / FPS
        while (left := due - time.perf_counter()) > 0:
            time.sleep(left)
        spent.clear()
        t = time.perf_counter()
        tracker.process(frame)
        rows.append([time.perf_counter() - t] + [spent[name] for name in STAGES])
    return 1e3 * np.array(rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--video", default=str(SHARED_DATA / "video" / "webcam" / "lujunwang_hand.mp4"))
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--max-hands", type=int, default=1)
    add_model_arguments(ap)
    args = ap.parse_args()
    models = model_paths(args)
    frames = read_video(args.video)[:args.frames]
    tracker = HandTracker(**{**models, "max_hands": args.max_hands})
    for frame in frames[:WARMUP]:
        tracker.process(frame)
    tracker.reset()
    ms = paced_times(tracker, frames)[int(FPS):]     # the first second: a new track's reads
    print(f"{args.video.split('/')[-1]}, {len(ms)} frames at {FPS:.0f} fps, max hands {args.max_hands}, {models or 'defaults'}")
    print("whole frame p50 / p95 / p99 ms:", " / ".join(f"{v:.1f}" for v in np.percentile(ms[:, 0], (50, 95, 99))))
    print(f"| frame index mod {PERIOD} | whole frame | detector | DetNet reads |\n|---|---|---|---|")
    for phase in range(PERIOD):
        print(f"| {phase} | " + " | ".join(f"{v:.1f}" for v in np.median(ms[phase::PERIOD], axis=0)) + " |")


if __name__ == "__main__":
    main()
