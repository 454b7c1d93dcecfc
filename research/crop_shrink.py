"""The detector's crop cutting: powers-of-two shrink (shipped in session 24) against the area
shrink by the whole factor it replaced, in time and in DetNet's accuracy.

    python research/crop_shrink.py [--clips DIR] [--videos V ...]

Time: the crops HandDetector cut while tracking each video's first 200 frames (max 2
hands), cut again by each method, CPU ms per frame (median of 5 passes, alternating).
Accuracy: every 3rd frame of the held-back people's clips, each reliable labelled hand cut
as the detector cuts a tracked hand (`crop_for_joints`, mirrored for its label's side),
DetNet int8 once per method: error / hand size, median and mean, PCK at 0.1.
"""
import argparse
import math
import time

import cv2
import numpy as np

from handmocap.perception import crops as C, detector as D, detnet_runner
from handmocap.training import eval_people, real_data


def cut_area_by_k(crop, image):
    """The cut before session 24: a crop more than twice the output size first shrunk by
    k = floor(side / size) (INTER_AREA), then the bilinear warp, mirrored after it."""
    h, w = image.shape[:2]
    s = crop.size / crop.side
    k = max(1, int(1.0 / s))
    src, ox, oy = image, 0, 0
    if k >= 2:
        lo = crop.box[:2] + 0.5
        span = crop.box[2] - crop.box[0]
        ox, oy = max(int(math.floor(lo[0])) - k, 0) // k * k, max(int(math.floor(lo[1])) - k, 0) // k * k
        x1, y1 = min(int(math.ceil(lo[0] + span)) + k, w), min(int(math.ceil(lo[1] + span)) + k, h)
        nx, ny = (x1 - ox) // k, (y1 - oy) // k
        if nx < 1 or ny < 1:
            k, ox, oy = 1, 0, 0
        else:
            src = cv2.resize(image[oy:oy + ny * k, ox:ox + nx * k], (nx, ny), interpolation=cv2.INTER_AREA)
    A = crop.rotation * s
    t = A @ (np.array([0.5 * k - 0.5 + ox, 0.5 * k - 0.5 + oy]) - crop.centre) + (crop.size - 1) / 2
    out = cv2.warpAffine(src, np.hstack([A * k, t[:, None]]), (crop.size, crop.size), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
    return np.ascontiguousarray(out[:, ::-1]) if crop.mirrored else out


METHODS = {"powers of two (shipped)": C.CropTransform.cut, "area by k (before)": cut_area_by_k}


def timing(video, max_hands=2, frames=200, passes=5):
    from handmocap.runtime.frames import read_video
    images = [f for _, f in zip(range(frames), read_video(str(video)))]
    seen, cut = [], C.CropTransform.cut
    C.CropTransform.cut = lambda self, image: (seen.append((self, image)), cut(self, image))[1]
    try:
        det = D.HandDetector.load(max_hands=max_hands)
        for im in images:
            det.process(im)
    finally:
        C.CropTransform.cut = cut
    spent = {m: [] for m in METHODS}
    for _ in range(passes):
        for name, fn in METHODS.items():
            t = time.process_time()
            for crop, image in seen:
                fn(crop, image)
            spent[name].append(1e3 * (time.process_time() - t) / len(images))
    return len(seen) / len(images), {k: float(np.median(v)) for k, v in spent.items()}


def accuracy(shared):
    detnet = detnet_runner.DetNetRunner.load()
    step = D.DetectorSettings().upright_step
    err = {m: [] for m in METHODS}
    for video in real_data.wild_clips(shared, held_back=True):
        for f, (image, hands, reliable, sides) in enumerate(eval_people.frames_of_clip(video)):
            for uv, ok, side in zip(hands, reliable, sides):
                if f % 3 or not ok:
                    continue
                crop = C.crop_for_joints(uv, mirrored=side == "left", upright_step=step)
                for name, fn in METHODS.items():
                    out = detnet(fn(crop, image)[None, ..., ::-1])      # BGR crop -> RGB
                    err[name].append(np.linalg.norm(crop.to_frame(out["uv"][0]) - uv, axis=-1)
                                     / real_data.hand_size(uv))
    return {k: np.asarray(v) for k, v in err.items()}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shared", default=str(real_data.SHARED_DATA))
    p.add_argument("--videos", nargs="+", default=["data/demo/hand_clip.mp4"] + [
        f"{real_data.SHARED_DATA}/{c}" for c in ("video/webcam/lujunwang_hand.mp4", "video/wild/Criminal-9527__hands.mp4")])
    args = p.parse_args()
    cv2.setNumThreads(1)
    print("| video | crops cut / frame | " + " | ".join(f"{m}, CPU ms / frame" for m in METHODS) + " |")
    print("|---|---|" + "---|" * len(METHODS))
    for v in args.videos:
        per_frame, ms = timing(v)
        print(f"| {v.split('/')[-1]} | {per_frame:.2f} | " + " | ".join(f"{ms[m]:.2f}" for m in METHODS) + " |",
              flush=True)
    err = accuracy(args.shared)
    print("\n| cut | hands | median error / hand size | mean | PCK@0.1 |\n|---|---|---|---|---|")
    for name, e in err.items():
        print(f"| {name} | {len(e)} | {np.median(e.mean(1)):.4f} | {e.mean():.4f} | {(e <= 0.1).mean():.4f} |")


if __name__ == "__main__":
    main()
