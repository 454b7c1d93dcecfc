"""How far a 3D reference's skeleton is from the hand model's, and what that alone costs
the 3D AUC.

    python research/skeleton_proportions.py [--work /tmp/handeval] [--only temugeb_cam0 ...]

handeval's 3D score aligns a prediction to the reference by the root (joint 9) and the
scale |j0 - j9| only, so a skeleton whose bones are proportioned differently from the
reference's is wrong even when every bone points the right way. For each split with 3D
under --work (built by `handeval splits`), this prints each bone's median length per
|j0 - j9| in the reference, in the hand model's rest skeleton (mean shape, β = 0), and in
the saved predictions (pred.npz: DetNet's xyz_rel and the posed model's xyz, when
present), then the 3D PCK AUC 20-50 mm of the reference's own pose rebuilt with the hand
model's proportions (every bone direction exact, each length = the model's ratio × the
frame's |j0 - j9|): the best any prediction on the hand model's skeleton can score there;
and the predictions' own AUC as they are and rebuilt on the reference's median
proportions (a diagnostic of what the proportions cost them, not a result: it reads the
reference).
"""
import argparse
from pathlib import Path

import numpy as np

from handmocap.training import metrics
from handmocap.perception.hand_model import HandModel

BONES = [(0, 9), (0, 5), (0, 17), (5, 17), (0, 1), (1, 2), (2, 3), (3, 4), (5, 6), (6, 7), (7, 8),
         (9, 10), (10, 11), (11, 12)]


def ratios(xyz, bones=BONES):
    """Median |ja - jb| / |j0 - j9| over the frames of xyz (N,21,3), for each pair in `bones`."""
    xyz = xyz[np.isfinite(xyz).all(axis=(1, 2))]
    palm = np.linalg.norm(xyz[:, 0] - xyz[:, 9], axis=-1)
    return np.array([np.median(np.linalg.norm(xyz[:, a] - xyz[:, b], axis=-1) / palm) for a, b in bones])


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, default=Path("/tmp/handeval"), help="handeval splits' work folder")
    p.add_argument("--only", nargs="*", help="split names (default: every split with 3D there)")
    p.add_argument("--world", type=Path, default=Path("runs/detnet_data/real_v4.npz"),
                   help="DetNet's real-crop cache (handtrain detnet builds it): its MediaPipe world landmarks "
                        "of the training videos get a row too, when the file is there")
    args = p.parse_args()
    if not args.work.is_dir():
        raise SystemExit(f"no handeval work folder at {args.work}: run `handeval splits --work {args.work}` first")
    rest = HandModel.load().rest_joints()[None]
    model_per_palm = metrics.bone_per_reference(rest)[0]
    splits = [args.work / s for s in args.only] if args.only else sorted(args.work.iterdir())
    header = " ".join(f"{a}-{b}".rjust(6) for a, b in BONES)
    print(f"bone length / |j0-j9|, median over frames\n{'':34s}{header}")
    print(f"{'hand model, rest (beta = 0)':34s}" + " ".join(f"{r:6.2f}" for r in ratios(rest)))
    if args.world.exists():
        with np.load(args.world) as cache:
            world = cache["xyz"][cache["has_3d"]].astype(np.float64)
        print(f"{'MediaPipe world, training videos':34s}" + " ".join(f"{r:6.2f}" for r in ratios(world)))
    for split in splits:
        gt_path = split / "gt.npz"
        if not gt_path.exists():
            continue
        with np.load(gt_path) as gt:
            if "xyz" not in gt.files:
                continue
            ref = gt["xyz"].astype(np.float64)
        ok = np.isfinite(ref).all(axis=(1, 2))
        if not ok.any():                         # a 2D-only split
            continue
        rows, preds, scored = [("reference", ref)], {}, ok
        if (split / "pred.npz").exists():
            with np.load(split / "pred.npz") as pred:
                found = pred["found"].astype(bool)
                rows += [(f"prediction {k}", pred[k][found].astype(np.float64)) for k in ("xyz_rel", "xyz")
                         if k in pred.files]
                scored = ok & found
                preds = {k: pred[k][scored].astype(np.float64) for k in ("xyz_rel", "xyz") if k in pred.files}
        print(f"{split.name}")
        for name, xyz in rows:
            print(f"  {name:32s}" + " ".join(f"{r:6.2f}" for r in ratios(xyz)))
        best = metrics.score_3d(metrics.with_proportions(ref[ok], model_per_palm), ref[ok])
        print(f"  the reference's pose on the hand model's proportions: 3D AUC 20-50 mm {best['auc']:.3f}, "
              f"mean {best['mean_mm']:.1f} mm ({int(ok.sum())} frames)")
        ref_per_palm = np.median(metrics.bone_per_reference(ref[ok]), axis=0)
        for k, xyz in preds.items():
            own = metrics.score_3d(xyz, ref[scored])["auc"]
            moved = metrics.score_3d(metrics.with_proportions(xyz, ref_per_palm), ref[scored])["auc"]
            print(f"  prediction {k} on the {int(scored.sum())} frames with a hand found: 3D AUC {own:.3f}; "
                  f"rebuilt on the reference's median proportions {moved:.3f}")


if __name__ == "__main__":
    main()
