"""How often each handedness cue says the labelled side, on the prepared evaluation splits
(`handeval splits --work W`), with each hand cut around its label as the detector would cut
it (a perfect finder and tracker): what the side decision could be built from.

    python research/side_cues.py [--work /tmp/handeval] [--detnet F] [--finder F]

Cues (columns):
- finder: the hand finder's right_prob of its found box nearest the labelled hand (share of
  the hands it found);
- head: DetNet's handedness head on the crop as filmed;
- vote: the head on the crop minus the head on it flipped (logits), the detector's mirror vote;
- vote x5: the vote summed over the crop and 4 test-time variants (detector.TEST_TIME_VARIANTS);
- peak: DetNet's mean heatmap peak read as a right hand (as filmed) minus read as a left
  one (flipped): the keypoint heads only ever saw right hands, so a hand read as the wrong
  side shows lower peaks;
- vote + 20 peak: the two combined (20: the weight that did best on these splits, so a
  figure for what the cue could add, not a setting chosen here; on the training side's
  held-out crops, where the vote is already right on 96%, no weight above 0 helped).
These are evaluation splits: read them, never tune on them.
"""
import argparse
import glob
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.detector import DetNetRunner, crop_for_joints, logit, nearby_crops
from handmocap.perception.hand_finder import HandFinder

SPLITS = ["temugeb_cam0", "temugeb_cam1", "howiema_040", "cmu_sample", "mmpose_freihand", "mmpose_rhd",
          "mmpose_interhand", "mmpose_panoptic"]


def finder_says_right(finder, image, uv):
    """The finder's side (bool) for its box nearest the labelled joints uv (21,2), None if it finds none."""
    found = finder.find(image, 0.1, 4)
    if not found:
        return None
    centre = uv.mean(axis=0)
    nearest = min(found, key=lambda h: np.linalg.norm((h.box[:2] + h.box[2:]) / 2 - centre))
    return nearest.right_prob > 0.5


def detnet_cues(detnet, image, uv):
    """{cue: score (> 0 says right)} of DetNet on the labelled hand's crop, its variants, all flipped."""
    own = crop_for_joints(uv, mirrored=False, upright_step=90.0)
    crops = [own] + nearby_crops(own, 4)
    pixels = np.stack([c.cut(image) for c in crops])
    out = detnet(np.ascontiguousarray(np.concatenate([pixels, pixels[:, :, ::-1]])[..., ::-1]))
    n = len(crops)
    head = logit(out["handedness"])
    vote = head[:n] - head[n:]
    peak = out["confidence"][0].mean() - out["confidence"][n].mean()
    return {"head": head[0], "vote": vote[0], "vote x5": vote.sum(), "peak": peak, "vote + 20 peak": vote[0] + 20 * peak}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=Path("/tmp/handeval"))
    p.add_argument("--detnet", default=None)
    p.add_argument("--finder", default=None)
    args = p.parse_args()
    detnet, finder = DetNetRunner.load(args.detnet), HandFinder.load(args.finder)
    cues = ["head", "vote", "vote x5", "peak", "vote + 20 peak"]
    print("| split | hands | finder | " + " | ".join(cues) + " |")
    print("|---|---|---|" + "---|" * len(cues))
    for split in SPLITS:
        gt = np.load(args.work / split / "gt.npz")
        if "handedness" not in gt.files:
            continue
        files = sorted(glob.glob(str(args.work / split / "images" / "*")))
        finder_right, right = [], {c: [] for c in cues}
        for f, uv, side in zip(files, gt["uv"], gt["handedness"]):
            if side not in ("left", "right") or not np.all(np.isfinite(uv)):
                continue
            image, truth = cv2.imread(f), side == "right"
            says = finder_says_right(finder, image, uv)
            if says is not None:
                finder_right.append(says == truth)
            for cue, score in detnet_cues(detnet, image, uv).items():
                right[cue].append((score > 0) == truth)
        n = len(right["head"])
        print(f"| {split} | {n} | {np.mean(finder_right):.1%} of {len(finder_right)} | "
              + " | ".join(f"{np.mean(right[c]):.1%}" for c in cues) + " |")


if __name__ == "__main__":
    main()
