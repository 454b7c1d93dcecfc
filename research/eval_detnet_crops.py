"""DetNet alone on crops cut around the labelled hand, per prepared evaluation split
(`handeval splits --work W`): what the 2D error would be with a perfect finder and tracker.

    python research/eval_detnet_crops.py --work /tmp/handeval [--detnet int8|float32|F.onnx] [--upright-step 90|0|none]

Each labelled hand is cut the way the detector cuts a tracked hand (`crop_for_joints`: the
square around its 21-joint box x CROP_SCALE, turned upright by the detector's
`upright_step` (default: HandDetector's), left hands mirrored by the label's handedness
where the split has one), DetNet runs once, and its 2D joints are mapped back to the frame.
Prints the mean px error in frame px and relative to the hand's joint-box side, to set
beside `handeval splits`' whole-frame figures. Where the split knows each hand's side, also
DetNet's handedness head on the unmirrored labelled crop (how often it says the label's
side), the same with the detector's mirror vote (the head's answers on the crop and on it
flipped, averaged in logit space) and the 2D error when the crop is mirrored the wrong way
(what a wrong handedness costs the keypoints, since they are read as a right hand).
"""
import argparse
import glob
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.crops import crop_for_joints
from handmocap.perception.detector import DetectorSettings
from handmocap.perception.detnet_runner import DetNetRunner
from handmocap.perception.tracks import logit

UPRIGHT_STEP = DetectorSettings().upright_step


def evaluate(detnet, split_dir, upright_step=UPRIGHT_STEP):
    gt = np.load(split_dir / "gt.npz")
    files = sorted(glob.glob(str(split_dir / "images" / "*")))
    sided = "handedness" in gt.files
    err, rel, head_right, vote_right, wrong_err = [], [], [], [], []
    for i, f in enumerate(files):
        uv = gt["uv"][i]
        if not np.all(np.isfinite(uv)):
            continue
        left = sided and gt["handedness"][i] == "left"
        known = sided and gt["handedness"][i] in ("left", "right")
        # the crop as DetNet should see it and, where the side is known, mirrored the wrong way
        crops = [crop_for_joints(uv, mirrored=m, upright_step=upright_step) for m in (left, not left)[:1 + known]]
        image = cv2.imread(f)
        out = detnet(np.stack([c.cut(image)[..., ::-1] for c in crops]))
        e = [np.linalg.norm(c.to_frame(out["uv"][k]) - uv, axis=1).mean() for k, c in enumerate(crops)]
        err.append(e[0])
        rel.append(e[0] / np.max(uv.max(0) - uv.min(0)))
        if known:
            unmirrored = 1 if left else 0       # the head is asked on the crop as filmed
            head_right.append((out["handedness"][unmirrored] > 0.5) == (not left))
            vote = logit(out["handedness"][unmirrored]) - logit(out["handedness"][1 - unmirrored])
            vote_right.append((vote > 0) == (not left))
            wrong_err.append(e[1])
    nan = float("nan")
    share = lambda v: float(np.mean(v)) if v else nan   # noqa: E731
    return len(err), float(np.mean(err)), float(np.median(rel)), share(head_right), share(vote_right), share(wrong_err)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=Path("/tmp/handeval"))
    p.add_argument("--detnet", type=Path, default=None)
    p.add_argument("--splits", nargs="+", default=["temugeb_cam0", "temugeb_cam1", "howiema_040", "cmu_sample"])
    p.add_argument("--upright-step", default=UPRIGHT_STEP, type=lambda v: None if v == "none" else float(v),
                   help="degrees; 0: any angle; none: never turned (default: the detector's, %(default)s)")
    args = p.parse_args()
    detnet = DetNetRunner.load(args.detnet)
    print("| split | hands | DetNet on labelled crops: mean px | median error / joint-box side "
          "| handedness head right | with the mirror vote | mean px, crop mirrored the wrong way |")
    print("|---|---|---|---|---|---|---|")
    for s in args.splits:
        n, e, r, hand, vote, wrong = evaluate(detnet, args.work / s, args.upright_step)
        print(f"| {s} | {n} | {e:.1f} | {r:.3f} | {hand:.1%} | {vote:.1%} | {wrong:.1f} |"
              .replace("nan%", "–").replace("nan", "–"))


if __name__ == "__main__":
    main()
