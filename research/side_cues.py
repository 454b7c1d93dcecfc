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

    python research/side_cues.py --heldout-crops [--detnet F]

The same question on DetNet's held-out real crops (detnet_eval.real_val_set, upright as the
detector turns them): howiema 001, the training videos' tails and the held-back people's
clips and photos, each crop read as the right side and mirrored the wrong way. Cues: the
head (as read minus mirrored, logits), the heatmap peaks (as above) and `2d-3d`: how well
the 2D joints agree with the 3D joints' projection (scale and shift fitted, error / hand
size; the 3D heads only ever learnt right hands, so a hand read as the wrong side should
agree worse). Session 26, the shipped network: on the held-back clips the head says the
side on 75.5%, the peaks on 74.6%, the 2D-3D agreement on 70.7% (photos: 100, 99.0, 66.3%).
"""
import argparse
import glob
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.crops import crop_for_joints, nearby_crops
from handmocap.perception.detnet_runner import DetNetRunner
from handmocap.perception.tracks import logit
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


def projection_disagreement(uv, xyz):
    """(N,) how far the 2D joints uv (N,21,2) lie from the 3D joints' xy (N,21,3) with the
    least-squares scale and shift fitted, mean over joints / the joints' box side."""
    p = xyz[..., :2] - xyz[..., :2].mean(1, keepdims=True)
    u = uv - uv.mean(1, keepdims=True)
    s = (p * u).sum((1, 2)) / (p ** 2).sum((1, 2))
    return np.linalg.norm(s[:, None, None] * p - u, axis=-1).mean(-1) / np.ptp(uv, axis=1).max(-1)


def heldout_crop_cues(detnet_path):
    """Print the share of held-out real crops whose side each cue says right, per group."""
    from handmocap.training.quantize_detnet import OnnxNet, heldout_sets
    from handmocap.training.detnet_eval import heldout_groups, shown_as_right
    _, crops = heldout_sets(upright=True)
    net = OnnxNet(detnet_path or str(Path(__file__).resolve().parents[1] / "models" / "detnet_int8.onnx"))
    n = len(crops["image"])
    flipped, _, _ = shown_as_right(crops["image"], crops["uv"], np.zeros((n, 21, 3)), np.ones(n, bool))
    (uv_r, xyz_r, peak_r), _, head_r = net.predict(crops["image"])    # every crop shows a right hand
    (uv_w, xyz_w, peak_w), _, head_w = net.predict(flipped)           # the same, a left hand
    cues = {"head": logit(head_r) - logit(head_w), "peak": peak_r.mean(1) - peak_w.mean(1),
            "2d-3d": projection_disagreement(uv_w, xyz_w) - projection_disagreement(uv_r, xyz_r)}
    groups = heldout_groups(crops["source"])
    print("| crops | n | " + " | ".join(cues) + " |")
    print("|---|---|" + "---|" * len(cues))
    for name, mask in groups.items():
        print(f"| {name} | {mask.sum()} | " + " | ".join(f"{np.mean(c[mask] > 0):.1%}" for c in cues.values()) + " |")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=Path("/tmp/handeval"))
    p.add_argument("--detnet", default=None)
    p.add_argument("--finder", default=None)
    p.add_argument("--heldout-crops", action="store_true", help="the cues on DetNet's held-out real crops instead")
    args = p.parse_args()
    if args.heldout_crops:
        return heldout_crop_cues(args.detnet)
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
