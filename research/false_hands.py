"""Where a clip's false hands lie: every hand the detector outputs on none of MediaPipe's
hands (handeval people's rule: its joints' centre half the hand's size or more from every
label), with its frame, track, distance to the nearest label (hand sizes; -1: no label in
the frame), box side (px), side and presence; every 15th is drawn (labels green, the false
hand red, the frame's other outputs blue) as OUT/<clip>_<frame>.png.

    python research/false_hands.py Kirichovka__want [--out runs/false_hands] [--detnet F] [--set KEY=VALUE ...]
    python research/false_hands.py held-back --montage runs/false_hands/v9.png [--finder F]
    python research/false_hands.py training --tracks [--detnet F --side-detnet int8 --set turn_by=palm]
                                   [--second-detnet models/detnet_lite0_int8.onnx]

A clip of video/wild or video/wild3, held-back or training (by its stem), or `held-back`: every
held-back clip of both drops, one after the other. --montage also draws up to --per-clip
false hands of each clip (evenly over its false hands; the scene three times the hand's size
around it, the false hand's joints red, MediaPipe's green) into one picture to look at: which
"false" hands are hands MediaPipe missed, and which are not hands at all. `training`: every
training people's clip of both drops (where a threshold may be chosen). --tracks: instead of the
rows of false hands, one row per track that is ever false (the frame it was born on, the mean
heatmap peak it was born at, frames false of frames tracked, its peaks while false), then the birth
peaks of the tracks mostly false, false at times and always on a real hand, and the false hands by
their track's birth peak (session 59: with the palm network, `akstheme__gesture`'s false hands are one
track on the face born at 0.34, just over birth_confidence 0.3; on the training clips the tracks
mostly false were born at a median 0.39, those always real at 0.42 or more in nine of ten).
--second-detnet F: each birth read again by F (session 59, the default network: the face 0.20, but the
training clips' tracks born below 0.3 by it carry only 74 of their 645 false hands).
"""
import argparse
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.crops import crop_for_joints
from handmocap.perception.detector import HandDetector
from handmocap.perception.detnet_runner import DetNetRunner
from handmocap.training import eval_people, real_data
from handmocap.training.eval_cli import add_model_arguments, detector_keywords, model_paths
from handmocap.training.pose_data import SHARED_DATA


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("clip", help="stem of a video/wild or video/wild3 clip, held-back or training (all of those clips)")
    p.add_argument("--shared", type=Path, default=SHARED_DATA)
    p.add_argument("--out", type=Path, default=Path("runs/false_hands"))
    p.add_argument("--montage", type=Path, help="draw up to --per-clip false hands of each clip into this PNG")
    p.add_argument("--per-clip", type=int, default=6)
    p.add_argument("--tracks", action="store_true", help="a row per track that is ever false, with its birth peak")
    p.add_argument("--second-detnet", type=Path, default=None, metavar="ONNX",
                   help="with --tracks: each birth read again by this DetNet on the crop its joints give (turned by "
                        "wrist -> middle knuckle), its mean peak beside the birth peak")
    add_model_arguments(p)
    args = p.parse_args()
    every = [v for held in (True, False) for v in real_data.wild_clips(args.shared, held, drops=real_data.WILD_DROPS)]
    clips = (real_data.wild_clips(args.shared, args.clip == "held-back", drops=real_data.WILD_DROPS)
             if args.clip in ("held-back", "training") else [v for v in every if v.stem == args.clip])
    if not clips:
        raise SystemExit(f"no clip {args.clip} in {args.shared / 'video'} {'/'.join(real_data.WILD_DROPS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    detector = HandDetector.load(**detector_keywords(model_paths(args)))
    if args.tracks:
        second = DetNetRunner.load(args.second_detnet, side_path="none") if args.second_detnet else None
        return false_tracks(detector, clips, second)
    tiles = []
    for clip in clips:
        found = false_hands(detector, clip, args.out if args.montage is None else None)
        print(f"{clip.stem}: {len(found)} false hands in {found.frames} frames", flush=True)
        picks = np.linspace(0, len(found) - 1, min(args.per_clip, len(found))).round().astype(int) if found else []
        tiles += [tile(*found[i], f"{clip.stem[:20]} {found[i][0]}") for i in picks]
    if args.montage is not None and tiles:
        tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % 8)
        cv2.imwrite(str(args.montage), np.vstack([np.hstack(tiles[k:k + 8]) for k in range(0, len(tiles), 8)]))
        print(f"wrote {args.montage} ({len(tiles)} tiles)")


class FalseHands(list):
    """(frame, image BGR, false hand's uv (21,2), labels (k,21,2)) of one clip; .frames read."""
    frames = 0


def false_hands(detector, clip, draw_to=None):
    """Every false hand of the detector on one clip, printed as a row; with draw_to, every 15th
    drawn whole (labels green, the false hand red, the frame's other outputs blue)."""
    detector.reset()
    found = FalseHands()
    print("frame track distance box_px side presence")
    for f, (image, labels, _, _) in enumerate(eval_people.frames_of_clip(clip)):
        hands = detector.process(image)
        found.frames = f + 1
        for hand in hands:
            _, dist = eval_people.nearest_label(hand["uv"], labels)
            if dist < eval_people.ON_HAND:
                continue
            found.append((f, image, hand["uv"], labels))
            print(f, hand["track_id"], round(dist, 2) if np.isfinite(dist) else -1,
                  round(float(np.ptp(hand["uv"], 0).max())), hand["handedness"], round(float(hand["score"]), 2))
            if draw_to is not None and len(found) % 15 == 1:
                drawn = image.copy()
                for uv, colour in [(uv, (0, 255, 0)) for uv in labels] + \
                        [(h["uv"], (0, 0, 255) if h is hand else (255, 0, 0)) for h in hands]:
                    for x, y in uv:
                        cv2.circle(drawn, (int(x), int(y)), 2, colour, -1)
                cv2.imwrite(str(draw_to / f"{clip.stem}_{f}.png"), drawn)
    return found


def false_tracks(detector, clips, second=None):
    """Print a row per track of the clips that is ever a false hand, then the birth peaks of the
    tracks by kind and the false hands by their track's birth peak (a tenth wide bands); with
    `second` (a DetNetRunner), each birth's mean peak as that network reads the crop of its joints."""
    births, false_by_band, seconds = defaultdict(list), defaultdict(int), defaultdict(list)
    print("| clip | track | born on frame | birth peak | frames false / tracked | peaks while false (median, max) "
          "| second network's birth peak |")
    print("|---|---|---|---|---|---|---|")
    for clip in clips:
        detector.reset()
        fps, tracks = eval_people.clip_fps(clip), {}
        for f, (image, labels, _, _) in enumerate(eval_people.frames_of_clip(clip)):
            for hand in detector.process(image, f / fps):
                peak = float(np.mean(hand["confidence"]))
                if hand["track_id"] not in tracks and second is not None:
                    crop = crop_for_joints(hand["uv"], hand["handedness"] == "left", detector.crop_scale,
                                           detector.upright_step, second.crop_side)
                    rgb = cv2.cvtColor(crop.cut(image), cv2.COLOR_BGR2RGB)[None]
                    second_peak = float(second(rgb)["confidence"].mean())
                else:
                    second_peak = np.nan
                t = tracks.setdefault(hand["track_id"], {"born": f, "birth_peak": peak, "false": [], "frames": 0,
                                                         "second": second_peak})
                t["frames"] += 1
                if eval_people.nearest_label(hand["uv"], labels)[1] >= eval_people.ON_HAND:
                    t["false"].append(peak)
        for tid, t in tracks.items():
            kind = "mostly false" if len(t["false"]) > t["frames"] / 2 else \
                "real, false at times" if t["false"] else "always real"
            births[kind].append(t["birth_peak"])
            seconds[kind].append(t["second"])
            false_by_band[min(int(t["birth_peak"] * 10), 9) / 10] += len(t["false"])
            if t["false"]:
                print(f"| {clip.stem} | {tid} | {t['born']} | {t['birth_peak']:.2f} | {len(t['false'])} / {t['frames']} "
                      f"| {np.median(t['false']):.2f}, {np.max(t['false']):.2f} | {t['second']:.2f} |", flush=True)
    for kind, peaks in sorted(births.items()):
        q = np.percentile(peaks, [10, 50, 90])
        print(f"{kind} tracks: {len(peaks)}, birth peak 10/50/90th percentile {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f}")
        if second is not None:
            q = np.percentile(seconds[kind], [10, 50, 90])
            print(f"  the second network's birth peak: {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f}")
    print("false hands by their track's birth peak:",
          ", ".join(f"{band:.1f}-{band + 0.1:.1f}: {n}" for band, n in sorted(false_by_band.items())))


def tile(frame, image, uv, labels, title, side=160):
    """The scene three times the false hand's size around it, `side` px square, the false hand's
    joints red and the labels' green, titled."""
    centre, size = uv.mean(0), max(float(np.ptp(uv, 0).max()), 16.0) * 3
    a = side / size
    M = np.array([[a, 0, side / 2 - a * centre[0]], [0, a, side / 2 - a * centre[1]]])
    out = cv2.warpAffine(image, M, (side, side), borderValue=(90, 90, 90))
    for points, colour in [(label, (0, 255, 0)) for label in labels] + [(uv, (0, 0, 255))]:
        for x, y in points @ M[:, :2].T + M[:, 2]:
            cv2.circle(out, (int(x), int(y)), 1, colour, -1)
    cv2.putText(out, title, (2, 10), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (255, 255, 255), 1)
    return out


if __name__ == "__main__":
    main()
