"""The held-back people's frames read as photos (each alone, photo mode) with each finder:
hands found of MediaPipe's, false hands a still, the 2D error of the found hands and their side.

    python research/finder_stills.py [--every 4] [--people held-back|training] [--thresholds T ...] [FINDER.onnx ...]
    (default: v9 and the lite0 int8 finder, each at the detector's finder_threshold)

Photo mode is what `handeval predict` uses on a folder of images (detector.PHOTO_SETTINGS: no birth
threshold, the centre square as a fallback, a new hand read on its crop and 4 variants). Frames: every
`--every`-th frame of every held-back clip of both drops (real_data.wild_clips held_back=True), and the
11K held-back photos. No frame of these people was trained on. `--people training`: the training
people's clips instead (no photos), where a setting may be chosen (both finders trained on frames
of these people: never accuracy). `--thresholds`: each finder but the first (the reference, at the
default) at each of these finder_threshold values.
"""
import argparse
import time

from handmocap.perception.detector import PHOTO_SETTINGS, HandDetector
from handmocap.perception.hand_finder import DEFAULT_PATH
from handmocap.training import eval_people, real_data
from handmocap.training.pose_data import SHARED_DATA


def stills(every, held_back=True):
    for video in real_data.wild_clips(SHARED_DATA, held_back=held_back, drops=real_data.WILD_DROPS):
        for f, frame in enumerate(eval_people.frames_of_clip(video)):
            if f % every == 0:
                yield frame


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("finders", nargs="*", default=[DEFAULT_PATH, "models/finder_lite0_int8.onnx"])
    p.add_argument("--every", type=int, default=4)
    p.add_argument("--people", choices=("held-back", "training"), default="held-back")
    p.add_argument("--thresholds", type=float, nargs="*", default=None)
    args = p.parse_args()
    held_back = args.people == "held-back"
    frames_of = {f"{args.people} clips, every {args.every}th frame": list(stills(args.every, held_back))}
    if held_back:
        frames_of["11K photos"] = list(eval_people.frames_of_photos(real_data.load_11khands(SHARED_DATA,
                                                                                          held_back=True)))
    print("| finder | set | stills | MediaPipe's hands | found % | false hands / still | median error / hand size "
          "| PCK@0.1 | side right % | ms a still |\n|---|---|---|---|---|---|---|---|---|---|")
    for k, path in enumerate(args.finders):
        for threshold in ([None] if k == 0 or not args.thresholds else args.thresholds):
            extra = {} if threshold is None else {"finder_threshold": threshold}
            det = HandDetector.load(finder=str(path), **PHOTO_SETTINGS, **extra)
            label = f"{path}" + ("" if threshold is None else f" at {threshold:g}")
            for name, frames in frames_of.items():
                t0 = time.perf_counter()
                m = eval_people.summary(eval_people.score_frames(det, frames, stills=True))
                ms = (time.perf_counter() - t0) / len(frames) * 1e3
                print(f"| {label} | {name} | {m['frames']} | {m['labelled']} | {100 * m['found']:.1f} | "
                      f"{m['false_per_frame']:.3f} | {m['median_err']:.3f} | {m['pck']:.3f} | {100 * m['side']:.1f} | "
                      f"{ms:.1f} |", flush=True)


if __name__ == "__main__":
    main()
