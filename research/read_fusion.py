"""Fusing DetNet's reads of a crop instead of choosing one: the crop read both ways (as a
right hand and mirrored), and the 2D joints with the 3D joints' projection. What each
would do to the 2D error, on DetNet's held-out real crops (detnet_eval.real_val_set,
upright as the detector turns them).

    python research/read_fusion.py [--detnet F]

Each crop is read as filmed-and-mirrored-right (the label's side: the "oracle" read) and
mirrored the wrong way (its joints flipped back into the crop). Columns, median of the mean
joint error / joint-box side per crop:
- right side, wrong side: each read alone;
- head: the read the handedness vote picks (head on the crop minus on it flipped, logits),
  the detector's choice without a track's memory;
- peak: the read with the higher mean heatmap peak;
- mean: the two reads averaged;
- joint pick: per joint, the read with the higher heatmap peak;
- weighted: per joint, the two reads weighted by their peaks (w = c / (c_right + c_wrong));
- 3D projected: the right-side read's 3D joints projected orthographically, scale and
  shift fitted to its 2D joints weighted by their peaks (the 3D heads give a whole,
  plausible hand; are its curled fingers better placed than the 2D heatmaps'?);
- 2D + 3D (0.25): the right-side 2D joints moved a quarter of the way to that projection.
"""
import argparse
from pathlib import Path

import numpy as np

from handmocap.perception.tracks import logit
from handmocap.training.real_data import hand_size


def relative_error(uv, truth):
    """(N,) mean joint distance of uv (N,21,2) from truth (N,21,2) / the truth's joint-box side."""
    return np.linalg.norm(uv - truth, axis=-1).mean(-1) / hand_size(truth)


def projected(uv, xyz, weight):
    """(N,21,2) the 3D joints xyz (N,21,3) projected orthographically onto the 2D joints uv
    (N,21,2): uv ~ s * xyz[..., :2] + t, least squares weighted per joint by weight (N,21)."""
    w = weight[..., None]
    p = xyz[..., :2]
    p_mean = (w * p).sum(1, keepdims=True) / w.sum(1, keepdims=True)
    uv_mean = (w * uv).sum(1, keepdims=True) / w.sum(1, keepdims=True)
    s = (w * (p - p_mean) * (uv - uv_mean)).sum((1, 2)) / (w * (p - p_mean) ** 2).sum((1, 2))
    return s[:, None, None] * (p - p_mean) + uv_mean


def fused_reads(uv_r, peak_r, head_r, uv_w, peak_w, head_w):
    """{rule: (N,21,2)} from the read as the right side (uv_r, peaks (N,21), handedness prob
    (N,)) and the read mirrored the wrong way (uv_w already flipped back, peak_w, head_w)."""
    vote = (logit(head_r) - logit(head_w)) > 0
    by_peak = peak_r.mean(1) >= peak_w.mean(1)
    w = peak_r / np.maximum(peak_r + peak_w, 1e-6)
    return {"right side": uv_r, "wrong side": uv_w,
            "head": np.where(vote[:, None, None], uv_r, uv_w),
            "peak": np.where(by_peak[:, None, None], uv_r, uv_w),
            "mean": (uv_r + uv_w) / 2,
            "joint pick": np.where((peak_r >= peak_w)[..., None], uv_r, uv_w),
            "weighted": w[..., None] * uv_r + (1 - w[..., None]) * uv_w}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--detnet", default=str(Path(__file__).resolve().parents[1] / "models" / "detnet_int8.onnx"))
    args = p.parse_args()
    from handmocap.training.quantize_detnet import OnnxNet, heldout_sets
    from handmocap.training.detnet_eval import heldout_groups, shown_as_right
    _, crops = heldout_sets(upright=True)
    net = OnnxNet(args.detnet)
    n, size = len(crops["image"]), crops["image"].shape[2]
    flipped, _, _ = shown_as_right(crops["image"], crops["uv"], np.zeros((n, 21, 3)), np.ones(n, bool))
    (uv_r, xyz_r, peak_r), _, head_r = net.predict(crops["image"])
    (uv_w, _, peak_w), _, head_w = net.predict(flipped)
    uv_w = uv_w.copy()
    uv_w[..., 0] = size - 1 - uv_w[..., 0]
    reads = fused_reads(uv_r, peak_r, head_r, uv_w, peak_w, head_w)
    reads["3D projected"] = projected(uv_r, xyz_r, peak_r)
    reads["2D + 3D (0.25)"] = 0.75 * uv_r + 0.25 * reads["3D projected"]
    groups = heldout_groups(crops["source"])
    errors = {rule: relative_error(uv, crops["uv"]) for rule, uv in reads.items()}
    print(f"DetNet {args.detnet}; median error / joint-box side (PCK@0.1 of the crops' mean joint error)")
    print("| crops | n | " + " | ".join(reads) + " |")
    print("|---|---|" + "---|" * len(reads))
    for name, mask in groups.items():
        print(f"| {name} | {mask.sum()} | " + " | ".join(
            f"{np.median(e[mask]):.4f} ({np.mean(e[mask] < 0.1):.2f})" for e in errors.values()) + " |")


if __name__ == "__main__":
    main()
