"""Issue 6's replay check: launch/replay.yaml on real clips, and the share of the frames that
show a hand (MediaPipe's pseudo-labels found one) for which the bag holds a /hand/pose with
at least one hand. Frames and poses are matched by stamp (each /hand/pose carries its
frame's capture stamp).

    python research/replay_coverage.py [CLIP.mp4 ...]     # default: every clip of shared/data/video/webcam

Needs the clip's `<clip>.mediapipe.npz` beside it (the data pack's pseudo-labels). The bags
go to a temporary folder (`--keep DIR` keeps them).
"""
import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from handmocap.runtime import codec
from handmocap.runtime.bag import iter_messages
from handmocap.training.pose_data import SHARED_DATA

ROOT = Path(__file__).resolve().parent.parent


def coverage(clip, bag):
    """(frames that show a hand, of them with a /hand/pose hand, poses on hand-free frames, replayed frames)."""
    shows = np.load(str(clip).replace(".mp4", ".mediapipe.npz"))["found"].any(1)
    frames, hands_at = [], {}
    for topic, t, payload, _ in iter_messages(bag):
        if topic == "/camera/image":
            frames.append(codec.decode(payload, t)["header"]["stamp_ns"])
        elif topic == "/hand/pose":
            m = codec.decode(payload, t)
            hands_at[m["header"]["stamp_ns"]] = len(m["hands"])
    got = np.array([hands_at.get(s, 0) > 0 for s in frames], bool)
    n = min(len(got), len(shows))
    return int(shows[:n].sum()), int((got[:n] & shows[:n]).sum()), int((got[:n] & ~shows[:n]).sum()), len(frames)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("clips", nargs="*", type=Path)
    p.add_argument("--keep", type=Path, help="write the bags here")
    args = p.parse_args()
    clips = args.clips or sorted((SHARED_DATA / "video" / "webcam").glob("*.mp4"))
    if not clips:
        sys.exit(f"no clips given and none under {SHARED_DATA / 'video' / 'webcam'}")
    out = args.keep or Path(tempfile.mkdtemp(prefix="replay_coverage_"))
    out.mkdir(parents=True, exist_ok=True)
    print("| clip | frames | show a hand | with a /hand/pose hand | share | poses on hand-free frames |\n|---|---|---|---|---|---|")
    for clip in clips:
        bag = out / f"{clip.stem}.mcap"
        run = subprocess.run([sys.executable, "-m", "handmocap.runtime.launch", str(ROOT / "launch" / "replay.yaml"),
                              f"input:={clip}", f"bag:={bag}"], cwd=ROOT, capture_output=True, text=True)
        if run.returncode != 0:
            print(f"| {clip.stem} | replay failed (exit {run.returncode}): {run.stderr.strip().splitlines()[-1:]} |")
            continue
        shows, got, extra, n = coverage(clip, bag)
        print(f"| {clip.stem} | {n} | {shows} | {got} | {got / max(shows, 1):.1%} | {extra} |", flush=True)


if __name__ == "__main__":
    main()
