"""Each finder's boxes and scores on chosen frames of one clip, down to a low threshold: what a
finder proposes that the tracker then births (e.g. a printed logo on a shirt).

    python research/finder_scores.py CLIP FRAMES [FINDER.onnx ...]
    python research/finder_scores.py rodrmilano00__ROSA 0,6,20 models/finder.onnx models/finder_lite0_int8.onnx

CLIP: a stem of a clip of the data pack's video/ folders; FRAMES: comma-separated frame numbers.
Prints per finder and frame its boxes (frame px) and scores at threshold 0.05, up to 6.
Session 69: on rodrmilano00__ROSA the lite0 finder scores the shirt's logo 0.45-0.47, v9 does not propose it.
"""
import argparse

from handmocap.perception.hand_finder import HandFinder
from handmocap.runtime.frames import read_video
from handmocap.training.pose_data import SHARED_DATA


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("clip")
    p.add_argument("frames", help="comma-separated frame numbers")
    p.add_argument("finders", nargs="*", default=["models/finder.onnx", "models/finder_lite0_int8.onnx"])
    args = p.parse_args()
    paths = sorted(SHARED_DATA.glob(f"video/*/{args.clip}.mp4"))
    if not paths:
        raise SystemExit(f"finder_scores: no clip {args.clip}.mp4 under {SHARED_DATA}/video/")
    video = read_video(str(paths[0]))
    frames = [int(x) for x in args.frames.split(",")]
    for path in args.finders:
        finder = HandFinder.load(path)
        for i in frames:
            boxes = [(h.box.round().astype(int).tolist(), round(float(h.score), 2))
                     for h in finder.find(video[i], threshold=0.05, max_hands=6)]
            print(f"{path} frame {i}: {boxes}")


if __name__ == "__main__":
    main()
