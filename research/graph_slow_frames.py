"""Which part of the graph makes its slowest frames: the product's chain at 30 fps on a real clip
(as benchmarks/bench_tail.py runs it), traced (HANDMOCAP_TRACE), each frame's time split into
benchmarks/bench_e2e.py's hops and stages (TRACE_SEGMENTS), and the slowest tenth of frames
against the rest, with the detector's time by frame index modulo 6 (a track's mirror vote and
side reading) and 10 (the finder's period).

    python research/graph_slow_frames.py [VIDEO] [--max-hands 1]

Session 45 (experiment log, "The detector's periodic work a frame late"): the slow frames are
slow in the detector, on the frames with a side reading and with a finder run.
"""
import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_e2e import TRACE_SEGMENTS, run_graph, trace_segments_ms  # noqa: E402
from bench_tail import clip_of  # noqa: E402
from handmocap.training.pose_data import SHARED_DATA  # noqa: E402

LABELS = [label for label, _, _ in TRACE_SEGMENTS]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("video", nargs="?", default=str(SHARED_DATA / "video" / "webcam" / "lujunwang_hand.mp4"))
    ap.add_argument("--max-hands", type=int, default=1)
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run_graph(tmp, clip_of(Path(args.video), args.frames, tmp), 1.0, False, "slow", args.max_hands,
                  trace=tmp / "trace")
        ms, _, _ = trace_segments_ms(tmp / "trace")
    total = ms[:, LABELS.index("total capture -> recorder")]
    slow = total >= np.nanpercentile(total, 90)
    print(f"{Path(args.video).name}, max hands {args.max_hands}: capture -> recorder p50 / p95 "
          f"{np.nanpercentile(total, 50):.1f} / {np.nanpercentile(total, 95):.1f} ms")
    print("| segment | p50 ms | slowest 10% mean | the rest mean |\n|---|---|---|---|")
    for k, name in enumerate(LABELS):
        print(f"| {name} | {np.nanmedian(ms[:, k]):.2f} | {np.nanmean(ms[slow, k]):.2f} | {np.nanmean(ms[~slow, k]):.2f} |")
    detector = ms[:, LABELS.index("detector compute")]
    for period in (6, 10):
        print(f"detector ms by frame index mod {period}:",
              " ".join(f"{np.nanmedian(detector[p::period]):.1f}" for p in range(period)))


if __name__ == "__main__":
    main()
