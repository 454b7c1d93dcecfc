"""Which part of the graph makes its slowest frames: the product's chain at 30 fps on a real clip
(as benchmarks/bench_tail.py runs it), traced (HANDMOCAP_TRACE), each frame's time split into its
hops and stages, and the slowest tenth of frames against the rest, with the detector's time by
frame index modulo 6 (a track's mirror vote and side reading) and 10 (the finder's period).

    python research/graph_slow_frames.py [VIDEO] [--max-hands 1]

Session 45 (experiment log, "The detector's periodic work a frame late"): the slow frames are
slow in the detector, on the frames with a side reading and with a finder run.
"""
import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_e2e import WARMUP_FRAMES, run_graph  # noqa: E402
from bench_tail import clip_of  # noqa: E402
from handmocap.training.pose_data import SHARED_DATA  # noqa: E402

# (name, from (node, event, topic) or None for the capture stamp, to (node, event, topic))
SEGMENTS = (("capture -> detector", None, ("detector", "recv", "/camera/image")),
            ("detector", ("detector", "recv", "/camera/image"), ("detector", "pub0", "/hand/keypoints")),
            ("detector -> ik", ("detector", "pub0", "/hand/keypoints"), ("ik", "recv", "/hand/keypoints")),
            ("ik", ("ik", "recv", "/hand/keypoints"), ("ik", "pub0", "/hand/pose")),
            ("ik -> recorder", ("ik", "pub0", "/hand/pose"), ("recorder", "recv", "/hand/pose")))


def traced_segments(trace: Path) -> np.ndarray:
    """(F, len(SEGMENTS)) ms per frame after the first second, from the nodes' trace files."""
    events = {}
    for f in trace.glob("*.trace.json"):
        node, last = f.name.split(".")[0], {}
        for kind, topic, stamp, t in json.loads(f.read_text()):
            if kind == "pub0":
                last[topic] = stamp
            if kind in ("pub0", "recv"):
                events[(node, kind, topic, stamp)] = t
    stamps = sorted(s for (n, k, tp, s) in events if n == "replay" and k == "pub0" and tp == "/camera/image")
    rows = []
    for s in stamps[WARMUP_FRAMES:]:
        row = []
        for _, a, b in SEGMENTS:
            ta, tb = s if a is None else events.get((*a, s)), events.get((*b, s))
            row.append(np.nan if ta is None or tb is None else (tb - ta) / 1e6)
        rows.append(row)
    return np.array(rows)


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
        ms = traced_segments(tmp / "trace")
    total = np.nansum(ms, axis=1)
    slow = total >= np.percentile(total, 90)
    print(f"{Path(args.video).name}, max hands {args.max_hands}: capture -> recorder p50 / p95 "
          f"{np.percentile(total, 50):.1f} / {np.percentile(total, 95):.1f} ms")
    print("| segment | p50 ms | slowest 10% mean | the rest mean |\n|---|---|---|---|")
    for k, (name, _, _) in enumerate(SEGMENTS):
        print(f"| {name} | {np.nanmedian(ms[:, k]):.2f} | {np.nanmean(ms[slow, k]):.2f} | {np.nanmean(ms[~slow, k]):.2f} |")
    detector = ms[:, 1]
    for period in (6, 10):
        print(f"detector ms by frame index mod {period}:",
              " ".join(f"{np.nanmedian(detector[p::period]):.1f}" for p in range(period)))


if __name__ == "__main__":
    main()
