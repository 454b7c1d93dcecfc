"""The tracker on the held-back people's clips made harder the ways issue 47's scenes are.

    python research/tracker_stress.py [--conditions as-is turned dim small] [--detnet ... --finder ... --set ...]

`handeval people`'s clips (video/wild's and video/wild3's held-back people), each read once
as it is and once under each condition, the whole frame changed and MediaPipe's labels moved
with it (research/finder_stress.py does the same for the finder alone):
- turned: the clip turned by (i % 3) + 1 quarter turns, i its index: hands that point
  sideways or down, as a camera above a desk, a sink or a piano sees them;
- dim: finder_stress.dim's dim room (exposure x0.45 after a gamma of 1.6, sensor noise);
- small: every frame shrunk to half its side on a canvas of its mean colour, in the quadrant
  (i % 4): hands half as large (a waist-up view).
Per condition, both drops summed: hands found (share of MediaPipe's), false hands a frame,
median error / hand size, PCK@0.1, side; and per clip the hands found.
"""
import argparse
import zlib
from pathlib import Path

import cv2
import numpy as np

from finder_stress import dim      # research/ is the script's folder: one dim room for both studies
from handmocap.training import eval_people, real_data
from handmocap.training.eval_cli import add_model_arguments, detector_keywords, model_paths

CONDITIONS = ("as-is", "turned", "dim", "small")


def turn(image, uv, k):
    """image (H,W,3) turned k quarter turns counter-clockwise (np.rot90) and points uv (...,2)
    px with it: (x, y) -> (y, W-1-x) per turn."""
    for _ in range(k):
        w = image.shape[1]
        image = np.ascontiguousarray(np.rot90(image))
        uv = np.stack([uv[..., 1], w - 1 - uv[..., 0]], -1)
    return image, uv


def shrink(image, uv, quadrant):
    h, w = image.shape[:2]
    out = np.empty_like(image)
    out[:] = image.reshape(-1, 3).mean(0).astype(np.uint8)
    x0, y0 = (quadrant % 2) * (w - w // 2), (quadrant // 2 % 2) * (h - h // 2)
    out[y0:y0 + h // 2, x0:x0 + w // 2] = cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    return out, uv * np.array([(w // 2) / w, (h // 2) / h]) + np.array([x0, y0])


def changed_frames(video, condition, index):
    """eval_people.frames_of_clip's tuples under `condition` (the clip's index `index` picks
    its turn and quadrant)."""
    rng = np.random.default_rng(zlib.crc32(video.stem.encode()))
    for image, hands, reliable, sides in eval_people.frames_of_clip(video):
        if condition == "turned":
            image, hands = turn(image, hands, index % 3 + 1)
        elif condition == "dim":
            image, _ = dim(image, None, rng)
        elif condition == "small":
            image, hands = shrink(image, hands, index % 4)
        yield image, hands, reliable, sides


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=real_data.SHARED_DATA)
    p.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS)
    add_model_arguments(p)
    args = p.parse_args()
    if not (args.data / "video" / "wild").is_dir():
        raise SystemExit(f"tracker_stress: {args.data} has no video/wild (the data pack's second drop)")
    from handmocap.perception.detector import HandDetector
    detector = HandDetector.load(**detector_keywords(model_paths(args)))
    videos = real_data.wild_clips(args.data, held_back=True, drops=real_data.WILD_DROPS)
    print("| condition | frames | hands | found % | false / frame | median | PCK@0.1 | side % |\n|---|---|---|---|---|---|---|---|")
    per_clip = {}
    for condition in args.conditions:
        clips = []
        for i, video in enumerate(videos):
            clips.append(eval_people.score_frames(detector, changed_frames(video, condition, i),
                                                  fps=eval_people.clip_fps(video)))
            per_clip.setdefault(video.stem, {})[condition] = eval_people.summary(clips[-1])["found"]
        m = eval_people.summary(eval_people.merge(clips))
        print(f"| {condition} | {m['frames']} | {m['labelled']} | {100 * m['found']:.1f} | {m['false_per_frame']:.3f} | "
              f"{m['median_err']:.3f} | {m['pck']:.3f} | {100 * m['side']:.1f} |", flush=True)
    print("\n| clip (scene): found % | " + " | ".join(args.conditions) + " |\n|---|" + "---|" * len(args.conditions))
    for stem, found in per_clip.items():
        scene = real_data.HELD_BACK_SCENES.get(stem)
        print(f"| {stem}" + (f" ({scene})" if scene else "") + " | "
              + " | ".join(f"{100 * found[c]:.1f}" for c in args.conditions) + " |")


if __name__ == "__main__":
    main()
