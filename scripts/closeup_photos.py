"""Close-up photos (the hand fills the frame, as in FreiHAND-style crops): how many hands
the detector finds in photo mode with and without the centre-square fallback.

    handsynth generate -n 1024 -o runs/detnet_data/synth_val --seed 424242   # held-out shard
    python scripts/closeup_photos.py [--val runs/detnet_data/synth_val] [-n 300] [--size 256]

Each photo is one held-out synthetic DetNet crop (128 px, never trained on) scaled up to
`--size` px. A hand counts as found when an output's mean joint distance to the label is
below half the hand's joint-box side; the error column is that distance / side (median of
the found). Settings: HandDetector.load(birth_confidence=0) (the photo setting before the
fallback), + fallback_path="centre" (detector.PHOTO_SETTINGS), and the centre square alone
(finder "none").
"""
import argparse
import glob

import cv2
import numpy as np

from handmocap.detector import CENTRE, HandDetector


def score(detector, images, labels):
    """(found count, median error / hand size of the found) over BGR images and (21,2) labels."""
    found, errors = 0, []
    for image, uv in zip(images, labels):
        detector.reset()
        hands = detector.process(image)
        side = np.max(uv.max(0) - uv.min(0))
        err = min((np.mean(np.linalg.norm(h["uv"] - uv, axis=1)) / side for h in hands), default=np.inf)
        if err < 0.5:
            found += 1
            errors.append(err)
    return found, float(np.median(errors)) if errors else float("nan")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--val", default="runs/detnet_data/synth_val")
    ap.add_argument("-n", type=int, default=300)
    ap.add_argument("--size", type=int, default=256)
    args = ap.parse_args()
    shards = sorted(glob.glob(f"{args.val}/shard_*.npz"))
    if not shards:
        raise SystemExit(f"no shards in {args.val}: make them with the handsynth command in this script's doc")
    data = np.load(shards[0])
    s = args.size / data["image"].shape[1]
    images = [cv2.resize(im, (args.size, args.size), interpolation=cv2.INTER_LINEAR)[..., ::-1].copy()
              for im in data["image"][:args.n]]                 # RGB crops -> BGR photos
    labels = (data["uv"][:args.n] + 0.5) * s - 0.5
    print(f"| {len(images)} close-ups, {args.size} px | hands found | error / hand size (median, found) |")
    print("|---|---|---|")
    for name, kwargs in (("finder, birth_confidence 0", {"birth_confidence": 0.0}),
                         ("+ centre fallback (PHOTO_SETTINGS)", {"birth_confidence": 0.0, "fallback_path": CENTRE}),
                         ("centre square only (finder none)", {"birth_confidence": 0.0, "finder_path": "none"})):
        found, err = score(HandDetector.load(**kwargs), images, labels)
        print(f"| {name} | {found}/{len(images)} ({found / len(images):.1%}) | {err:.3f} |", flush=True)


if __name__ == "__main__":
    main()
