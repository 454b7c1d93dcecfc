"""Bag size and detection with compressed images, on a real clip at 640x480, 30 fps.

The clip's frames, resized to 640x480, are written losslessly (PNG) and replayed at 30 fps
through launch/replay.yaml three times:
  raw      the source publishes raw frames, the recorder stores them raw (raw:=true);
  default  raw frames, the recorder stores JPEG (its default, quality 90);
  jpeg     the source publishes JPEG (jpeg:=90), as a network camera would; stored as received.
Printed per run: the bag's size and its growth in MB per second of clip, and the hands found
(/hand/keypoints) against the raw run: how many, and in how many of the raw run's frames with a
hand the run found none.

    python benchmarks/bench_recording.py [--clip VIDEO] [--frames 300]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CLIP = ROOT.parent / "shared" / "data" / "video" / "webcam" / "lujunwang_hand2.mp4"
FPS = 30

from handmocap.runtime import codec  # noqa: E402
from handmocap.runtime.bag import iter_messages  # noqa: E402


def write_frames(clip: Path, out: Path, count: int) -> int:
    """The clip's first `count` frames, resized to 640x480, as PNG files; how many."""
    cap = cv2.VideoCapture(str(clip))
    n = 0
    while n < count:
        ok, frame = cap.read()
        if not ok:
            break
        cv2.imwrite(str(out / f"{n:05d}.png"), cv2.resize(frame, (640, 480), interpolation=cv2.INTER_AREA))
        n += 1
    if n == 0:
        sys.exit(f"bench_recording: no frames in {clip}")
    return n


def run(frames: Path, bag: Path, *args: str) -> dict:
    """Replay the frames through replay.yaml into `bag`; per frame stamp its number of hands."""
    cmd = [sys.executable, "-m", "handmocap.runtime.launch", str(ROOT / "launch" / "replay.yaml"), f"input:={frames}",
           f"bag:={bag}", *args]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    if done.returncode != 0:
        sys.exit(f"bench_recording: {' '.join(cmd)} failed:\n{done.stderr[-2000:]}")
    hands = [len(codec.decode(p, t)["hands"]) for _, t, p, _ in iter_messages(bag, ["/hand/keypoints"])]
    return {"bytes": bag.stat().st_size, "hands": hands}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clip", type=Path, default=DEFAULT_CLIP)
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    if not args.clip.is_file():
        sys.exit(f"bench_recording: {args.clip} not found (the data pack's video/webcam/, or --clip)")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "frames").mkdir()
        n = write_frames(args.clip, tmp / "frames", args.frames)
        seconds = n / FPS
        print(f"{args.clip.name}: {n} frames at 640x480, {seconds:.1f} s at {FPS} fps")
        runs = {"raw": run(tmp / "frames", tmp / "raw.mcap", "raw:=true"),
                "default": run(tmp / "frames", tmp / "default.mcap"),
                "jpeg": run(tmp / "frames", tmp / "jpeg.mcap", "jpeg:=90")}
        base = runs["raw"]["hands"]
        print(f"{'run':8s} {'bag MB':>8s} {'MB/s':>7s} {'hands':>6s} {'frames lost':>12s}")
        for name, r in runs.items():
            lost = sum(1 for a, b in zip(base, r["hands"]) if a > 0 and b == 0)
            print(f"{name:8s} {r['bytes'] / 1e6:8.1f} {r['bytes'] / 1e6 / seconds:7.2f} {sum(r['hands']):6d} "
                  f"{lost:5d} of {sum(1 for a in base if a > 0)}")


if __name__ == "__main__":
    main()
