"""The latency tail a robot feels: the graph against MediaPipe, both fed at 30 fps.

    python benchmarks/bench_tail.py [--rounds 3] [--frames 300] [--videos V ...] [--max-hands 1 2] [--record-all]

Ours: the product's graph (replay at rate 1 in the perception container with detector, shape
and ik; the recorder a process of its own, as benchmarks/bench_e2e.py runs it): latency =
the recorder's receipt of /hand/pose - the frame's capture stamp. MediaPipe Hands 0.10.21
(legacy solution, tracking mode, the same max_num_hands), frames decoded first and handed to
it on a 30 fps clock in one process (scripts/mediapipe_reference.py --paced; its venv found or
built as bench_tracker.py does): latency = result - the frame's due time. Our side also pays
the graph's hops and decodes each frame (stamped after decoding). Both leave out the first
second. Rounds alternate ours and MediaPipe's; the ratios are the medians of the rounds'.
Default clips: the data pack's one-hand and two-hand real clips (bench_tracker.REAL_CLIPS),
else the demo clip.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_e2e import WARMUP_FRAMES, latency_ms, run_graph  # noqa: E402
from bench_tracker import ROOT, default_videos  # noqa: E402
from handmocap.training.eval_cli import reference_python  # noqa: E402

PERCENTILES = (50, 95, 99)


def clip_of(video: Path, frames: int, tmp: Path) -> Path:
    """The video's first `frames` frames ping-ponged (no jump where it repeats) into an MP4 at 30 fps."""
    import cv2

    from handmocap.runtime.frames import read_video
    src = read_video(str(video))
    order = src + src[-2:0:-1]
    h, w = src[0].shape[:2]
    out = tmp / f"{video.stem}.mp4"
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), 30, (w, h))
    for i in range(frames):
        writer.write(order[i % len(order)])
    writer.release()
    return out


def mediapipe_latency_ms(python: Path, clip: Path, frames: int, max_hands: int) -> np.ndarray:
    r = subprocess.run([str(python), str(ROOT / "scripts" / "mediapipe_reference.py"), "--bench", str(clip),
                        "--paced", "30", "--frames", str(frames), "--max-hands", str(max_hands)],
                       capture_output=True, text=True)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    if r.returncode or not lines:
        raise SystemExit(f"MediaPipe failed: {r.stderr[-400:]}")
    return np.array(json.loads(lines[-1])["latency_ms"])[WARMUP_FRAMES:]


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--videos", nargs="+", type=Path, default=None)
    p.add_argument("--frames", type=int, default=300, help="frames per run (default %(default)s)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--max-hands", type=int, nargs="+", default=None,
                   help="per video (default: 1 for the first, 2 for the second real clip)")
    p.add_argument("--record-all", action="store_true", help="the recorder records every topic (JPEG frames)")
    args = p.parse_args()
    python = reference_python()
    if python is None:
        raise SystemExit("no MediaPipe venv (see the line above)")
    videos = args.videos or [v for v in default_videos() if "demo" not in str(v)] or default_videos()
    max_hands = args.max_hands or [1, 2][:len(videos)]
    print("| video | max hands | round | ours p50 / p95 / p99 ms | MediaPipe p50 / p95 / p99 ms |")
    print("|---|---|---|---|---|")
    summary = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for video, hands in zip(videos, max_hands):
            clip = clip_of(video, args.frames, tmp)
            ratios = []
            for r in range(args.rounds):
                ours = latency_ms(run_graph(tmp, clip, 1.0, args.record_all, f"r{r}", hands))[WARMUP_FRAMES:]
                mp = mediapipe_latency_ms(python, clip, args.frames, hands)
                po, pm = np.percentile(ours, PERCENTILES), np.percentile(mp, PERCENTILES)
                ratios.append(po / pm)
                print(f"| {video.name} | {hands} | {r} | {' / '.join(f'{v:.1f}' for v in po)} | "
                      f"{' / '.join(f'{v:.1f}' for v in pm)} |", flush=True)
            summary.append((video.name, hands, np.median(ratios, axis=0)))
    print("\n| video | max hands | graph / MediaPipe p50 | p95 | p99 (medians of the rounds) |\n|---|---|---|---|---|")
    for name, hands, ratio in summary:
        print(f"| {name} | {hands} | {ratio[0]:.2f}x | {ratio[1]:.2f}x | {ratio[2]:.2f}x |")


if __name__ == "__main__":
    main()
