"""Hand finders alone on the held-back people's clips: recall against false boxes a frame.

    python scripts/finder_pr.py models/finder.onnx models/finder_lite0_int8.onnx --png docs/finder_pr.png

Each finder reads every 2nd frame of the held-back clips (real_data.WILD_HELD_BACK of
video/wild, WILD3_HELD_BACK of video/wild3), letterboxed into its own input side, with
MediaPipe's hands as the boxes to find (train_finder.evaluate_thresholds: a hand is found
when a peak's box has IoU >= 0.3 with the square around its joints; any other peak is a
false box). Prints recall and false boxes a frame per drop at the default threshold and
the recall each reaches at <= 0.10 false boxes a frame (issue 47's bound), and draws the
precision-recall curves (threshold swept 0.05..0.9) into --png.
"""
import argparse
from pathlib import Path

import numpy as np

from handmocap.perception.detector import DetectorSettings
from handmocap.training import real_data, train_finder
from handmocap.training.eval_cli import plot_curves

THRESHOLDS = np.round(np.concatenate([np.arange(0.05, 0.3, 0.05), np.arange(0.3, 0.91, 0.1)]), 2)
DEFAULT_THRESHOLD = DetectorSettings.finder_threshold     # the detector's, one of THRESHOLDS
FALSE_BOUND = 0.10           # issue 47: recall at <= 0.10 false boxes a frame


def onnx_side(path):
    from handmocap.perception.hand_finder import HandFinder
    return HandFinder.load(path).size


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("finders", type=Path, nargs="+", help="finder ONNX files")
    p.add_argument("--data", type=Path, default=real_data.SHARED_DATA)
    p.add_argument("--png", type=Path, help="precision-recall plot")
    args = p.parse_args()
    if not (args.data / "video" / "wild").is_dir():
        raise SystemExit(f"finder_pr: {args.data} has no video/wild (the data pack's second drop)")
    frames, curves = {}, {}
    print("| finder | side px | set | hands | recall @0.3 | false / frame @0.3 | side right @0.3 | "
          f"recall @ <= {FALSE_BOUND} false (threshold) |\n|---|---|---|---|---|---|---|---|")
    for path in args.finders:
        side = onnx_side(path)
        maps_of = train_finder.onnx_maps(path)
        totals = []
        for drop in real_data.WILD_DROPS:
            if (side, drop) not in frames:
                clips = real_data.wild_clips(args.data, held_back=True, drops=(drop,))
                frames[side, drop] = train_finder.load_real_frames(args.data, clips, stride=2, size=side) \
                    if clips else None
            if frames[side, drop] is None:
                continue
            sweep = train_finder.evaluate_thresholds(maps_of, *frames[side, drop], THRESHOLDS)
            totals.append(sweep)
            print(row(path, side, drop, sweep))
        merged = [{"threshold": a["threshold"], "hands": sum(s[i]["hands"] for s in totals),
                   "frames": sum(s[i]["frames"] for s in totals),
                   "recall": sum(s[i]["recall"] * s[i]["hands"] for s in totals) / sum(s[i]["hands"] for s in totals),
                   "false_per_frame": sum(s[i]["false_per_frame"] * s[i]["frames"] for s in totals)
                   / sum(s[i]["frames"] for s in totals),
                   "handedness_acc": float("nan")} for i, a in enumerate(totals[0])]
        print(row(path, side, "both", merged))
        order = np.argsort([m["false_per_frame"] for m in merged])
        curves[f"{path.parent.name}/{path.name} ({side} px)"] = (
            np.array([merged[i]["false_per_frame"] for i in order]), np.array([merged[i]["recall"] for i in order]))
    if args.png:
        plot_curves(curves, args.png, "held-back clips, both drops", xlabel="false boxes a frame",
                    ylabel="recall", auc=False)
        print(f"wrote {args.png}")


def row(path, side, name, sweep):
    at = next(m for m in sweep if m["threshold"] == DEFAULT_THRESHOLD)
    within = [m for m in sweep if m["false_per_frame"] <= FALSE_BOUND]
    best = max(within, key=lambda m: m["recall"]) if within else None
    side_right = "–" if not np.isfinite(at["handedness_acc"]) else f"{at['handedness_acc']:.3f}"
    return (f"| {path} | {side} | {name} | {at['hands']} | {at['recall']:.3f} | {at['false_per_frame']:.3f} | "
            f"{side_right} | " + (f"{best['recall']:.3f} ({best['threshold']:g})" if best else "–") + " |")


if __name__ == "__main__":
    main()
