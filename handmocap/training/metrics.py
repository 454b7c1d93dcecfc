"""Keypoint accuracy: PCK curves, AUC, 2D pixel error (paper's evaluation protocol).

3D: the prediction is root- and scale-aligned as in the paper's ports: normalized
(joint 9 at the origin, |0-9| = 1), scaled by the ground truth's |0-9| and moved to the
ground truth's joint 9; errors in mm; PCK at PCK_THRESHOLDS_MM = 15 thresholds
linspace(20, 50) mm; AUC by the trapezoid rule over that range, divided by its width.
A joint of a hand that was not found (NaN) counts as beyond every threshold; joints
without ground truth (joint_valid False or NaN) are left out.
"""
from __future__ import annotations

import numpy as np

from handmocap.perception.skeleton import normalize_joints, PARENTS, REF_BONE, ROOT

PCK_THRESHOLDS_MM = np.linspace(20.0, 50.0, 15)
PCK_THRESHOLDS_PX = np.linspace(0.0, 30.0, 16)


def align_to_ground_truth(pred, gt):
    """(N,21,3) prediction in any unit/frame -> aligned to gt (N,21,3): normalized, times
    the gt reference bone |0-9|, plus the gt joint 9. NaN stays NaN."""
    gt = np.asarray(gt, dtype=np.float64)
    ref = np.linalg.norm(gt[:, REF_BONE[0]] - gt[:, REF_BONE[1]], axis=-1)[:, None, None]
    return normalize_joints(pred) * ref + gt[:, ROOT:ROOT + 1]


def joint_errors(pred, gt, joint_valid=None):
    """Euclidean errors (N,21) (the unit of gt); NaN where the gt is missing or invalid,
    +inf where the prediction is missing (not found)."""
    pred, gt = np.asarray(pred, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    err = np.linalg.norm(pred - gt, axis=-1)
    err = np.where(np.isfinite(err), err, np.inf)
    no_gt = ~np.all(np.isfinite(gt), axis=-1)
    if joint_valid is not None:
        no_gt |= ~np.asarray(joint_valid, dtype=bool)
    return np.where(no_gt, np.nan, err)


def pck(errors, thresholds):
    """Share (T,) of joints with an error <= each threshold; NaN errors are left out, inf
    (not found) counts as a miss."""
    e = np.asarray(errors, dtype=np.float64).ravel()
    e = e[~np.isnan(e)]
    if e.size == 0:
        return np.full(len(thresholds), np.nan)
    return (e[None, :] <= np.asarray(thresholds)[:, None]).mean(axis=1)


def auc(thresholds, curve):
    """Area under a PCK curve over [thresholds[0], thresholds[-1]], normalized to [0, 1]."""
    t, c = np.asarray(thresholds, dtype=np.float64), np.asarray(curve, dtype=np.float64)
    return float(np.sum((c[1:] + c[:-1]) * np.diff(t)) / 2.0 / (t[-1] - t[0]))


def score_3d(pred, gt, joint_valid=None, thresholds=PCK_THRESHOLDS_MM):
    """Root/scale-aligned 3D accuracy of pred (N,21,3) against gt (N,21,3) metres.
    Returns {pck (T,), auc, mean_mm (found hands), thresholds_mm}."""
    err = joint_errors(align_to_ground_truth(pred, gt), gt, joint_valid) * 1000.0
    curve = pck(err, thresholds)
    finite = err[np.isfinite(err)]
    return {"pck": curve, "auc": auc(thresholds, curve), "mean_mm": float(finite.mean()) if finite.size else np.nan,
            "thresholds_mm": np.asarray(thresholds)}


def score_2d(pred_uv, gt_uv, joint_valid=None, thresholds=PCK_THRESHOLDS_PX):
    """2D accuracy of pred_uv (N,21,2) px against gt_uv (N,21,2). Returns {mean_px,
    median_px (found hands), pck (T,) (missing = miss), auc, thresholds_px}."""
    err = joint_errors(pred_uv, gt_uv, joint_valid)
    curve = pck(err, thresholds)
    finite = err[np.isfinite(err)]
    return {"mean_px": float(finite.mean()) if finite.size else np.nan,
            "median_px": float(np.median(finite)) if finite.size else np.nan,
            "pck": curve, "auc": auc(thresholds, curve), "thresholds_px": np.asarray(thresholds)}


def bone_per_reference(xyz):
    """Bone lengths over the reference bone: xyz (N,21,3) -> (N,21), row j the bone from
    PARENTS[j] to j divided by |j0 - j9| (column 0: zero). The proportions that root and
    scale alignment keep: two skeletons whose ratios differ cannot match by alignment."""
    xyz = np.asarray(xyz, dtype=np.float64)
    bones = np.linalg.norm(xyz - xyz[:, np.maximum(PARENTS, 0)], axis=-1)
    return bones / np.linalg.norm(xyz[:, REF_BONE[0]] - xyz[:, REF_BONE[1]], axis=-1)[:, None]


def with_proportions(xyz, bone_ratio):
    """Joints xyz (N,21,3) rebuilt down the kinematic tree from the wrist: every bone keeps
    its direction, its length becomes bone_ratio (21,) (as bone_per_reference gives) times
    the hand's own |j0 - j9|. -> (N,21,3), the wrist where it was."""
    xyz = np.asarray(xyz, dtype=np.float64)
    ref = np.linalg.norm(xyz[:, REF_BONE[0]] - xyz[:, REF_BONE[1]], axis=-1)[:, None]
    out = np.repeat(xyz[:, :1], xyz.shape[1], axis=1)
    for j in range(1, xyz.shape[1]):                # PARENTS lists every parent before its child
        d = xyz[:, j] - xyz[:, PARENTS[j]]
        out[:, j] = out[:, PARENTS[j]] + d / np.linalg.norm(d, axis=-1, keepdims=True) * (bone_ratio[j] * ref)
    return out
