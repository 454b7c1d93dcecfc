"""Close-up photos (the hand fills the frame, as in FreiHAND-style crops): how many hands
the detector finds in photo mode with and without the centre-square fallback.

    handsynth generate -n 1024 -o runs/detnet_data/synth_val --seed 424242   # held-out shard
    python research/closeup_photos.py [--val runs/detnet_data/synth_val] [-n 300] [--size 256]
    python research/closeup_photos.py --real [--size 224]      # real close-ups, training-side held-out

Each photo is one held-out synthetic DetNet crop (128 px, never trained on) scaled up to
`--size` px; with --real, a square cut around a labelled hand of every other frame of
scripts/detector_thresholds.py's held-out clips (never the evaluation splits), 1.3-2.2x
the hand's joint-box side, its centre moved by up to 10% of the side, kept inside the
frame, and scaled to `--size` px (FreiHAND's photos are 224 px; a second hand may be in
the picture too). A hand counts as found when an output's mean joint distance to the label is
below half the hand's joint-box side; the error column is that distance / side (median of
the found); the side column is the share of the found published as the label's side
(--real only). Settings: HandDetector.load(birth_confidence=0) (the photo setting before
the fallback), + fallback="centre", detector.PHOTO_SETTINGS (that, and each new hand
read on five crops), and the centre square alone (finder "none").
"""
import argparse
import glob

import cv2
import numpy as np

from handmocap.perception.detector import CENTRE, PHOTO_SETTINGS, HandDetector


def score(detector, images, labels, sides=None):
    """(found count, median error / hand size of the found, share of the found published
    as the labelled side or NaN) over BGR images, (21,2) labels and their sides."""
    found, errors, right = 0, [], []
    for k, (image, uv) in enumerate(zip(images, labels)):
        detector.reset()
        hands = detector.process(image)
        side = np.max(uv.max(0) - uv.min(0))
        err, hand = min(((np.mean(np.linalg.norm(h["uv"] - uv, axis=1)) / side, h) for h in hands),
                        default=(np.inf, None), key=lambda e_h: e_h[0])
        if err < 0.5:
            found += 1
            errors.append(err)
            if sides is not None:
                right.append(hand["handedness"] == sides[k])
    return found, float(np.median(errors)) if errors else float("nan"), float(np.mean(right)) if right else float("nan")


def real_closeups(size=224, seed=0):
    """BGR close-ups (size,size,3), their labels (21,2) px and sides, cut from the
    training-side held-out clips of scripts/detector_thresholds.py (see the module doc)."""
    from detector_thresholds import clips
    from handmocap.training.pose_data import SHARED_DATA
    if not SHARED_DATA.is_dir():
        raise SystemExit(f"--real needs the shared data pack at {SHARED_DATA}")
    rng = np.random.default_rng(seed)
    images, labels, sides = [], [], []
    for _, frames in clips(SHARED_DATA):
        for image, frame_labels, frame_sides in frames[::2]:
            h, w = image.shape[:2]
            for uv, hand_side in zip(frame_labels, frame_sides):
                lo, hi = uv.min(0), uv.max(0)
                s = np.max(hi - lo) * rng.uniform(1.3, 2.2)
                x0, y0 = ((lo + hi) / 2 + rng.uniform(-0.1, 0.1, 2) * s - s / 2).round().astype(int)
                n = int(round(s))
                if n > min(h, w):
                    continue
                x0, y0 = min(max(x0, 0), w - n), min(max(y0, 0), h - n)
                if np.any(lo < [x0, y0]) or np.any(hi > [x0 + n, y0 + n]):     # the hand must be whole
                    continue
                images.append(cv2.resize(np.ascontiguousarray(image[y0:y0 + n, x0:x0 + n]), (size, size),
                                         interpolation=cv2.INTER_AREA))
                labels.append((uv - [x0, y0] + 0.5) * size / n - 0.5)
                sides.append(hand_side)
    return images, np.array(labels), sides


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--val", default="runs/detnet_data/synth_val")
    ap.add_argument("-n", type=int, default=300)
    ap.add_argument("--size", type=int, default=None, help="photo side, px (default 256; --real 224)")
    ap.add_argument("--real", action="store_true", help="real close-ups cut from training-side held-out clips")
    ap.add_argument("--detnet", default=None, help="DetNet file (default: the bundled int8 one)")
    args = ap.parse_args()
    if args.real:
        args.size = args.size or 224
        images, labels, sides = real_closeups(args.size)
    else:
        args.size = args.size or 256
        images, labels = synthetic_closeups(args.val, args.n, args.size)
        sides = None
    print(f"| {len(images)} {'real' if args.real else 'synthetic'} close-ups, {args.size} px | hands found "
          f"| error / hand size (median, found) | published side right |")
    print("|---|---|---|---|")
    for name, kwargs in (("finder, birth_confidence 0", {"birth_confidence": 0.0}),
                         ("+ centre fallback", {"birth_confidence": 0.0, "fallback": CENTRE}),
                         ("PHOTO_SETTINGS (+ test_time_crops 4)", PHOTO_SETTINGS),
                         ("centre square only (finder none)", {"birth_confidence": 0.0, "finder_path": "none"})):
        found, err, right = score(HandDetector.load(args.detnet, **kwargs), images, labels, sides)
        print(f"| {name} | {found}/{len(images)} ({found / len(images):.1%}) | {err:.3f} | "
              f"{'–' if np.isnan(right) else f'{right:.1%}'} |", flush=True)


def synthetic_closeups(val, n, size):
    """BGR photos (size,size,3) of the first n held-out synthetic crops and their labels."""
    shards = sorted(glob.glob(f"{val}/shard_*.npz"))
    if not shards:
        raise SystemExit(f"no shards in {val}: make them with the handsynth command in this script's doc")
    data = np.load(shards[0])
    s = size / data["image"].shape[1]
    images = [cv2.resize(im, (size, size), interpolation=cv2.INTER_LINEAR)[..., ::-1].copy()
              for im in data["image"][:n]]                 # RGB crops -> BGR photos
    return images, (data["uv"][:n] + 0.5) * s - 0.5


if __name__ == "__main__":
    main()
