"""HandTracker.process paced at 30 fps, each frame sorted by the work the detector did on it: how
many crops DetNet read (mirror votes and second looks included) and whether the finder ran, with
each kind's share of the frames, its median wall time and how many of the slowest tenth it holds.

    python research/paced_frame_kinds.py VIDEO [--max-hands 1] [--passes 2] [--set KEY=VALUE ...]

The first line gives the process CPU per frame (mean), the finder runs and the wall p50 / p95 / p99
(ms) over every pass but the first 60 frames. Session 50 (experiment log): on a one-hand clip the
slowest tenth are mostly finder frames; on `Criminal-9527__hands` (two hands) frames with mirror
votes, and a frame with one hand's vote costs about what a frame with both did.
"""
import argparse
import collections
import time

import numpy as np

from handmocap.perception.tracker import HandTracker
from handmocap.runtime.frames import read_video
from handmocap.training.eval_cli import detector_settings

FPS, WARMUP = 30.0, 60


def paced(tracker, frames, passes):
    """[(wall ms, CPU ms, {detector stat: increase})] per frame, frames fed on a 30 fps clock."""
    det, rows = tracker.detector, []
    due = time.perf_counter()
    for p in range(passes):
        for i, frame in enumerate(frames):
            due += 1 / FPS
            time.sleep(max(0.0, due - time.perf_counter()))
            before = dict(det.stats)
            wall, cpu = time.perf_counter(), time.process_time()
            tracker.process(frame)
            wall, cpu = 1e3 * (time.perf_counter() - wall), 1e3 * (time.process_time() - cpu)
            if p or i >= WARMUP:
                rows.append((wall, cpu, {k: v - before[k] for k, v in det.stats.items() if v != before[k]}))
    return rows


def kind(changes):
    """A frame's kind: the finder's run and the crops DetNet read, e.g. "finder+crops2"."""
    return ("finder+" if changes.get("finder_runs") else "") + f"crops{changes.get('crops', 0)}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("video")
    ap.add_argument("--max-hands", type=int, default=1)
    ap.add_argument("--passes", type=int, default=2, help="passes over the clip (default %(default)s)")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", help="detector settings")
    args = ap.parse_args()
    tracker = HandTracker(max_hands=args.max_hands, **detector_settings(args.set))
    rows = paced(tracker, read_video(args.video), args.passes)
    wall = np.array([r[0] for r in rows])
    finder_runs = sum(r[2].get("finder_runs", 0) for r in rows)
    print(f"CPU mean {np.mean([r[1] for r in rows]):.2f} ms, finder runs {finder_runs}, {len(rows)} frames: wall p50 / "
          f"p95 / p99 {' / '.join(f'{v:.1f}' for v in np.percentile(wall, [50, 95, 99]))} ms")
    slow = wall >= np.percentile(wall, 90)
    kinds = [kind(r[2]) for r in rows]
    print("| frames | share | median wall ms | in the slowest tenth |\n|---|---|---|---|")
    for k, n in collections.Counter(kinds).most_common():
        mine = np.array([x == k for x in kinds])
        print(f"| {k} | {n / len(rows):.1%} | {np.median(wall[mine]):.1f} | {int((mine & slow).sum())} |")


if __name__ == "__main__":
    main()
